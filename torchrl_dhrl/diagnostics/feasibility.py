"""Whether the high level's subgoals and the planner's waypoints are feasible: the fractions inside walls
and outside the arena of a maze.
"""

from __future__ import annotations

import math

from tensordict import TensorDictBase
from torch import Tensor

from torchrl_dhrl.envs.geometry import MazeGeometry

__all__ = ["feasibility_fractions"]


def _fraction(mask: Tensor) -> float:
    return mask.float().mean().item() if mask.numel() else math.nan


def feasibility_fractions(geometry: MazeGeometry, rollout: TensorDictBase, *, margin: float = 0.0) -> dict:
    """The fractions of a rollout's subgoals and waypoints in walls and outside the arena.

    Subgoals: the ``subgoal`` entries of the steps where ``new_subgoal`` is ``True`` (the proposals,
    one per ``c_h`` steps), so each proposal counts once. Waypoints: the ``waypoint`` entry of every
    step, i.e. the fraction of steps spent chasing an infeasible waypoint. ``NaN`` where a rollout has
    none. "In walls" and "outside" are disjoint (see :class:`MazeGeometry`).

    Args:
        geometry (MazeGeometry): the maze.
        rollout (TensorDictBase): a ``[..., T]`` rollout with ``subgoal``, ``new_subgoal`` and ``waypoint``.

    Keyword Args:
        margin (float): wall growth of the "in walls" test (e.g. the agent's radius). Defaults to ``0``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> geometry = MazeGeometry.from_maze("PointMaze")
        >>> points = torch.tensor([[0.0, 0.0], [2.0, 4.0], [12.0, 0.0], [8.0, 4.0]])  # free, wall, out, free
        >>> td = TensorDict(subgoal=points, waypoint=points.flip(0),
        ...                 new_subgoal=torch.tensor([[True], [True], [True], [False]]), batch_size=[4])
        >>> {k: round(v, 3) for k, v in feasibility_fractions(geometry, td).items()}
        {'subgoals_in_walls': 0.333, 'subgoals_outside': 0.333,
         'waypoints_in_walls': 0.25, 'waypoints_outside': 0.25}
    """
    out = {}
    for name, points in (
        ("subgoals", rollout["subgoal"][rollout["new_subgoal"].squeeze(-1).bool()]),
        ("waypoints", rollout["waypoint"].reshape(-1, rollout["waypoint"].shape[-1])),
    ):
        points = points.reshape(-1, points.shape[-1])
        out[f"{name}_in_walls"] = _fraction(geometry.in_walls(points, margin))
        out[f"{name}_outside"] = _fraction(geometry.outside(points))
    return out
