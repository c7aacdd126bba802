"""Maze layouts: cell coordinates, bad grids, wall membership."""

from __future__ import annotations

import numpy as np
import pytest
from torchrl_dhrl.envs import COMPLEX_MAZE, U_MAZE, MazeLayout


def test_layout_coordinates():
    small = MazeLayout(U_MAZE, scale=4.0)
    assert small.start_cell == (1, 1) and small.goal_cell == (3, 1)
    np.testing.assert_allclose(small.cell_center(1, 1), [0.0, 0.0])
    np.testing.assert_allclose(small.cell_center(3, 1), [0.0, 8.0])  # rows map to y
    np.testing.assert_allclose(small.cell_center(1, 3), [8.0, 0.0])  # columns map to x
    low, high = small.bounds
    np.testing.assert_allclose(low, [-2, -2]) and np.testing.assert_allclose(high, [10, 10])
    complex_low, complex_high = MazeLayout(COMPLEX_MAZE, scale=8.0).bounds
    np.testing.assert_allclose(complex_low, [-4, -4]) and np.testing.assert_allclose(complex_high, [52, 52])
    assert small.in_free_cell([[0.0, 0.0], [4.0, 4.0], [8.0, 4.0], [100.0, 0.0]]).tolist() == [
        True,
        False,
        True,
        False,
    ]


@pytest.mark.parametrize("grid", [("111", "1r1", "11"), ("111", "101", "111"), ("111", "1x1", "1r1")])
def test_layout_rejects_bad_grids(grid):
    with pytest.raises(ValueError):
        MazeLayout(grid, scale=1.0)


def test_in_wall_counts_shared_block_faces_as_inside():
    """The inner wall of the U is two blocks: the face they share is wall, the face on free space is not."""
    from torchrl_dhrl.envs import get_maze_spec

    layout = get_maze_spec("PointMaze").layout
    points = [
        [2.0, 4.0],
        [-2.0, 4.0],
        [4.0, 4.0],
        [6.0, 4.0],
        [5.999, 4.0],
        [6.001, 4.0],
        [2.0, 2.0],
        [0.0, 0.0],
    ]
    assert layout.in_wall(points).tolist() == [True, True, True, False, True, False, False, False]
    # grown by a margin, the free-facing face moves out with it
    assert layout.in_wall([[6.3, 4.0], [6.6, 4.0]], margin=0.5).tolist() == [True, False]
