"""The landmark graph of DHRL: FPS landmarks, cutoff edges, all-pairs shortest paths, batched queries."""

from __future__ import annotations

import contextlib
import math
from typing import NamedTuple

import torch
from torch import Tensor, nn

from torchrl_dhrl._unregistered import UnregisteredAttributes, callable_attribute
from torchrl_dhrl.checks import checked, choice, integer, number

from ._distance import (
    DEFAULT_CHUNK_SIZE,
    build_distance,
    check_build_autocast_dtype,
    check_chunk_size,
    paired_distances,
    pairwise_distances,
)
from .distances import TemporalDistance
from .edges import CutoffEdgeRule, EdgeRule
from .fps import DEFAULT_LAZY_BATCH, FPS_STRATEGIES, ProxyFn, farthest_point_sampling, resolve_proxy
from .shortest_paths import count_hops, floyd_warshall, reconstruct_paths
from .storage import DynamicStorage, FixedSizeStorage, GraphTensors, own_tensors

#: Buffers whose shapes follow the number of landmarks (resized when a state dict is loaded).
_GRAPH_BUFFERS = (
    "landmark_states",
    "landmark_goals",
    "landmark_distances",
    "edge_weights",
    "shortest_distances",
    "next_hop",
    "hop_counts",
)

#: Where :meth:`LandmarkGraph.plan` leads when a subgoal cannot be reached (the first is the reference's).
UNREACHABLE_RULES = ("nearest_landmark", "subgoal")


class GraphPlan(NamedTuple):
    """A batch of planned waypoint sequences, as returned by :meth:`LandmarkGraph.plan`.

    The waypoints of row ``b`` are the landmarks ``path[b, :length[b]]`` followed by the subgoal.

    Attributes:
        path (Tensor): ``[B, L]`` int64 landmark indices, padded with ``-1``.
        length (Tensor): ``[B]`` int64 number of landmarks on the stored path.
        budgets (Tensor): ``[B, L + 1]`` float, the estimated number of steps of each hop:
            ``budgets[b, t]`` is the length of the edge leading to waypoint ``t`` (start -> first
            landmark for ``t = 0``, landmark -> subgoal for ``t = length``; ``inf`` past the end).
        truncated (Tensor): ``[B]`` bool, the path had more than ``L`` landmarks and was cut; the
            tracker replans once the stored part is used up.
        cost (Tensor): ``[B]`` float, estimated steps of the plan to the subgoal (``inf`` when the
            subgoal is unreachable).
        reachable (Tensor): ``[B]`` bool, the subgoal is reachable directly or through the graph;
            ``False`` rows use the fallback of :attr:`LandmarkGraph.unreachable` (by default the
            reachable landmark nearest to the subgoal, then the subgoal) or go straight for the subgoal.
    """

    path: Tensor
    length: Tensor
    budgets: Tensor
    truncated: Tensor
    cost: Tensor
    reachable: Tensor


class LandmarkGraph(UnregisteredAttributes, nn.Module):
    """Directed landmark graph with precomputed all-pairs shortest paths (the graph level of DHRL).

    :meth:`build` selects landmarks among candidate states by farthest point sampling with the
    temporal distance (Algorithm 2 of the paper: from each chosen *state* to every candidate's
    *achieved goal*), computes the landmark distance matrix ``D[i, j] = d(state_i -> goal_j)``,
    keeps the edges ``i -> j`` chosen by ``edge_rule`` (by default :class:`CutoffEdgeRule`, the
    reference rule: ``D[i, j] < cutoff`` or ``D[i, j] < 1.2 * min_k D[i, k]``, so every landmark has
    an outgoing edge), and solves all shortest paths once
    (:func:`~torchrl_dhrl.planner.floyd_warshall`, with a next-hop table). :meth:`plan` then
    answers a batch of ``(state, subgoal)`` queries with tensor operations only: the best plan is
    ``min_{i, j} d(s, i) + D*[i, j] + d(j, sg)`` over the entry landmarks ``i`` connected to the
    state and the exit landmarks ``j`` connected to the subgoal.

    Everything that describes the graph lives in registered buffers, so ``state_dict()`` /
    ``load_state_dict()`` round-trip it; the buffers are resized on load because the number of
    landmarks varies from build to build. ``version`` increases at every rebuild, which lets
    trackers holding landmark indices detect stale plans; ``coverage_radius`` is the FPS radius
    of the last :meth:`build` (the largest min-distance left uncovered, a resolution diagnostic
    worth logging; ``NaN`` for graphs set from given landmarks).

    The distance (a :class:`~torchrl_dhrl.planner.TemporalDistance`) is passed to each method rather
    than stored, so that one graph serves a learned distance (whose parameters belong to the learner,
    not to this module) or an oracle. A :class:`~torchrl_dhrl.planner.GraphPlanner` owns one graph and
    passes it its distance.

    Args:
        cutoff (float): edge threshold in steps, for graph edges and for connecting a query's
            state and subgoal. Defaults to ``30.0`` (the reference value for the mazes).
        max_landmarks (int): landmarks selected by FPS. Defaults to ``300``.
        early_stop (float): FPS stops once the largest remaining min-distance is below this
            value. Defaults to ``10.0``.
        min_landmarks (int, optional): FPS early stopping needs at least this many landmarks.
            Defaults to ``max_landmarks // 10``.

    Keyword Args:
        edge_rule (callable, optional): which landmark pairs become edges,
            ``edge_rule(distances[K, K], cutoff) -> bool[K, K]`` (see
            :class:`~torchrl_dhrl.planner.EdgeRule`). A plain attribute, not a submodule; assigning
            ``graph.edge_rule`` takes effect at the next build. Defaults to
            ``CutoffEdgeRule(nn_factor=1.2)``.
        start_fallback_factor (float): when no landmark is within ``cutoff`` of a query state, the
            state is connected to the landmarks within ``start_fallback_factor`` times its
            smallest landmark distance. Defaults to ``1.5``.
        unreachable (str): where :meth:`plan` leads when the subgoal cannot be reached through the
            graph. ``"nearest_landmark"`` (the reference): to the reachable landmark nearest to the
            subgoal (by ``d(landmark_state -> subgoal)``), then to the subgoal. ``"subgoal"``: straight
            to the subgoal, as without a graph (the low level chases it). A plain attribute (not in
            ``state_dict()``), read at every query. Defaults to ``"nearest_landmark"``.
        chunk_size (int): maximum number of pairs per distance call. Defaults to ``65536``.
        fps_strategy (str): ``"lazy"`` or ``"dense"`` (same result, see
            :func:`~torchrl_dhrl.planner.farthest_point_sampling`). Defaults to ``"lazy"``.
        fps_proxy (str, callable or None): the evaluation-order heuristic of lazy FPS (``"goal"``:
            Euclidean distance between goals; ``None``: none). Changes the cost, never the
            landmarks. A callable (an ``nn.Module`` included) is a plain attribute, not a
            submodule. Defaults to ``"goal"``.
        fps_lazy_batch (int): candidates refreshed per round of lazy FPS. Defaults to ``64``.
        build_autocast_dtype (torch.dtype, optional): ``torch.bfloat16`` or ``torch.float16`` to
            evaluate the distances of :meth:`build` and :meth:`set_landmarks` in reduced precision,
            through the distance's ``with_autocast(dtype)`` (e.g.
            :meth:`~torchrl_dhrl.planner.GoalDistance.with_autocast`; other distances raise a
            TypeError). With bfloat16 on a CPU with bfloat16 units: 2-3.5x faster per pair, at a
            relative distance error of about 0.1% (median) to 0.6% (max) on a 3x256 critic. FPS
            may part ways with a full-precision build after a near-tie (other landmarks, same
            coverage radius within about 1%), and an edge whose length sits at the cutoff may
            flip. Queries (:meth:`plan`, :meth:`distance_from_graph`) always use the distance as
            given. Defaults to ``None`` (full precision).
        fixed_size (bool): also keep the planning tensors at a fixed size, ``max_landmarks`` rows (the
            landmarks, then invalid padding rows), updated in place at every build and :meth:`clear`, and
            plan on them with ``capturable=True``: their shapes and storage stay the same across rebuilds,
            so a compiled planner is not recompiled when the number of landmarks changes, and a planner
            captured in a CUDA graph after the first build reads every later graph (capture after
            ``.to(device)``; moving reallocates). The same plans (every padding row is masked; a learned
            distance evaluated on ``max_landmarks`` rows instead of ``K`` may round differently). The
            copies are derived, not in ``state_dict()`` (a checkpoint is the same either way). A graph
            then holds at most ``max_landmarks`` landmarks. The planning storage is a strategy object,
            :attr:`storage`: a :class:`~torchrl_dhrl.planner.FixedSizeStorage` with ``fixed_size``, else a
            :class:`~torchrl_dhrl.planner.DynamicStorage` (queries read the graph's own buffers). Defaults to
            ``False``.

    Examples:
        >>> import torch
        >>> dist = lambda s, g: (g - s[..., :2]).norm(dim=-1)
        >>> graph = LandmarkGraph(cutoff=1.5, max_landmarks=20, early_stop=0.9)
        >>> xs = torch.linspace(0, 5, 51)
        >>> states = torch.stack([xs, torch.zeros_like(xs)], -1)
        >>> graph = graph.build(states, states.clone(), dist)
        >>> graph.num_landmarks
        5
        >>> plan = graph.plan(torch.tensor([[0.0, 0.0]]), torch.tensor([[5.0, 0.0]]), dist)
        >>> [round(x, 1) for x in graph.landmark_goals[plan.path[0, : plan.length[0]]][:, 0].tolist()]
        [0.0, 1.2, 2.5, 3.7, 5.0]
    """

    #: callables (possibly ``nn.Module`` s) are plain attributes, never submodules
    _unregistered = ("fps_proxy", "edge_rule")

    @checked(
        cutoff=number(0.0, low_open=True),
        max_landmarks=integer(2),  # a graph needs two nodes
        early_stop=number(0.0),
        min_landmarks=integer(0, optional=True),
        start_fallback_factor=number(1.0),
        unreachable=choice(UNREACHABLE_RULES),
        fps_lazy_batch=integer(1),
    )
    def __init__(
        self,
        cutoff: float = 30.0,
        max_landmarks: int = 300,
        early_stop: float = 10.0,
        min_landmarks: int | None = None,
        *,
        edge_rule: EdgeRule | None = None,
        start_fallback_factor: float = 1.5,
        unreachable: str = "nearest_landmark",
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        fps_strategy: str = "lazy",
        fps_proxy: str | ProxyFn | None = "goal",
        fps_lazy_batch: int = DEFAULT_LAZY_BATCH,
        build_autocast_dtype: torch.dtype | None = None,
        fixed_size: bool = False,
    ) -> None:
        super().__init__()
        self.cutoff = float(cutoff)
        self.max_landmarks = max_landmarks
        self.early_stop = float(early_stop)
        self.min_landmarks = max_landmarks // 10 if min_landmarks is None else min_landmarks
        self.edge_rule = CutoffEdgeRule() if edge_rule is None else edge_rule
        self.start_fallback_factor = float(start_fallback_factor)
        self.unreachable = unreachable
        self.chunk_size = check_chunk_size(chunk_size)
        if fps_strategy not in FPS_STRATEGIES:
            raise ValueError(f"`fps_strategy` must be one of {FPS_STRATEGIES}, got {fps_strategy!r}.")
        self.fps_strategy = fps_strategy
        resolve_proxy(fps_proxy)
        self.fps_proxy = fps_proxy
        self.fps_lazy_batch = fps_lazy_batch
        self.build_autocast_dtype = check_build_autocast_dtype(build_autocast_dtype)
        self.register_buffer("landmark_states", torch.zeros(0, 0))
        self.register_buffer("landmark_goals", torch.zeros(0, 0))
        self.register_buffer("landmark_distances", torch.zeros(0, 0))
        self.register_buffer("edge_weights", torch.zeros(0, 0))
        self.register_buffer("shortest_distances", torch.zeros(0, 0))
        self.register_buffer("next_hop", torch.zeros(0, 0, dtype=torch.int64))
        self.register_buffer("hop_counts", torch.zeros(0, 0, dtype=torch.int64))
        self.register_buffer("version", torch.zeros((), dtype=torch.int64))
        self.register_buffer("coverage_radius", torch.full((), math.nan))
        self.fixed_size = fixed_size  # the planning storage: DynamicStorage or FixedSizeStorage

    # ------------------------------------------------------------------ properties
    @property
    def unreachable(self) -> str:
        """Where :meth:`plan` leads when a subgoal cannot be reached (one of :data:`UNREACHABLE_RULES`); may be
        set at any time, the next query reads it."""
        return self.__dict__["_unreachable"]

    @unreachable.setter
    def unreachable(self, value: str) -> None:
        if value not in UNREACHABLE_RULES:
            raise ValueError(f"`unreachable` must be one of {UNREACHABLE_RULES}, got {value!r}.")
        self.__dict__["_unreachable"] = value

    @property
    def fixed_size(self) -> bool:
        """Whether capture-safe queries read fixed-size copies of the graph (:attr:`storage` is a
        :class:`~torchrl_dhrl.planner.storage.FixedSizeStorage`); setting it replaces the storage (a new
        fixed-size storage is allocated by :meth:`reserve` or the next build)."""
        return isinstance(self.storage, FixedSizeStorage)

    @fixed_size.setter
    def fixed_size(self, value: bool) -> None:
        if not isinstance(value, bool):
            raise TypeError(f"`fixed_size` must be a bool, got {value!r}.")
        if "storage" in self._modules and value == self.fixed_size:
            return
        self.storage = FixedSizeStorage() if value else DynamicStorage()
        if value:
            self.storage.update(self)

    @property
    def num_landmarks(self) -> int:
        """The number of landmarks (``0`` before the first build)."""
        return self.landmark_goals.shape[0]

    @property
    def has_graph(self) -> bool:
        """Whether the graph has at least one landmark."""
        return self.num_landmarks > 0

    @property
    def edge_mask(self) -> Tensor:
        """``[K, K]`` bool adjacency (no self loops)."""
        mask = torch.isfinite(self.edge_weights)
        mask.fill_diagonal_(False)
        return mask

    @property
    def edges(self) -> Tensor:
        """``[E, 2]`` int64 directed edges ``(i, j)`` as landmark index pairs (e.g. for plotting)."""
        return self.edge_mask.nonzero()

    @property
    def edge_costs(self) -> Tensor:
        """``[E]`` weights of :attr:`edges`, in the same order."""
        return self.edge_weights[self.edge_mask]

    # ------------------------------------------------------------------ building
    def clear(self) -> LandmarkGraph:
        """Removes every landmark (queries then go straight for the subgoal)."""
        device = self.version.device
        for name in _GRAPH_BUFFERS:
            old = getattr(self, name)
            setattr(self, name, torch.zeros(0, 0, dtype=old.dtype, device=device))
        self.version += 1
        self.storage.update(self)
        return self

    @torch.no_grad()
    def build(
        self, candidate_states: Tensor, candidate_goals: Tensor, distance: TemporalDistance
    ) -> LandmarkGraph:
        """Rebuilds the graph from scratch from candidate states (e.g. sampled from the replay buffer).

        The landmark distance matrix reuses every pair FPS evaluated (all ``d(l_m -> l_j)`` with
        ``l_m`` selected before ``l_j``); only the others are evaluated afterwards.

        Args:
            candidate_states (Tensor): ``[N, obs_dim]`` states.
            candidate_goals (Tensor): ``[N, goal_dim]`` their achieved goals.
            distance (callable): ``distance(states, goals) -> steps`` (its
                ``with_autocast(build_autocast_dtype)`` when that option is set).

        Returns:
            this graph, rebuilt (on the device of the candidates).
        """
        if candidate_states.ndim != 2 or candidate_goals.ndim != 2:
            raise ValueError(
                "`candidate_states` and `candidate_goals` must be 2-D [N, dim], got shapes "
                f"{tuple(candidate_states.shape)} and {tuple(candidate_goals.shape)}."
            )
        if candidate_states.shape[0] == 0:
            return self.clear()
        distance = build_distance(distance, self.build_autocast_dtype)
        with self._build_autocast(candidate_states.device):
            result = farthest_point_sampling(
                candidate_states,
                candidate_goals,
                distance,
                self.max_landmarks,
                early_stop=self.early_stop,
                min_count=self.min_landmarks,
                strategy=self.fps_strategy,
                lazy_batch=self.fps_lazy_batch,
                chunk_size=self.chunk_size,
                proxy=self.fps_proxy,
            )
            states = candidate_states[result.indices]
            goals = candidate_goals[result.indices]
            matrix = result.landmark_distances
            matrix.fill_diagonal_(0.0)  # ignored by set_distance_matrix: not worth evaluating
            missing = torch.isnan(matrix)
            if missing.any():
                rows, cols = missing.nonzero(as_tuple=True)
                matrix[rows, cols] = paired_distances(
                    distance, states[rows], goals[cols], self.chunk_size
                ).to(matrix.dtype)
        self.set_distance_matrix(states, goals, matrix)
        self.coverage_radius = result.radius.to(self.landmark_states)
        return self

    @torch.no_grad()
    def set_landmarks(self, states: Tensor, goals: Tensor, distance: TemporalDistance) -> LandmarkGraph:
        """Uses the given landmarks as they are (no sampling): computes their distances, edges and paths.

        Args:
            states (Tensor): ``[K, obs_dim]`` landmark states.
            goals (Tensor): ``[K, goal_dim]`` landmark goals (achieved goals of ``states``).
            distance (callable): ``distance(states, goals) -> steps``.
        """
        self._check_landmarks(states, goals)
        distance = build_distance(distance, self.build_autocast_dtype)
        with self._build_autocast(states.device):
            matrix = pairwise_distances(distance, states, goals, self.chunk_size)
        return self.set_distance_matrix(states, goals, matrix)

    def _build_autocast(self, device: torch.device):
        """``torch.autocast(build_autocast_dtype)`` around the distance evaluations of a build.

        The distance (``distance.with_autocast(dtype)``) runs in reduced precision anyway; the
        enclosing context keeps autocast's cache of the networks' reduced-precision weights alive
        for the whole build, so they are cast once per build instead of once per call (about 10%
        of a CPU rebuild).
        """
        dtype = self.build_autocast_dtype
        if dtype is None or not torch.amp.is_autocast_available(device.type):
            return contextlib.nullcontext()
        return torch.autocast(device.type, dtype=dtype)

    @torch.no_grad()
    def set_distance_matrix(self, states: Tensor, goals: Tensor, distances: Tensor) -> LandmarkGraph:
        """Builds edges and shortest paths from landmarks and a given ``[K, K]`` distance matrix.

        ``distances[i, j]`` is ``d(states[i] -> goals[j])``; its diagonal is ignored (set to 0) and
        negative values (possible from an unclamped learned critic) are clamped to 0.
        """
        self._check_landmarks(states, goals)
        num = states.shape[0]
        if distances.shape != (num, num):
            raise ValueError(f"`distances` must have shape {(num, num)}, got {tuple(distances.shape)}.")
        if torch.isnan(distances).any():
            raise ValueError("`distances` contains NaN.")
        matrix = distances.to(device=states.device, dtype=states.dtype).clamp_min(0.0)
        matrix.fill_diagonal_(0.0)
        if num == 0:
            return self.clear()
        if self.fixed_size and num > self.max_landmarks:  # before anything changes
            raise ValueError(
                f"A fixed_size graph holds at most max_landmarks={self.max_landmarks} landmarks, got {num}."
            )
        off_diag = matrix.clone()
        off_diag.fill_diagonal_(math.inf)
        keep = self._edges(off_diag)
        weights = torch.where(keep, off_diag, torch.full_like(off_diag, math.inf))
        weights.fill_diagonal_(0.0)
        paths = floyd_warshall(weights)
        self.landmark_states = states.detach().clone()
        self.landmark_goals = goals.detach().clone()
        self.landmark_distances = matrix
        self.edge_weights = weights
        self.shortest_distances = paths.distances
        self.next_hop = paths.next_hop
        self.hop_counts = paths.hop_counts
        self.version = self.version.to(states.device) + 1
        self.coverage_radius = torch.full((), math.nan, dtype=states.dtype, device=states.device)
        self.storage.update(self)
        return self

    @torch.no_grad()
    def redo_edges(self) -> LandmarkGraph:
        """The edges and shortest paths redone from the same landmarks and distances with the graph's current
        :attr:`cutoff` and :attr:`edge_rule` (both take effect at the next build otherwise), e.g. on a loaded
        graph evaluated with another edge rule. The landmarks, their distances and the coverage radius stay;
        a graph without landmarks stays empty.

        Examples:
            >>> import torch
            >>> from torchrl_dhrl.planner import ConnectedEdgeRule
            >>> graph = LandmarkGraph(max_landmarks=3, cutoff=2.0)
            >>> points = torch.tensor([[0.0], [1.0], [4.0]])
            >>> graph = graph.set_distance_matrix(points, points, torch.cdist(points, points))
            >>> graph.edges.tolist()  # 1 -> 2 (3 steps) is above the cutoff and 1.2x 1's nearest neighbour
            [[0, 1], [1, 0], [2, 1]]
            >>> graph.edge_rule = ConnectedEdgeRule()
            >>> graph.redo_edges().edges.tolist()  # the shortest edge that lets 0 and 1 reach 2
            [[0, 1], [1, 0], [1, 2], [2, 1]]
        """
        if not self.has_graph:
            return self
        coverage = self.coverage_radius.clone()
        self.set_distance_matrix(self.landmark_states, self.landmark_goals, self.landmark_distances)
        self.coverage_radius = coverage
        return self

    @torch.no_grad()
    def reserve(
        self,
        obs_dim: int,
        goal_dim: int,
        *,
        dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
    ) -> LandmarkGraph:
        """Allocates a ``fixed_size`` graph's planning tensors before its first build, every row padding.

        :meth:`planning_tensors` with ``capturable=True`` then returns them at once: a capturable planner plans
        on them as on a graph without landmarks (every plan the subgoal alone, like the graph's own empty
        buffers), and the first :meth:`build` writes into the same storage. A policy compiled or captured in a
        CUDA graph before the first build therefore reads every later graph without being recompiled or
        captured again (:func:`~torchrl_dhrl.factory.make_agent` reserves the graph of a capturable planner).
        The tensors are allocated where and as the builds will write them: ``obs_dim`` and ``goal_dim`` features,
        ``dtype`` (default: PyTorch's default dtype) on ``device`` (default: the graph's); a build of another
        size, dtype or device reallocates them. Reserve after moving the graph (``.to(device)`` reallocates).
        A graph that already has landmarks keeps them (its sizes must match).

        Args:
            obs_dim (int): the landmark states' features.
            goal_dim (int): the landmark goals' features.

        Keyword Args:
            dtype (torch.dtype, optional): the floating dtype of states, goals and distances.
            device (torch.device or str, optional): where to allocate.

        Returns:
            this graph.

        Examples:
            >>> graph = LandmarkGraph(max_landmarks=8, fixed_size=True).reserve(4, 2)
            >>> graph.num_landmarks, graph.planning_tensors(capturable=True).valid
            (0, tensor([False, False, False, False, False, False, False, False]))
            >>> storage = graph.planning_tensors(capturable=True).states.data_ptr()
            >>> points = torch.rand(20, 4)
            >>> _ = graph.build(points, points[:, :2], lambda s, g: (s[..., :2] - g).norm(dim=-1))
            >>> graph.planning_tensors(capturable=True).states.data_ptr() == storage  # the same storage
            True
        """
        if not self.fixed_size:
            self.storage.reserve(self, obs_dim, goal_dim, dtype, device)  # refuses, saying why
        for name, value in (("obs_dim", obs_dim), ("goal_dim", goal_dim)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"reserve(): `{name}` must be a positive int, got {value!r}.")
        if self.num_landmarks:
            sizes = (self.landmark_states.shape[1], self.landmark_goals.shape[1])
            if sizes != (obs_dim, goal_dim):
                raise ValueError(
                    f"reserve({obs_dim}, {goal_dim}): the graph already holds landmarks with {sizes[0]} state "
                    f"and {sizes[1]} goal features."
                )
            return self
        dtype = torch.get_default_dtype() if dtype is None else dtype
        device = self.version.device if device is None else torch.device(device)
        self.storage.reserve(self, obs_dim, goal_dim, dtype, device)
        return self

    def planning_tensors(self, capturable: bool = False) -> GraphTensors | None:
        """The tensors :meth:`plan` reads, ``None`` without a graph.

        With ``capturable`` on a ``fixed_size`` graph built once: its fixed-size copies (``max_landmarks``
        rows, ``valid`` marking the landmarks; the same storage after every rebuild and :meth:`clear`);
        otherwise the graph's own buffers (``K`` rows, ``valid`` is ``None``).
        """
        if capturable:
            tensors = self.storage.capture_tensors()
            if tensors is not None:
                return tensors
        return own_tensors(self)

    edge_rule = callable_attribute(
        "edge_rule",
        "(distances[K, K], cutoff) -> bool[K, K]",
        "Which landmark pairs become edges (an :class:`~torchrl_dhrl.planner.EdgeRule`); not a submodule.",
    )

    def _edges(self, distances: Tensor) -> Tensor:
        """The ``[K, K]`` bool edge mask of the edge rule, checked."""
        keep = self.edge_rule(distances.clone(), self.cutoff)
        if not isinstance(keep, Tensor) or keep.dtype != torch.bool or keep.shape != distances.shape:
            got = f"{keep.dtype} {tuple(keep.shape)}" if isinstance(keep, Tensor) else type(keep).__name__
            raise ValueError(
                f"The edge rule {self.edge_rule!r} must return a bool tensor of shape {tuple(distances.shape)} "
                f"(keep[i, j]: edge i -> j), got {got}."
            )
        return keep.to(distances.device)

    @staticmethod
    def _check_landmarks(states: Tensor, goals: Tensor) -> None:
        if states.ndim != 2 or goals.ndim != 2 or states.shape[0] != goals.shape[0]:
            raise ValueError(
                "Landmark `states` [K, obs_dim] and `goals` [K, goal_dim] must be 2-D with the same K, "
                f"got {tuple(states.shape)} and {tuple(goals.shape)}."
            )
        if not states.is_floating_point() or not goals.is_floating_point():
            raise TypeError("Landmark `states` and `goals` must be floating tensors.")

    # ------------------------------------------------------------------ queries
    def _check_query(
        self, states: Tensor, goals: Tensor | None = None, tensors: GraphTensors | None = None
    ) -> None:
        """Feature sizes and device of a query against the landmarks (``tensors``: those planned on)."""
        if states.ndim < 1:
            raise ValueError(f"`states` must have a feature dim, got shape {tuple(states.shape)}.")
        if tensors is None:
            tensors = self.planning_tensors()
        if tensors is not None:
            if states.shape[-1] != tensors.states.shape[-1]:
                raise ValueError(
                    f"`states` have {states.shape[-1]} features but the landmarks have "
                    f"{tensors.states.shape[-1]}."
                )
            if states.device != tensors.states.device:
                raise ValueError(
                    f"Query on {states.device} but the graph lives on {tensors.states.device}; "
                    "move the planner with `.to(device)`."
                )
            if goals is not None and goals.shape[-1] != tensors.goals.shape[-1]:
                raise ValueError(
                    f"`goals` have {goals.shape[-1]} features but the landmark goals have "
                    f"{tensors.goals.shape[-1]}."
                )

    @torch.no_grad()
    def start_costs(self, states: Tensor, distance: TemporalDistance) -> Tensor:
        """``[B, K]`` cost of the edges start -> landmark (``inf`` where not connected).

        A state connects to the landmarks within ``cutoff``; when there are none, to the
        landmarks within ``start_fallback_factor`` times its smallest landmark distance.
        """
        to_landmarks = pairwise_distances(distance, states, self.landmark_goals, self.chunk_size)
        return self._connect_start(to_landmarks)

    def _connect_start(self, to_landmarks: Tensor) -> Tensor:
        inf = torch.full((), math.inf, dtype=to_landmarks.dtype, device=to_landmarks.device)
        within = to_landmarks < self.cutoff
        nearest = to_landmarks.min(dim=-1, keepdim=True).values
        fallback = (to_landmarks <= self.start_fallback_factor * nearest) & torch.isfinite(to_landmarks)
        connected = torch.where(within.any(dim=-1, keepdim=True), within, fallback)
        return torch.where(connected, to_landmarks, inf)

    @staticmethod
    def _padded(costs: Tensor) -> tuple[Tensor, Tensor]:
        """Column indices and costs of the finite entries of each row, left-aligned and padded.

        Returns ``[B, W]`` indices (``0`` in the padding) and costs (``inf`` in the padding), with
        ``W`` the largest number of finite entries in a row.
        """
        finite = torch.isfinite(costs)
        counts = finite.sum(dim=-1)
        width = int(counts.max()) if costs.shape[0] else 0
        rows, cols = finite.nonzero(as_tuple=True)
        offsets = torch.cumsum(counts, 0) - counts
        slots = torch.arange(rows.numel(), device=costs.device) - offsets[rows]
        index = torch.zeros(costs.shape[0], width, dtype=torch.int64, device=costs.device)
        index[rows, slots] = cols
        padded = torch.full((costs.shape[0], width), math.inf, dtype=costs.dtype, device=costs.device)
        padded[rows, slots] = costs[rows, cols]
        return index, padded

    @staticmethod
    def _dense(costs: Tensor) -> tuple[Tensor, Tensor]:
        """:meth:`_padded`'s output over every column: ``[B, K]`` indices ``0..K-1`` and the costs themselves.

        Static shapes and no host synchronisation (the capturable path); ``inf`` entries never win a
        minimum that a finite entry can win, and the finite entries keep their column order, so minima
        and their first-occurrence indices agree with the padded form.
        """
        index = torch.arange(costs.shape[-1], device=costs.device).expand(costs.shape)
        return index, costs

    def _reach(
        self, start_cost: Tensor, capturable: bool = False, shortest: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """Graph distance start -> every landmark and the entry landmark achieving it: ``[B, K]`` each."""
        shortest = self.shortest_distances if shortest is None else shortest
        entries, entry_cost = (self._dense if capturable else self._padded)(start_cost)  # [B, E]
        if entries.shape[1] == 0:
            return torch.full_like(start_cost, math.inf), torch.zeros_like(start_cost, dtype=torch.int64)
        through = entry_cost.unsqueeze(-1) + shortest[entries]  # [B, E, K]
        cost, arg = through.min(dim=1)
        return cost, entries.gather(1, arg)

    @torch.no_grad()
    def reach_costs(self, states: Tensor, distance: TemporalDistance) -> Tensor:
        """``[..., K]`` estimated steps from each state to each landmark through the graph.

        ``inf`` marks landmarks the graph cannot reach from the state.
        """
        self._check_query(states)
        batch = states.shape[:-1]
        flat = states.reshape(-1, states.shape[-1])
        if not self.has_graph:
            return torch.zeros(*batch, 0, dtype=states.dtype, device=states.device)
        cost, _ = self._reach(self.start_costs(flat, distance))
        return cost.reshape(*batch, self.num_landmarks)

    @torch.no_grad()
    def distance_from_graph(
        self,
        goals: Tensor,
        distance: TemporalDistance,
        *,
        at_most: float | None = None,
        candidates: int = 16,
        capturable: bool = False,
    ) -> Tensor:
        """``min_k d(landmark_state_k -> goal)`` for goals ``[..., goal_dim]`` -> ``[...]``.

        ``inf`` everywhere when there is no graph.

        With ``at_most`` the result only has to be right relative to that threshold, which is all the
        gradual penalty (``> 3 x cutoff``) and FGS (``< cutoff``) ask: each goal is first evaluated from
        the ``candidates`` landmarks nearest to it in goal space; a goal with one of them closer than
        ``at_most`` is settled (its value is that smaller-than-``at_most`` upper bound of the minimum),
        and only the other goals are evaluated from every landmark (their value is the exact minimum).
        Comparisons ``<, <=, >, >=`` with ``at_most`` therefore give exactly the answers of the full
        minimum, for about ``candidates / num_landmarks`` of its cost when most goals are near the graph
        (the learned distance is evaluated for ``B x candidates`` pairs instead of ``B x K``).

        With ``capturable=True`` (a ``fixed_size`` graph, reserved or built once) the exact minimum over the
        fixed-size planning tensors, padding rows masked (``inf`` without landmarks): static shapes, no host
        synchronisation, for a query captured in a CUDA graph or compiled whole (the high level's capture-safe
        sampling). ``at_most`` and ``candidates`` are not used (the exact minimum answers every threshold); the
        distance is evaluated for ``B x max_landmarks`` pairs.
        """
        if capturable:
            return self._distance_from_fixed(goals, distance)
        batch = goals.shape[:-1]
        if not self.has_graph:
            return torch.full(batch, math.inf, dtype=goals.dtype, device=goals.device)
        if goals.shape[-1] != self.landmark_goals.shape[-1]:
            raise ValueError(
                f"`goals` have {goals.shape[-1]} features but the landmark goals have "
                f"{self.landmark_goals.shape[-1]}."
            )
        if candidates < 1:
            raise ValueError(f"`candidates` must be >= 1, got {candidates}.")
        flat = goals.reshape(-1, goals.shape[-1])
        num_landmarks = self.landmark_states.shape[0]
        if at_most is None or candidates >= num_landmarks:
            # [K, M] = d(landmark_state_k -> goal_m)
            matrix = pairwise_distances(distance, self.landmark_states, flat, self.chunk_size)
            return matrix.min(dim=0).values.reshape(batch)
        # 1) the `candidates` landmarks nearest in goal space (a cheap ordering; exactness does not need it)
        nearest = (
            torch.cdist(flat, self.landmark_goals.to(flat.dtype)).topk(candidates, largest=False).indices
        )
        states = self.landmark_states[nearest.reshape(-1)]
        first = paired_distances(distance, states, flat.repeat_interleave(candidates, 0), self.chunk_size)
        result = first.reshape(-1, candidates).min(dim=-1).values.to(flat.dtype)
        # 2) goals not settled below the threshold: the exact minimum over every landmark
        open_rows = (~(result < at_most)).nonzero().squeeze(-1)  # NaN stays open too
        if open_rows.numel():
            matrix = pairwise_distances(distance, self.landmark_states, flat[open_rows], self.chunk_size)
            result[open_rows] = matrix.min(dim=0).values.to(flat.dtype)
        return result.reshape(batch)

    def _distance_from_fixed(self, goals: Tensor, distance: TemporalDistance) -> Tensor:
        """:meth:`distance_from_graph` on the fixed-size planning tensors (``capturable=True``)."""
        tensors = self.planning_tensors(capturable=True)
        if tensors is None or tensors.valid is None:
            raise RuntimeError(
                "distance_from_graph(capturable=True) needs a fixed_size graph whose planning tensors exist "
                "(LandmarkGraph(fixed_size=True), then reserve(obs_dim, goal_dim) or a first build)."
            )
        if goals.shape[-1] != tensors.goals.shape[-1]:
            raise ValueError(
                f"`goals` have {goals.shape[-1]} features but the landmark goals have {tensors.goals.shape[-1]}."
            )
        flat = goals.reshape(-1, goals.shape[-1])
        matrix = pairwise_distances(distance, tensors.states, flat, self.chunk_size).to(flat.dtype)  # [K, M]
        inf = torch.full((), math.inf, dtype=flat.dtype, device=flat.device)
        matrix = torch.where(tensors.valid.unsqueeze(1), matrix, inf)
        return matrix.min(dim=0).values.reshape(goals.shape[:-1])  # K >= 1 rows: also right for no goal

    @torch.no_grad()
    def plan(
        self,
        states: Tensor,
        subgoals: Tensor,
        distance: TemporalDistance,
        max_path_length: int | None = None,
        *,
        capturable: bool = False,
    ) -> GraphPlan:
        """Plans waypoint sequences for a batch of ``(state, subgoal)`` queries.

        The state and the subgoal are temporarily added to the graph: state -> landmark edges as
        in :meth:`start_costs`, landmark -> subgoal edges within ``cutoff``, and a direct edge
        state -> subgoal within ``cutoff``. The cheapest route is chosen with the precomputed
        all-pairs table. When the subgoal cannot be reached, the plan follows :attr:`unreachable`:
        by default it leads to the reachable landmark nearest to the subgoal (by
        ``d(landmark_state -> subgoal)``) and then to the subgoal; when no landmark is reachable (or
        there is no graph), the plan is the subgoal alone. A plan is always returned.

        Args:
            states (Tensor): ``[B, obs_dim]`` current states.
            subgoals (Tensor): ``[B, goal_dim]`` subgoals.
            distance (callable): ``distance(states, goals) -> steps``.
            max_path_length (int, optional): landmarks kept per path; longer paths are truncated
                (``GraphPlan.truncated``). Defaults to no limit.

        Keyword Args:
            capturable (bool): plan with tensor operations of static shapes only, without a host
                synchronisation (no ``nonzero``, no ``.item()``, no branch on the data), so that the call
                can be traced whole by ``torch.compile(fullgraph=True)`` or captured in a CUDA graph.
                Every (entry, exit) landmark pair is considered, and the fallback is computed for every
                row; the plans are the same as without it (ties resolved alike), at ``O(B K^2)`` work
                instead of ``O(B E X)`` over the landmarks actually connected. Needs ``max_path_length``
                (the width of the paths). Defaults to ``False``.

        Returns:
            GraphPlan: the plans, one row per query.
        """
        if states.ndim != 2 or subgoals.ndim != 2 or states.shape[0] != subgoals.shape[0]:
            raise ValueError(
                "`states` [B, obs_dim] and `subgoals` [B, goal_dim] must be 2-D with the same B, got "
                f"{tuple(states.shape)} and {tuple(subgoals.shape)}."
            )
        if capturable and (isinstance(max_path_length, bool) or not isinstance(max_path_length, int)):
            raise ValueError(
                "`capturable=True` needs `max_path_length` (an int: the static width of the paths), got "
                f"{max_path_length!r}."
            )
        graph = self.planning_tensors(capturable)
        self._check_query(states, subgoals, graph)
        num_rows, device = states.shape[0], states.device
        width = 0 if max_path_length is None else max_path_length
        if graph is None or num_rows == 0:
            cost = (
                paired_distances(distance, states, subgoals, self.chunk_size)
                if num_rows
                else (torch.zeros(0, device=device))
            )
            budgets = torch.full((num_rows, width + 1), math.inf, dtype=cost.dtype, device=device)
            budgets[:, 0] = cost
            return GraphPlan(
                path=torch.full((num_rows, width), -1, dtype=torch.int64, device=device),
                length=torch.zeros(num_rows, dtype=torch.int64, device=device),
                budgets=budgets,
                truncated=torch.zeros(num_rows, dtype=torch.bool, device=device),
                cost=torch.where(cost < self.cutoff, cost, torch.full_like(cost, math.inf)),
                reachable=cost < self.cutoff,
            )
        to_landmarks = pairwise_distances(distance, states, graph.goals, self.chunk_size)  # [B, K]
        # [K, B] -> [B, K]: d(landmark_state_k -> subgoal_b)
        from_landmarks = pairwise_distances(distance, graph.states, subgoals, self.chunk_size).transpose(0, 1)
        straight = paired_distances(distance, states, subgoals, self.chunk_size)  # [B]
        inf = torch.full((), math.inf, dtype=to_landmarks.dtype, device=device)
        if graph.valid is not None:  # a fixed-size graph's padding rows: not landmarks
            to_landmarks = torch.where(graph.valid, to_landmarks, inf)
            from_landmarks = torch.where(graph.valid, from_landmarks, inf)

        start_cost = self._connect_start(to_landmarks)
        exit_cost = torch.where(from_landmarks < self.cutoff, from_landmarks, inf)
        rows = torch.arange(num_rows, device=device)
        # best route through the graph: min over (entry i, exit j) of d(s, i) + D*[i, j] + d(j, sg),
        # over the few landmarks connected to the state and to the subgoal only
        connected = self._dense if capturable else self._padded
        entry_ids, entry_cost = connected(start_cost)  # [B, E]
        exit_ids, exit_padded = connected(exit_cost)  # [B, X]
        via_cost = torch.full((num_rows,), math.inf, dtype=to_landmarks.dtype, device=device)
        via_entry = torch.zeros(num_rows, dtype=torch.int64, device=device)
        via_exit = torch.zeros(num_rows, dtype=torch.int64, device=device)
        if entry_ids.shape[1] and exit_ids.shape[1]:
            block = graph.shortest[entry_ids.unsqueeze(2), exit_ids.unsqueeze(1)]  # [B, E, X]
            total = entry_cost.unsqueeze(2) + block + exit_padded.unsqueeze(1)
            via_cost, flat = total.flatten(1).min(dim=1)
            via_entry = entry_ids[rows, flat // exit_ids.shape[1]]
            via_exit = exit_ids[rows, flat % exit_ids.shape[1]]
        direct_cost = torch.where(straight < self.cutoff, straight, inf)
        use_direct = torch.isfinite(direct_cost) & (direct_cost <= via_cost)
        use_graph = torch.isfinite(via_cost) & ~use_direct
        # fallback (subgoal unreachable): the reachable landmark nearest to the subgoal, when that
        # distance is finite; the full reachable set is only computed for these rows
        stuck = ~use_direct & ~use_graph
        use_fallback = torch.zeros_like(stuck)
        exits, entries = via_exit.clone(), via_entry.clone()
        if self.unreachable == "subgoal":
            pass  # stuck rows go straight for the subgoal
        elif capturable:  # the fallback of every row, kept where the row is stuck
            near_cost, near_exit, near_entry = self._fallback(
                start_cost, from_landmarks, True, graph.shortest
            )
            use_fallback = stuck & torch.isfinite(near_cost)
            exits = torch.where(stuck, near_exit, exits)
            entries = torch.where(stuck, near_entry, entries)
        elif bool(stuck.any()):
            idx = stuck.nonzero().squeeze(-1)
            near_cost, near_exit, near_entry = self._fallback(
                start_cost[idx], from_landmarks[idx], False, graph.shortest
            )
            use_fallback[idx] = torch.isfinite(near_cost)
            exits[idx] = near_exit
            entries[idx] = near_entry
        has_path = use_graph | use_fallback
        sources = torch.where(has_path, entries, exits)
        paths, lengths = reconstruct_paths(
            graph.next_hop, graph.hop_counts, sources, exits, max_path_length, capturable=capturable
        )
        full_lengths = torch.where(has_path, graph.hop_counts[sources, exits] + 1, 0)
        lengths = torch.where(has_path, lengths, 0)
        paths = paths.masked_fill(~has_path.unsqueeze(-1), -1)
        if max_path_length is not None and paths.shape[1] < max_path_length:
            pad = torch.full(
                (num_rows, max_path_length - paths.shape[1]), -1, dtype=paths.dtype, device=device
            )
            paths = torch.cat([paths, pad], dim=1)
        truncated = full_lengths > lengths
        # hop budgets: start -> path[0], path[t-1] -> path[t], last landmark -> subgoal
        num_cols = paths.shape[1]
        budgets = torch.full((num_rows, num_cols + 1), math.inf, dtype=to_landmarks.dtype, device=device)
        if num_cols:
            first = paths[:, 0].clamp_min(0)
            budgets[:, 0] = torch.where(has_path, to_landmarks[rows, first], inf)
            if num_cols > 1:
                prev, nxt = paths[:, :-1].clamp_min(0), paths[:, 1:].clamp_min(0)
                hop = graph.distances[prev, nxt]
                valid = torch.arange(1, num_cols, device=device).unsqueeze(0) < lengths.unsqueeze(1)
                budgets[:, 1:num_cols] = torch.where(valid, hop, inf)
        last = paths.gather(1, (lengths - 1).clamp_min(0).unsqueeze(1)).squeeze(1).clamp_min(0)
        final_hop = torch.where(has_path, from_landmarks[rows, last], straight)
        final_hop = torch.where(truncated, inf, final_hop)
        budgets.scatter_(1, lengths.unsqueeze(1), final_hop.unsqueeze(1))
        cost = torch.where(use_direct, direct_cost, torch.where(use_graph, via_cost, inf))
        return GraphPlan(
            path=paths,
            length=lengths,
            budgets=budgets,
            truncated=truncated,
            cost=cost,
            reachable=use_direct | use_graph,
        )

    def _fallback(
        self, start_cost: Tensor, from_landmarks: Tensor, capturable: bool, shortest: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        """The reachable landmark nearest to the subgoal: its distance to it, its index and the entry landmark."""
        reach, entry = self._reach(start_cost, capturable, shortest)
        inf = torch.full((), math.inf, dtype=from_landmarks.dtype, device=from_landmarks.device)
        near = torch.where(torch.isfinite(reach), from_landmarks, inf)
        near_cost, near_exit = near.min(dim=-1)
        return near_cost, near_exit, entry.gather(1, near_exit.unsqueeze(1)).squeeze(1)

    # ------------------------------------------------------------------ state dict
    def _load_from_state_dict(
        self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
    ):
        # the number of landmarks varies between builds: adopt the stored shapes before loading
        for name in _GRAPH_BUFFERS:
            key = prefix + name
            if key in state_dict:
                current = getattr(self, name)
                stored = state_dict[key]
                setattr(self, name, torch.empty(stored.shape, dtype=current.dtype, device=current.device))
        super()._load_from_state_dict(
            state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys, error_msgs
        )
        # hop counts are derived from the next-hop table: recount them, so that a checkpoint written
        # before they were (whose counts could disagree with the table after ties) plans full paths
        if prefix + "next_hop" in state_dict and self.next_hop.shape == self.hop_counts.shape:
            try:
                self.hop_counts = count_hops(self.next_hop)
            except ValueError as err:
                error_msgs.append(f"{prefix}next_hop: {err}")
        if not error_msgs:
            self.storage.update(self)

    def extra_repr(self) -> str:
        return (
            f"num_landmarks={self.num_landmarks}, cutoff={self.cutoff}, max_landmarks={self.max_landmarks}, "
            f"early_stop={self.early_stop}, edge_rule={self.edge_rule!r}, "
            f"start_fallback_factor={self.start_fallback_factor}, unreachable={self.unreachable!r}, "
            f"fixed_size={self.fixed_size}"
        )
