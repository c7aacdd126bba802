"""The graph rebuilt from one buffer with several landmark budgets, against a direct computation."""

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl_dhrl.envs.geometry import MazeGeometry

from torchrl_dhrl.diagnostics import landmark_budget_sweep, landmark_coverage
from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph


def _maze_points(geometry: MazeGeometry, count: int, generator: torch.Generator) -> torch.Tensor:
    """``count`` random free grid-cell centres of ``geometry`` reachable from the start."""
    centers = geometry.cell_centers[geometry.free]
    centers = centers[torch.isfinite(geometry.path_length(torch.zeros(2), centers))]
    return centers[torch.randint(0, centers.shape[0], (count,), generator=generator)]


@pytest.mark.parametrize("lanes", [1, pytest.param(3, marks=pytest.mark.slow)])
def test_landmark_budget_sweep_against_direct_progress(lanes):
    """Over random buffers of maze points: a graph reaches at most as far as its buffer, a budget holding every
    point reaches exactly as far, more landmarks from the same candidates never reach less far (FPS is
    greedy), the rows match a direct computation from the rebuilt landmarks, and the planner is untouched."""
    geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
    generator = torch.Generator().manual_seed(0)
    distance = lambda s, g: (s[..., :2] - g).norm(dim=-1)  # noqa: E731
    for trial in range(6):
        count = int(torch.randint(4, 40, (1,), generator=generator)) * lanes
        points = _maze_points(geometry, count, generator)
        if trial == 0:
            points[:] = points[:1]  # every state the same: a single landmark, progress of that point
        storage = LazyTensorStorage(4 * count, ndim=2 if lanes > 1 else 1)  # max_size: elements, not rows
        rb = ReplayBuffer(storage=storage)
        data = TensorDict(
            observation=torch.cat([points, torch.randn(count, 2)], -1),
            achieved_goal=points,
            batch_size=[count],
        )
        rb.extend(data.reshape(count // lanes, lanes) if lanes > 1 else data)
        planner = GraphPlanner(LandmarkGraph(cutoff=3.0, early_stop=0.0), distance, goal_dim=2)
        planner.build(data["observation"][:2], points[:2])
        before = {k: v.clone() for k, v in planner.state_dict().items()}
        budgets = [(1, 60 * count), (3, 60 * count), (count, 60 * count), (3, 5)]
        rows, buffer_progress = landmark_budget_sweep(
            geometry, planner, rb, budgets, draws=2, coverage_radius=2.0, generator=generator
        )
        expected = max(geometry.path_length(torch.zeros(2), points).tolist())
        assert buffer_progress == pytest.approx(expected)
        assert [(r["max_landmarks"], r["candidates"]) for r in rows] == budgets
        for row in rows:
            assert (
                row["progress_min"] <= row["progress_mean"] <= row["progress_max"] <= buffer_progress + 1e-5
            )
            assert 0.0 < row["coverage_mean"] <= 1.0 and 1 <= row["landmarks"] <= row["max_landmarks"]
        # 60 draws per point: every point among the candidates, and as many landmarks as points
        assert rows[2]["progress_min"] == pytest.approx(buffer_progress)
        assert rows[0]["progress_mean"] <= rows[1]["progress_mean"] + 1e-6 <= rows[2]["progress_mean"] + 2e-6
        if trial == 0:
            assert rows[0]["progress_max"] == pytest.approx(expected)
        after = planner.state_dict()
        assert before.keys() == after.keys() and all(torch.equal(before[k], after[k]) for k in before)
        # the coverage of a row is the coverage of the landmarks a direct rebuild with the same draw gives
        seeds = torch.Generator().manual_seed(trial)
        one, _ = landmark_budget_sweep(
            geometry, planner, rb, [(count, 60 * count)], draws=1, coverage_radius=2.0, generator=seeds
        )
        assert one[0]["coverage_mean"] == pytest.approx(landmark_coverage(geometry, points, 2.0))


def test_landmark_budget_sweep_refuses_bad_input():
    geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
    planner = GraphPlanner(LandmarkGraph(cutoff=3.0), lambda s, g: (s - g).norm(dim=-1), goal_dim=2)
    empty = ReplayBuffer(storage=LazyTensorStorage(10))
    with pytest.raises(ValueError, match="empty"):
        landmark_budget_sweep(geometry, planner, empty, [(10, 10)], coverage_radius=2.0)
    rb = ReplayBuffer(storage=LazyTensorStorage(10))
    rb.extend(TensorDict(observation=torch.zeros(4, 2), achieved_goal=torch.zeros(4, 2), batch_size=[4]))
    for budgets in ([(0, 10)], [(10,)], [(10, 2.5)], [(True, 10)]):
        with pytest.raises(ValueError, match="budgets"):
            landmark_budget_sweep(geometry, planner, rb, budgets, coverage_radius=2.0)
    with pytest.raises(ValueError, match="draws"):
        landmark_budget_sweep(geometry, planner, rb, [(10, 10)], draws=0, coverage_radius=2.0)
