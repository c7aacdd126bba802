"""Farthest point sampling of landmarks with a learned, asymmetric temporal distance (DHRL Algorithm 2)."""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from ._distance import DEFAULT_CHUNK_SIZE, DistanceFn, check_chunk_size, paired_distances

FPS_STRATEGIES = ("lazy", "dense")


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
            all of them).
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
    distance: DistanceFn,
    max_count: int,
    *,
    early_stop: float = 0.0,
    min_count: int | None = None,
    start_index: int = 0,
    strategy: str = "lazy",
    lazy_batch: int = 256,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
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
    - ``"lazy"`` (default): lazy-greedy evaluation. Min-distances only decrease, so a stale value
      is an upper bound; a candidate is brought up to date (against the landmarks added since its
      last update, in one batched call per round for up to ``lazy_batch`` candidates) only while
      its bound can still beat the best exact value. Roughly halves the number of distance
      evaluations on maze-like point sets, which dominate the rebuild cost of a learned distance
      on a CPU.

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
        lazy_batch (int): candidates refreshed per round by the lazy strategy. Defaults to ``256``.
        chunk_size (int): maximum number of pairs per distance call. Defaults to ``65536``.

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
    if lazy_batch < 1:
        raise ValueError(f"`lazy_batch` must be >= 1, got {lazy_batch}.")
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
    )


def _finish(
    cache: Tensor, indices: list[int], selection: list[float], radius: float, device
) -> FarthestPointSamplingResult:
    idx = torch.tensor(indices, dtype=torch.int64, device=device)
    count = idx.numel()
    return FarthestPointSamplingResult(
        indices=idx,
        selection_distances=torch.tensor(selection, dtype=cache.dtype, device=device),
        radius=torch.tensor(radius, dtype=cache.dtype, device=device),
        landmark_distances=cache[:count].index_select(1, idx),
    )


def _dense_fps(states, goals, distance, max_count, early_stop, min_count, start, lazy_batch, chunk_size):
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
    return _finish(cache, indices, selection, radius, device)


def _lazy_fps(states, goals, distance, max_count, early_stop, min_count, start, lazy_batch, chunk_size):
    num, device = states.shape[0], states.device
    # upper[j]: min-distance of j to the first `refreshed[j]` landmarks (exact when refreshed[j] == k).
    upper = None
    refreshed = torch.zeros(num, dtype=torch.int64, device=device)
    selected = torch.zeros(num, dtype=torch.bool, device=device)
    landmark_ids = torch.empty(max_count, dtype=torch.int64, device=device)
    cache = None
    indices, selection = [start], [math.inf]
    current = start
    while True:
        count = len(indices)
        landmark_ids[count - 1] = current
        selected[current] = True
        if count == num:
            radius = 0.0
            break
        while True:
            open_ = ~selected
            exact = open_ & (refreshed == count)
            stale = open_ & (refreshed < count)
            if upper is None:
                need = stale
            else:
                best = upper.masked_fill(~exact, -math.inf).max()
                # A stale value is an upper bound of the exact one: only bounds that can still
                # reach the best exact value need an update (ties included, for index order).
                need = stale & (upper >= best)
            num_need = int(need.sum())
            if num_need == 0:
                break
            if num_need > lazy_batch and upper is not None:
                # every infinite bound must be refreshed anyway; the finite ones go by decreasing bound
                infinite = need & torch.isinf(upper)
                finite_scores = upper.masked_fill(~need | infinite, -math.inf)
                k_top = min(lazy_batch, int((need & ~infinite).sum()))
                top = (
                    finite_scores.topk(k_top).indices
                    if k_top
                    else finite_scores.new_empty(0, dtype=torch.int64)
                )
                batch = torch.cat([infinite.nonzero().squeeze(-1), top])
            else:
                batch = need.nonzero().squeeze(-1)
            # every (landmark m, candidate j) pair with refreshed[j] <= m < count
            counts = count - refreshed[batch]
            total = int(counts.sum())
            cand = batch.repeat_interleave(counts, output_size=total)
            offsets = torch.cumsum(counts, 0) - counts
            marks = refreshed[batch].repeat_interleave(counts, output_size=total) + (
                torch.arange(total, device=device) - offsets.repeat_interleave(counts, output_size=total)
            )
            values = _check_distances(
                paired_distances(distance, states[landmark_ids[marks]], goals[cand], chunk_size)
            )
            if upper is None:
                upper = torch.full((num,), math.inf, dtype=values.dtype, device=device)
                cache = torch.full((max_count, num), math.nan, dtype=values.dtype, device=device)
            cache[marks, cand] = values
            upper.scatter_reduce_(0, cand, values, reduce="amin", include_self=True)
            refreshed[batch] = count
        exact = ~selected & (refreshed == count)
        masked = upper.masked_fill(~exact, -math.inf)
        current = int(masked.argmax())
        radius = float(masked[current])
        if count >= max_count or (count >= min_count and radius < early_stop):
            break
        indices.append(current)
        selection.append(radius)
    if cache is None:  # a single candidate: nothing was evaluated
        row = paired_distances(distance, states[:1], goals[:1], chunk_size)
        cache = torch.full((max_count, num), math.nan, dtype=row.dtype, device=device)
        cache[0, 0] = row[0]
    return _finish(cache, indices, selection, radius, device)
