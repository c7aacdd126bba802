"""The graph level of DHRL: landmark graph, shortest paths, the GraphPlanner transform and FGS."""

from .fgs import FrontierGoalShifting
from .fps import FarthestPointSamplingResult, farthest_point_sampling
from .graph import GraphPlan, LandmarkGraph
from .graph_planner import GraphPlanner
from .shortest_paths import ShortestPaths, floyd_warshall, reconstruct_paths

__all__ = [
    "FarthestPointSamplingResult",
    "FrontierGoalShifting",
    "GraphPlan",
    "GraphPlanner",
    "LandmarkGraph",
    "ShortestPaths",
    "farthest_point_sampling",
    "floyd_warshall",
    "reconstruct_paths",
]
