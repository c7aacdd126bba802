"""The high level's subgoal landscape (``subgoal_values``, ``subgoal_landscape``) and recipes/diagnose_high_level.py.

The values are checked against the loss's own actor objective (``-Q_1(s, pi(s, g))`` with ``action_l2=0``) and
against the critic's TD-loss diagnostics (the mean Q over its members), on a trained-from-scratch critic whose
landscape has a known maximum; the script on a PointMaze smoke run (walls counted against the geometry).
"""

import pytest
import torch
from tensordict import TensorDict

from torchrl_dhrl.modules import GoalConditionedCritic, HighLevelActor
from torchrl_dhrl.objectives import HighLevelLoss
from torchrl_dhrl.training import (
    MazeGeometry,
    SubgoalLandscape,
    landscape_summary,
    maze_epoch_diagnostics,
    subgoal_box,
    subgoal_landscape,
    subgoal_values,
)
from torchrl_dhrl.training.maze_diagnostics import LANDSCAPE_DIAG_KEYS

LOW, HIGH = [-2.0, -2.0], [10.0, 10.0]


def _loss(seed=0, num_cells=(16,)):
    torch.manual_seed(seed)
    actor = HighLevelActor(6, 2, LOW, HIGH, num_cells=num_cells)
    critic = GoalConditionedCritic(
        6, 2, action_low=LOW, action_high=HIGH, goal_key="desired_goal", action_key="subgoal",
        relative_goal=False, num_cells=num_cells,
    )  # fmt: skip
    return HighLevelLoss(actor, critic, action_l2=0.0), actor


def test_values_agree_with_the_actor_objective_and_the_td_diagnostics():
    loss, actor = _loss()
    gen = torch.Generator().manual_seed(1)
    for _ in range(5):
        obs, goal = torch.randn(6, generator=gen), torch.rand(2, generator=gen) * 12 - 2
        land = subgoal_landscape(loss, actor, obs, goal, LOW, HIGH, resolution=1.0)
        actor_loss, _ = loss.actor_loss(
            TensorDict(observation=obs[None], desired_goal=goal[None], batch_size=[1])
        )
        torch.testing.assert_close(land.actor_q, -actor_loss.detach(), rtol=1e-5, atol=1e-5)
        # the TD loss's mean Q over the critic's members, at subgoals given as the transitions' actions
        subgoals = torch.rand(7, 2, generator=gen) * 12 - 2
        batch = TensorDict(
            observation=obs.expand(7, 6), desired_goal=goal.expand(7, 2), subgoal=subgoals,
            next=TensorDict(observation=torch.randn(7, 6), reward=-torch.ones(7, 1), batch_size=[7]),
            batch_size=[7],
        )  # fmt: skip
        _, metadata = loss.value_loss(batch)
        values = subgoal_values(loss, obs, goal, subgoals)
        assert values.shape == (2, 7)
        torch.testing.assert_close(values.mean(), metadata["q"], rtol=1e-5, atol=1e-5)
        # the grid: its points, first member and minimum over the members
        points = land.points().reshape(-1, 2)
        assert points.shape == (13 * 13, 2) and points.min(0).values.tolist() == LOW
        assert points.max(0).values.tolist() == HIGH
        grid = subgoal_values(loss, obs, goal, points)
        torch.testing.assert_close(land.q.reshape(-1), grid[0])
        torch.testing.assert_close(land.q_min.reshape(-1), grid.min(0).values)


def test_chunks_change_nothing():
    loss, _ = _loss()
    subgoals = torch.rand(50, 2) * 12 - 2
    obs, goal = torch.randn(6), torch.rand(2)
    torch.testing.assert_close(
        subgoal_values(loss, obs, goal, subgoals, chunk_size=7), subgoal_values(loss, obs, goal, subgoals)
    )


def test_best_finds_a_known_maximum_and_respects_the_mask():
    xs, ys = torch.arange(0.0, 5.0), torch.arange(0.0, 4.0)
    grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
    q = -((grid_x - 3) ** 2 + (grid_y - 1) ** 2)  # peak at (3, 1)
    land = SubgoalLandscape(xs, ys, q, q, torch.zeros(2), torch.tensor(0.0))
    point, value = land.best()
    assert point.tolist() == [3.0, 1.0] and value.item() == 0.0
    mask = torch.ones_like(q, dtype=torch.bool)
    mask[1, 3] = False  # the peak is "in a wall"
    point, value = land.best(mask)
    assert value.item() == -1.0 and point.tolist() in ([2.0, 1.0], [4.0, 1.0], [3.0, 0.0], [3.0, 2.0])


def test_summary_against_direct_counts():
    gen = torch.Generator().manual_seed(4)
    for _ in range(20):
        h, w = (int(v) for v in torch.randint(1, 9, (2,), generator=gen))
        q = torch.randint(0, 5, (h, w), generator=gen).float()  # ties
        walls = torch.rand(h, w, generator=gen) < 0.4
        land = SubgoalLandscape(
            torch.arange(float(w)), torch.arange(float(h)), q, q, torch.zeros(2), torch.tensor(1.5)
        )
        top = float(torch.empty(()).uniform_(0.05, 1.0, generator=gen))
        out = landscape_summary(land, walls, top)
        count = max(1, round(top * h * w))
        threshold = q.reshape(-1).sort(descending=True).values[count - 1]  # ties at the threshold: a range
        above, at = q > threshold, q == threshold
        low = (walls & above).sum() / count
        high = ((walls & above).sum() + min(int((walls & at).sum()), count - int(above.sum()))) / count
        assert float(low) - 1e-6 <= out["top_in_walls"] <= float(high) + 1e-6
        assert out["q_range"] == float(q.max() - q.min())
        assert out["walls_share"] == pytest.approx(float(walls.float().mean()))
        if (~walls).any():
            assert out["actor_q_gap"] == float(q[~walls].max()) - 1.5
        else:
            assert out["actor_q_gap"] != out["actor_q_gap"]  # NaN
        assert out["best_in_wall"] in (0.0, 1.0)
        if not bool((q == q.max()).logical_and(~walls).any()):
            assert out["best_in_wall"] == 1.0  # every maximum is in a wall
        if not bool((q == q.max()).logical_and(walls).any()):
            assert out["best_in_wall"] == 0.0


def test_maze_epoch_diagnostics_adds_the_landscape_of_the_first_start():
    loss, actor = _loss(seed=2)
    assert subgoal_box(loss) == (LOW, HIGH)
    from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph

    planner = GraphPlanner(
        LandmarkGraph(), lambda s, g: (g - s[..., :2]).norm(dim=-1), goal_dim=2
    )  # no graph
    obs = torch.tensor([0.5, 0.2, 0.0, 0.0, 0.0, 0.0])
    rollout = TensorDict(
        observation=obs.expand(2, 3, 6), desired_goal=torch.tensor([0.0, 8.0]).expand(2, 3, 2),
        subgoal=torch.zeros(2, 3, 2), waypoint=torch.zeros(2, 3, 2),
        new_subgoal=torch.ones(2, 3, 1, dtype=torch.bool), batch_size=[2, 3],
    )  # fmt: skip
    out = maze_epoch_diagnostics("PointMaze", planner, rollout, actor, high_loss=loss)
    land = subgoal_landscape(loss, actor, obs, torch.tensor([0.0, 8.0]), LOW, HIGH, resolution=12 / 48)
    summary = landscape_summary(land, MazeGeometry.from_maze("PointMaze").in_walls(land.points()))
    assert land.q.shape == (49, 49)
    assert [out[k] for k in LANDSCAPE_DIAG_KEYS] == [
        summary["q_range"], summary["best_in_wall"], summary["top_in_walls"], summary["actor_q_gap"]
    ]  # fmt: skip
    assert not set(LANDSCAPE_DIAG_KEYS) & set(maze_epoch_diagnostics("PointMaze", planner, rollout, actor))


def test_bad_inputs():
    loss, actor = _loss()
    with pytest.raises(ValueError, match="2-D subgoal box"):
        subgoal_landscape(loss, actor, torch.zeros(6), torch.zeros(2), [0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="`resolution` must be > 0"):
        subgoal_landscape(loss, actor, torch.zeros(6), torch.zeros(2), LOW, HIGH, resolution=0.0)
    land = subgoal_landscape(loss, actor, torch.zeros(6), torch.zeros(2), LOW, HIGH, resolution=2.0)
    with pytest.raises(ValueError, match="`in_walls` must have the grid's shape"):
        landscape_summary(land, torch.zeros(3, 3, dtype=torch.bool))
    with pytest.raises(ValueError, match="`top` must be in"):
        landscape_summary(land, torch.zeros_like(land.q, dtype=torch.bool), top=0.0)
    with pytest.raises(ValueError, match=r"`observation` \[obs_dim\]"):
        subgoal_values(loss, torch.zeros(1, 6), torch.zeros(2), torch.zeros(3, 2))


def test_script_on_a_pointmaze_run(tmp_path, capsys):
    from _recipe import load_recipe, recipe_config

    torch.manual_seed(0)
    load_recipe().train(
        recipe_config("env=PointMaze", "preset=smoke", "logger.backend=none", "plots.every_epochs=0"),
        run_dir=tmp_path,
    )
    import csv

    with (tmp_path / "metrics.csv").open() as file:
        rows = list(csv.DictReader(file))
    for row in rows:  # every epoch logs the critic's landscape at the first test start
        assert float(row["diag/start_q_range"]) >= 0.0
        assert float(row["diag/start_best_subgoal_in_wall"]) in (0.0, 1.0)
        assert 0.0 <= float(row["diag/start_top_subgoals_in_walls"]) <= 1.0
        assert float(row["diag/start_actor_q_gap"]) == float(row["diag/start_actor_q_gap"])  # not NaN
    picture = tmp_path / "landscape.png"
    report = load_recipe("diagnose_high_level").main(
        [str(tmp_path), "--resolution", "1", "--plot", str(picture), "--along"]
    )
    out = capsys.readouterr().out
    assert "actor's subgoal" in out and "best free subgoal" in out and picture.stat().st_size > 1000
    geometry = MazeGeometry.from_maze("PointMaze")
    # PointMaze's subgoal box is the arena [-2, 10]^2; the U's inner wall, joined to the left outer wall, fills
    # -6 < x < 6, 2 < y < 6: 8 x 3 of the 13 x 13 grid points (x = -2 lies inside the joined walls)
    assert report["walls_share"] == pytest.approx(24 / 169)
    assert report["actor_in_wall"] == bool(geometry.in_walls(report["actor_subgoal"][None])[0])
    assert not bool(geometry.in_walls(report["best_free_subgoal"][None])[0])
    assert report["best_free_q"] <= report["best_q"] and report["starts"] >= 1
    assert 0.0 <= report["top_in_walls"] <= 1.0 and 0.0 <= report["actor_in_walls_over_starts"] <= 1.0
    # along one or two test episodes: a row per new subgoal (every c_h steps, from step 0)
    along = report["along"]
    episodes = sorted({row["episode"] for row in along})
    assert 1 <= len(episodes) <= 2 and "along test episode" in out
    for episode in episodes:
        steps = [row["step"] for row in along if row["episode"] == episode]
        assert steps[0] == 0 and all(b > a for a, b in zip(steps, steps[1:], strict=False))
