"""Which landmarks a plan from a given state can use: the part of the graph connected to the start, how far
along the maze it reaches, and how close it comes to the goal.

A graph can hold landmarks all the way to the goal and still not lead there: an edge exists only where the
learned distance is below the cutoff, so landmarks in newly explored ground, whose distances the critics
still overestimate, can form an island no plan from the start enters. :func:`graph_reach` measures that gap.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchrl_dhrl.envs.geometry import MazeGeometry, furthest_progress

__all__ = ["graph_reach"]


@torch.no_grad()
def graph_reach(
    geometry: MazeGeometry,
    planner,
    state: Tensor,
    goal: Tensor | None = None,
    *,
    start: Tensor | None = None,
) -> dict:
    """The landmarks the planner can route to from ``state``, measured against the maze.

    A landmark is reachable when :meth:`~torchrl_dhrl.planner.LandmarkGraph.plan` has a route to it from
    ``state``: an entry edge of :meth:`~torchrl_dhrl.planner.LandmarkGraph.start_costs` (the planner's own
    rule, with its learned distance) followed by the graph's shortest paths. Returns:

    * ``reachable_landmarks``: the fraction of the landmarks reachable from ``state``;
    * ``reachable_progress``: the largest true path length from ``start`` to a reachable landmark (goal
      units): how far along the maze the plans from ``state`` can go (``landmark_progress`` of
      :func:`~torchrl_dhrl.diagnostics.graph_quality` is the same over every landmark);
    * ``goal_to_reachable``: the true path length from ``goal`` to the nearest reachable landmark: what a
      plan to ``goal`` must cover beyond the graph when ``goal`` is not itself reachable (``inf`` when no
      landmark is reachable, ``NaN`` without ``goal``);
    * ``bridge_distance``: the smallest learned distance ``landmark_distances[i, j]`` (steps) from a
      reachable landmark ``i`` to an unreachable one ``j``: how far the graph is from an edge into the rest
      (compare with ``cutoff``; ``inf`` when every landmark is reachable, or none).

    All ``NaN`` without a graph.

    Args:
        geometry (MazeGeometry): the maze.
        planner (GraphPlanner): the planner (its graph and its learned distance).
        state (Tensor): ``[obs_dim]`` the state plans start from (e.g. a test episode's first observation).
        goal (Tensor, optional): ``[goal_dim]`` the goal (its first two features are the position).

    Keyword Args:
        start (Tensor, optional): ``[2]`` where ``reachable_progress`` is measured from. Defaults to the
            origin, every maze's start.

    Examples:
        >>> import torch
        >>> from torchrl_dhrl.planner import CutoffEdgeRule, GraphPlanner, LandmarkGraph
        >>> geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
        >>> euclid = lambda s, g: (g - s[..., :2]).norm(dim=-1) / 0.2  # steps at 0.2 per step
        >>> planner = GraphPlanner(LandmarkGraph(cutoff=25.0, edge_rule=CutoffEdgeRule(nn_factor=None)), euclid,
        ...                        goal_dim=2)
        >>> goals = torch.tensor([[0.0, 0.0], [4.0, 0.0], [8.0, 0.0], [8.0, 8.0], [4.0, 8.0], [0.0, 8.0]])
        >>> _ = planner.graph.set_landmarks(goals, goals, euclid)  # 4 apart: 20 steps, an edge; 8 apart: 40, none
        >>> out = graph_reach(geometry, planner, torch.zeros(2), torch.tensor([0.0, 8.0]))
        >>> out["reachable_landmarks"], out["reachable_progress"], out["bridge_distance"]  # the far corridor: an island
        (0.5, 8.0, 40.0)
        >>> round(out["goal_to_reachable"], 1)  # from (0, 8) round the inner wall's end to (8, 0)
        14.0
    """
    graph = getattr(planner, "graph", None)
    if graph is None or not hasattr(planner, "distance"):
        raise TypeError(
            f"`planner` must be a GraphPlanner (a graph and its distance), got {type(planner).__name__}."
        )
    keys = ("reachable_landmarks", "reachable_progress", "goal_to_reachable", "bridge_distance")
    if not graph.has_graph:
        return dict.fromkeys(keys, math.nan)
    tensors = graph.planning_tensors()
    state = state.reshape(1, -1).to(device=tensors.states.device, dtype=tensors.states.dtype)
    entry = graph.start_costs(state, planner.distance)[0]  # [K]
    routes = (entry[:, None] + tensors.shortest).amin(0)  # [K]: the cheapest route to each landmark
    reachable = torch.isfinite(routes).cpu()
    goals = tensors.goals.detach().float().cpu()[:, :2]
    out = {"reachable_landmarks": int(reachable.sum()) / reachable.numel()}
    progress = furthest_progress(geometry, goals[reachable], start)
    out["reachable_progress"] = progress if math.isfinite(progress) else math.nan
    if goal is None:
        out["goal_to_reachable"] = math.nan
    elif reachable.any():
        to_goal = geometry.path_length(goal.reshape(-1)[:2].float().cpu(), goals[reachable])
        out["goal_to_reachable"] = to_goal.min().item()
    else:
        out["goal_to_reachable"] = math.inf
    across = tensors.distances.detach().float().cpu()[reachable][:, ~reachable]
    out["bridge_distance"] = across.min().item() if across.numel() else math.inf
    return out
