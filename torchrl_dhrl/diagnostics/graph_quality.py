"""The landmark graph against the true geometry: edges crossing walls, shortcuts, and how the learned
distances rank landmark pairs against the obstacle-free path lengths.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchrl_dhrl.envs.geometry import MazeGeometry, furthest_progress

from .coverage import landmark_coverage
from .feasibility import _fraction
from .statistics import spearman_correlation

__all__ = ["graph_quality"]


def _source_pairs(num: int, max_sources: int | None) -> tuple[Tensor, Tensor]:
    """Rows ``i < max_sources`` (the first landmarks: FPS order spreads them out) and every other column."""
    sources = torch.arange(min(num, max_sources or num))
    rows, cols = torch.meshgrid(sources, torch.arange(num), indexing="ij")
    keep = rows != cols
    return rows[keep], cols[keep]


def graph_quality(
    geometry: MazeGeometry,
    planner,
    *,
    coverage_radius: float,
    max_sources: int | None = 64,
    shortcut_ratio: float = 1.5,
    start: Tensor | None = None,
    return_pairs: bool = False,
):
    """The planner's graph against the maze: edges through walls, distance ranks, coverage, reach.

    * ``edges_crossing_walls``: the fraction of directed graph edges whose straight segment between the
      two landmark goals crosses a wall box (not inflated). An edge around a wall's corner counts too,
      though the agent can follow it with a small detour;
    * ``edges_shortcut``: the fraction of edges whose true path length is more than ``shortcut_ratio``
      times the straight distance between their landmarks: edges through a wall, which the graph
      believes short and which in fact need a long way round (corner cuts do not count); over the
      edges leaving the first ``max_sources`` landmarks (whose distance fields are computed anyway);
    * ``distance_rank_corr``: Spearman's correlation between the learned landmark-to-landmark distance
      ``landmark_distances[i, j] = d(state_i -> goal_j)`` and the true path length
      (:meth:`MazeGeometry.path_length`) between the goals, over the pairs ``(i, j)``, ``i != j``, with
      ``i`` among the first ``max_sources`` landmarks (all pairs when ``None``);
    * ``graph_distance_rank_corr``: the same with the graph's all-pairs shortest distances (``inf`` for
      disconnected pairs, ranked last);
    * ``landmark_coverage``: :func:`landmark_coverage` with ``coverage_radius``;
    * ``landmark_progress``: how far the graph reaches into the maze, the largest true path length from
      ``start`` to a landmark (goal units; the U of AntMaze is about 37 long from the start to the test goal).

    All ``NaN`` without a graph.

    Args:
        geometry (MazeGeometry): the maze.
        planner (GraphPlanner or LandmarkGraph): its graph (2-D goals).

    Keyword Args:
        coverage_radius (float): the radius of :func:`landmark_coverage`.
        max_sources (int, optional): landmarks whose rows enter the rank correlations (a distance field
            each). Defaults to ``64``.
        shortcut_ratio (float): see ``edges_shortcut``. Defaults to ``1.5``.
        start (Tensor, optional): ``[2]`` where ``landmark_progress`` is measured from. Defaults to the
            origin, every maze's start.
        return_pairs (bool): also return ``(rows, cols, true, learned, graph)`` tensors of those pairs.

    Examples:
        >>> import torch
        >>> from torchrl_dhrl.planner import LandmarkGraph
        >>> geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
        >>> goals = torch.tensor([[0.0, 0.0], [4.0, 0.0], [8.0, 0.0], [8.0, 8.0], [0.0, 8.0]])
        >>> euclid = lambda s, g: (g - s[..., :2]).norm(dim=-1)
        >>> graph = LandmarkGraph(cutoff=8.5).set_landmarks(goals, goals, euclid)  # ignores the wall
        >>> out = graph_quality(geometry, graph, coverage_radius=2.0)
        >>> round(out["edges_crossing_walls"], 2), round(out["distance_rank_corr"], 2)
        (0.29, 0.72)
        >>> round(out["landmark_progress"], 1)  # (0, 8): behind the U's inner wall, the long way round
        19.0
    """
    graph = getattr(planner, "graph", planner)
    nan = {
        "edges_crossing_walls": math.nan,
        "edges_shortcut": math.nan,
        "distance_rank_corr": math.nan,
        "graph_distance_rank_corr": math.nan,
        "landmark_coverage": math.nan,
        "landmark_progress": math.nan,
    }
    if not graph.has_graph:
        return (nan, None) if return_pairs else nan
    goals = graph.landmark_goals.detach().float().cpu()
    edges = graph.edges.cpu()
    crossing = geometry.crosses_walls(goals[edges[:, 0]], goals[edges[:, 1]])
    out = {"edges_crossing_walls": _fraction(crossing)}
    # true path lengths from the first landmarks (one distance field each) to all
    num_sources = min(goals.shape[0], max_sources or goals.shape[0])
    true_matrix = geometry.path_length(goals[:num_sources, None], goals[None])  # [S, K]
    from_source = edges[edges[:, 0] < num_sources]
    straight = (goals[from_source[:, 1]] - goals[from_source[:, 0]]).norm(dim=-1)
    shortcut = true_matrix[from_source[:, 0], from_source[:, 1]] > shortcut_ratio * straight
    out["edges_shortcut"] = _fraction(shortcut)
    rows, cols = _source_pairs(goals.shape[0], max_sources)
    if rows.numel():
        true = true_matrix[rows, cols]
        learned = graph.landmark_distances.detach().float().cpu()[rows, cols]
        shortest = graph.shortest_distances.detach().float().cpu()[rows, cols]
        out["distance_rank_corr"] = spearman_correlation(learned, true)
        out["graph_distance_rank_corr"] = spearman_correlation(shortest, true)
    else:
        true = learned = shortest = torch.zeros(0)
        out["distance_rank_corr"] = out["graph_distance_rank_corr"] = math.nan
    out["landmark_coverage"] = landmark_coverage(geometry, goals, coverage_radius)
    reach = furthest_progress(geometry, goals, start)
    out["landmark_progress"] = reach if math.isfinite(reach) else math.nan
    if return_pairs:
        return out, (rows, cols, true, learned, shortest)
    return out
