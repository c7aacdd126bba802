"""episode_progress (how far each training episode got along a maze) and TrainingEpisodeLog (the training
episodes per epoch)."""

import json
import math

import pytest
import torch
from _recipe import recipe_config
from scipy.spatial.transform import Rotation
from tensordict import TensorDict
from torchrl_dhrl.envs import AntAgent
from torchrl_dhrl.envs.geometry import MazeGeometry

from torchrl_dhrl.diagnostics import TrainingEpisodeLog, episode_progress, episodes_in_boxes


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


def _episodes(generator, num_envs, steps, shifted=True):
    """``[num_envs, steps]`` episodes along the first corridor, all in sight of the origin, random successes."""
    x = torch.rand(num_envs, steps, generator=generator) * 8.0 - 1.0
    y = torch.rand(num_envs, steps, generator=generator) * 2.0 - 1.0
    data = {
        ("next", "achieved_goal"): torch.stack([x, y], -1),
        ("next", "is_success"): torch.rand(num_envs, steps, 1, generator=generator) < 0.1,
    }
    if shifted:  # one flag per episode, held at every step (as GoalShiftOnReset writes it)
        flag = torch.rand(num_envs, 1, 1, generator=generator) < 0.5
        data["goal_shifted"] = flag.expand(num_envs, steps, 1)
    return TensorDict(data, [num_envs, steps])


@pytest.mark.parametrize("num_envs", [1, 3])
def test_training_episode_log_against_a_direct_count(geometry, num_envs):
    generator = torch.Generator().manual_seed(num_envs)
    log = TrainingEpisodeLog(geometry)
    frontier = -math.inf
    for epoch in range(4):
        batches = [_episodes(generator, num_envs, 7) for _ in range(epoch + 1)]
        for batch in batches:
            log.update(batch)
        metrics = log.pop_metrics()
        episodes = torch.cat([b.get(("next", "is_success")).squeeze(-1) for b in batches])  # [E, T]
        shifted = torch.cat([b.get("goal_shifted")[:, 0, 0] for b in batches])
        points = torch.cat([b.get(("next", "achieved_goal")).reshape(-1, 2) for b in batches])
        furthest = points.norm(dim=-1).max().item()  # every point in sight of the origin: its distance
        frontier = max(frontier, furthest)
        assert metrics["train/episodes"] == len(episodes) == num_envs * (epoch + 1)
        assert metrics["train/success"] == pytest.approx(episodes[:, -1].float().mean().item())
        assert metrics["train/any_success"] == pytest.approx(episodes.any(-1).float().mean().item())
        assert metrics["train/goal_shifted"] == pytest.approx(shifted.float().mean().item())
        assert metrics["train/max_progress"] == pytest.approx(furthest, rel=1e-5)
        assert metrics["train/frontier"] == pytest.approx(frontier, rel=1e-5)  # the largest so far


def test_ant_upside_down_against_scipy_rotations():
    """The torso's up axis below the horizon, checked on random orientations (scipy rotates (0, 0, 1))."""
    quats = Rotation.random(2000, random_state=0).as_quat()  # (x, y, z, w)
    obs = torch.zeros(2000, 29, dtype=torch.float64)
    obs[:, 3] = torch.as_tensor(quats[:, 3])
    obs[:, 4:7] = torch.as_tensor(quats[:, :3])
    expected = Rotation.from_quat(quats).apply([0.0, 0.0, 1.0])[:, 2] < 0
    assert AntAgent.is_upside_down(obs).tolist() == expected.tolist()
    assert 0.3 < expected.mean() < 0.7  # both cases well represented


def test_training_episode_log_counts_upside_down_steps(geometry):
    """train/upside_down (fraction of steps) and train/ended_upside_down (of episodes) against a direct count,
    across a mid-epoch checkpoint."""
    generator = torch.Generator().manual_seed(11)
    batches = []
    for _ in range(3):
        batch = _episodes(generator, 3, 8)
        flipped = torch.rand(3, 8, generator=generator) < 0.4
        obs = torch.zeros(3, 8, 29)
        obs[..., 3] = (~flipped).float()  # identity quaternion: upright
        obs[..., 4] = flipped.float()  # half a turn about x: upside down
        batch.set(("next", "observation"), obs)
        batches.append((batch, flipped))
    log = TrainingEpisodeLog(geometry, upside_down=AntAgent.is_upside_down)
    log.update(batches[0][0])
    resumed = TrainingEpisodeLog(geometry, upside_down=AntAgent.is_upside_down)
    resumed.load_state_dict(json.loads(json.dumps(log.state_dict())))
    for batch, _ in batches[1:]:
        resumed.update(batch)
    metrics = resumed.pop_metrics()
    flipped = torch.cat([f for _, f in batches])
    assert metrics["train/upside_down"] == pytest.approx(flipped.float().mean().item())
    assert metrics["train/ended_upside_down"] == pytest.approx(flipped[:, -1].float().mean().item())
    assert math.isnan(resumed.pop_metrics()["train/upside_down"])  # an empty epoch


def test_training_episode_log_progress_behind_the_wall(geometry):
    log = TrainingEpisodeLog(geometry)
    path = torch.tensor([[[1.0, 0.0], [8.0, 0.0], [8.0, 8.0], [0.0, 8.0]]])
    log.update(
        TensorDict(
            {("next", "achieved_goal"): path, ("next", "is_success"): torch.zeros(1, 4, 1).bool()}, [1, 4]
        )
    )
    metrics = log.pop_metrics()
    # around the U's inner wall with a 0.5 margin: 18.3 exactly; the grid path within a few percent
    assert 18.3 <= metrics["train/max_progress"] <= 18.3 * 1.05


def test_training_episode_log_resumes_mid_epoch_exactly(geometry):
    generator = torch.Generator().manual_seed(7)
    batches = [_episodes(generator, 2, 5) for _ in range(5)]
    whole = TrainingEpisodeLog(geometry)
    for batch in batches[:2]:
        whole.update(batch)
    expected_first = whole.pop_metrics()
    for batch in batches[2:]:
        whole.update(batch)
    expected = whole.pop_metrics()

    first = TrainingEpisodeLog(geometry)
    for batch in batches[:2]:
        first.update(batch)
    assert first.pop_metrics() == expected_first
    first.update(batches[2])
    state = json.loads(json.dumps(first.state_dict()))  # the recipe keeps it in its JSON counters
    second = TrainingEpisodeLog(geometry)
    second.load_state_dict(state)
    for batch in batches[3:]:
        second.update(batch)
    assert second.pop_metrics() == expected
    fresh = TrainingEpisodeLog(geometry)  # no frontier yet: -inf, stored as None
    fresh.load_state_dict(json.loads(json.dumps(fresh.state_dict())))
    assert fresh.state_dict() == TrainingEpisodeLog(geometry).state_dict()


def test_training_episode_log_without_maze_or_shifting():
    generator = torch.Generator().manual_seed(3)
    log = TrainingEpisodeLog()  # an arm env: no geometry
    empty = log.pop_metrics()
    assert empty["train/episodes"] == 0 and math.isnan(empty["train/success"])
    batch = _episodes(generator, 4, 6, shifted=False)
    log.update(batch[0])  # one env's [T] episode
    log.update(batch)
    metrics = log.pop_metrics()
    assert metrics["train/episodes"] == 5
    assert set(metrics) == {"train/episodes", "train/success", "train/any_success"}


def test_training_episode_log_errors(geometry):
    log = TrainingEpisodeLog(geometry)
    batch = _episodes(torch.Generator().manual_seed(0), 2, 3)
    with pytest.raises(KeyError, match="is_success"):
        log.update(batch.exclude(("next", "is_success")))
    with pytest.raises(KeyError, match="achieved_goal"):
        log.update(batch.exclude(("next", "achieved_goal")))
    with pytest.raises(ValueError, match=r"\[num_envs, T\]"):
        log.update(batch.unsqueeze(0))
    with pytest.raises(KeyError, match="unknown entry 'bogus'"):
        log.load_state_dict({"bogus": 3})
    flips = TrainingEpisodeLog(geometry, upside_down=AntAgent.is_upside_down)
    with pytest.raises(KeyError, match="observation"):
        flips.update(batch)


@pytest.mark.parametrize(
    ("env", "tracks_flips"), [("AntMazeSmall", True), ("PointMaze", False), ("Reacher3D", False)]
)
def test_the_recipe_logs_upside_down_for_the_ant(env, tracks_flips):
    """The recipe's training-episode log counts the steps spent upside down in the ant mazes only."""
    from dhrl_utils import build_episode_log

    log = build_episode_log(recipe_config(f"env={env}"))
    assert (log.upside_down is AntAgent.is_upside_down) is tracks_flips
    assert (log.upside_down is None) is not tracks_flips


@pytest.mark.parametrize("seed", range(6))
def test_episodes_in_boxes_against_a_direct_loop(seed):
    generator = torch.Generator().manual_seed(seed)
    n = int(torch.randint(1, 400, (1,), generator=generator))
    positions = torch.randint(0, 9, (n, 2), generator=generator).float() / 2  # on a grid: ties with the box edges
    episode_ids = torch.randint(-3, 40, (n,), generator=generator) * 7  # unordered, gaps, negative ids
    boxes = torch.rand(5, 4, generator=generator) * 4
    boxes = torch.stack([boxes[:, 0], boxes[:, 0] + boxes[:, 1], boxes[:, 2], boxes[:, 2] + boxes[:, 3]], -1)
    boxes = torch.cat([boxes, torch.tensor([[1.0, 1.0, 2.0, 2.0], [3.0, 1.0, 0.0, 4.0]])])  # a point; min > max
    ids, inside = episodes_in_boxes(positions, episode_ids, boxes)
    expected_ids = sorted(set(episode_ids.tolist()))
    assert ids.tolist() == expected_ids
    for e, episode in enumerate(expected_ids):
        steps = [positions[i].tolist() for i in range(n) if int(episode_ids[i]) == episode]
        for b, (x0, x1, y0, y1) in enumerate(boxes.tolist()):
            assert bool(inside[e, b]) == any(x0 <= x <= x1 and y0 <= y <= y1 for x, y in steps)
    assert not inside[:, -1].any()  # an empty box holds nothing


def test_episodes_in_boxes_errors():
    with pytest.raises(ValueError, match="must match"):
        episodes_in_boxes(torch.zeros(3, 2), torch.zeros(2), torch.zeros(1, 4))


@pytest.mark.parametrize("seed", range(6))
def test_upside_down_by_episode_against_a_direct_loop(seed):
    """Random flips over unordered episode ids; with a step count (an episode split by the ring buffer's wrap, so
    that its last step is not its last stored one, and ties broken by storage order) and without."""
    from torchrl_dhrl.diagnostics import upside_down_by_episode

    generator = torch.Generator().manual_seed(seed)
    n = int(torch.randint(1, 300, (1,), generator=generator))
    flipped = torch.rand(n, generator=generator) < 0.4
    episode_ids = torch.randint(-2, 12, (n,), generator=generator) * 3
    step_count = torch.randint(0, 5, (n,), generator=generator)  # ties
    for count in (None, step_count):
        ids, share, ended = upside_down_by_episode(flipped, episode_ids, count)
        assert ids.tolist() == sorted(set(episode_ids.tolist()))
        for e, episode in enumerate(ids.tolist()):
            steps = [i for i in range(n) if int(episode_ids[i]) == episode]
            assert share[e].item() == pytest.approx(sum(bool(flipped[i]) for i in steps) / len(steps))
            last = steps[-1] if count is None else max(steps, key=lambda i: (int(count[i]), i))
            assert bool(ended[e]) == bool(flipped[last])
    with pytest.raises(ValueError, match="must match"):
        upside_down_by_episode(torch.zeros(3, dtype=torch.bool), torch.zeros(2))
    with pytest.raises(ValueError, match="must match"):
        upside_down_by_episode(torch.zeros(3, dtype=torch.bool), torch.zeros(3), torch.zeros(2))
