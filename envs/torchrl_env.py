"""Native batched TorchRL environment of every DHRL task (the mazes and the arms)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from .goal_env import GoalEnvError, check_goal_env
from .gymnasium_goal_env import GymnasiumGoalEnv, gymnasium_id
from .registry import get_env_factory, get_env_spec
from .simulation import GoalSimulation
from .task import OVERVIEW_CAMERA, TaskSpec

__all__ = ["GoalEnv", "make_env"]


class GoalEnv(EnvBase):
    """A batch of ``num_envs`` DHRL episodes as one TorchRL environment (``batch_size=[num_envs]``).

    One MuJoCo model and ``num_envs`` MjData are stepped in a plain loop by the shared
    :class:`~torchrl_dhrl.envs.GoalSimulation` core (simulated in float64); this class only converts actions
    in and float32 tensors out, which keeps TorchRL's per-step overhead amortised over the batch. Every
    task (the five mazes, Reacher3D and UR3Obstacle) has the same keys; only their sizes differ.

    Keys (all with leading dim ``num_envs``):

    * ``"observation"`` float32 ``[obs_dim]``: mazes ``qpos ++ qvel`` (29 for the ant, 6 for the point),
      Reacher3D ``qpos ++ goal ++ qvel`` (17), UR3Obstacle ``flange position ++ qpos ++ qvel`` (15).
    * ``"achieved_goal"`` float32 ``[goal_dim]``: a maze agent's (x, y) (``observation[..., :2]``) or an
      arm's end-effector position (``goal_dim = 3``; UR3Obstacle: ``observation[..., :3]``).
    * ``"desired_goal"`` float32 ``[goal_dim]``: the episode's goal.
    * ``"is_success"`` bool ``[1]``: within the evaluation threshold of the goal (DHRL scores the final
      state of an episode).
    * ``"step_count"`` int64 ``[1]``: the step index within the episode, ``0`` at reset.
    * ``"reward"`` float32 ``[1]``: sparse, ``0`` within ``reward_threshold`` of the goal (0.5 in the mazes,
      0.25 for Reacher3D, 0.08 for UR3Obstacle), else ``-1``.
    * ``"done"``, ``"terminated"``, ``"truncated"`` bool ``[1]``: the only end of an episode is the time limit:
      ``truncated`` at ``max_episode_steps``, ``terminated`` is always ``False`` and ``done == truncated``.

    Resets honour the ``"_reset"`` mask (partial resets leave the other envs untouched). A reset tensordict
    carrying a ``"desired_goal"`` entry sets the goals of the envs being reset explicitly (they must lie
    inside the goal bounds); TorchRL's automatic resets (``rollout``, collectors) never pass it, so they draw
    fresh goals. A :class:`~torchrl.envs.TransformedEnv` forwards only reset and state keys to its base env,
    so it drops that entry (goals are deliberately not state keys: automatic resets would then reuse the old
    goal); build the env with ``eval=True`` for the fixed test goals, or reset the base env. A ``"start"`` entry
    (``[num_envs, goal_dim]``, the mazes only) moves the agents' reset pose to those positions, e.g. for a reach
    test from anywhere in the maze; it must leave the agent's body clear of the walls. Episodes of different envs
    stay distinguishable in collected data through
    ``"step_count"`` and the collectors' ``("collector", "traj_ids")``.

    Seeding: :meth:`set_seed` spawns one numpy RNG stream per env (reset noise and goals); the RNG state
    lives in the env object. The same seed gives the same first observation and the same rollout under the
    same actions.

    Args:
        task (str or TaskSpec): one of :data:`~torchrl_dhrl.envs.ENV_NAMES` (or ``"dhrl/<name>-v0"``).

    Keyword Args:
        num_envs (int): number of parallel episodes. Defaults to ``1``.
        max_episode_steps (int, optional): time limit; defaults to the task's episode length.
        eval_goals (bool): draw test goals instead of train goals. Defaults to ``False``.
            Can be changed later through the :attr:`eval_goals` attribute.
        device (torch.device, optional): device of the output tensors. Defaults to CPU.
        seed (int, optional): seed passed to :meth:`set_seed`.
        right_flipped_after (int, optional): ant mazes only: put a flipped ant back on its feet after this
            many consecutive env steps upside down (see :class:`~torchrl_dhrl.envs.GoalSimulation`).
            Defaults to ``None``: never, as the reference.
        reference_engine (bool): ant mazes only: emulate MuJoCo 2.0 where MuJoCo 3 differs (0.01 margin per
            contact, MuJoCo 2.0's capsule masses and inertias; see :class:`~torchrl_dhrl.envs.AntAgent`).
            Defaults to ``False``.
        step_threads (int): threads stepping the envs in groups (MuJoCo releases the GIL); the same transitions
            as one thread (see :class:`~torchrl_dhrl.envs.GoalSimulation`). Defaults to ``1``.

    Examples:
        >>> import torch
        >>> from torchrl.envs.utils import check_env_specs
        >>> from torchrl_dhrl.envs import GoalEnv
        >>> env = GoalEnv("AntMazeSmall", num_envs=3, seed=0, max_episode_steps=5)
        >>> check_env_specs(env)
        >>> rollout = env.rollout(6, break_when_any_done=False)
        >>> rollout["observation"].shape, rollout["next", "step_count"][0, :, 0].tolist()
        (torch.Size([3, 6, 29]), [1, 2, 3, 4, 5, 1])
        >>> td = env.reset(env.reset().set("desired_goal", torch.tensor([[0.0, 8.0]]).expand(3, 2)))
        >>> td["desired_goal"][:, 1].tolist()
        [8.0, 8.0, 8.0]
        >>> arm = GoalEnv("UR3Obstacle", num_envs=2, seed=0)
        >>> td = arm.reset()
        >>> td["observation"].shape, td["achieved_goal"].shape
        (torch.Size([2, 15]), torch.Size([2, 3]))
        >>> bool((td["achieved_goal"] == td["observation"][:, :3]).all())
        True
    """

    def __init__(
        self,
        task: str | TaskSpec,
        *,
        num_envs: int = 1,
        max_episode_steps: int | None = None,
        eval_goals: bool = False,
        device=None,
        seed: int | None = None,
        right_flipped_after: int | None = None,
        reference_engine: bool = False,
        step_threads: int = 1,
    ) -> None:
        spec = get_env_spec(task)
        sim = GoalSimulation(
            spec,
            num_envs,
            max_episode_steps=max_episode_steps,
            eval_goals=eval_goals,
            right_flipped_after=right_flipped_after,
            reference_engine=reference_engine,
            step_threads=step_threads,
        )
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        self._sim = sim
        self._make_specs()
        if seed is not None:
            self.set_seed(seed)

    # ------------------------------------------------------------------ attributes
    @property
    def task(self) -> TaskSpec:
        """The spec of this environment (:class:`~torchrl_dhrl.envs.MazeSpec` or
        :class:`~torchrl_dhrl.envs.ArmSpec`)."""
        return self._sim.spec

    @property
    def simulation(self) -> GoalSimulation:
        """The underlying batched simulation core (float64 numpy state)."""
        return self._sim

    @property
    def num_envs(self) -> int:
        """Number of parallel episodes."""
        return self._sim.num_envs

    @property
    def max_episode_steps(self) -> int:
        """Time limit in env steps."""
        return self._sim.max_episode_steps

    @property
    def eval_goals(self) -> bool:
        """Whether resets draw test goals (``True``) or train goals (``False``)."""
        return self._sim.eval_goals

    @eval_goals.setter
    def eval_goals(self, value: bool) -> None:
        self._sim.eval_goals = bool(value)

    def _make_specs(self) -> None:
        shape = self.batch_size
        sim, device, dim = self._sim, self.device, self._sim.goal_dim
        low, high = (torch.as_tensor(bound, dtype=torch.float32) for bound in sim.spec.goal_bounds)
        self.observation_spec = Composite(
            observation=Unbounded(shape=(*shape, sim.obs_dim), dtype=torch.float32, device=device),
            achieved_goal=Unbounded(shape=(*shape, dim), dtype=torch.float32, device=device),
            desired_goal=Bounded(
                low=low.expand(*shape, dim),
                high=high.expand(*shape, dim),
                shape=(*shape, dim),
                dtype=torch.float32,
                device=device,
            ),
            is_success=Categorical(2, shape=(*shape, 1), dtype=torch.bool, device=device),
            step_count=Bounded(
                low=0, high=sim.max_episode_steps, shape=(*shape, 1), dtype=torch.int64, device=device
            ),
            shape=shape,
            device=device,
        )
        action_low = torch.as_tensor(sim.agent.action_low, dtype=torch.float32)
        action_high = torch.as_tensor(sim.agent.action_high, dtype=torch.float32)
        self.action_spec = Bounded(
            low=action_low.expand(*shape, sim.action_dim),
            high=action_high.expand(*shape, sim.action_dim),
            shape=(*shape, sim.action_dim),
            dtype=torch.float32,
            device=device,
        )
        self.reward_spec = Bounded(low=-1.0, high=0.0, shape=(*shape, 1), dtype=torch.float32, device=device)
        self.done_spec = Composite(
            done=Categorical(2, shape=(*shape, 1), dtype=torch.bool, device=device),
            terminated=Categorical(2, shape=(*shape, 1), dtype=torch.bool, device=device),
            truncated=Categorical(2, shape=(*shape, 1), dtype=torch.bool, device=device),
            shape=shape,
            device=device,
        )

    # ------------------------------------------------------------------ conversions
    def _tensor(self, array: np.ndarray, dtype: torch.dtype) -> torch.Tensor:
        # ``.to(dtype)`` copies when the dtype changes; same-dtype arrays are copied explicitly since the
        # simulation reuses its buffers.
        tensor = torch.from_numpy(array)
        tensor = tensor.to(dtype) if tensor.dtype != dtype else tensor.clone()
        return tensor if self.device is None or self.device.type == "cpu" else tensor.to(self.device)

    def _observations(self, success: np.ndarray) -> dict[str, torch.Tensor]:
        sim = self._sim
        return {
            "observation": self._tensor(sim.observation, torch.float32),
            "achieved_goal": self._tensor(sim.achieved_goal, torch.float32),
            "desired_goal": self._tensor(sim.desired_goal, torch.float32),
            "is_success": self._tensor(success[:, None], torch.bool),
            "step_count": self._tensor(sim.step_count[:, None], torch.int64),
        }

    # ------------------------------------------------------------------ EnvBase API
    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action")
        if action.shape != self.action_spec.shape:
            raise ValueError(
                f"{self.task.name} expects an 'action' of shape {tuple(self.action_spec.shape)} "
                f"(num_envs, action_dim), got {tuple(action.shape)}."
            )
        reward, success, truncated = self._sim.step(action.detach().cpu().numpy())
        out = self._observations(success)
        truncated = self._tensor(truncated[:, None], torch.bool)
        out["reward"] = self._tensor(reward[:, None], torch.float32)
        out["done"] = truncated.clone()  # no terminal states: done == truncated (distinct tensors)
        out["truncated"] = truncated
        out["terminated"] = torch.zeros_like(truncated)
        return TensorDict(out, batch_size=self.batch_size, device=self.device)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = goals = starts = None
        if tensordict is not None:
            reset = tensordict.get("_reset", None)
            if reset is not None:
                mask = reset.reshape(self.batch_size).cpu().numpy()
            goals, starts = (self._reset_entry(tensordict, key, mask) for key in ("desired_goal", "start"))
        self._sim.reset(mask, goals, starts=starts)
        _, success = self._sim.evaluate()
        out = self._observations(success)
        done = torch.zeros((*self.batch_size, 1), dtype=torch.bool, device=self.device)
        out.update(done=done, terminated=done.clone(), truncated=done.clone())
        return TensorDict(out, batch_size=self.batch_size, device=self.device)

    def _reset_entry(self, tensordict: TensorDictBase, key: str, mask) -> np.ndarray | None:
        """A ``[*batch, goal_dim]`` entry of a reset tensordict as numpy, the rows of the envs being reset."""
        value = tensordict.get(key, None)
        if value is None:
            return None
        expected = (*self.batch_size, self._sim.goal_dim)
        if value.shape != expected:
            raise ValueError(
                f"A '{key}' passed to reset must have shape {expected}, got {tuple(value.shape)}."
            )
        value = value.detach().cpu().numpy()
        return value if mask is None else value[mask]

    def _set_seed(self, seed: int | None) -> None:
        self._sim.seed(seed)

    def get_extra_state(self) -> dict:
        """The simulation's exact state (physics, goals, step counts, RNG streams), saved by ``state_dict()``.

        ``env.load_state_dict(env.state_dict())`` then continues every episode, and every future reset,
        exactly as the saved env would have (the training recipe's resume relies on it).
        """
        return self._sim.get_state()

    def set_extra_state(self, state: dict) -> None:
        self._sim.set_full_state(state)

    def render(
        self, env_index: int = 0, *, width: int = 480, height: int = 480, camera: str | int = OVERVIEW_CAMERA
    ) -> torch.Tensor:
        """Offscreen RGB frame (uint8 ``[height, width, 3]``) of env ``env_index`` through MuJoCo's renderer.

        Needs an OpenGL backend (``MUJOCO_GL=egl`` or ``osmesa``). The default camera shows the whole scene
        (a maze from above, an arm obliquely); ``"ant/track"`` or ``"point/track"`` follow a maze agent.
        """
        return torch.from_numpy(self._sim.render(env_index, width=width, height=height, camera=camera).copy())

    def close(self, *, raise_if_closed: bool = True) -> None:
        self._sim.close()
        super().close(raise_if_closed=raise_if_closed)


def make_env(
    name: str,
    *,
    num_envs: int = 1,
    seed: int | None = None,
    device=None,
    eval: bool = False,  # noqa: A002 - the documented option name
    max_episode_steps: int | None = None,
    right_flipped_after: int | None = None,
    reference_engine: bool = False,
    step_threads: int = 1,
    env_kwargs: Mapping[str, Any] | None = None,
) -> EnvBase:
    """Builds a DHRL environment as a native batched TorchRL environment.

    Args:
        name (str): ``"PointMaze"``, ``"AntMazeSmall"``, ``"AntMaze"``, ``"AntMazeBottleneck"``,
            ``"AntMazeComplex"``, ``"Reacher3D"`` or ``"UR3Obstacle"`` (the Gymnasium ids
            ``"dhrl/<name>-v0"`` are accepted too), or the name of an env registered with
            :func:`~torchrl_dhrl.envs.register_env`: its factory is called with the keyword arguments
            below and the env it returns is checked against the goal-env contract
            (:func:`~torchrl_dhrl.envs.check_goal_env` on the specs, batch size ``[num_envs]``); or
            ``"gymnasium:<id>"``, any registered Gymnasium goal env (:class:`~torchrl_dhrl.envs.GymnasiumGoalEnv`).

    Keyword Args:
        num_envs (int): batch size of the env. Defaults to ``1``.
        seed (int, optional): seed of the per-env RNG streams.
        device (torch.device, optional): device of the output tensors.
        eval (bool): use the test goals (mazes: the fixed test goals, AntMazeComplex one of its four per
            episode; Reacher3D: the train distribution; UR3Obstacle: goals inside the bin, behind the
            fence). Defaults to ``False`` (train goals).
        max_episode_steps (int, optional): time limit override (defaults to the paper's episode length).
        right_flipped_after (int, optional): ant mazes only (the built-in ones and gymnasium-robotics'
            ``AntMaze_*``): put a flipped ant back on its feet after this many consecutive env steps upside down.
            Defaults to ``None`` (never, as the reference and the Gymnasium envs).
        reference_engine (bool): built-in ant mazes only: emulate MuJoCo 2.0 where MuJoCo 3 differs: every
            geom of the scene gets a 0.005 margin (0.01 per contact, as the reference's MuJoCo 2.0, which took
            the larger of the two margins where MuJoCo 3 adds them) and the leg capsules MuJoCo 2.0's masses and
            inertias (a cylinder ``radius`` longer; the ant weighs 0.879 instead of 0.911). The env is built from
            the spec with ``agent=dataclasses.replace(agent, reference_engine=True)``. Defaults to ``False``.
        step_threads (int): built-in envs only: threads stepping the envs in groups, the same transitions as
            one thread (:class:`~torchrl_dhrl.envs.GoalSimulation`). Defaults to ``1``.
        env_kwargs (dict, optional): ``"gymnasium:<id>"`` only: keyword arguments of
            :class:`~torchrl_dhrl.envs.GymnasiumGoalEnv` (``reset_options``, ``success_threshold``,
            ``make_kwargs``). Defaults to ``None``.

    Raises:
        ValueError: for an unknown name; the message lists the valid ones; for ``right_flipped_after``
            or ``reference_engine`` with an env that has no ant.
        GoalEnvError: when a registered factory returns an env that does not meet the contract.

    Examples:
        >>> from torchrl_dhrl.envs import make_env
        >>> env = make_env("AntMaze", num_envs=2, seed=0, eval=True)
        >>> env.reset()["desired_goal"].tolist()
        [[0.0, 16.0], [0.0, 16.0]]
        >>> make_env("Reacher3D", seed=0).rollout(3)["next", "achieved_goal"].shape
        torch.Size([1, 3, 3])
    """
    env_id = gymnasium_id(name)
    if step_threads != 1 and (env_id is not None or get_env_factory(name) is not None):
        raise ValueError(f"step_threads is an option of the built-in envs, not of {name!r}; leave it at 1.")
    if env_kwargs and env_id is None:
        raise ValueError(f"env_kwargs are options of the Gymnasium goal envs (gymnasium:<id>), not of {name!r}.")
    if env_id is not None:
        if reference_engine:
            raise ValueError(f"reference_engine is an option of the built-in ant mazes, not of {name!r}.")
        kwargs = dict(env_kwargs or {})
        if right_flipped_after is not None:
            kwargs["right_flipped_after"] = right_flipped_after
        env = GymnasiumGoalEnv(env_id, num_envs, seed=seed, device=device, max_episode_steps=max_episode_steps, **kwargs)
        check_goal_env(env, steps=0)
        return env
    factory = get_env_factory(name)
    if factory is not None:
        if right_flipped_after is not None:
            raise ValueError(
                f"right_flipped_after is an option of the built-in ant mazes, not of the registered env {name!r}."
            )
        if reference_engine:
            raise ValueError(
                f"reference_engine is an option of the built-in ant mazes, not of the registered env {name!r}."
            )
        env = factory(
            num_envs=num_envs, seed=seed, device=device, eval=eval, max_episode_steps=max_episode_steps
        )
        if not isinstance(env, EnvBase):
            raise TypeError(
                f"The factory registered as {name!r} returned a {type(env).__name__}, not an EnvBase."
            )
        if tuple(env.batch_size) != (num_envs,):
            raise GoalEnvError(
                f"The factory registered as {name!r} returned an env of batch_size {tuple(env.batch_size)} "
                f"for num_envs={num_envs}; expected ({num_envs},) (see docs/goal_env.md)."
            )
        check_goal_env(env, steps=0)
        return env
    return GoalEnv(
        name,
        num_envs=num_envs,
        max_episode_steps=max_episode_steps,
        eval_goals=eval,
        device=device,
        seed=seed,
        right_flipped_after=right_flipped_after,
        reference_engine=reference_engine,
        step_threads=step_threads,
    )
