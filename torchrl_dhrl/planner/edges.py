"""Edge rules of the landmark graph: which landmark pairs ``i -> j`` become graph edges."""

from __future__ import annotations

import math
from typing import Protocol, runtime_checkable

from torch import Tensor

__all__ = ["CutoffEdgeRule", "EdgeRule"]


@runtime_checkable
class EdgeRule(Protocol):
    """The protocol of an edge rule: ``edge_rule(distances, cutoff) -> keep``.

    :meth:`LandmarkGraph.set_distance_matrix <torchrl_dhrl.planner.LandmarkGraph.set_distance_matrix>`
    (and so every :meth:`~torchrl_dhrl.planner.LandmarkGraph.build`) calls the graph's ``edge_rule``
    once per build with

    - ``distances``: the ``[K, K]`` landmark distance matrix, ``distances[i, j] = d(state_i -> goal_j)``
      in env steps, ``>= 0``, with ``inf`` on the diagonal (no self loops); a copy, which the rule
      may modify;
    - ``cutoff``: the graph's ``cutoff`` (the threshold it also uses to connect a query's state and
      subgoal to the landmarks),

    and expects a ``[K, K]`` bool tensor: ``keep[i, j]`` makes ``i -> j`` a directed edge weighing
    ``distances[i, j]``. The diagonal of the result is ignored. Shortest paths (and so plans) only
    follow kept edges. Any callable qualifies (a function, a ``lambda`` or an ``nn.Module``, kept as a
    plain attribute of the graph, not a submodule).

    Examples:
        >>> import torch
        >>> from torchrl_dhrl.planner import LandmarkGraph
        >>> def within_cutoff(distances, cutoff):  # no nearest-neighbour edges
        ...     return distances < cutoff
        >>> isinstance(within_cutoff, EdgeRule)
        True
        >>> points = torch.tensor([[0.0, 0.0], [1.0, 0.0], [3.0, 0.0]])
        >>> dist = lambda s, g: (g - s[..., :2]).norm(dim=-1)
        >>> graph = LandmarkGraph(cutoff=1.5, edge_rule=within_cutoff).set_landmarks(points, points, dist)
        >>> graph.edges.tolist()  # landmark 2 is 2 steps from its nearest neighbour: isolated
        [[0, 1], [1, 0]]
    """

    def __call__(self, distances: Tensor, cutoff: float) -> Tensor:
        """``Tensor[K, K]`` distances (``inf`` diagonal), the cutoff -> ``Tensor[K, K]`` bool edges."""
        ...


class CutoffEdgeRule:
    """DHRL's edge rule: ``i -> j`` when ``D[i, j] < cutoff`` or ``D[i, j] < nn_factor * min_k D[i, k]``.

    The reference rule of the landmark graph (the default ``edge_rule`` of
    :class:`~torchrl_dhrl.planner.LandmarkGraph`): a landmark connects to every landmark its distance
    puts within ``cutoff`` steps, and also to the landmarks nearly as close as its nearest one (within
    ``nn_factor`` times that distance), so that every landmark keeps at least one outgoing edge even
    when the learned distances are still large. ``nn_factor=None`` keeps the cutoff edges only (as
    does ``nn_factor=1.0``: the comparisons are strict).

    Args:
        nn_factor (float, optional): the nearest-neighbour factor (``> 0``). Defaults to ``1.2``;
            ``None`` disables the nearest-neighbour edges.

    Examples:
        >>> import math, torch
        >>> distances = torch.tensor([[math.inf, 40.0, 45.0], [5.0, math.inf, 60.0], [50.0, 50.0, math.inf]])
        >>> CutoffEdgeRule()(distances, cutoff=30.0).int().tolist()  # row 0: 40, 45 < 1.2 x 40
        [[0, 1, 1], [1, 0, 0], [1, 1, 0]]
        >>> CutoffEdgeRule(nn_factor=None)(distances, cutoff=30.0).int().tolist()  # only 5 < 30
        [[0, 0, 0], [1, 0, 0], [0, 0, 0]]
    """

    def __init__(self, nn_factor: float | None = 1.2) -> None:
        if nn_factor is not None and (
            isinstance(nn_factor, bool)
            or not isinstance(nn_factor, (int, float))
            or math.isnan(nn_factor)
            or nn_factor <= 0
        ):
            raise ValueError(f"`nn_factor` must be a number > 0 or None, got {nn_factor!r}.")
        self.nn_factor = None if nn_factor is None else float(nn_factor)

    def __call__(self, distances: Tensor, cutoff: float) -> Tensor:
        keep = distances < cutoff
        if self.nn_factor is not None:
            nearest = distances.min(dim=1, keepdim=True).values
            keep = keep | (distances < self.nn_factor * nearest)
        return keep

    def __repr__(self) -> str:
        return f"{type(self).__name__}(nn_factor={self.nn_factor})"
