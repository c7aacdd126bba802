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
            unreachable or ``i == j``).
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
    next-hop table acyclic even with zero-weight edges.

    The next-hop and hop-count tables are packed into one integer tensor (next hop in the high
    bits, hop count in the low bits) so that a single masked update moves both.

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
    # int32 packing (next << 16 | hops) while both fit in 15 bits, int64 (next << 32 | hops) beyond.
    if n < 2**15:
        dtype, shift = torch.int32, 16
    else:
        dtype, shift = torch.int64, 32
    low_mask = (1 << shift) - 1
    arange = torch.arange(n, device=device, dtype=dtype)
    finite = torch.isfinite(dist)
    # Unreachable pairs start with next hop 0 (masked to -1 at the end) so that every packed value
    # stays in [0, 2**31) and differences of packed values never overflow.
    nxt = torch.where(finite, arange.expand(n, n), torch.zeros((), dtype=dtype, device=device))
    nxt.diagonal().copy_(arange)
    hops = finite.to(dtype)
    hops.diagonal().zero_()
    packed = (nxt << shift) | hops

    cand = torch.empty_like(dist)
    better = torch.empty(n, n, dtype=dtype, device=device)
    update = torch.empty_like(packed)
    for k in range(n):
        torch.add(dist[:, k : k + 1], dist[k : k + 1, :], out=cand)
        torch.lt(cand, dist, out=better)
        torch.minimum(dist, cand, out=dist)
        # packed[i, j] <- packed[i, k] + hops[k, j] where the path through k is strictly better:
        # the next hop of i -> j becomes that of i -> k, the hop count adds up.
        torch.add(packed[:, k : k + 1], (packed[k] & low_mask).unsqueeze(0), out=update)
        update.sub_(packed).mul_(better)
        packed.add_(update)
    next_hop = (packed >> shift).to(torch.int64)
    hop_counts = (packed & low_mask).to(torch.int64)
    unreachable = torch.isinf(dist)
    next_hop.masked_fill_(unreachable, -1)
    hop_counts.masked_fill_(unreachable, 0)
    return ShortestPaths(dist, next_hop, hop_counts)


@torch.no_grad()
def reconstruct_paths(
    next_hop: Tensor, hop_counts: Tensor, sources: Tensor, targets: Tensor, max_length: int | None = None
) -> tuple[Tensor, Tensor]:
    """Reads a batch of shortest paths out of a next-hop table, all rows at once.

    Args:
        next_hop (Tensor): ``[N, N]`` next-hop table from :func:`floyd_warshall`.
        hop_counts (Tensor): ``[N, N]`` hop counts from :func:`floyd_warshall`.
        sources (Tensor): ``[B]`` int64 start nodes.
        targets (Tensor): ``[B]`` int64 end nodes. Rows whose target is unreachable from their
            source get an empty path.
        max_length (int, optional): keep at most this many nodes per path (the first ones).
            Defaults to the longest path in the batch.

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
    num = sources.shape[0]
    reachable = next_hop[sources, targets] >= 0 if num else sources.new_zeros(0, dtype=torch.bool)
    full_lengths = torch.where(reachable, hop_counts[sources, targets] + 1, 0)
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
