"""How much of a maze's free space the landmarks cover, walls blocking the view."""

import pytest
import torch
from torchrl_dhrl.envs.geometry import MazeGeometry

from tests.envs.test_geometry import _visible_by_sampling
from torchrl_dhrl.diagnostics import landmark_coverage


def test_landmark_coverage():
    geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
    every_cell = geometry.cell_centers[geometry.free]
    assert landmark_coverage(geometry, every_cell, 0.01) == 1.0
    one = landmark_coverage(geometry, torch.tensor([[0.0, 0.0]]), 2.0)
    assert 0.0 < one < 0.2
    assert landmark_coverage(geometry, torch.zeros(0, 2), 2.0) == 0.0
    # the inner wall blocks: a landmark under it does not cover the top corridor within 8 units
    below = torch.tensor([[0.0, 1.0]])
    centers = geometry.cell_centers[geometry.free]
    within = ((centers - below).norm(dim=-1) <= 8.0).float().mean().item()
    near = centers[(centers - below).norm(dim=-1) <= 8.0]
    visible = [_visible_by_sampling(geometry, below[0], c, 0.0) for c in near]
    expected = sum(visible) / centers.shape[0]
    assert landmark_coverage(geometry, below, 8.0) == pytest.approx(expected, abs=2 / centers.shape[0])
    assert expected < within - 0.1
