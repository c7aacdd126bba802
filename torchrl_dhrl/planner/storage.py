"""Where a landmark graph's plans read its tensors: the graph's own buffers, or fixed-size capture-safe copies.

A :class:`~torchrl_dhrl.planner.LandmarkGraph` keeps its landmarks, distances and shortest paths in its own buffers,
``K`` rows, reallocated by every rebuild (they are its ``state_dict``). Its planning storage, a strategy object, says
what a capture-safe query (``capturable=True``: a compiled policy, a CUDA graph) reads:

- :class:`DynamicStorage`: nothing of its own; queries read the graph's buffers (shapes follow the landmarks).
- :class:`FixedSizeStorage`: copies at ``max_landmarks`` rows (the landmarks first, then invalid padding rows),
  updated in place at every rebuild and clear, so that their shapes and storage never change.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor, nn

#: the graph a storage reads: a :class:`~torchrl_dhrl.planner.LandmarkGraph` (not imported here: it imports this module)
_Graph = nn.Module

__all__ = ["DynamicStorage", "FixedSizeStorage", "GraphTensors", "own_tensors"]


class GraphTensors(NamedTuple):
    """The tensors a plan reads (:meth:`LandmarkGraph.planning_tensors <torchrl_dhrl.planner.LandmarkGraph.planning_tensors>`).

    Either the graph's own buffers (``K`` landmarks, ``valid`` is ``None``) or a ``fixed_size`` graph's copies of
    them at ``max_landmarks`` rows: the landmarks first, then padding rows that ``valid`` marks invalid (no edge
    to or from them, never an entry or an exit of a plan).

    Attributes:
        states (Tensor): ``[K, obs_dim]`` landmark states.
        goals (Tensor): ``[K, goal_dim]`` landmark goals.
        distances (Tensor): ``[K, K]`` landmark distance matrix.
        shortest (Tensor): ``[K, K]`` all-pairs shortest distances.
        next_hop (Tensor): ``[K, K]`` int64 next-hop table.
        hop_counts (Tensor): ``[K, K]`` int64 hop counts.
        valid (Tensor or None): ``[K]`` bool, which rows are landmarks.
        version (Tensor): the graph's build counter (int64 scalar).
    """

    states: Tensor
    goals: Tensor
    distances: Tensor
    shortest: Tensor
    next_hop: Tensor
    hop_counts: Tensor
    valid: Tensor | None
    version: Tensor


def own_tensors(graph: _Graph) -> GraphTensors | None:
    """The graph's own buffers as :class:`GraphTensors` (``valid`` is ``None``), ``None`` without landmarks."""
    if not graph.has_graph:
        return None
    return GraphTensors(
        graph.landmark_states,
        graph.landmark_goals,
        graph.landmark_distances,
        graph.shortest_distances,
        graph.next_hop,
        graph.hop_counts,
        None,
        graph.version,
    )


class DynamicStorage(nn.Module):
    """The planning storage of a graph whose queries read its own buffers (``fixed_size=False``): nothing to keep,
    nothing to reserve; capture-safe queries get no tensors of their own.

    Examples:
        >>> from torchrl_dhrl.planner import LandmarkGraph
        >>> graph = LandmarkGraph()
        >>> type(graph.storage).__name__, graph.storage.capture_tensors() is None
        ('DynamicStorage', True)
    """

    def update(self, graph: _Graph) -> None:
        """Nothing: the graph's buffers are what its queries read."""

    def capture_tensors(self) -> GraphTensors | None:
        """``None``: a capture-safe query reads the graph's own buffers."""
        return None

    def reserve(self, graph: _Graph, obs_dim, goal_dim, dtype, device) -> None:
        raise ValueError(
            "reserve() allocates the fixed-size planning tensors of a graph made with fixed_size=True; this "
            "graph has fixed_size=False."
        )


#: :class:`FixedSizeStorage`'s tensors, in :class:`GraphTensors`' order (``version`` last).
_FIXED = ("states", "goals", "distances", "shortest", "next_hop", "hop_counts", "valid")


class FixedSizeStorage(nn.Module):
    """Capture-safe planning tensors of a graph: copies of its buffers at ``max_landmarks`` rows (the landmarks,
    then padding rows with no edge to or from them, marked invalid), written in place at every :meth:`update`.

    Allocated by :meth:`reserve` (before the first build: every row padding) or by the first update that has
    landmarks, again when the feature sizes, dtype or device change; non-persistent buffers (derived from the
    graph, so not in its ``state_dict``). Their shapes and storage stay the same across rebuilds, so that a policy
    compiled or captured in a CUDA graph reads every later graph.

    The number of rows is the graph's ``max_landmarks`` when they are allocated (a change of it reallocates them at
    the next update).

    Examples:
        >>> import torch
        >>> from torchrl_dhrl.planner import LandmarkGraph
        >>> graph = LandmarkGraph(max_landmarks=6, fixed_size=True)  # rows: max_landmarks
        >>> type(graph.storage).__name__, graph.storage.capture_tensors() is None  # not allocated yet
        ('FixedSizeStorage', True)
        >>> points = torch.rand(30, 2)
        >>> _ = graph.build(points, points, lambda s, g: (s - g).norm(dim=-1))
        >>> tensors = graph.storage.capture_tensors()
        >>> tuple(tensors.states.shape), int(tensors.valid.sum()) == graph.num_landmarks
        ((6, 2), True)
    """

    def __init__(self) -> None:
        super().__init__()
        for name in _FIXED:
            dtype = torch.int64 if "hop" in name else torch.bool if name == "valid" else None
            self.register_buffer(name, torch.zeros(0, 0, dtype=dtype), persistent=False)
        self.register_buffer("version", torch.zeros((), dtype=torch.int64), persistent=False)

    @property
    def allocated(self) -> bool:
        """Whether the tensors exist (after :meth:`reserve` or a first update with landmarks)."""
        return self.valid.numel() > 0

    def capture_tensors(self) -> GraphTensors | None:
        """The fixed-size tensors, ``None`` before they are allocated."""
        if not self.allocated:
            return None
        return GraphTensors(*(getattr(self, name) for name in _FIXED), self.version)

    def reserve(self, graph: _Graph, obs_dim: int, goal_dim: int, dtype, device) -> None:
        """Allocates the tensors, every row padding (see :meth:`LandmarkGraph.reserve
        <torchrl_dhrl.planner.LandmarkGraph.reserve>`)."""
        self._allocate(graph.max_landmarks, obs_dim, goal_dim, (dtype, dtype, dtype, dtype), device)
        self._fill(graph, 0)
        self.version = self.version.to(device)
        self.version.copy_(graph.version)

    @torch.no_grad()
    def update(self, graph: _Graph) -> None:
        """Copies the graph into the tensors, in place (allocating them at its first landmarks, again when the
        feature sizes, dtype or device change); without landmarks every row becomes padding."""
        num, size = graph.num_landmarks, graph.max_landmarks
        if num > size:
            raise ValueError(f"A fixed_size graph holds at most max_landmarks={size} landmarks, got {num}.")
        if num:
            dtypes = tuple(
                getattr(graph, name).dtype
                for name in ("landmark_states", "landmark_goals", "landmark_distances", "shortest_distances")
            )
            self._allocate(
                size,
                graph.landmark_states.shape[1],
                graph.landmark_goals.shape[1],
                dtypes,
                graph.landmark_states.device,
            )
            self._fill(graph, num)
        elif self.allocated:
            self.valid.fill_(False)
        if self.version.device != graph.version.device:
            self.version = torch.zeros((), dtype=torch.int64, device=graph.version.device)
        self.version.copy_(graph.version)

    def _allocate(
        self, size: int, obs_dim: int, goal_dim: int, dtypes: tuple[torch.dtype, ...], device: torch.device
    ) -> None:
        """(Re)allocates the tensors whose size, dtype or device differ from the given ones (``size`` rows)."""
        states, goals, distances, shortest = dtypes
        layout = {
            "states": ((size, obs_dim), states),
            "goals": ((size, goal_dim), goals),
            "distances": ((size, size), distances),
            "shortest": ((size, size), shortest),
            "next_hop": ((size, size), torch.int64),
            "hop_counts": ((size, size), torch.int64),
            "valid": ((size,), torch.bool),
        }
        for name, (shape, dtype) in layout.items():
            old = getattr(self, name)
            if old.shape != shape or old.dtype != dtype or old.device != device:
                setattr(self, name, torch.empty(shape, dtype=dtype, device=device))

    def _fill(self, graph: _Graph, num: int) -> None:
        """Writes the graph's first ``num`` landmarks, in place; the other rows are padding (no edge to or from
        them, themselves at no cost like Floyd-Warshall's diagonal, invalid)."""
        pad = slice(num, None)
        for name, source, fill, square in (
            ("states", graph.landmark_states, 0.0, False),
            ("goals", graph.landmark_goals, 0.0, False),
            ("distances", graph.landmark_distances, math.inf, True),
            ("shortest", graph.shortest_distances, math.inf, True),
            ("next_hop", graph.next_hop, -1, True),
            ("hop_counts", graph.hop_counts, 0, True),
        ):
            target = getattr(self, name)
            if square:  # the [K, K] block, the rest padding
                target.fill_(fill)
                if num:
                    target[:num, :num].copy_(source)
            else:
                if num:
                    target[:num].copy_(source)
                target[pad].fill_(fill)
        rows = torch.arange(num, self.valid.shape[0], device=self.valid.device)
        self.shortest[rows, rows] = 0.0
        self.distances[rows, rows] = 0.0
        self.next_hop[rows, rows] = rows
        self.valid[:num] = True
        self.valid[pad] = False

    def extra_repr(self) -> str:
        return f"rows={self.valid.shape[0]}, allocated={self.allocated}"
