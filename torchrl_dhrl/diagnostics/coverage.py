"""How much of a maze's free space the landmarks cover."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchrl_dhrl.envs.geometry import MazeGeometry

__all__ = ["default_coverage_radius", "landmark_coverage"]


def default_coverage_radius(maze: str | MazeGeometry) -> float:
    """The ``coverage_radius`` of the recipe's ``diag/landmark_coverage``: half the maze's scale, half a corridor width
    (2 for PointMaze and AntMazeSmall, 4 for the other mazes; ``maze`` a built-in maze's name or a geometry that
    knows its ``scale``).

    Examples:
        >>> default_coverage_radius("PointMaze"), default_coverage_radius("AntMaze")
        (2.0, 4.0)
    """
    if isinstance(maze, MazeGeometry):
        if maze.scale is None:
            raise ValueError("default_coverage_radius: the geometry has no `scale`; pass coverage_radius.")
        return maze.scale / 2
    from torchrl_dhrl.envs import get_maze_spec

    return get_maze_spec(maze).layout.scale / 2


def landmark_coverage(geometry: MazeGeometry, landmarks: Tensor, radius: float) -> float:
    """The fraction of the free grid cells within ``radius`` of a landmark, in a straight line clear of walls.

    A free cell (of ``geometry``'s occupancy grid) is covered when some landmark goal lies within
    Euclidean distance ``radius`` of its centre and the segment between them crosses no wall box.

    Examples:
        >>> import torch
        >>> geometry = MazeGeometry.from_maze("PointMaze")
        >>> landmark_coverage(geometry, geometry.cell_centers[geometry.free], 0.1)
        1.0
        >>> round(landmark_coverage(geometry, torch.tensor([[0.0, 0.0]]), 2.0), 3)
        0.116
    """
    centers = geometry.cell_centers[geometry.free]  # [F, 2]
    landmarks = landmarks.float().cpu().reshape(-1, 2)
    if landmarks.shape[0] == 0 or centers.shape[0] == 0:
        return 0.0 if centers.shape[0] else math.nan
    cell, mark = (torch.cdist(centers, landmarks) <= radius).nonzero(as_tuple=True)
    clear = ~geometry.crosses_walls(centers[cell], landmarks[mark])
    covered = torch.zeros(centers.shape[0], dtype=torch.bool)
    covered[cell[clear]] = True
    return covered.float().mean().item()
