"""Farthest point sampling of landmarks with a learned, asymmetric temporal distance (DHRL Algorithm 2)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from ._distance import DEFAULT_CHUNK_SIZE, check_chunk_size, paired_distances
from .distances import TemporalDistance

FPS_STRATEGIES = ("lazy", "dense")
#: Named proxies of the lazy strategy (see :func:`farthest_point_sampling`).
FPS_PROXIES = ("goal",)
#: Default number of candidates refreshed per round by the lazy strategy.
DEFAULT_LAZY_BATCH = 64

#: A cheap stand-in for the distance that orders the lazy refreshes:
#: ``proxy(landmark_goal[1, goal_dim], goals[N, goal_dim]) -> Tensor[N]`` (smaller is nearer).
ProxyFn = Callable[[Tensor, Tensor], Tensor]


class FarthestPointSamplingResult(NamedTuple):
    """Output of :func:`farthest_point_sampling`.

    Attributes:
        indices (Tensor): ``[K]`` int64 candidate indices of the landmarks, in selection order.
        selection_distances (Tensor): ``[K]`` the min-distance of each landmark to the previously
            selected ones at the moment it was picked (``inf`` for the first).
        radius (Tensor): 0-d, the largest min-distance over the unselected candidates when
            sampling stopped (the coverage radius of the landmark set; ``0`` when every candidate
            was selected).
        landmark_distances (Tensor): ``[K, K]`` ``d(state_i -> goal_j)`` between landmarks, as far as
            sampling evaluated them (``NaN`` where it did not; the ``"dense"`` strategy evaluates
            all of them, the ``"lazy"`` one every ``i < j``: a landmark is exact against all the
            earlier ones when it is selected).
    """

    indices: Tensor
    selection_distances: Tensor
    radius: Tensor
    landmark_distances: Tensor


def _check_inputs(states: Tensor, goals: Tensor) -> None:
    for name, value in (("states", states), ("goals", goals)):
        if not isinstance(value, Tensor):
            raise TypeError(f"`{name}` must be a Tensor, got {type(value).__name__}.")
        if value.ndim != 2:
            raise ValueError(f"`{name}` must be 2-D [num_candidates, dim], got shape {tuple(value.shape)}.")
        if not value.is_floating_point():
            raise TypeError(f"`{name}` must be a floating tensor, got {value.dtype}.")
    if states.shape[0] != goals.shape[0]:
        raise ValueError(
            f"`states` and `goals` must have the same number of candidates, got {states.shape[0]} "
            f"and {goals.shape[0]}."
        )
    if states.device != goals.device:
        raise ValueError(f"`states` ({states.device}) and `goals` ({goals.device}) must share a device.")


def _check_distances(values: Tensor) -> Tensor:
    if torch.isnan(values).any():
        raise ValueError("The distance function returned NaN during farthest point sampling.")
    return values


@torch.no_grad()
def farthest_point_sampling(
    states: Tensor,
    goals: Tensor,
    distance: TemporalDistance,
    max_count: int,
    *,
    early_stop: float = 0.0,
    min_count: int | None = None,
    start_index: int = 0,
    strategy: str = "lazy",
    lazy_batch: int = DEFAULT_LAZY_BATCH,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    proxy: str | ProxyFn | None = "goal",
) -> FarthestPointSamplingResult:
    """Greedy farthest point sampling with a directed temporal distance (DHRL Algorithm 2).

    Starting from candidate ``start_index``, repeatedly selects the candidate whose
    min-distance ``min_{l selected} d(state_l -> goal_j)`` is the largest, where ``state_l`` is the
    selected candidate's *state* and ``goal_j`` the candidate's *achieved goal*. Stops after
    ``max_count`` landmarks, when every candidate is selected, or as soon as the largest
    remaining min-distance is below ``early_stop`` while at least ``min_count`` landmarks exist.
    Already-selected candidates are never selected twice (their own ``d(s_j -> g_j)`` is ignored,
    which matters for a learned distance that is not exactly ``0`` there). Ties go to the lowest
    candidate index.

    Two strategies give the *same* selection:

    - ``"dense"``: the textbook algorithm, one distance row ``d(state_new -> all goals)`` per
      landmark (``K x N`` evaluations). Best on a GPU, where a row is one cheap batched call.
    - ``"lazy"`` (default): lazy-greedy evaluation. Min-distances only decrease, so the minimum
      over the landmarks evaluated so far is an upper bound; a candidate is refreshed (in one
      batched call per round for up to ``lazy_batch`` candidates, largest bounds first) only while
      its bound can still beat the best exact value, and it is exact once every landmark has been
      evaluated against it. With a ``proxy``, a refresh evaluates the landmarks the proxy says are
      *nearest* first (1, then 4, 16, ... per refresh; the largest bounds of a round are completed),
      so most bounds drop below the best exact value after one or a few evaluations instead of
      one per landmark added since the last refresh. On maze-like point sets this evaluates
      10-15x fewer pairs than ``"dense"`` (about 2x fewer without a proxy), which dominates the
      rebuild cost of a learned distance on a CPU. Memory: three ``[N, max_count]`` tables
      (distances, evaluated flags, proxy values).

    The proxy only orders the evaluations: the selection is the exact greedy one for *any* proxy
    (a poor proxy costs evaluations, never correctness).

    Args:
        states (Tensor): ``[N, obs_dim]`` candidate states.
        goals (Tensor): ``[N, goal_dim]`` the candidates' achieved goals.
        distance (callable): ``distance(states, goals) -> steps`` broadcasting over leading dims.
        max_count (int): maximum number of landmarks.

    Keyword Args:
        early_stop (float): stop once the largest remaining min-distance is below this value.
            Defaults to ``0.0`` (never).
        min_count (int, optional): early stopping needs at least this many landmarks. Defaults to
            ``max_count // 10`` (the reference rule).
        start_index (int): the first landmark. Defaults to ``0``.
        strategy (str): ``"lazy"`` or ``"dense"``. Defaults to ``"lazy"``.
        lazy_batch (int): candidates refreshed per round by the lazy strategy. Defaults to ``64``.
        chunk_size (int): maximum number of pairs per distance call. Defaults to ``65536``.
        proxy (str, callable or None): the ordering heuristic of the lazy strategy: ``"goal"``
            (default) is the Euclidean distance between the landmark's and the candidate's goals;
            a callable ``proxy(landmark_goal[1, goal_dim], goals[N, goal_dim]) -> Tensor[N]``
            (smaller is nearer); ``None`` evaluates every missing landmark at each refresh.
            Ignored by ``"dense"``.

    Returns:
        FarthestPointSamplingResult: the landmark indices and diagnostics.

    Examples:
        >>> import torch
        >>> points = torch.tensor([[0.0, 0.0], [1.0, 0.0], [10.0, 0.0], [5.0, 0.0]])
        >>> dist = lambda s, g: (g - s).norm(dim=-1)
        >>> res = farthest_point_sampling(points, points, dist, max_count=3)
        >>> res.indices.tolist(), res.radius.item()
        ([0, 2, 3], 1.0)
    """
    _check_inputs(states, goals)
    if not isinstance(max_count, int) or max_count < 1:
        raise ValueError(f"`max_count` must be a positive int, got {max_count!r}.")
    if min_count is None:
        min_count = max_count // 10
    if min_count < 0:
        raise ValueError(f"`min_count` must be >= 0, got {min_count}.")
    if math.isnan(early_stop):
        raise ValueError("`early_stop` must be a number, got NaN.")
    if strategy not in FPS_STRATEGIES:
        raise ValueError(f"`strategy` must be one of {FPS_STRATEGIES}, got {strategy!r}.")
    if isinstance(lazy_batch, bool) or not isinstance(lazy_batch, int) or lazy_batch < 1:
        raise ValueError(f"`lazy_batch` must be a positive int, got {lazy_batch!r}.")
    proxy = resolve_proxy(proxy)
    check_chunk_size(chunk_size)
    num = states.shape[0]
    if num == 0:
        raise ValueError("farthest_point_sampling needs at least one candidate.")
    if not 0 <= start_index < num:
        raise ValueError(f"`start_index` must be in [0, {num}), got {start_index}.")
    sampler = _dense_fps if strategy == "dense" else _lazy_fps
    return sampler(
        states,
        goals,
        distance,
        min(max_count, num),
        early_stop,
        min_count,
        start_index,
        lazy_batch,
        chunk_size,
        proxy,
    )


def resolve_proxy(proxy: str | ProxyFn | None) -> ProxyFn | None:
    """Validates an FPS proxy: a name of :data:`FPS_PROXIES`, a callable or ``None``."""
    if proxy is None or (callable(proxy) and not isinstance(proxy, str)):
        return proxy
    if proxy == "goal":
        return _goal_proxy
    raise ValueError(f"`proxy` must be one of {FPS_PROXIES}, a callable or None, got {proxy!r}.")


def _finish(
    landmark_distances: Tensor, indices: list[int], selection: list[float], radius: float, device
) -> FarthestPointSamplingResult:
    dtype = landmark_distances.dtype
    return FarthestPointSamplingResult(
        indices=torch.tensor(indices, dtype=torch.int64, device=device),
        selection_distances=torch.tensor(selection, dtype=dtype, device=device),
        radius=torch.tensor(radius, dtype=dtype, device=device),
        landmark_distances=landmark_distances,
    )


def _dense_fps(
    states, goals, distance, max_count, early_stop, min_count, start, lazy_batch, chunk_size, proxy
):
    num, device = states.shape[0], states.device
    cache = None
    min_dist = None
    selected = torch.zeros(num, dtype=torch.bool, device=device)
    indices, selection = [start], [math.inf]
    current = start
    radius = 0.0
    while True:
        selected[current] = True
        row = _check_distances(paired_distances(distance, states[current].expand(num, -1), goals, chunk_size))
        if cache is None:
            cache = torch.full((max_count, num), math.nan, dtype=row.dtype, device=device)
            min_dist = torch.full((num,), math.inf, dtype=row.dtype, device=device)
        cache[len(indices) - 1] = row
        torch.minimum(min_dist, row, out=min_dist)
        if len(indices) == num:
            radius = 0.0
            break
        masked = min_dist.masked_fill(selected, -math.inf)
        current = int(masked.argmax())
        radius = float(masked[current])
        if len(indices) >= max_count or (len(indices) >= min_count and radius < early_stop):
            break
        indices.append(current)
        selection.append(radius)
    idx = torch.tensor(indices, dtype=torch.int64, device=device)
    return _finish(cache[: idx.numel()].index_select(1, idx), indices, selection, radius, device)


def _goal_proxy(landmark_goal: Tensor, goals: Tensor) -> Tensor:
    """Euclidean distance in goal space: the default ordering heuristic of the lazy strategy."""
    return (goals - landmark_goal).norm(dim=-1)


def _proxy_row(proxy, goals: Tensor, current: int) -> Tensor:
    row = proxy(goals[current].unsqueeze(0), goals)
    if not isinstance(row, Tensor) or row.shape != goals.shape[:1]:
        raise ValueError(
            "The FPS proxy must return one value per candidate: proxy(landmark_goal[1, goal_dim], "
            f"goals[N, goal_dim]) -> Tensor[N]; got {row!r:.80}."
        )
    # a heuristic only: NaN or infinite values go last (but before the already evaluated pairs)
    big = torch.finfo(torch.float32).max
    return torch.nan_to_num(row.to(torch.float32), nan=big, posinf=big, neginf=-big)


def _lazy_fps(
    states, goals, distance, max_count, early_stop, min_count, start, lazy_batch, chunk_size, proxy
):
    num, device = states.shape[0], states.device
    # Candidate-major bookkeeping: row j holds what is known of d(state_{l_m} -> goal_j) for the
    # landmarks m = 0, 1, ... in selection order. upper[j] = min of the known entries of row j, an
    # upper bound of j's min-distance, exact when the whole row is known (known_count[j] == count).
    cache = None
    upper = None
    known = torch.zeros(num, max_count, dtype=torch.bool, device=device)
    known_count = torch.zeros(num, dtype=torch.int64, device=device)
    nearness = None if proxy is None else torch.empty(num, max_count, dtype=torch.float32, device=device)
    selected = torch.zeros(num, dtype=torch.bool, device=device)
    landmark_ids = torch.empty(max_count, dtype=torch.int64, device=device)
    indices, selection = [start], [math.inf]
    current = start
    while True:
        count = len(indices)
        landmark_ids[count - 1] = current
        selected[current] = True
        if count == num:
            radius = 0.0
            break
        if nearness is not None:
            nearness[:, count - 1] = _proxy_row(proxy, goals, current)
        tries = torch.zeros(num, dtype=torch.int64, device=device)  # refreshes of j for this landmark
        while True:
            stale = ~selected & (known_count < count)
            if upper is None:
                need = stale
            else:
                exact = ~selected & (known_count == count)
                best = upper.masked_fill(~exact, -math.inf).max()
                # A bound below the best exact value cannot win: only the others need work (ties
                # included, for index order).
                need = stale & (upper >= best)
            num_need = int(need.sum())
            if num_need == 0:
                break
            batch = need.nonzero().squeeze(-1)
            if upper is not None:
                # the largest bounds first (infinite ones included): they decide the winner
                batch = batch[upper[batch].topk(min(lazy_batch, num_need)).indices]
            rows, marks = _refresh_pairs(
                known[batch, :count], None if nearness is None else nearness[batch, :count], tries[batch]
            )
            cand = batch[rows]
            values = _check_distances(
                paired_distances(distance, states[landmark_ids[marks]], goals[cand], chunk_size)
            )
            if upper is None:
                upper = torch.full((num,), math.inf, dtype=values.dtype, device=device)
                cache = torch.full((num, max_count), math.nan, dtype=values.dtype, device=device)
            cache[cand, marks] = values
            known[cand, marks] = True
            known_count.index_add_(0, cand, torch.ones_like(cand))
            upper.scatter_reduce_(0, cand, values, reduce="amin", include_self=True)
            tries[batch] += 1
        exact = ~selected & (known_count == count)
        masked = upper.masked_fill(~exact, -math.inf)
        current = int(masked.argmax())
        radius = float(masked[current])
        if count >= max_count or (count >= min_count and radius < early_stop):
            break
        indices.append(current)
        selection.append(radius)
    idx = torch.tensor(indices, dtype=torch.int64, device=device)
    if cache is None:  # a single candidate: nothing was evaluated
        row = paired_distances(distance, states[:1], goals[:1], chunk_size)
        cache = torch.full((num, max_count), math.nan, dtype=row.dtype, device=device)
        cache[0, 0] = row[0]
    # landmark_distances[m, i] = d(state_{l_m} -> goal_{l_i}) = cache[l_i, m]
    return _finish(cache[idx, : idx.numel()].T.contiguous(), indices, selection, radius, device)


#: The refresh schedule of the lazy strategy with a proxy: a candidate's first refresh for a new
#: landmark evaluates its ``1`` nearest unevaluated landmark (by the proxy), the next ones
#: ``_GROWTH`` times more each, and the ``_FULL_REFRESH`` largest bounds of a round that were
#: already probed for this landmark are brought fully up to date.
_GROWTH = 4
_FULL_REFRESH = 16


def _refresh_pairs(known: Tensor, nearness: Tensor | None, tries: Tensor) -> tuple[Tensor, Tensor]:
    """The ``(row, landmark)`` pairs to evaluate for a batch of stale candidates.

    Args:
        known (Tensor): ``[B, count]`` bool, the pairs already evaluated, one row per candidate
            sorted by decreasing bound.
        nearness (Tensor, optional): ``[B, count]`` proxy values (``None``: no proxy, every
            missing pair is evaluated).
        tries (Tensor): ``[B]`` refreshes of each candidate since the last landmark was added.
    """
    todo = ~known
    if nearness is None:
        return todo.nonzero(as_tuple=True)
    remaining = todo.sum(1)
    width = _GROWTH ** tries.clamp(max=16)
    probed = (tries > 0).nonzero().squeeze(-1)[:_FULL_REFRESH]
    width[probed] = remaining[probed]
    partial = width < remaining
    if bool(partial.any()):
        top = int(width[partial].max())
        # the `top` nearest unevaluated landmarks of every row, nearest first (evaluated ones last)
        order = nearness.masked_fill(known, math.inf).topk(top, dim=1, largest=False).indices
        take = torch.arange(top, device=known.device) < width.unsqueeze(1)
        chosen = torch.zeros_like(todo).scatter_(1, order, take)
        todo = torch.where(partial.unsqueeze(1), chosen, todo)
    return todo.nonzero(as_tuple=True)
