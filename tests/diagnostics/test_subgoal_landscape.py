"""The high level's subgoal landscape (``subgoal_values``, ``subgoal_landscape``).

The values are checked against the loss's own actor objective (``-Q_1(s, pi(s, g))`` with ``action_l2=0``) and
against the critic's TD-loss diagnostics (the mean Q over its members), on a trained-from-scratch critic whose
landscape has a known maximum."""

import pytest
import torch
from tensordict import TensorDict

from torchrl_dhrl.diagnostics import SubgoalLandscape, landscape_summary, subgoal_landscape, subgoal_values
from torchrl_dhrl.modules import GoalConditionedCritic, HighLevelActor
from torchrl_dhrl.objectives import HighLevelLoss

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
