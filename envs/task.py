"""The task interface that every DHRL environment plugs into the shared simulation core.

A task spec (:class:`TaskSpec`: :class:`~torchrl_dhrl.envs.MazeSpec` for the mazes,
:class:`~torchrl_dhrl.envs.ArmSpec` for the robot arms) holds every fact of one environment: its MuJoCo
scene, the actuated agent (reset pose and noise, frame skip, how actions become controls), the observation
layout, where the achieved goal is read, the goal distributions, the thresholds and the episode length.
The batched core :class:`~torchrl_dhrl.envs.GoalSimulation` and its two front ends (TorchRL and
Gymnasium) only read these facts, so a new environment is one new spec.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import TypeVar

import mujoco
import numpy as np

__all__ = ["TaskSpec", "GOAL_BODY", "OVERVIEW_CAMERA", "OBSERVATION_PARTS", "lookup_spec"]

#: Name of the mocap body that marks the desired goal (visual only).
GOAL_BODY = "goal_marker"
#: Name of the fixed camera that shows the whole scene.
OVERVIEW_CAMERA = "overview"
#: The pieces an observation can be made of (see :attr:`TaskSpec.observation_layout`).
OBSERVATION_PARTS = ("qpos", "qvel", "goal", "achieved")

_Spec = TypeVar("_Spec")


class TaskSpec:
    """Base class of the environment specs (frozen dataclasses) read by the simulation core.

    Subclasses provide the fields ``name`` (str), ``agent`` (the actuated body: ``action_dim``,
    ``action_low``/``action_high``, ``timestep``, ``frame_skip``, ``control_field`` and ``command(actions,
    qpos)``, ``init_qpos``, ``qpos_noise``, ``qvel_noise``, ``normalize_qpos(qpos)``), ``episode_length``,
    ``success_threshold``, ``reward_threshold`` and ``train_goals`` (a
    :class:`~torchrl_dhrl.envs.GoalSampler`), and implement :attr:`goal_bounds`, :attr:`test_goal_sampler`,
    :attr:`reference_goal`, :attr:`obs_dim` and :meth:`build_mjcf`.

    Every env resets to ``agent.init_qpos + U(-qpos_noise, qpos_noise)`` (then ``normalize_qpos``) with joint
    velocities ``N(0, qvel_noise)``, and steps ``frame_skip`` physics steps per env step after writing
    ``agent.command(actions, qpos)`` into ``MjData.<control_field>``.

    Class attributes (overridable by subclass fields):

    * :attr:`observation_layout`: the observation is the concatenation of these parts, each one of
      ``"qpos"`` (all joint positions), ``"qvel"`` (all joint velocities), ``"goal"`` (the desired goal) and
      ``"achieved"`` (the achieved goal). Defaults to ``("qpos", "qvel")``.
    * :attr:`achieved_goal_site`: name of the MuJoCo site whose world position is the achieved goal;
      ``None`` (the default) takes the first ``goal_dim`` entries of ``qpos`` (a maze agent's x, y).
    * :attr:`start_position_noise`: ``False`` sets the first ``goal_dim`` entries of ``qpos`` back to the
      start after the noise is drawn (the same draws either way). Defaults to ``True``.

    Examples:
        >>> from torchrl_dhrl.envs import TaskSpec, get_env_spec
        >>> spec = get_env_spec("Reacher3D")
        >>> isinstance(spec, TaskSpec), spec.gym_id, spec.goal_dim, spec.observation_layout
        (True, 'dhrl/Reacher3D-v0', 3, ('qpos', 'goal', 'qvel'))
        >>> spec.compile_model().opt.timestep
        0.01
    """

    observation_layout: tuple[str, ...] = ("qpos", "qvel")
    achieved_goal_site: str | None = None
    start_position_noise: bool = True

    @property
    def gym_id(self) -> str:
        """The registered Gymnasium id, ``dhrl/<name>-v0``."""
        return f"dhrl/{self.name}-v0"

    @property
    def goal_dim(self) -> int:
        """Dimension of the goal space."""
        return len(self.goal_bounds[0])

    @property
    def goal_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)`` of the goal space; explicit goals must lie inside."""
        raise NotImplementedError

    @property
    def test_goal_sampler(self):
        """The :class:`~torchrl_dhrl.envs.GoalSampler` of evaluation episodes."""
        raise NotImplementedError

    @property
    def reference_goal(self) -> np.ndarray:
        """The goal an env holds before its first reset (a typical test goal)."""
        raise NotImplementedError

    @property
    def obs_dim(self) -> int:
        """Size of the observation vector."""
        raise NotImplementedError

    def build_mjcf(self):
        """The :class:`dm_control.mjcf.RootElement` of the whole scene (agent, obstacles, goal marker)."""
        raise NotImplementedError

    def compile_model(self) -> mujoco.MjModel:
        """A fresh :class:`mujoco.MjModel` of the scene (its MJCF text is built once and cached)."""
        return mujoco.MjModel.from_xml_string(_scene_xml(self))


@functools.cache
def _scene_xml(spec: TaskSpec) -> str:
    return spec.build_mjcf().to_xml_string()


def lookup_spec(value: str | _Spec, table: Mapping[str, _Spec], spec_type: type, kind: str) -> _Spec:
    """Resolves ``value`` (a spec, a name or a ``dhrl/<name>-v0`` id) against ``table``.

    Raises:
        ValueError: for an unknown name (the message lists the valid ones).
        TypeError: for anything else than a string or a ``spec_type``.

    Examples:
        >>> from torchrl_dhrl.envs import ENVS, TaskSpec, lookup_spec
        >>> lookup_spec("dhrl/UR3Obstacle-v0", ENVS, TaskSpec, "environment").name
        'UR3Obstacle'
    """
    if isinstance(value, spec_type):
        return value
    if not isinstance(value, str):
        raise TypeError(f"{kind} must be a name or a {spec_type.__name__}, got {type(value).__name__}.")
    name = value
    if name.startswith("dhrl/") and name.endswith("-v0"):
        name = name[len("dhrl/") : -len("-v0")]
    if name not in table:
        raise ValueError(f"Unknown {kind} {value!r}. Valid names: {', '.join(table)}.")
    return table[name]
