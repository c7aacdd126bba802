"""Frontier-based goal shifting (FGS, DHRL Algorithm 5), standalone and at each episode start of an env."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey, unravel_key
from torch import Tensor
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from torchrl_dhrl._unregistered import UnregisteredAttributes
from torchrl_dhrl.checks import checked, choice, number

from ._distance import paired_distances, pairwise_distances
from .graph_planner import GraphPlanner

__all__ = ["FGS_TRIGGERS", "FGS_WEIGHTINGS", "FrontierGoalShifting", "GoalShiftOnReset"]

FGS_WEIGHTINGS = ("path_length", "softmax", "reference")
#: When a goal counts as "already covered by the graph" (``trigger`` of :class:`FrontierGoalShifting`).
FGS_TRIGGERS = ("reachable", "near_graph")


class FrontierGoalShifting(UnregisteredAttributes, TensorDictModuleBase):
    """Moves training goals that the graph already covers to its frontier (DHRL Algorithm 5).

    Called by the recipe at the start of training episodes, batched over envs. For each env,
    when the goal ``g`` is already covered by the graph, the goal is replaced by a landmark
    sampled toward the rim of the graph, plus uniform noise ``U(-noise, noise)`` per axis.
    "Covered" is decided by ``trigger``:

    - ``"reachable"`` (default, the reference implementation's test): the graph expanded with the
      start ``s`` and the goal has a path ``s -> g``. The expansion adds edges ``s -> v`` for the
      landmarks with ``d(s -> v) < cutoff`` (no fallback), ``v -> g`` for ``d(v -> g) < cutoff``
      and ``s -> g`` when ``d(s -> g) < cutoff``.
    - ``"near_graph"`` (the paper's Algorithm 5): ``min_v d(v -> g) < cutoff`` over the landmark
      states ``v``, whether or not the start can reach those landmarks.

    Landmark weights come from the graph
    distance ``c_v`` from the episode's start state to each landmark (the planner's start
    connection rules plus the all-pairs table, :meth:`LandmarkGraph.reach_costs`):

    - ``"path_length"`` (default): ``w_v = c_v`` for reachable landmarks, ``0`` for unreachable
      ones. Far-along landmarks of the *connected* graph are favoured, which is what "frontier"
      means for exploration; landmarks the graph cannot reach (often artefacts of distances that
      are still optimistic across walls) are never proposed.
    - ``"softmax"``: ``w_v = exp(c_v / temperature)`` over reachable landmarks, a sharper focus
      on the rim (``temperature`` defaults to the cutoff).
    - ``"reference"``: the reference implementation's rule, ``w_v = c_v`` for reachable
      landmarks and ``unreachable_weight`` (5000) for unreachable ones. With path lengths of a
      few hundred steps, unreachable landmarks then take most of the probability mass.

    Rows with no positive weight (no graph, nothing reachable) keep their goal. The paper's
    text weights by ``-Q(s_0, pi(s_0, v) | v)``, a monotone function of the *direct* learned
    distance; the graph distance used here is its multi-hop counterpart, as in the reference.

    Randomness comes from ``generator`` (a :class:`torch.Generator` on the graph's device) when
    given, from the global torch RNG otherwise.

    Args:
        planner (GraphPlanner): provides the graph, the distance and the cutoff. Not registered
            as a submodule (FGS holds no state of its own).

    Keyword Args:
        noise (float): half-width of the uniform noise added per goal axis. Defaults to ``3.0``.
        weighting (str): ``"path_length"``, ``"softmax"`` or ``"reference"``. Defaults to
            ``"path_length"``.
        temperature (float, optional): softmax temperature in steps. Defaults to the cutoff.
        unreachable_weight (float): weight of unreachable landmarks for ``"reference"``.
            Defaults to ``5000.0``.
        trigger (str): ``"reachable"`` or ``"near_graph"`` (see above). Defaults to
            ``"reachable"``.
        cutoff (float, optional): "goal is in the graph" threshold. Defaults to the planner's.
        low (float or Tensor, optional): lower bound to clamp shifted goals to.
        high (float or Tensor, optional): upper bound to clamp shifted goals to.
        generator (torch.Generator, optional): the random generator.
        observation_key (NestedKey): the start state. Defaults to ``"observation"``.
        goal_key (NestedKey): the goal to shift. Defaults to ``"desired_goal"``.
        out_goal_key (NestedKey, optional): where to write the (possibly shifted) goal. Defaults
            to ``goal_key``.
        shifted_key (NestedKey): bool ``[1]`` entry telling which goals were shifted. Defaults to
            ``"goal_shifted"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_dhrl.planner import LandmarkGraph
        >>> dist = lambda s, g: (g - s[..., :2]).norm(dim=-1)
        >>> planner = GraphPlanner(LandmarkGraph(cutoff=1.5, max_landmarks=20, early_stop=0.9), dist, goal_dim=2)
        >>> xs = torch.linspace(0, 5, 51)
        >>> line = torch.stack([xs, torch.zeros_like(xs)], -1)
        >>> planner = planner.build(line, line.clone())
        >>> fgs = FrontierGoalShifting(planner, noise=0.0, generator=torch.Generator().manual_seed(0))
        >>> td = TensorDict(
        ...     observation=torch.zeros(2, 2),
        ...     desired_goal=torch.tensor([[2.5, 0.0], [20.0, 20.0]]),
        ...     batch_size=[2],
        ... )
        >>> td = fgs(td)
        >>> td["goal_shifted"].squeeze(-1).tolist()
        [True, False]
        >>> td["desired_goal"][1].tolist()
        [20.0, 20.0]
    """

    #: the planner is a plain attribute, not a submodule (it owns the graph buffers)
    _unregistered = ("planner",)

    @checked(
        noise=number(0.0),
        weighting=choice(FGS_WEIGHTINGS),
        unreachable_weight=number(0.0),
        temperature=number(0.0, low_open=True, optional=True),
        trigger=choice(FGS_TRIGGERS),
        cutoff=number(0.0, low_open=True, optional=True),
    )
    def __init__(
        self,
        planner: GraphPlanner,
        *,
        noise: float = 3.0,
        weighting: str = "path_length",
        temperature: float | None = None,
        unreachable_weight: float = 5000.0,
        trigger: str = "reachable",
        cutoff: float | None = None,
        low: float | Tensor | None = None,
        high: float | Tensor | None = None,
        generator: torch.Generator | None = None,
        observation_key: NestedKey = "observation",
        goal_key: NestedKey = "desired_goal",
        out_goal_key: NestedKey | None = None,
        shifted_key: NestedKey = "goal_shifted",
    ) -> None:
        super().__init__()
        self.planner = planner
        self.noise = float(noise)
        self.weighting = weighting
        self.trigger = trigger
        self._temperature = temperature
        self.unreachable_weight = float(unreachable_weight)
        self._cutoff = cutoff
        self.low = low
        self.high = high
        self.generator = generator
        self.observation_key = unravel_key(observation_key)
        self.goal_key = unravel_key(goal_key)
        self.out_goal_key = self.goal_key if out_goal_key is None else unravel_key(out_goal_key)
        self.shifted_key = unravel_key(shifted_key)
        self.in_keys = [self.observation_key, self.goal_key]
        self.out_keys = [self.out_goal_key, self.shifted_key]

    @property
    def planner(self) -> GraphPlanner:
        """The planner whose graph, distance and cutoff define the frontier (not a submodule).

        Assigning another :class:`GraphPlanner` takes effect at the next call.
        """
        return self.__dict__["_planner"]

    @planner.setter
    def planner(self, value: GraphPlanner) -> None:
        if not isinstance(value, GraphPlanner):
            raise TypeError(f"`planner` must be a GraphPlanner, got {type(value).__name__}.")
        self.__dict__["_planner"] = value

    @property
    def cutoff(self) -> float:
        """The "goal is already in the graph" threshold, in steps."""
        return self.planner.cutoff if self._cutoff is None else float(self._cutoff)

    @property
    def temperature(self) -> float:
        """The softmax temperature, in steps."""
        return self.cutoff if self._temperature is None else float(self._temperature)

    @torch.no_grad()
    def weights(self, states: Tensor) -> Tensor:
        """Unnormalised sampling weights ``[B, K]`` of the landmarks for start ``states[B, obs_dim]``."""
        reach = self.planner.graph.reach_costs(states, self.planner.distance)
        reachable = torch.isfinite(reach)
        if self.weighting == "path_length":
            return torch.where(reachable, reach, torch.zeros_like(reach))
        if self.weighting == "reference":
            return torch.where(reachable, reach, torch.full_like(reach, self.unreachable_weight))
        logits = torch.where(reachable, reach / self.temperature, torch.full_like(reach, -math.inf))
        # rows without any reachable landmark give NaN: zero weight (no shift)
        return torch.softmax(logits, dim=-1).nan_to_num(0.0)

    @torch.no_grad()
    def covered(self, states: Tensor, goals: Tensor) -> Tensor:
        """``[B]`` bool: which goals the graph already covers from ``states`` (see ``trigger``).

        ``states`` are ``[B, obs_dim]``, ``goals`` ``[B, goal_dim]``; all ``False`` without a graph.
        """
        planner = self.planner
        if not planner.has_graph:
            return torch.zeros(goals.shape[0], dtype=torch.bool, device=goals.device)
        cutoff = self.cutoff
        if self.trigger == "near_graph":
            return planner.distance_from_graph(goals, at_most=cutoff) < cutoff
        graph, distance = planner.graph, planner.distance
        # start -> landmark edges of the expanded graph: within the cutoff only
        to_landmarks = pairwise_distances(distance, states, graph.landmark_goals, graph.chunk_size)
        start_cost = torch.where(to_landmarks < cutoff, to_landmarks, torch.full_like(to_landmarks, math.inf))
        reach, _ = graph._reach(start_cost)  # [B, K] through the all-pairs table
        to_goal = pairwise_distances(distance, graph.landmark_states, goals, graph.chunk_size)  # [K, B]
        via_graph = (torch.isfinite(reach) & (to_goal.transpose(0, 1).to(reach.device) < cutoff)).any(-1)
        direct = paired_distances(distance, states, goals, graph.chunk_size).to(via_graph.device) < cutoff
        return (via_graph | direct).to(goals.device)

    @torch.no_grad()
    def shift(self, states: Tensor, goals: Tensor) -> tuple[Tensor, Tensor]:
        """Shifts the goals that the graph already covers.

        Args:
            states (Tensor): ``[B, obs_dim]`` episode start states.
            goals (Tensor): ``[B, goal_dim]`` goals.

        Returns:
            ``(new_goals, shifted)``: ``[B, goal_dim]`` goals and the ``[B]`` bool mask of the
            rows that were replaced.
        """
        if states.ndim != 2 or goals.ndim != 2 or states.shape[0] != goals.shape[0]:
            raise ValueError(
                "`states` [B, obs_dim] and `goals` [B, goal_dim] must be 2-D with the same B, got "
                f"{tuple(states.shape)} and {tuple(goals.shape)}."
            )
        shifted = torch.zeros(goals.shape[0], dtype=torch.bool, device=goals.device)
        if not self.planner.has_graph or goals.shape[0] == 0:
            return goals.clone(), shifted
        weights = self.weights(states)
        shifted = self.covered(states, goals) & (weights.sum(dim=-1) > 0).to(goals.device)
        new_goals = goals.clone()
        rows = shifted.nonzero().squeeze(-1)
        if rows.numel():
            picks = torch.multinomial(weights[rows], 1, generator=self.generator).squeeze(-1)
            noise = torch.rand(
                rows.numel(),
                goals.shape[-1],
                generator=self.generator,
                device=goals.device,
                dtype=goals.dtype,
            )
            candidate = self.planner.landmark_goals[picks].to(goals.dtype) + (2 * noise - 1) * self.noise
            if self.low is not None or self.high is not None:
                candidate = candidate.clamp(
                    min=self._bound(self.low, candidate), max=self._bound(self.high, candidate)
                )
            new_goals[rows] = candidate
        return new_goals, shifted

    @staticmethod
    def _bound(value, like: Tensor):
        if value is None or not isinstance(value, Tensor):
            return None if value is None else torch.full_like(like, float(value))
        return value.to(like)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Shifts ``goal_key`` for every row of ``tensordict`` (pass the rows of starting episodes)."""
        batch = tensordict.batch_size
        for key in self.in_keys:
            if tensordict.get(key, None) is None:
                raise KeyError(f"{type(self).__name__} needs {key!r} in the tensordict.")
        states = tensordict.get(self.observation_key)
        goals = tensordict.get(self.goal_key)
        num = batch.numel()
        new_goals, shifted = self.shift(
            states.reshape(num, states.shape[-1]), goals.reshape(num, goals.shape[-1])
        )
        tensordict.set(self.out_goal_key, new_goals.reshape(goals.shape))
        tensordict.set(self.shifted_key, shifted.reshape(*batch, 1))
        return tensordict


class GoalShiftOnReset(UnregisteredAttributes, Transform):
    """Env transform running :class:`~torchrl_dhrl.planner.FrontierGoalShifting` when episodes start.

    DHRL's Algorithm 6 (lines 4-7) shifts the goal of a training episode right after ``Env.reset``, once the
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
        >>> from torchrl_dhrl.planner import LandmarkGraph
        >>> dist = lambda s, g: (g - s[..., :2]).norm(dim=-1) / 0.2
        >>> graph = LandmarkGraph(cutoff=30.0, max_landmarks=10, early_stop=0.0)
        >>> planner = GraphPlanner(graph, dist, goal_dim=2)
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
