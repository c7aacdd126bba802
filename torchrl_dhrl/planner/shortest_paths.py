"""All-pairs shortest paths in torch (Floyd-Warshall with a next-hop table) and batched path read-out."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor


class ShortestPaths(NamedTuple):
    """All-pairs shortest paths of a weighted directed graph with ``N`` nodes.

    Attributes:
        distances (Tensor): ``[N, N]`` float, ``distances[i, j]`` is the length of a shortest
            path ``i -> j`` (``inf`` when ``j`` is unreachable from ``i``, ``0`` on the diagonal).
        next_hop (Tensor): ``[N, N]`` int64, the node following ``i`` on that path
            (``next_hop[i, i] = i``; ``-1`` when unreachable).
        hop_counts (Tensor): ``[N, N]`` int64, the number of edges on that path (``0`` when
            unreachable or ``i == j``), counted on ``next_hop`` itself (:func:`count_hops`).
    """

    distances: Tensor
    next_hop: Tensor
    hop_counts: Tensor


def _check_weights(weights: Tensor) -> None:
    if not isinstance(weights, Tensor):
        raise TypeError(f"`weights` must be a Tensor, got {type(weights).__name__}.")
    if weights.ndim != 2 or weights.shape[0] != weights.shape[1]:
        raise ValueError(f"`weights` must be a square [N, N] matrix, got shape {tuple(weights.shape)}.")
    if not weights.is_floating_point():
        raise TypeError(f"`weights` must be a floating tensor, got {weights.dtype}.")
    if torch.isnan(weights).any():
        raise ValueError("`weights` contains NaN; use `inf` for missing edges.")
    if (weights < 0).any():
        raise ValueError("`weights` must be >= 0 (temporal distances); got negative entries.")


@torch.no_grad()
def floyd_warshall(weights: Tensor) -> ShortestPaths:
    """Exact all-pairs shortest paths of a dense weight matrix, vectorised in torch.

    ``weights[i, j]`` is the cost of the directed edge ``i -> j`` (``inf`` for no edge). The
    diagonal is treated as ``0``. The algorithm runs ``N`` relaxation rounds, each a handful of
    ``N x N`` tensor operations, so it runs unchanged on CPU and GPU (``O(N)`` kernel launches,
    ``O(N^3)`` work). A path is only replaced by a *strictly* shorter one, which keeps the
    next-hop table acyclic, also with zero-weight edges and under float rounding (ties, large
    weights): following ``next_hop`` from ``i`` always reaches ``j`` along existing edges.

    The hop counts are read off the final next-hop table (:func:`count_hops`), so they always
    match the paths that :func:`reconstruct_paths` follows, even where a sub-path was later
    replaced by one that is shorter only by rounding.

    Args:
        weights (Tensor): ``[N, N]`` non-negative float edge weights, ``inf`` for missing edges.

    Returns:
        ShortestPaths: distances, next-hop table and hop counts.

    Examples:
        >>> import torch
        >>> inf = float("inf")
        >>> w = torch.tensor([[0.0, 1.0, 5.0], [inf, 0.0, 1.0], [inf, inf, 0.0]])
        >>> sp = floyd_warshall(w)
        >>> sp.distances[0, 2].item(), sp.next_hop[0, 2].item(), sp.hop_counts[0, 2].item()
        (2.0, 1, 2)
    """
    _check_weights(weights)
    n = weights.shape[0]
    device = weights.device
    dist = weights.clone()
    dist.fill_diagonal_(0.0)
    if n == 0:
        empty = torch.empty(0, 0, dtype=torch.int64, device=device)
        return ShortestPaths(dist, empty, empty.clone())
    dtype = torch.int32 if n < 2**31 else torch.int64
    arange = torch.arange(n, device=device, dtype=dtype)
    finite = torch.isfinite(dist)
    # Unreachable pairs start with next hop 0 (masked to -1 at the end): a pair only takes a next
    # hop from a finite path, so the placeholder is never followed.
    nxt = torch.where(finite, arange.expand(n, n), torch.zeros((), dtype=dtype, device=device))
    nxt.diagonal().copy_(arange)

    cand = torch.empty_like(dist)
    better = torch.empty(n, n, dtype=dtype, device=device)
    update = torch.empty_like(nxt)
    for k in range(n):
        torch.add(dist[:, k : k + 1], dist[k : k + 1, :], out=cand)
        torch.lt(cand, dist, out=better)
        torch.minimum(dist, cand, out=dist)
        # nxt[i, j] <- nxt[i, k] where the path through k is strictly better
        torch.sub(nxt[:, k : k + 1], nxt, out=update)
        update.mul_(better)
        nxt.add_(update)
    next_hop = nxt.to(torch.int64)
    next_hop.masked_fill_(torch.isinf(dist), -1)
    return ShortestPaths(dist, next_hop, count_hops(next_hop))


@torch.no_grad()
def count_hops(next_hop: Tensor) -> Tensor:
    """Number of edges of every path of a next-hop table, by pointer jumping.

    Row ``i``, column ``j`` of the result is the number of steps ``i -> next_hop[i, j] -> ... -> j``.
    All pairs are followed at once, doubling the jump length each round (``ceil(log2(N))`` rounds
    of two ``[N, N]`` gathers, no per-node loop), so the count always agrees with the table, which
    is what :func:`reconstruct_paths` and :class:`~torchrl_dhrl.planner.LandmarkGraph` rely on.

    Args:
        next_hop (Tensor): ``[N, N]`` int64 next-hop table (``next_hop[j, j] = j``, ``-1`` for
            unreachable pairs), e.g. from :func:`floyd_warshall`.

    Returns:
        Tensor: ``[N, N]`` int64 hop counts (``0`` on the diagonal and for unreachable pairs).

    Raises:
        ValueError: if the table has a cycle (some path never reaches its target) or an
            out-of-range entry.

    Examples:
        >>> import torch
        >>> next_hop = torch.tensor([[0, 1, 1], [-1, 1, 2], [-1, -1, 2]])
        >>> count_hops(next_hop).tolist()
        [[0, 1, 2], [0, 0, 1], [0, 0, 0]]
    """
    if next_hop.ndim != 2 or next_hop.shape[0] != next_hop.shape[1]:
        raise ValueError(f"`next_hop` must be a square [N, N] table, got shape {tuple(next_hop.shape)}.")
    n = next_hop.shape[0]
    if n == 0:
        return torch.zeros(0, 0, dtype=torch.int64, device=next_hop.device)
    next_hop = next_hop.to(torch.int64)
    targets = torch.arange(n, device=next_hop.device).expand(n, n)
    if bool(((next_hop < -1) | (next_hop >= n)).any()) or not torch.equal(next_hop.diagonal(), targets[0]):
        raise ValueError(f"`next_hop` entries must lie in [-1, {n}) with `next_hop[j, j] = j`.")
    reachable = next_hop >= 0
    # jump[i, j]: the node 2**t steps after i on the way to j (capped at j); hops: those steps
    jump = torch.where(reachable, next_hop, targets)
    hops = reachable.to(torch.int64)
    hops.fill_diagonal_(0)
    for _ in range(max(n - 2, 0).bit_length()):  # 2**rounds >= n - 1, the longest simple path
        hops.add_(hops.gather(0, jump))
        jump = jump.gather(0, jump)
    if not torch.equal(jump, targets):
        raise ValueError("`next_hop` has a cycle: some path never reaches its target.")
    return hops


@torch.no_grad()
def reconstruct_paths(
    next_hop: Tensor,
    hop_counts: Tensor,
    sources: Tensor,
    targets: Tensor,
    max_length: int | None = None,
    *,
    capturable: bool = False,
) -> tuple[Tensor, Tensor]:
    """Reads a batch of shortest paths out of a next-hop table, all rows at once.

    Args:
        next_hop (Tensor): ``[N, N]`` next-hop table from :func:`floyd_warshall`.
        hop_counts (Tensor): ``[N, N]`` hop counts from :func:`floyd_warshall` (or
            :func:`count_hops` of ``next_hop``); they set the path lengths, so they must match
            ``next_hop``.
        sources (Tensor): ``[B]`` int64 start nodes.
        targets (Tensor): ``[B]`` int64 end nodes. Rows whose target is unreachable from their
            source get an empty path.
        max_length (int, optional): keep at most this many nodes per path (the first ones).
            Defaults to the longest path in the batch.

    Keyword Args:
        capturable (bool): return exactly ``max_length`` columns (padded with ``-1``) instead of
            reading the longest path's length back to the host, so that the call has static shapes
            and no host synchronisation (``torch.compile(fullgraph=True)``, CUDA graphs). Needs
            ``max_length``. Defaults to ``False``.

    Returns:
        ``(paths, lengths)``: ``paths`` is ``[B, L]`` int64 (node indices, ``source`` first and
        ``target`` last, padded with ``-1``), ``lengths`` is ``[B]`` int64, the number of valid
        nodes of each row (``hop_count + 1``, capped at ``max_length``).

    Examples:
        >>> import torch
        >>> inf = float("inf")
        >>> w = torch.tensor([[0.0, 1.0, inf], [inf, 0.0, 1.0], [inf, inf, 0.0]])
        >>> sp = floyd_warshall(w)
        >>> sources, targets = torch.tensor([0, 2]), torch.tensor([2, 0])
        >>> paths, lengths = reconstruct_paths(sp.next_hop, sp.hop_counts, sources, targets)
        >>> paths.tolist(), lengths.tolist()
        ([[0, 1, 2], [-1, -1, -1]], [3, 0])
    """
    if sources.shape != targets.shape or sources.ndim != 1:
        raise ValueError(
            f"`sources` and `targets` must be 1-D of equal shape, got {tuple(sources.shape)} "
            f"and {tuple(targets.shape)}."
        )
    if capturable and (isinstance(max_length, bool) or not isinstance(max_length, int)):
        raise ValueError(f"`capturable=True` needs `max_length` (an int), got {max_length!r}.")
    num = sources.shape[0]
    reachable = next_hop[sources, targets] >= 0 if num else sources.new_zeros(0, dtype=torch.bool)
    full_lengths = torch.where(reachable, hop_counts[sources, targets] + 1, 0)
    if capturable:
        width = max_length
    else:
        longest = int(full_lengths.max()) if num else 0
        width = longest if max_length is None else min(longest, max_length)
    lengths = full_lengths.clamp_max(width)
    paths = torch.full((num, width), -1, dtype=torch.int64, device=sources.device)
    cursor = sources.clone()
    columns = torch.arange(width, device=sources.device)
    valid = columns.unsqueeze(0) < lengths.unsqueeze(1)
    for t in range(width):
        paths[:, t] = cursor
        cursor = next_hop[cursor, targets].clamp_min(0)
    paths.masked_fill_(~valid, -1)
    return paths, lengths
