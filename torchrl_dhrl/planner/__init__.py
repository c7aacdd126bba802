"""The graph level of DHRL: temporal distances, landmark graph, shortest paths, the GraphPlanner transform and FGS.

The swap points of the graph level live here:

- ``distances``: the :class:`TemporalDistance` protocol, the learned :class:`GoalDistance` and the
  oracle :class:`LineOfSightDistance`;
- ``edges``: the :class:`EdgeRule` protocol, the reference :class:`CutoffEdgeRule` and :class:`ConnectedEdgeRule`
  (a base rule's edges plus the shortest ones that keep the graph strongly connected; :func:`make_edge_rule` by name);
- ``graph``: :class:`LandmarkGraph` (FPS landmarks, edges, all-pairs shortest paths), composed into
  :class:`GraphPlanner`;
- ``fgs``: :class:`FrontierGoalShifting` and its env transform :class:`GoalShiftOnReset`.
"""

from .distances import AutocastDistance, GoalDistance, LineOfSightDistance, TemporalDistance
from .edges import ConnectedEdgeRule, CutoffEdgeRule, EdgeRule, make_edge_rule
from .fgs import FrontierGoalShifting, GoalShiftOnReset
from .fps import FarthestPointSamplingResult, farthest_point_sampling
from .graph import UNREACHABLE_RULES, GraphPlan, LandmarkGraph
from .graph_planner import GraphPlanner
from .shortest_paths import ShortestPaths, count_hops, floyd_warshall, reconstruct_paths
from .storage import DynamicStorage, FixedSizeStorage, GraphTensors

__all__ = [
    "AutocastDistance",
    "ConnectedEdgeRule",
    "CutoffEdgeRule",
    "EdgeRule",
    "FarthestPointSamplingResult",
    "FrontierGoalShifting",
    "GoalDistance",
    "GoalShiftOnReset",
    "GraphPlan",
    "UNREACHABLE_RULES",
    "GraphTensors",
    "DynamicStorage",
    "FixedSizeStorage",
    "GraphPlanner",
    "LandmarkGraph",
    "LineOfSightDistance",
    "ShortestPaths",
    "TemporalDistance",
    "count_hops",
    "farthest_point_sampling",
    "floyd_warshall",
    "make_edge_rule",
    "reconstruct_paths",
]
