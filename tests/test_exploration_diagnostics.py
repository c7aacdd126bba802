"""episode_progress (how far each training episode got along a maze) and recipes/diagnose_exploration.py."""

import math

import pytest
import torch
from _recipe import load_recipe, recipe_config
from tensordict import TensorDict

from torchrl_dhrl.training import MazeGeometry, episode_progress


@pytest.fixture(scope="module")
def geometry():
    return MazeGeometry.from_maze("PointMaze", margin=0.5)


def _records(episodes, achieved, goals):
    return TensorDict(
        {
            "episode_id": torch.tensor(episodes, dtype=torch.long).reshape(-1, 1),
            ("next", "achieved_goal"): torch.tensor(achieved, dtype=torch.float32).reshape(-1, 2),
            "desired_goal": torch.tensor(goals, dtype=torch.float32).reshape(-1, 2),
        },
        [len(episodes)],
    )


def test_progress_per_episode_against_straight_line_distances(geometry):
    # three episodes, records interleaved as a two-env collector writes them; every point is in sight of the
    # start along the first corridor, so its progress is its Euclidean distance from the start
    torch.manual_seed(0)
    ids = [0, 1, 0, 1, 2, 2, 0]
    points = torch.stack([torch.rand(7) * 8.0 - 1.0, torch.rand(7) * 2.0 - 1.0], -1)
    goals = [[6.0, 0.5], [3.0, -1.0], [6.0, 0.5], [3.0, -1.0], [7.5, 1.0], [7.5, 1.0], [6.0, 0.5]]
    start = torch.tensor([0.2, -0.1])
    out = episode_progress(geometry, _records(ids, points.tolist(), goals), start)
    euclid = (points - start).norm(dim=-1)
    assert out.episode_ids.tolist() == [0, 1, 2]
    for k, episode in enumerate([0, 1, 2]):
        rows = [i for i, e in enumerate(ids) if e == episode]
        torch.testing.assert_close(out.max_progress[k], euclid[rows].max())
        torch.testing.assert_close(out.end_progress[k], euclid[rows[-1]])  # the last record written
        goal = torch.tensor(goals[rows[0]])
        torch.testing.assert_close(out.goals[k], goal)
        torch.testing.assert_close(out.goal_progress[k], (goal - start).norm())
    assert out.explored == pytest.approx(euclid.max().item())
    recent = episode_progress(geometry, _records(ids, points.tolist(), goals), start, last=2)
    assert recent.episode_ids.tolist() == [1, 2] and recent.explored == out.explored


def test_a_goal_behind_the_wall_is_as_far_as_the_way_around(geometry):
    out = episode_progress(geometry, _records([0], [[1.0, 0.0]], [[0.0, 8.0]]), torch.zeros(2))
    # around the U's inner wall with a 0.5 margin: 18.3 exactly; the grid path is within a few percent
    assert 18.3 <= out.goal_progress.item() <= 18.3 * 1.05
    assert out.goal_progress.item() > 8.0 * 2  # far more than the straight line


def test_bad_records(geometry):
    with pytest.raises(ValueError, match="non-empty 1-D"):
        episode_progress(
            geometry, _records([], torch.zeros(0, 2).tolist(), torch.zeros(0, 2).tolist()), torch.zeros(2)
        )
    records = _records([0], [[1.0, 0.0]], [[0.0, 8.0]]).exclude("episode_id")
    with pytest.raises(KeyError, match="episode_id"):
        episode_progress(geometry, records, torch.zeros(2))


def test_the_script_reads_a_run(tmp_path, capsys):
    run = tmp_path / "run"
    load_recipe().train(
        recipe_config("env=PointMaze", "preset=smoke", "logger.backend=none", "plots.every_epochs=0"),
        run_dir=run,
    )
    capsys.readouterr()  # the training's own output
    out, summary = load_recipe("diagnose_exploration").main([str(run), "--episodes", "3", "--rows", "2"])
    printed = capsys.readouterr().out
    assert summary["episodes"] == len(out.episode_ids) <= 3 and len(out.episode_ids) >= 1
    assert (
        "goals lay beyond it" in printed and len(printed.strip().splitlines()) == 4
    )  # header, 2 rows, summary
    assert all(math.isfinite(v) for v in out.max_progress.tolist())
    assert (out.max_progress <= summary["explored"] + 1e-6).all()
    assert summary["reached_frontier"] == int((out.max_progress >= 0.9 * summary["explored"]).sum())
