"""Subgoal feasibility against the maze's true geometry: the fractions inside walls and outside the arena."""

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl_dhrl.envs.geometry import MazeGeometry

from torchrl_dhrl.diagnostics import feasibility_fractions


def test_feasibility_fractions_of_hand_made_subgoals():
    geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
    wall = [[4.0, 4.0], [2.0, 4.0], [0.0, 3.0]]  # inner wall, incl. a face shared by two blocks
    outside = [[12.0, 0.0], [-3.0, 5.0]]  # beyond the arena [-2, 10]^2 (the second also in an outer wall)
    free = [[0.0, 0.0], [8.0, 4.0], [0.0, 8.0], [0.0, 1.7]]  # the last 0.3 from the inner wall
    points = torch.tensor(wall + outside + free)
    assert geometry.in_walls(points).tolist() == [True] * 3 + [False] * 6
    assert geometry.outside(points).tolist() == [False] * 3 + [True] * 2 + [False] * 4
    assert geometry.feasible(points).tolist() == [False] * 5 + [True] * 4
    assert geometry.in_walls(points, margin=0.5).tolist() == [True] * 3 + [False] * 5 + [True]
    # a [2, 9] rollout: proposals at the first 3 steps of env 0 and 2 steps of env 1
    new = torch.zeros(2, 9, 1, dtype=torch.bool)
    new[0, :3] = True  # 3 wall points
    new[1, [3, 5]] = True  # an outside point and a free one
    td = TensorDict(
        subgoal=points.expand(2, 9, 2),
        waypoint=torch.stack([points, points.flip(0)]),
        new_subgoal=new,
        batch_size=[2, 9],
    )
    out = feasibility_fractions(geometry, td)
    assert out["subgoals_in_walls"] == pytest.approx(3 / 5)
    assert out["subgoals_outside"] == pytest.approx(1 / 5)
    assert out["waypoints_in_walls"] == pytest.approx(6 / 18)
    assert out["waypoints_outside"] == pytest.approx(4 / 18)
    strict = feasibility_fractions(geometry, td, margin=0.5)
    assert strict["waypoints_in_walls"] == pytest.approx(8 / 18)
    # no proposal at all: NaN, not 0
    none = feasibility_fractions(geometry, td.set("new_subgoal", torch.zeros_like(new)))
    assert math.isnan(none["subgoals_in_walls"]) and math.isnan(none["subgoals_outside"])
