"""Frontier-based goal shifting applied inside a training environment, at each episode start."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from torchrl_dhrl._unregistered import UnregisteredAttributes
from torchrl_dhrl.planner import FrontierGoalShifting

__all__ = ["GoalShiftOnReset"]


class GoalShiftOnReset(UnregisteredAttributes, Transform):
    """Env transform running :class:`~torchrl_dhrl.planner.FrontierGoalShifting` when episodes start.

    DHRL's Algorithm 2 shifts the goal of a training episode right after ``Env.reset``, once the
    graph covers the real goal. This transform does it inside the environment so that a
    :class:`~torchrl.collectors.Collector` (which resets envs itself) applies FGS to every new
    episode: on reset it calls ``fgs`` on the fresh observation and goal of the envs being reset,
    holds the resulting goal in the tensordict under ``held_goal_key`` (per env, so batched envs,
    collectors and checkpoints need no Python-side state) and rewrites ``goal_key`` with it at every
    step of the episode. Whether a goal was shifted is reported under ``shifted_key``. Without a
    graph nothing is shifted. The base env keeps its own goal: its ``is_success`` and reward refer
    to the real goal, while the agent (and the replay buffers, which recompute rewards from goals)
    sees the shifted one.

    Args:
        fgs (FrontierGoalShifting): the goal-shifting module (it reads ``observation`` and the goal).
            A plain attribute, not a submodule (the planner and its graph are owned elsewhere);
            assigning ``transform.fgs`` replaces it.

    Keyword Args:
        goal_key (NestedKey): the goal entry. Defaults to ``"desired_goal"``.
        held_goal_key (NestedKey): where the episode's goal is held. Defaults to ``"episode_goal"``.
        shifted_key (NestedKey): bool ``[1]`` entry, ``True`` for shifted episodes. Defaults to
            ``"goal_shifted"``.

    Examples:
        >>> import torch
        >>> from torchrl.envs import TransformedEnv
        >>> from torchrl_dhrl.envs import make_env
        >>> from torchrl_dhrl.planner import FrontierGoalShifting, GraphPlanner
        >>> dist = lambda s, g: (g - s[..., :2]).norm(dim=-1) / 0.2
        >>> planner = GraphPlanner(dist, goal_dim=2, cutoff=30.0, max_landmarks=10, early_stop=0.0)
        >>> env = TransformedEnv(make_env("PointMaze", num_envs=2, seed=0),
        ...     GoalShiftOnReset(FrontierGoalShifting(planner)))
        >>> td = env.reset()  # no graph yet: goals are kept
        >>> td["goal_shifted"].any().item(), torch.equal(td["episode_goal"], td["desired_goal"])
        (False, True)
    """

    #: a plain attribute, not a submodule: the planner (and its graph) is owned elsewhere
    _unregistered = ("fgs",)

    def __init__(
        self,
        fgs: FrontierGoalShifting,
        *,
        goal_key: NestedKey = "desired_goal",
        held_goal_key: NestedKey = "episode_goal",
        shifted_key: NestedKey = "goal_shifted",
    ) -> None:
        if not isinstance(fgs, FrontierGoalShifting):
            raise TypeError(f"`fgs` must be a FrontierGoalShifting, got {type(fgs).__name__}.")
        super().__init__(in_keys=[goal_key], out_keys=[held_goal_key, shifted_key])
        self.fgs = fgs
        self.goal_key = goal_key
        self.held_goal_key = held_goal_key
        self.shifted_key = shifted_key

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        goal = tensordict_reset.get(self.goal_key)
        query = tensordict_reset.select(self.fgs.observation_key, self.goal_key).clone()
        query = self.fgs(query)
        shifted = query.get(self.fgs.shifted_key).reshape(*goal.shape[:-1], 1)
        new_goal = query.get(self.goal_key).to(goal.dtype)
        reset = tensordict.get("_reset", None) if tensordict is not None else None
        if reset is not None and tensordict.get(self.held_goal_key, None) is not None:
            reset = reset.reshape(*goal.shape[:-1], 1)
            new_goal = torch.where(reset, new_goal, tensordict.get(self.held_goal_key))
            shifted = torch.where(reset, shifted, tensordict.get(self.shifted_key))
        tensordict_reset.set(self.goal_key, new_goal)
        tensordict_reset.set(self.held_goal_key, new_goal.clone())
        tensordict_reset.set(self.shifted_key, shifted)
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        held = tensordict.get(self.held_goal_key)
        next_tensordict.set(self.goal_key, held)
        next_tensordict.set(self.held_goal_key, held)
        next_tensordict.set(self.shifted_key, tensordict.get(self.shifted_key))
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return tensordict

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        goal_spec = observation_spec[self.goal_key]
        shape = goal_spec.shape
        observation_spec[self.goal_key] = Unbounded(
            shape=shape, dtype=goal_spec.dtype, device=goal_spec.device
        )
        observation_spec[self.held_goal_key] = Unbounded(
            shape=shape, dtype=goal_spec.dtype, device=goal_spec.device
        )
        observation_spec[self.shifted_key] = Unbounded(
            shape=(*shape[:-1], 1), dtype=torch.bool, device=goal_spec.device
        )
        return observation_spec
