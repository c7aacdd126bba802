"""Gymnasium goal-env front end of every DHRL task, and the registration of their ids."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces

from .registry import ENVS, get_env_spec
from .simulation import GoalSimulation
from .task import OVERVIEW_CAMERA, TaskSpec

__all__ = ["GymGoalEnv", "register_gym_envs"]


class GymGoalEnv(gym.Env):
    """One DHRL task as a Gymnasium goal-conditioned env (gymnasium-robotics convention).

    Observations are a ``Dict`` of float64 arrays: ``"observation"`` (mazes: ``qpos ++ qvel``, 29-D for the
    ant, 6-D for the point; Reacher3D: ``qpos ++ goal ++ qvel``, 17-D; UR3Obstacle: ``flange position ++
    qpos ++ qvel``, 15-D), ``"achieved_goal"`` (a maze agent's x, y or an arm's end-effector position) and
    ``"desired_goal"``. The reward is sparse, ``compute_reward(achieved_goal, desired_goal, info)`` (``-1``,
    or ``0`` within the reward threshold of the goal: 0.5 in the mazes, 0.25 for Reacher3D, 0.08 for
    UR3Obstacle), vectorised over leading dims so that HER implementations (e.g. Stable-Baselines3) can
    relabel; ``info["is_success"]`` tells whether the agent is within the evaluation threshold of the goal.
    Episodes never terminate; they are truncated at ``max_episode_steps`` (the registered ids also carry
    the same time limit for Gymnasium's ``TimeLimit`` wrapper).

    Args:
        task (str or TaskSpec): one of :data:`~torchrl_dhrl.envs.ENV_NAMES`.

    Keyword Args:
        eval (bool): draw test goals instead of train goals (AntMazeComplex: one of its four per
            episode). Defaults to ``False``; ``reset(options={"eval": ...})`` overrides it per episode.
        max_episode_steps (int, optional): time limit; defaults to the task's episode length.
        render_mode (str, optional): ``"rgb_array"`` renders the overview camera offscreen (needs
            ``MUJOCO_GL=egl`` or ``osmesa``).
        width (int): render width. Defaults to ``480``.
        height (int): render height. Defaults to ``480``.
        right_flipped_after (int, optional): ant mazes only: put a flipped ant back on its feet after this
            many consecutive env steps upside down (see :class:`~torchrl_dhrl.envs.GoalSimulation`).
            Defaults to ``None``: never, as the reference.
        reference_engine (bool): ant mazes only: emulate MuJoCo 2.0 where MuJoCo 3 differs (0.01 margin per
            contact, MuJoCo 2.0's capsule masses and inertias; see :class:`~torchrl_dhrl.envs.AntAgent`);
            ``gym.make("dhrl/AntMaze-v0", reference_engine=True)``. Defaults to ``False``.

    ``reset(options={"goal": goal})`` sets the goal explicitly (it must lie inside the goal bounds);
    ``reset(options={"start": position})`` starts a maze agent at that position (clear of the walls).

    Examples:
        >>> import gymnasium as gym
        >>> import torchrl_dhrl.envs  # registers the dhrl/ ids
        >>> env = gym.make("dhrl/AntMaze-v0", eval=True)
        >>> obs, info = env.reset(seed=0)
        >>> obs["observation"].shape, obs["desired_goal"].tolist()
        ((29,), [0.0, 16.0])
        >>> obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        >>> bool(reward == env.unwrapped.compute_reward(obs["achieved_goal"], obs["desired_goal"], info))
        True
        >>> arm = gym.make("dhrl/Reacher3D-v0")
        >>> obs, info = arm.reset(seed=0, options={"goal": (0.0, 0.3, 0.1)})
        >>> obs["observation"].shape, obs["desired_goal"].tolist(), obs["observation"][7:10].tolist()
        ((17,), [0.0, 0.3, 0.1], [0.0, 0.3, 0.1])
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        task: str | TaskSpec,
        *,
        eval: bool = False,  # noqa: A002 - the documented option name
        max_episode_steps: int | None = None,
        render_mode: str | None = None,
        width: int = 480,
        height: int = 480,
        right_flipped_after: int | None = None,
        reference_engine: bool = False,
    ) -> None:
        spec = get_env_spec(task)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}."
            )
        self._sim = GoalSimulation(
            spec,
            1,
            max_episode_steps=max_episode_steps,
            eval_goals=eval,
            right_flipped_after=right_flipped_after,
            reference_engine=reference_engine,
        )
        self.render_mode = render_mode
        self.width, self.height = width, height
        self.metadata = {**self.metadata, "render_fps": int(round(1.0 / self._sim.dt))}
        spec = self._sim.spec  # with reference_engine: the ant emulating MuJoCo 2.0
        agent, dim = spec.agent, spec.goal_dim
        low, high = spec.goal_bounds
        self.observation_space = spaces.Dict(
            {
                "observation": spaces.Box(-np.inf, np.inf, shape=(spec.obs_dim,), dtype=np.float64),
                "achieved_goal": spaces.Box(-np.inf, np.inf, shape=(dim,), dtype=np.float64),
                "desired_goal": spaces.Box(low, high, shape=(dim,), dtype=np.float64),
            }
        )
        self.action_space = spaces.Box(
            agent.action_low.astype(np.float32), agent.action_high.astype(np.float32), dtype=np.float32
        )

    @property
    def task(self) -> TaskSpec:
        """The spec of this environment."""
        return self._sim.spec

    @property
    def simulation(self) -> GoalSimulation:
        """The underlying simulation core (one env)."""
        return self._sim

    @property
    def model(self) -> mujoco.MjModel:
        """The live :class:`mujoco.MjModel` of the scene, where Gymnasium's MuJoCo envs keep theirs.

        Renderers, viewers and tools written for ``gymnasium.envs.mujoco`` envs (``env.unwrapped.model``)
        work with it. It is the simulation's own model, not a copy: read it; writing to it changes the
        physics of every later step.

        Examples:
            >>> import gymnasium as gym, mujoco
            >>> import torchrl_dhrl.envs  # registers the dhrl/ ids
            >>> env = gym.make("dhrl/PointMaze-v0").unwrapped
            >>> isinstance(env.model, mujoco.MjModel), env.model is env.simulation.model
            (True, True)
        """
        return self._sim.model

    @property
    def data(self) -> mujoco.MjData:
        """The live :class:`mujoco.MjData` of the env (``qpos``, ``qvel``, ``time``, contacts, ...).

        As Gymnasium's MuJoCo envs' ``env.unwrapped.data``: the very object :meth:`reset` and :meth:`step`
        advance, so it always holds the current state. Read it; writing to it bypasses the env's
        bookkeeping (observations, goals and step counts are not updated until the next step).

        Examples:
            >>> import gymnasium as gym
            >>> import torchrl_dhrl.envs  # registers the dhrl/ ids
            >>> env = gym.make("dhrl/PointMaze-v0")
            >>> _ = env.reset(seed=0)
            >>> data = env.unwrapped.data
            >>> before = data.time
            >>> _ = env.step(env.action_space.sample())
            >>> data.time > before, data is env.unwrapped.simulation.datas[0]
            (True, True)
        """
        return self._sim.datas[0]

    def _get_obs(self) -> dict[str, np.ndarray]:
        sim = self._sim
        return {
            "observation": sim.observation[0].copy(),
            "achieved_goal": sim.achieved_goal[0].copy(),
            "desired_goal": sim.desired_goal[0].copy(),
        }

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        options = {} if options is None else dict(options)
        unknown = set(options) - {"goal", "eval", "start"}
        if unknown:
            raise ValueError(f"Unknown reset options {sorted(unknown)}; supported: 'goal', 'eval', 'start'.")
        self._sim.rngs[0] = self.np_random
        goal, start = options.get("goal"), options.get("start")
        self._sim.reset(
            None,
            None if goal is None else np.asarray(goal, dtype=np.float64)[None],
            eval_goals=options.get("eval"),
            starts=None if start is None else np.asarray(start, dtype=np.float64)[None],
        )
        _, success = self._sim.evaluate()
        return self._get_obs(), {"is_success": bool(success[0])}

    def step(self, action):
        action = np.asarray(action, dtype=np.float64)
        if action.shape != self.action_space.shape:
            raise ValueError(
                f"{self.task.name} expects an action of shape {self.action_space.shape}, got {action.shape}."
            )
        reward, success, truncated = self._sim.step(action[None])
        return self._get_obs(), float(reward[0]), False, bool(truncated[0]), {"is_success": bool(success[0])}

    def compute_reward(self, achieved_goal, desired_goal, info=None) -> np.ndarray:
        """Sparse reward of goal pairs over leading dims: ``0`` within the reward threshold, else ``-1``."""
        return self._sim.compute_reward(achieved_goal, desired_goal)

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        return self._sim.render(0, width=self.width, height=self.height, camera=OVERVIEW_CAMERA)

    def close(self) -> None:
        self._sim.close()


def register_gym_envs() -> list[str]:
    """Registers ``dhrl/<name>-v0`` for every environment (idempotent) and returns the ids, mazes first.

    Each id carries the task's episode length as ``max_episode_steps`` (Gymnasium's ``TimeLimit``).

    Examples:
        >>> from torchrl_dhrl.envs import register_gym_envs
        >>> ids = register_gym_envs()
        >>> ids[0], ids[-2:]
        ('dhrl/PointMaze-v0', ['dhrl/Reacher3D-v0', 'dhrl/UR3Obstacle-v0'])
    """
    ids = []
    for name, spec in ENVS.items():
        if spec.gym_id not in gym.registry:
            gym.register(
                id=spec.gym_id,
                entry_point="torchrl_dhrl.envs.gym_env:GymGoalEnv",
                kwargs={"task": name},
                max_episode_steps=spec.episode_length,
            )
        ids.append(spec.gym_id)
    return ids
