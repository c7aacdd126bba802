"""The ``diag/...`` metrics of a maze run (``maze_epoch_diagnostics``) and the start subgoal."""

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl_dhrl.envs.geometry import MazeGeometry

from tests.diagnostics.test_graph_quality import _candidates
from tests.diagnostics.test_subgoal_landscape import HIGH, LOW, _loss
from torchrl_dhrl.diagnostics import (
    DIAG_KEYS,
    LANDSCAPE_DIAG_KEYS,
    landscape_summary,
    maze_epoch_diagnostics,
    start_subgoal,
    subgoal_box,
    subgoal_landscape,
)
from torchrl_dhrl.modules import HighLevelActor
from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph


def test_start_subgoal_is_the_deterministic_actor_output():
    torch.manual_seed(0)
    actor = HighLevelActor(6, 2, [-2.0, -2.0], [10.0, 10.0], num_cells=(16,))
    observation, goal = torch.randn(6), torch.tensor([0.0, 8.0])
    subgoal = start_subgoal(actor, observation, goal)
    td = TensorDict(observation=observation[None], desired_goal=goal[None], batch_size=[1])
    torch.testing.assert_close(subgoal, actor(td)["subgoal"][0])
    assert ((subgoal >= -2) & (subgoal <= 10)).all()


def test_maze_epoch_diagnostics_keys_and_arms():
    planner = GraphPlanner(
        LandmarkGraph(cutoff=5.0, early_stop=0.0), lambda s, g: (g - s[..., :2]).norm(dim=-1), goal_dim=2
    )
    geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
    states, goals = _candidates(geometry, 60)
    planner.build(states, goals)
    actor = HighLevelActor(6, 2, [-2.0, -2.0], [10.0, 10.0], num_cells=(8,))
    rollout = TensorDict(
        observation=states[:4, None].expand(4, 5, 6),
        desired_goal=torch.tensor([0.0, 8.0]).expand(4, 5, 2),
        subgoal=goals[:4, None].expand(4, 5, 2),
        waypoint=goals[:4, None].expand(4, 5, 2),
        new_subgoal=torch.ones(4, 5, 1, dtype=torch.bool),
        batch_size=[4, 5],
    )
    out = maze_epoch_diagnostics("PointMaze", planner, rollout, actor)
    assert set(out) == {*DIAG_KEYS, "time/diag_s"}
    assert all(math.isfinite(out[k]) for k in DIAG_KEYS)
    assert out["diag/subgoals_in_walls"] == 0.0 and out["diag/landmark_coverage"] > 0.5
    expected = start_subgoal(actor, states[0], torch.tensor([0.0, 8.0]))
    assert [out["diag/start_subgoal_x"], out["diag/start_subgoal_y"]] == pytest.approx(expected.tolist())
    assert maze_epoch_diagnostics("UR3Obstacle", planner, rollout, actor) == {}


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
