"""The low-level reach diagnostic: offsets, wall filtering, a scripted controller."""

import math

import pytest
import torch
from tensordict.nn import TensorDictModule
from torchrl_dhrl.envs import make_env
from torchrl_dhrl.envs.geometry import obstacle_boxes

from torchrl_dhrl.diagnostics import (
    low_level_reach_test,
    reach_offsets,
    reach_test,
    summarize_reach,
    visible_offsets,
)
from torchrl_dhrl.planner import LineOfSightDistance


def test_reach_offsets_radii_and_directions():
    offsets = reach_offsets(2, [1.0, 2.5], 8)
    assert offsets.shape == (16, 2)
    torch.testing.assert_close(offsets.norm(dim=-1), torch.tensor([1.0] * 8 + [2.5] * 8))
    angles = torch.atan2(offsets[:8, 1], offsets[:8, 0]).remainder(2 * math.pi)
    torch.testing.assert_close(angles, torch.arange(8) * (math.pi / 4), atol=1e-5, rtol=0)
    three = reach_offsets(3, [0.1, 0.2], 5, seed=3)
    torch.testing.assert_close(three.norm(dim=-1), torch.tensor([0.1] * 5 + [0.2] * 5))
    torch.testing.assert_close(three[5:], 2 * three[:5])  # same directions at every radius
    with pytest.raises(ValueError, match="positive radii"):
        reach_offsets(2, [0.0], 4)


def test_visible_offsets_match_dense_segment_sampling():
    """The slab test agrees with checking 2001 points along every segment against the inflated boxes."""
    boxes = torch.tensor([[[1.0, -1.0], [2.0, 3.0]], [[-3.0, -3.0], [-2.0, -2.5]]])
    walls = LineOfSightDistance(1.0, boxes=boxes, margin=0.25, goal_indices=(0, 1))
    start = torch.tensor([0.2, 0.1])
    offsets = reach_offsets(2, [1.0, 2.0, 3.5, 5.0], 24)
    kept = visible_offsets(start, offsets, walls)
    t = torch.linspace(0, 1, 2001)[:, None, None]
    points = start + t * offsets  # [2001, N, 2]
    lo, hi = boxes[:, 0] - 0.25, boxes[:, 1] + 0.25
    inside = ((points[:, :, None] >= lo) & (points[:, :, None] <= hi)).all(-1).any(-1).any(0)
    torch.testing.assert_close(kept, offsets[~inside])
    assert 0 < len(kept) < len(offsets)


def _point_controller():
    """Turn towards the waypoint (at most 0.25 rad per step), drive forward once roughly aligned."""

    def act(observation, waypoint):
        delta = waypoint - observation[..., :2]
        error = torch.atan2(delta[..., 1], delta[..., 0]) - observation[..., 2]
        error = torch.atan2(error.sin(), error.cos())
        forward = (error.abs() < 0.3).float()
        return torch.stack([forward, error.clamp(-0.25, 0.25)], -1)

    return TensorDictModule(act, in_keys=["observation", "waypoint"], out_keys=["action"])


def test_scripted_point_reaches_every_visible_goal_in_analytic_time():
    radii = [1.5, 3.0, 6.0]
    offsets = reach_offsets(2, radii, 16)
    # the maze walls, inflated by the nose's reach (1.1 ahead of the centre) so that it cannot hit a wall first
    walls = LineOfSightDistance(1.0, boxes=obstacle_boxes("PointMaze"), margin=1.2, goal_indices=(0, 1))
    offsets = visible_offsets(torch.zeros(2), offsets, walls)
    env = make_env("PointMaze", num_envs=len(offsets), seed=1)
    result = low_level_reach_test(env, _point_controller(), offsets, max_steps=60, reach_radius=0.5)
    assert result.reached.all()
    # 0.2 per step once aligned; turning by up to pi takes at most 13 steps; reset noise moves the start <= 0.15
    lower = torch.ceil((result.radius - 0.5 - 0.15) / 0.2)
    upper = torch.ceil((result.radius - 0.5 + 0.15) / 0.2) + 14
    assert (result.steps_to_reach >= lower).all() and (result.steps_to_reach <= upper).all()
    torch.testing.assert_close(result.start_distance, result.radius, atol=0.15, rtol=0)
    rows = summarize_reach(result)
    assert [row["radius"] for row in rows] == pytest.approx(radii)
    assert sum(row["goals"] for row in rows) == len(offsets)
    assert all(row["reach_rate"] == 1.0 and row["mean_min_distance"] <= 0.5 for row in rows)


def test_reach_test_from_another_start_per_offset_with_repeats():
    # PointMaze's right-hand corridor (x = 8): from (8, 4) the goals up and down it are visible, those left and
    # right are blocked (the inner wall, the outer wall)
    rows = reach_test(
        _point_controller(),
        "PointMaze",
        radii=[2.0, 4.0],
        max_steps=60,
        reach_radius=0.5,
        num_directions=4,
        start=(8.0, 4.0),
        repeats=3,
        per_offset=True,
    )
    offsets = sorted(tuple(round(v) for v in row["offset"]) for row in rows)
    assert offsets == [(0, -4), (0, -2), (0, 2), (0, 4)]
    assert all(row["goals"] == 3 and row["reach_rate"] == 1.0 for row in rows)
    assert all(row["radius"] == pytest.approx(abs(sum(row["offset"]))) for row in rows)
    # per radius, the repeats pool: 2 directions x 3 tries
    rows = reach_test(
        _point_controller(), "PointMaze", radii=[2.0, 4.0], max_steps=60, reach_radius=0.5,
        num_directions=4, start=(8.0, 4.0), repeats=3,
    )  # fmt: skip
    assert [(row["radius"], row["goals"]) for row in rows] == [(2.0, 6), (4.0, 6)]
    with pytest.raises(ValueError, match="inside a wall"):
        reach_test(
            _point_controller(), "PointMaze", radii=[2.0], max_steps=5, reach_radius=0.5, start=(4.0, 4.0)
        )
    with pytest.raises(ValueError, match="repeats must be >= 1"):
        reach_test(_point_controller(), "PointMaze", radii=[2.0], max_steps=5, reach_radius=0.5, repeats=0)


def test_a_still_actor_reaches_nothing_and_bad_batch_is_refused():
    offsets = reach_offsets(2, [1.5], 4)
    still = TensorDictModule(
        lambda o, w: torch.zeros(*o.shape[:-1], 2), in_keys=["observation", "waypoint"], out_keys=["action"]
    )
    result = low_level_reach_test(
        make_env("PointMaze", num_envs=4, seed=0), still, offsets, max_steps=10, reach_radius=0.5
    )
    assert not result.reached.any() and (result.steps_to_reach == 11).all()
    torch.testing.assert_close(result.final_distance, result.start_distance, atol=0.05, rtol=0)
    with pytest.raises(ValueError, match="batch size"):
        low_level_reach_test(
            make_env("PointMaze", num_envs=3), still, offsets, max_steps=10, reach_radius=0.5
        )


def _pd_controller():
    """A gymnasium-robotics point (observation x, y, vx, vy; action a force): push towards the waypoint, damped."""
    return TensorDictModule(
        lambda o, w: (5.0 * (w - o[..., :2]) - o[..., 2:4]).clamp(-1, 1),
        in_keys=["observation", "waypoint"],
        out_keys=["action"],
    )


def test_reach_test_in_a_gymnasium_maze_from_its_reset_cell_or_the_cell_of_a_start():
    """PointMaze_UMaze-v3 (1-unit cells; free: row 1 and row 3 of columns 1-3, and column 3): from the centre of its
    reset cell (3, 1), (-1, -1), only the goal along the corridor (+x) is visible at 1 and 1.8 units; all four at 0.3
    (the walls 0.5 away, inflated by 0.125). From the cell holding (1, 1), (1, 3), the corridor runs -x and -y."""
    pytest.importorskip("gymnasium_robotics")
    corridor = {"reset_options": {"reset_cell": [3, 1]}}
    kwargs = dict(max_steps=100, reach_radius=0.2, num_directions=4, oracle_margin=0.125, env_kwargs=corridor)
    rows = reach_test(_pd_controller(), "gymnasium:PointMaze_UMaze-v3", radii=[0.3, 1.0, 1.8], **kwargs)
    assert [(round(row["radius"], 3), row["goals"]) for row in rows] == [(0.3, 4), (1.0, 1), (1.8, 1)]
    assert all(row["reach_rate"] == 1.0 for row in rows)
    rows = reach_test(
        _pd_controller(), "gymnasium:PointMaze_UMaze-v3", radii=[1.0], start=(1.0, 1.0), per_offset=True, **kwargs
    )
    assert sorted(tuple(round(v) for v in row["offset"]) for row in rows) == [(-1, 0), (0, -1)]
    assert all(row["reach_rate"] == 1.0 for row in rows)
    # the env takes the test's goals at reset: each starts about its radius from its goal (the goals are offsets from
    # a first reset's position, the episode starts from a second: two draws of noise within 0.25 a side)
    env = make_env("gymnasium:PointMaze_UMaze-v3", num_envs=3, seed=0, env_kwargs=corridor)
    offsets = torch.tensor([[0.3, 0.0], [1.0, 0.0], [1.8, 0.0]])
    result = low_level_reach_test(env, _pd_controller(), offsets, max_steps=100, reach_radius=0.2)
    torch.testing.assert_close(result.start_distance, result.radius, atol=0.5 * 2**0.5, rtol=0)
    assert result.reached.all()
    with pytest.raises(ValueError, match="resets start anywhere"):
        reach_test(_pd_controller(), "gymnasium:PointMaze_UMaze-v3", radii=[1.0], max_steps=5, reach_radius=0.2)
    with pytest.raises(ValueError, match=r"lies in cell \(2, 1\), a wall"):
        reach_test(_pd_controller(), "gymnasium:PointMaze_UMaze-v3", radii=[1.0], start=(-1.0, 0.0), **kwargs)
