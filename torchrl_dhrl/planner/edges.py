"""Edge rules of the landmark graph: which landmark pairs ``i -> j`` become graph edges.

- :class:`EdgeRule`: the protocol, ``edge_rule(distances[K, K], cutoff) -> bool[K, K]``;
- :class:`CutoffEdgeRule`: the reference rule (cutoff and nearest-neighbour edges), the default;
- :class:`ConnectedEdgeRule`: a base rule's edges plus the shortest edges that keep the graph strongly
  connected where the cutoff cuts it (ours; the recipe's ``planner.edge_rule=connected``);
- :func:`make_edge_rule`: a rule by its recipe name (:data:`EDGE_RULES`).
"""

from __future__ import annotations

import math
from typing import Protocol, runtime_checkable

import torch
from torch import Tensor

from torchrl_dhrl.checks import checked, choice

__all__ = ["EDGE_RULES", "ConnectedEdgeRule", "CutoffEdgeRule", "EdgeRule", "make_edge_rule", "reachability"]


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


def reachability(adjacency: Tensor) -> Tensor:
    """The reflexive transitive closure of a directed graph: ``reach[i, j]`` when ``j`` is reachable from ``i``.

    Repeated squaring of the ``[K, K]`` bool adjacency matrix (with the diagonal set) as float matrix
    products: ``ceil(log2(h)) + 1`` products of ``O(K^3)`` for paths of up to ``h`` hops, on the adjacency's
    device, no loop over landmarks (about 1 ms per product for ``K = 300`` on one CPU thread). The products
    count paths, so only ``> 0`` is read, exact in any floating precision.

    Args:
        adjacency (Tensor): ``[K, K]`` bool, ``adjacency[i, j]``: edge ``i -> j`` (the diagonal is ignored).

    Returns:
        ``[K, K]`` bool, ``True`` on the diagonal.

    Examples:
        >>> import torch
        >>> chain = torch.tensor([[False, True, False], [False, False, True], [False, False, False]])
        >>> reachability(chain).int().tolist()
        [[1, 1, 1], [0, 1, 1], [0, 0, 1]]
    """
    num = adjacency.shape[0]
    reach = adjacency.to(torch.bool) | torch.eye(num, dtype=torch.bool, device=adjacency.device)
    while True:
        counts = reach.to(torch.float32)
        longer = (counts @ counts) > 0.5  # paths of up to twice as many hops
        if torch.equal(longer, reach):
            return reach
        reach = longer


class ConnectedEdgeRule:
    """A base rule's edges, plus the shortest edges that connect what the base rule leaves cut apart (ours).

    The reference rule (:class:`CutoffEdgeRule`) drops every edge at or above ``cutoff`` steps (unless nearly as
    short as a landmark's nearest neighbour), so a learned distance a little too long cuts the graph: in a
    diagnosed AntMazeBottleneck run the shortest learned edge into the goal's corridor was 31.3 steps against
    the cutoff of 30, and the 13 landmarks there could not be planned to. A plan runs from any entry landmark
    (near the state) to any exit landmark (near the subgoal) along *directed* edges, so "connected" here means
    **strongly connected**: every landmark reaches every other one. This rule keeps every edge of ``base`` and
    then, while some landmark ``i`` with a finite ``distances[i, j]`` cannot reach ``j`` along the kept edges,
    adds the shortest such pair ``i -> j`` (ties: the lowest ``(i, j)``, row-major), as Kruskal's algorithm does
    for a spanning tree. So:

    - the graph is strongly connected whenever the finite distances connect it (a learned distance is finite
      everywhere); in general ``i`` reaches ``j`` whenever a path of finite distances leads from ``i`` to ``j``.
      Landmarks whose distances to (from) all others are ``inf`` (an oracle blocked by walls) get no edge out
      (in): a landmark with only infinite distances stays isolated;
    - every added edge was, when added, the shortest pair (ties: the lowest) that added any reachability, so it is
      the shortest edge from the strongly connected component of ``i`` to that of ``j`` at that point, and for
      every length ``t`` the kept edges of length ``<= t`` reach exactly what the base edges and all finite edges
      of length ``<= t`` reach: no plan needs a longer added edge than it must (the minimax path of a spanning
      tree), and an edge that adds no reachability is never added;
    - with a base graph that is already strongly connected (or reaches all it can), nothing is added: the result
      is the base rule's.

    The added edges carry their own (long) distances as weights, so shortest paths take them only where nothing
    shorter leads. Cost: the base rule, one :func:`reachability` (``O(K^3 log K)`` as float matrix products) and
    ``O(K^2)`` tensor operations per added edge, on the distances' device (two host reads per added edge);
    deterministic.

    Args:
        base (callable, optional): the rule whose edges are kept, an :class:`EdgeRule`. Defaults to
            ``CutoffEdgeRule()`` (the reference rule, ``nn_factor=1.2``).

    Examples:
        >>> import math, torch
        >>> inf = math.inf
        >>> distances = torch.tensor([[inf, 10.0, 50.0, 60.0], [10.0, inf, 40.0, 55.0],
        ...                           [45.0, 42.0, inf, 10.0], [70.0, 65.0, 10.0, inf]])
        >>> cut = CutoffEdgeRule(nn_factor=None)(distances, cutoff=30.0)  # {0, 1} and {2, 3}: cut apart
        >>> rule = ConnectedEdgeRule(base=CutoffEdgeRule(nn_factor=None))
        >>> keep, added = rule.connect(distances, cut)
        >>> added.tolist()  # 1 -> 2 (40 steps), then 2 -> 1 (42)
        [[1, 2], [2, 1]]
        >>> torch.equal(rule(distances, cutoff=30.0), keep)
        True
    """

    def __init__(self, base: EdgeRule | None = None) -> None:
        if base is not None and not callable(base):
            raise TypeError(f"`base` must be an edge rule (distances, cutoff) -> bool edges, got {base!r}.")
        self.base = CutoffEdgeRule() if base is None else base

    def __call__(self, distances: Tensor, cutoff: float) -> Tensor:
        keep = self.base(distances.clone(), cutoff)  # the base rule may write into its input
        if not isinstance(keep, Tensor) or keep.dtype != torch.bool or keep.shape != distances.shape:
            got = f"{keep.dtype} {tuple(keep.shape)}" if isinstance(keep, Tensor) else type(keep).__name__
            raise ValueError(
                f"The base rule {self.base!r} must return a bool tensor of shape {tuple(distances.shape)}, got {got}."
            )
        return self.connect(distances, keep)[0]

    @staticmethod
    @torch.no_grad()
    def connect(distances: Tensor, keep: Tensor) -> tuple[Tensor, Tensor]:
        """``keep`` and the edges that connect it: ``(keep | added, added)``.

        Args:
            distances (Tensor): ``[K, K]`` distances (the diagonal and ``inf``/``NaN`` entries never become edges).
            keep (Tensor): ``[K, K]`` bool, the base edges (kept, whatever their distance).

        Returns:
            the ``[K, K]`` bool edges (on the distances' device) and the ``[M, 2]`` int64 ``(i, j)`` pairs added,
            in the order they were added (ascending distance; ties: the lowest ``(i, j)``).
        """
        num, device = distances.shape[0], distances.device
        keep = keep.to(device=device, dtype=torch.bool)
        off_diagonal = ~torch.eye(num, dtype=torch.bool, device=device)
        reach = reachability(keep & off_diagonal)
        # the lengths of the pairs that would add reachability; inf for the others (never chosen)
        score = torch.where(torch.isfinite(distances) & off_diagonal & ~reach, distances, math.inf)
        flat, pairs = score.view(-1), []
        while num > 1:
            value, index = flat.min(dim=0)  # ties: the first (lowest row-major) index
            if not torch.isfinite(value):
                break
            i, j = divmod(int(index), num)
            pairs.append((i, j))
            # whatever reaches i now reaches whatever j reaches
            gained = reach[:, i, None] & reach[None, j, :]
            reach |= gained
            score.masked_fill_(gained, math.inf)
        added = torch.tensor(pairs, dtype=torch.int64, device=device).reshape(-1, 2)
        keep = keep.clone()
        keep[added[:, 0], added[:, 1]] = True
        return keep, added

    def __repr__(self) -> str:
        return f"{type(self).__name__}(base={self.base!r})"


#: The edge rules by the recipe's names (``planner.edge_rule``; the first is the default, the reference's).
EDGE_RULES = {"cutoff": CutoffEdgeRule, "connected": ConnectedEdgeRule}


@checked(edge_rule=choice(tuple(EDGE_RULES)))
def make_edge_rule(edge_rule: str = "cutoff") -> EdgeRule:
    """The edge rule named ``edge_rule``, with its defaults: ``"cutoff"`` (:class:`CutoffEdgeRule`, the reference
    rule) or ``"connected"`` (:class:`ConnectedEdgeRule` over it), see :data:`EDGE_RULES`.

    The recipe's ``planner.edge_rule`` reaches this function (its argument's name is the key), and the choice is
    checked before anything is built.

    Examples:
        >>> make_edge_rule("connected")
        ConnectedEdgeRule(base=CutoffEdgeRule(nn_factor=1.2))
        >>> try:
        ...     make_edge_rule("nearest")
        ... except ValueError as err:
        ...     print(err)
        `edge_rule` must be one of ('cutoff', 'connected'), got 'nearest'.
    """
    return EDGE_RULES[edge_rule]()
