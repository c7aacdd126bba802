"""GraphPlanner: the non-parametric middle level of DHRL as a TorchRL transform."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey, unravel_key
from torch import Tensor
from torchrl.data import Composite, Unbounded
from torchrl.envs import TensorDictPrimer
from torchrl.envs.transforms import Transform

from torchrl_dhrl._unregistered import UnregisteredAttributes, callable_attribute
from torchrl_dhrl.checks import checked, integer, number

from ._distance import check_supports_autocast
from .distances import TemporalDistance
from .graph import GraphPlan, GraphTensors, LandmarkGraph


def _capturing_cuda_graph(device: torch.device) -> bool:
    """Whether the current CUDA stream is being captured into a CUDA graph (no host read allowed)."""
    return device.type == "cuda" and torch.cuda.is_current_stream_capturing()


#: Per-env tracking entries stored under ``state_key`` (all with a trailing feature dim).
STATE_ENTRIES = ("path", "path_length", "budgets", "index", "steps", "truncated", "has_plan", "graph_version")


class GraphPlanner(UnregisteredAttributes, Transform):
    """Plans waypoints from the current state to the subgoal on a landmark graph and tracks them.

    The graph level of DHRL (Lee et al., 2022, Section 4.1 and Algorithm 3). Each call reads the
    current ``observation``, ``achieved_goal``, ``subgoal`` and ``new_subgoal`` and writes the
    ``waypoint`` the low-level policy should chase now:

    - **plan** (when ``new_subgoal`` is ``True``, when the env has no plan yet, e.g. after a reset,
      when the graph was rebuilt since the plan was made, or when a truncated path is used up):
      the shortest waypoint sequence ``(landmark_1, ..., landmark_k, subgoal)`` through the graph
      (see :meth:`LandmarkGraph.plan`; unreachable subgoals fall back to the reachable landmark
      nearest to the subgoal, then the subgoal; without a graph the subgoal is the waypoint);
    - **track** (every other call): one more step is spent on the current waypoint; it is passed
      when ``||achieved_goal - waypoint|| <= reach_radius`` or when the steps spent on it exceed
      the estimated length of the edge leading to it. After the last landmark the subgoal itself
      is chased.

    All per-env tracking state lives in the tensordict under ``state_key`` (``"planner"``):
    ``path`` (landmark indices, ``[max_path_length]``), ``path_length``, ``budgets`` (steps
    allowed per hop, ``[max_path_length + 1]``), ``index`` (current waypoint), ``steps`` (spent on
    it), ``truncated``, ``has_plan`` and ``graph_version``. Nothing per-env is kept in Python, so
    the planner works for any batch shape and survives ``step_mdp``, collectors, batched envs and
    checkpoints. The planner is composed of a :class:`LandmarkGraph` (``graph``, a registered
    submodule: landmarks, distance matrix, edges, all-pairs distances and next-hop table, all
    buffers, so ``state_dict()`` round-trips it) and a :class:`TemporalDistance` (``distance``, a
    plain attribute). How the graph is built (cutoff, FPS settings, the edge rule, reduced-precision
    building) is the graph's business; the planner adds the tracking of waypoints.

    **Why a** :class:`~torchrl.envs.transforms.Transform`: a transform is an ``nn.Module`` with
    ``in_keys``/``out_keys`` and a ``forward(tensordict)``, so the same object serves in the three
    places DHRL needs it:

    1. *In the acting policy* (recommended when the high-level actor is part of the policy):
       ``TensorDictSequential(high_actor, planner, low_actor)`` calls :meth:`forward`, so the
       waypoint of step ``t`` uses the subgoal issued at step ``t``. Append
       :meth:`make_tensordict_primer` to the env: a :class:`~torchrl.envs.TensorDictPrimer` resets
       the tracking state at reset and
       carries it from ``t`` to ``t + 1`` (its ``_step`` copies the root entries into ``"next"``,
       then ``step_mdp`` moves them back to the root; verified with ``env.rollout`` and
       :class:`~torchrl.collectors.Collector` in torchrl 0.14.1).
    2. *As an env transform*: ``TransformedEnv(env, Compose(..., planner))``. At reset and after
       every step (:meth:`_step` reads the previous state from the root tensordict and the new
       observation from ``"next"``) it writes ``waypoint`` and the tracking state as
       observations. The subgoal must then be in ``"next"`` too, written by a previous transform
       or carried by a primer; a subgoal issued by the *policy* at step ``t`` takes effect at
       ``t + 1`` in this mode. Append the planner to the outer (batched) env so the graph stays
       in the main process where it is rebuilt.
    3. *Standalone*: ``planner(td)`` on any tensordict with the input keys, e.g. in tests or
       inside a replay buffer (``rb.append_transform(planner)``), where each sampled transition
       is advanced by one tracking step from its stored state with the current graph (it replans
       the transitions whose stored ``graph_version`` is stale). That is mechanical rather than
       useful for learning: DHRL relabels the low-level goals instead.

    Args:
        graph (LandmarkGraph): the landmark graph to build and plan on, with its settings (``cutoff``,
            ``max_landmarks``, ``early_stop``, ``edge_rule``, ``build_autocast_dtype``, ...). Registered
            as a submodule: ``state_dict()`` holds it and ``.to()`` moves it.
        distance (TemporalDistance): ``distance(states[..., obs_dim], goals[..., goal_dim]) ->
            steps[...]``, e.g. :class:`GoalDistance` (the learned graph-critic distance),
            :class:`LineOfSightDistance` (an oracle) or any callable, an ``nn.Module`` included. It is
            not registered as a submodule (its parameters belong to the learner): it is not part of
            ``state_dict()`` or ``parameters()``, ``.to()`` does not move it, and assigning
            ``planner.distance`` replaces it for the next build and query. With the graph's
            ``build_autocast_dtype`` set, it needs ``with_autocast`` (:class:`AutocastDistance`).
        goal_dim (int): the size of goals, subgoals and waypoints.

    Keyword Args:
        reach_radius (float): a waypoint counts as reached within this Euclidean distance in goal
            space. Defaults to ``0.5``.
        max_path_length (int): landmarks stored per plan; a longer path is cut and replanned
            (from the state reached) once its stored part is used up. Defaults to ``32``.
        capturable (bool): track and plan with tensor operations of static shapes only: every env
            is planned (:meth:`LandmarkGraph.plan` with ``capturable=True``) and the new plans are kept
            where a replan is due, instead of planning only those rows behind a host-side branch (``nonzero``).
            The waypoints and tracking state are the same; the acting policy then compiles whole
            (``torch.compile(fullgraph=True)``, e.g. the collector's ``compile_policy``). A planning query
            costs ``O(K^2)`` per env on top of ``2 K`` distance evaluations (``K`` landmarks); with
            ``plan_on_demand`` (the default) it runs only in the calls where some env is due for a replan, and
            the compiled policy is then faster than the eager one on a CPU too (``benchmarks/bench_acting.py``).
            With a ``fixed_size`` graph
            (``LandmarkGraph(fixed_size=True)``) it plans and reads waypoints from the graph's fixed-size
            copies: the same shapes and storage after every rebuild, so the compiled policy is not
            recompiled when the number of landmarks changes and a CUDA graph captured after the first
            build stays valid. Defaults to ``False``.
        plan_on_demand (bool): with ``capturable=True``, plan (every env) only in the calls where some env is
            due for a replan: under ``torch.compile`` through :func:`torch.cond` (one graph; its predicate is
            read on the host when the branch runs), eagerly through a Python branch. Most calls then only track
            (a replan is due once per subgoal, every ``c_h`` steps), which makes the compiled policy cheaper than
            the eager one on a CPU. ``False`` plans at every call: static control flow, no host read, e.g. for a
            policy captured whole in a CUDA graph (an eager ``torch.cuda.graph`` capture always plans at every
            call). The waypoints and tracking state are the same either way. Defaults to ``True``.
        observation_key (NestedKey): Defaults to ``"observation"``.
        achieved_goal_key (NestedKey): Defaults to ``"achieved_goal"``.
        subgoal_key (NestedKey): Defaults to ``"subgoal"``.
        new_subgoal_key (NestedKey): a bool ``[1]`` entry; when absent from the input, only the
            other replanning triggers apply. Defaults to ``"new_subgoal"``.
        waypoint_key (NestedKey): Defaults to ``"waypoint"``.
        state_key (NestedKey): prefix of the tracking entries. Defaults to ``"planner"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> # distances count env steps (the planner gives each waypoint that many steps to be reached): this one
        >>> # is an agent that moves one goal unit per step; a slower agent's is the length divided by its speed
        >>> dist = lambda s, g: (g - s[..., :2]).norm(dim=-1)
        >>> graph = LandmarkGraph(cutoff=1.5, max_landmarks=20, early_stop=0.9)
        >>> planner = GraphPlanner(graph, dist, goal_dim=2)
        >>> xs = torch.linspace(0, 5, 51)
        >>> candidates = torch.stack([xs, torch.zeros_like(xs)], -1)
        >>> planner = planner.build(candidates, candidates.clone())
        >>> td = TensorDict(
        ...     observation=torch.zeros(3, 2),
        ...     achieved_goal=torch.zeros(3, 2),
        ...     subgoal=torch.tensor([[5.0, 0.0]]).expand(3, 2),
        ...     new_subgoal=torch.ones(3, 1, dtype=torch.bool),
        ...     batch_size=[3],
        ... )
        >>> td = planner(td)
        >>> td["waypoint"][0].tolist(), td["planner", "path_length"][0].item()
        ([0.0, 0.0], 5)
        >>> [round(x, 1) for x in planner.planned_path(td, 0)[:, 0].tolist()]  # landmarks, then the subgoal
        [0.0, 1.2, 2.5, 3.7, 5.0, 5.0]
    """

    #: plain attributes, never registered as submodules (see ``torchrl_dhrl._unregistered``)
    _unregistered = ("distance",)

    @checked(
        goal_dim=integer(1),
        reach_radius=number(0.0, low_open=True),
        max_path_length=integer(1),
    )
    def __init__(
        self,
        graph: LandmarkGraph,
        distance: TemporalDistance,
        goal_dim: int,
        *,
        reach_radius: float = 0.5,
        max_path_length: int = 32,
        capturable: bool = False,
        plan_on_demand: bool = True,
        observation_key: NestedKey = "observation",
        achieved_goal_key: NestedKey = "achieved_goal",
        subgoal_key: NestedKey = "subgoal",
        new_subgoal_key: NestedKey = "new_subgoal",
        waypoint_key: NestedKey = "waypoint",
        state_key: NestedKey = "planner",
    ) -> None:
        if not isinstance(graph, LandmarkGraph):
            raise TypeError(
                "`graph` must be a LandmarkGraph, e.g. GraphPlanner(LandmarkGraph(cutoff=30.0, "
                f"max_landmarks=300), distance, goal_dim), got {type(graph).__name__}."
            )
        self.observation_key = unravel_key(observation_key)
        self.achieved_goal_key = unravel_key(achieved_goal_key)
        self.subgoal_key = unravel_key(subgoal_key)
        self.new_subgoal_key = unravel_key(new_subgoal_key)
        self.waypoint_key = unravel_key(waypoint_key)
        prefix = self.state_key = unravel_key(state_key)
        self._state_keys = {
            name: unravel_key((prefix, name) if isinstance(prefix, str) else (*prefix, name))
            for name in STATE_ENTRIES
        }
        state_keys = list(self._state_keys.values())
        super().__init__(
            in_keys=[
                self.observation_key,
                self.achieved_goal_key,
                self.subgoal_key,
                self.new_subgoal_key,
                *state_keys,
            ],
            out_keys=[self.waypoint_key, *state_keys],
        )
        self.goal_dim = goal_dim
        self.reach_radius = float(reach_radius)
        if not isinstance(capturable, bool):
            raise TypeError(f"`capturable` must be a bool, got {capturable!r}.")
        if not isinstance(plan_on_demand, bool):
            raise TypeError(f"`plan_on_demand` must be a bool, got {plan_on_demand!r}.")
        self.plan_on_demand = plan_on_demand
        self.max_path_length = max_path_length
        self.capturable = capturable
        self.graph = graph
        self.distance = distance
        check_supports_autocast(distance, graph.build_autocast_dtype)

    # ------------------------------------------------------------------ distance and graph
    # stored outside nn.Module registration (`_unregistered` routes assignments of an nn.Module here too):
    # the learner owns (and checkpoints) its parameters
    distance = callable_attribute(
        "distance",
        "(states, goals) -> steps",
        """The temporal distance used to build and query the graph (not a registered submodule).

        Any :class:`TemporalDistance` ``distance(states, goals) -> steps``, an ``nn.Module`` included;
        assigning a new one takes effect at the next :meth:`build` or query.
        """,
    )

    @property
    def cutoff(self) -> float:
        """The edge / connection threshold in steps."""
        return self.graph.cutoff

    @property
    def has_graph(self) -> bool:
        """Whether a graph with at least one landmark exists."""
        return self.graph.has_graph

    @property
    def num_landmarks(self) -> int:
        """The number of landmarks of the current graph."""
        return self.graph.num_landmarks

    @property
    def landmark_states(self) -> Tensor:
        """``[K, obs_dim]`` landmark states."""
        return self.graph.landmark_states

    @property
    def landmark_goals(self) -> Tensor:
        """``[K, goal_dim]`` landmark goals (e.g. for plotting)."""
        return self.graph.landmark_goals

    @property
    def edges(self) -> Tensor:
        """``[E, 2]`` directed edges as landmark index pairs (e.g. for plotting)."""
        return self.graph.edges

    @property
    def edge_costs(self) -> Tensor:
        """``[E]`` estimated steps of :attr:`edges`."""
        return self.graph.edge_costs

    def build(self, candidate_states: Tensor, candidate_goals: Tensor) -> GraphPlanner:
        """Rebuilds the graph from scratch (once per epoch in DHRL) with the current distance.

        Args:
            candidate_states (Tensor): ``[N, obs_dim]`` states (the reference samples 6000 from the
                low-level replay buffer).
            candidate_goals (Tensor): ``[N, goal_dim]`` their achieved goals.

        Every env replans at its next step (its stored ``graph_version`` is then stale).
        """
        if candidate_goals.ndim != 2 or candidate_goals.shape[-1] != self.goal_dim:
            raise ValueError(
                f"`candidate_goals` must be [N, {self.goal_dim}], got {tuple(candidate_goals.shape)}."
            )
        self.graph.build(candidate_states, candidate_goals, self.distance)
        return self

    def clear_graph(self) -> GraphPlanner:
        """Removes the graph: waypoints become the subgoals themselves."""
        self.graph.clear()
        return self

    def distance_from_graph(
        self, goals: Tensor, *, at_most: float | None = None, candidates: int = 16, capturable: bool = False
    ) -> Tensor:
        """``min_k d(landmark_state_k -> goal)`` for ``goals[..., goal_dim]`` -> ``[...]``.

        ``inf`` everywhere when there is no graph. With ``at_most``, exact only relative to that threshold
        and much cheaper; with ``capturable`` (a ``fixed_size`` graph), capture-safe (see
        :meth:`LandmarkGraph.distance_from_graph`).

        Used by the gradual penalty (Algorithm 4) and by frontier-based goal shifting.
        """
        return self.graph.distance_from_graph(
            goals, self.distance, at_most=at_most, candidates=candidates, capturable=capturable
        )

    def plan(self, states: Tensor, subgoals: Tensor) -> GraphPlan:
        """Plans for ``states[B, obs_dim]`` and ``subgoals[B, goal_dim]`` (see :meth:`LandmarkGraph.plan`)."""
        return self.graph.plan(
            states, subgoals, self.distance, self.max_path_length, capturable=self.capturable
        )

    # ------------------------------------------------------------------ specs and primer
    def state_spec(
        self, shape: torch.Size | tuple = (), device: torch.device | str | None = None
    ) -> Composite:
        """The :class:`~torchrl.data.Composite` of the tracking state (under ``state_key``).

        Args:
            shape: the batch shape of the specs. Defaults to ``()``.
            device: the device of the specs. Defaults to ``None``.
        """
        shape = torch.Size(shape)
        length = self.max_path_length
        entries = {
            "path": Unbounded(shape=(*shape, length), dtype=torch.int64, device=device),
            "path_length": Unbounded(shape=(*shape, 1), dtype=torch.int64, device=device),
            "budgets": Unbounded(shape=(*shape, length + 1), dtype=torch.float32, device=device),
            "index": Unbounded(shape=(*shape, 1), dtype=torch.int64, device=device),
            "steps": Unbounded(shape=(*shape, 1), dtype=torch.int64, device=device),
            "truncated": Unbounded(shape=(*shape, 1), dtype=torch.bool, device=device),
            "has_plan": Unbounded(shape=(*shape, 1), dtype=torch.bool, device=device),
            "graph_version": Unbounded(shape=(*shape, 1), dtype=torch.int64, device=device),
        }
        spec = Composite(shape=shape, device=device)
        spec[self.state_key] = Composite(entries, shape=shape, device=device)
        return spec

    def make_tensordict_primer(self) -> TensorDictPrimer:
        """A :class:`~torchrl.envs.TensorDictPrimer` for policy mode: zeros (``has_plan=False``) at reset.

        Append it to the env when the planner runs inside the policy, so that the tracking state
        is reset with the env, carried across ``step_mdp`` and declared in the env specs. The name
        follows TorchRL's recurrent modules, so
        :func:`~torchrl.modules.utils.get_primers_from_module` finds it in a policy.

        Examples:
            >>> from torchrl.envs import TransformedEnv
            >>> from torchrl.testing.mocking_classes import ContinuousActionVecMockEnv
            >>> planner = GraphPlanner(LandmarkGraph(), lambda s, g: (g - s[..., :2]).norm(dim=-1), goal_dim=2)
            >>> env = TransformedEnv(ContinuousActionVecMockEnv(), planner.make_tensordict_primer())
            >>> env.reset()["planner", "has_plan"]
            tensor([False])
        """
        return TensorDictPrimer(self.state_spec(), default_value=0.0, expand_specs=True)

    #: Alias of :meth:`make_tensordict_primer`.
    make_primer = make_tensordict_primer

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        shape, device = observation_spec.shape, observation_spec.device
        dtype = torch.float32
        if self.achieved_goal_key in observation_spec.keys(True, True):
            dtype = observation_spec[self.achieved_goal_key].dtype
        observation_spec[self.waypoint_key] = Unbounded(
            shape=(*shape, self.goal_dim), dtype=dtype, device=device
        )
        observation_spec.update(self.state_spec(shape, device))
        return observation_spec

    # ------------------------------------------------------------------ tracking
    def _read(self, tensordict: TensorDictBase, key: NestedKey, what: str) -> Tensor:
        value = tensordict.get(key, None)
        if value is None:
            raise KeyError(
                f"{type(self).__name__} needs the {what} entry {key!r} in the tensordict; got keys "
                f"{sorted(map(str, tensordict.keys(True, True)))}. In env mode, a previous transform or "
                "a primer must provide it in the reset and 'next' tensordicts."
            )
        return value

    def _flat_state(self, source: TensorDictBase | None, batch: torch.Size, device) -> dict[str, Tensor]:
        """Tracking state as flat ``[n, ...]`` tensors (defaults where missing: no plan)."""
        num = batch.numel()
        length = self.max_path_length
        defaults = {
            "path": lambda: torch.full((num, length), -1, dtype=torch.int64, device=device),
            "path_length": lambda: torch.zeros(num, dtype=torch.int64, device=device),
            "budgets": lambda: torch.full((num, length + 1), math.inf, device=device),
            "index": lambda: torch.zeros(num, dtype=torch.int64, device=device),
            "steps": lambda: torch.zeros(num, dtype=torch.int64, device=device),
            "truncated": lambda: torch.zeros(num, dtype=torch.bool, device=device),
            "has_plan": lambda: torch.zeros(num, dtype=torch.bool, device=device),
            "graph_version": lambda: torch.zeros(num, dtype=torch.int64, device=device),
        }
        state = {}
        for name, key in self._state_keys.items():
            value = None if source is None else source.get(key, None)
            if value is None:
                state[name] = defaults[name]()
                continue
            # a copy: in env mode the source is the stored root tensordict of the previous step
            value = value.reshape(num, -1).clone()
            state[name] = value if name in ("path", "budgets") else value.squeeze(-1)
        if state["path"].shape[-1] != length:
            raise ValueError(
                f"The stored path has {state['path'].shape[-1]} entries but max_path_length={length}."
            )
        return state

    @torch.no_grad()
    def _update(
        self,
        state_source: TensorDictBase | None,
        inputs: TensorDictBase,
        out: TensorDictBase,
        active: Tensor | None = None,
    ) -> TensorDictBase:
        batch = inputs.batch_size
        num = batch.numel()
        obs = self._read(inputs, self.observation_key, "observation")
        achieved = self._read(inputs, self.achieved_goal_key, "achieved goal")
        subgoal = self._read(inputs, self.subgoal_key, "subgoal")
        if subgoal.shape[-1] != self.goal_dim or achieved.shape[-1] != self.goal_dim:
            raise ValueError(
                f"`{self.subgoal_key}` and `{self.achieved_goal_key}` must have goal_dim={self.goal_dim} "
                f"features, got {subgoal.shape[-1]} and {achieved.shape[-1]}."
            )
        device = obs.device
        obs = obs.reshape(num, obs.shape[-1])
        achieved = achieved.reshape(num, self.goal_dim)
        subgoal = subgoal.reshape(num, self.goal_dim)
        new_subgoal = inputs.get(self.new_subgoal_key, None)
        st = self._flat_state(state_source, batch, device)

        graph = self.graph.planning_tensors(self.capturable)  # a fixed-size graph's copies: static storage
        version = (self.graph.version if graph is None else graph.version).to(device)
        replan = ~st["has_plan"] | (st["graph_version"] != version)
        if new_subgoal is not None:
            replan = replan | new_subgoal.reshape(num, -1).any(-1)
        keep = ~replan
        # one more step spent on the current waypoint, then Algorithm 3's advance test
        st["steps"] = st["steps"] + keep.to(torch.int64)
        on_path = keep & (st["index"] < st["path_length"])
        target = self._waypoints(st, subgoal, on_path, graph)
        reached = (achieved - target).norm(dim=-1) <= self.reach_radius
        budget = st["budgets"].gather(1, st["index"].clamp(0, self.max_path_length).unsqueeze(1)).squeeze(1)
        timeout = st["steps"].to(budget.dtype) > budget
        advance = on_path & (reached | timeout)
        st["index"] = st["index"] + advance.to(torch.int64)
        st["steps"] = torch.where(advance, 0, st["steps"])
        used_up = keep & st["truncated"] & (st["index"] >= st["path_length"])
        replan = replan | used_up
        if active is not None:
            replan = replan & active.reshape(num)
        if self.capturable:
            # every row planned, the new plans kept where a replan is due (eagerly: nothing when none is)
            plan = self._capturable_plan(obs, subgoal, replan, st) if num else None
            if plan is not None:
                self._merge_plan(st, replan, plan, version)
        elif num and bool(replan.any()):
            rows = replan.nonzero().squeeze(-1)
            plan = self.plan(obs[rows], subgoal[rows])
            st["path"][rows] = plan.path
            st["path_length"][rows] = plan.length
            st["budgets"][rows] = plan.budgets.to(st["budgets"].dtype)
            st["truncated"][rows] = plan.truncated
            st["index"][rows] = 0
            st["steps"][rows] = 0
            st["has_plan"][rows] = True
            st["graph_version"][rows] = version
        on_path = st["index"] < st["path_length"]
        waypoint = self._waypoints(st, subgoal, on_path, graph)
        out.set(self.waypoint_key, waypoint.reshape(*batch, self.goal_dim).to(subgoal.dtype))
        for name, key in self._state_keys.items():
            value = st[name]
            shape = (*batch, value.shape[-1]) if name in ("path", "budgets") else (*batch, 1)
            out.set(key, value.reshape(shape))
        return out

    def _capturable_plan(
        self, obs: Tensor, subgoal: Tensor, replan: Tensor, st: dict[str, Tensor]
    ) -> tuple[Tensor, Tensor, Tensor, Tensor] | None:
        """``(path, length, budgets, truncated)`` of every row, planned when some row is due (``plan_on_demand``).

        When no row is due: under ``torch.compile`` placeholders of the same shapes (``torch.cond``'s branches
        agree on their outputs; ``_merge_plan`` keeps none of them), eagerly ``None`` (nothing to merge).
        """
        budgets_dtype = st["budgets"].dtype

        def planned(obs: Tensor, subgoal: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
            plan = self.plan(obs, subgoal)
            return plan.path, plan.length, plan.budgets.to(budgets_dtype), plan.truncated

        def unplanned(obs: Tensor, subgoal: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
            return (
                torch.zeros_like(st["path"]),
                torch.zeros_like(st["path_length"]),
                torch.zeros_like(st["budgets"]),
                torch.zeros_like(st["truncated"]),
            )

        if not self.plan_on_demand or _capturing_cuda_graph(obs.device):
            return planned(obs, subgoal)
        if torch.compiler.is_compiling():
            return torch.cond(replan.any(), planned, unplanned, (obs, subgoal))
        return planned(obs, subgoal) if bool(replan.any()) else None

    @staticmethod
    def _merge_plan(
        st: dict[str, Tensor], replan: Tensor, plan: tuple[Tensor, Tensor, Tensor, Tensor], version: Tensor
    ) -> None:
        """``st`` takes ``plan``'s rows where ``replan`` (``[n]`` bool) is set: tensor operations only."""
        path, length, budgets, truncated = plan
        fresh = {
            "path": path,
            "path_length": length,
            "budgets": budgets,
            "truncated": truncated,
            "index": torch.zeros_like(st["index"]),
            "steps": torch.zeros_like(st["steps"]),
            "has_plan": torch.ones_like(st["has_plan"]),
            "graph_version": version.expand_as(st["graph_version"]),
        }
        for name, value in fresh.items():
            mask = replan.reshape(-1, *([1] * (st[name].ndim - 1)))
            st[name] = torch.where(mask, value, st[name])

    def _waypoints(
        self, st: dict[str, Tensor], subgoal: Tensor, on_path: Tensor, graph: GraphTensors | None
    ) -> Tensor:
        if graph is None:
            return subgoal.clone()
        index = st["index"].clamp(0, self.max_path_length - 1).unsqueeze(1)
        landmark = st["path"].gather(1, index).squeeze(1).clamp(0, graph.goals.shape[0] - 1)
        coords = graph.goals[landmark].to(subgoal.dtype)
        return torch.where(on_path.unsqueeze(-1), coords, subgoal)

    # ------------------------------------------------------------------ TorchRL entry points
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """One planning/tracking step on ``tensordict`` (policy mode, standalone, replay buffer)."""
        return self._update(tensordict, tensordict, tensordict)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        # env mode: previous tracking state at the root (time t), new observation in "next" (t + 1)
        return self._update(tensordict, next_tensordict, next_tensordict)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return self._update(next_tensordict, next_tensordict, next_tensordict)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        # a fresh plan for the envs being reset; the other rows of `tensordict_reset` are
        # discarded by the env's partial-reset update, so they are not planned
        active = None
        if tensordict is not None:
            reset = tensordict.get("_reset", None)
            if reset is not None and reset.shape[: tensordict_reset.ndim] == tensordict_reset.batch_size:
                active = reset.reshape(*tensordict_reset.batch_size, -1).any(-1)
        return self._update(None, tensordict_reset, tensordict_reset, active=active)

    # ------------------------------------------------------------------ inspection
    def planned_waypoints(self, tensordict: TensorDictBase) -> tuple[Tensor, Tensor]:
        """The full planned sequence of each env, as goal coordinates.

        Returns:
            ``(waypoints, mask)``: ``[*B, max_path_length + 1, goal_dim]`` coordinates (the path's
            landmarks, then the subgoal at position ``path_length``) and the ``[*B,
            max_path_length + 1]`` bool mask of valid entries.
        """
        batch = tensordict.batch_size
        num = batch.numel()
        subgoal = self._read(tensordict, self.subgoal_key, "subgoal").reshape(num, self.goal_dim)
        st = self._flat_state(tensordict, batch, subgoal.device)
        length = self.max_path_length
        coords = subgoal.unsqueeze(1).expand(num, length + 1, self.goal_dim).clone()
        columns = torch.arange(length + 1, device=subgoal.device)
        on_path = columns[:length].unsqueeze(0) < st["path_length"].unsqueeze(1)
        if self.has_graph:
            landmarks = self.landmark_goals[st["path"].clamp(0, self.num_landmarks - 1)].to(coords.dtype)
            coords[:, :length] = torch.where(on_path.unsqueeze(-1), landmarks, coords[:, :length])
        mask = columns.unsqueeze(0) <= st["path_length"].unsqueeze(1)
        return coords.reshape(*batch, length + 1, self.goal_dim), mask.reshape(*batch, length + 1)

    def planned_path(self, tensordict: TensorDictBase, index: int | tuple = ()) -> Tensor:
        """One env's planned waypoints ``[n, goal_dim]`` (landmarks then subgoal), e.g. for plotting.

        Args:
            tensordict (TensorDictBase): a tensordict holding the tracking state and subgoal.
            index (int or tuple): the env's index in the batch (``()`` for an unbatched tensordict).
        """
        waypoints, mask = self.planned_waypoints(tensordict)
        return waypoints[index][mask[index]]

    def extra_repr(self) -> str:
        return (
            f"goal_dim={self.goal_dim}, reach_radius={self.reach_radius}, "
            f"max_path_length={self.max_path_length}, capturable={self.capturable}, "
            f"plan_on_demand={self.plan_on_demand}, "
            f"waypoint_key={self.waypoint_key!r}"
        )
