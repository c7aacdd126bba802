"""Tests of FutureGoalRelabel (low-level hindsight relabelling) on synthetic, traceable trajectories.

Every achieved goal encodes where it comes from: ``achieved_goal = (episode uid, step)`` and
``("next", "achieved_goal") = (uid, step + 1)``, so a relabelled goal tells exactly which episode and
step it was taken from. Also on real TorchRL collector output (batched envs with desynchronised episodes), and
the replay-buffer transforms refusing to go in an environment with a clear error."""

from __future__ import annotations

import math

import pytest
import torch
from scipy import stats
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.data import (
    Bounded,
    Composite,
    LazyTensorStorage,
    ListStorage,
    ReplayBuffer,
    TensorDictReplayBuffer,
    Unbounded,
)
from torchrl.envs import Compose, EnvBase, RenameTransform, SerialEnv, StepCounter, TransformedEnv
from torchrl_dhrl.envs import make_env

from torchrl_dhrl.data import (
    FutureGoalRelabel,
    HighLevelTransitionBuilder,
    HindsightSubgoalRelabel,
    RelabelReplayBuffer,
    SparseGoalReward,
)

SENTINEL = -1000.0  # the stored (chased) goal: never an achieved goal


class GoalStream:
    """Collector-shaped batches ``[num_envs, T]`` of desynchronised episodes of random lengths."""

    def __init__(self, num_envs: int, min_len: int, max_len: int, seed: int = 0) -> None:
        self.num_envs = num_envs
        self.min_len, self.max_len = min_len, max_len
        self.generator = torch.Generator().manual_seed(seed)
        self.uid = torch.arange(num_envs)
        self.next_uid = num_envs
        self.step = torch.zeros(num_envs, dtype=torch.long)
        self.length = self._lengths(num_envs)
        self.episode_length: dict[int, int] = {
            int(u): int(n) for u, n in zip(self.uid, self.length, strict=True)
        }
        self.last_written: dict[int, int] = {}  # uid -> largest next-step written so far

    def _lengths(self, n: int) -> torch.Tensor:
        return torch.randint(self.min_len, self.max_len + 1, (n,), generator=self.generator)

    def batch(self, horizon: int) -> TensorDict:
        uids, steps, dones = [], [], []
        for _ in range(horizon):
            done = self.step + 1 == self.length
            uids.append(self.uid.clone())
            steps.append(self.step.clone())
            dones.append(done)
            for uid, step in zip(self.uid.tolist(), (self.step + 1).tolist(), strict=True):
                self.last_written[uid] = step
            self.step = torch.where(done, 0, self.step + 1)
            if done.any():
                n_new = int(done.sum())
                new_uid = torch.arange(self.next_uid, self.next_uid + n_new)
                self.next_uid += n_new
                new_len = self._lengths(n_new)
                self.uid[done] = new_uid
                self.length[done] = new_len
                self.episode_length.update({int(u): int(n) for u, n in zip(new_uid, new_len, strict=True)})
        uid = torch.stack(uids, 1)
        step = torch.stack(steps, 1)
        done = torch.stack(dones, 1)
        achieved = torch.stack([uid, step], -1).float()
        next_achieved = torch.stack([uid, step + 1], -1).float()
        env = torch.arange(self.num_envs)[:, None].expand_as(uid).float()
        return TensorDict(
            {
                "observation": torch.cat([achieved, env.unsqueeze(-1)], -1),
                "achieved_goal": achieved,
                "desired_goal": torch.full_like(achieved, SENTINEL),
                "action": torch.zeros(*uid.shape, 1),
                "step_count": step.unsqueeze(-1),
                ("collector", "traj_ids"): uid,
                ("next", "observation"): torch.cat([next_achieved, env.unsqueeze(-1)], -1),
                ("next", "achieved_goal"): next_achieved,
                ("next", "done"): done.unsqueeze(-1),
                ("next", "truncated"): done.unsqueeze(-1),
            },
            batch_size=list(uid.shape),
        )

    def expected_window(self, achieved: torch.Tensor, window: int) -> torch.Tensor:
        """min(W, number of stored transitions of the episode from t on), from the ground truth."""
        uid, step = achieved[..., 0].long(), achieved[..., 1].long()
        last = torch.tensor([self.last_written[int(u)] for u in uid.reshape(-1)]).reshape(uid.shape)
        return torch.clamp(last - step, max=window)


def check_goals(sample: TensorDict, goal_key: str, window_len: torch.Tensor | None = None) -> torch.Tensor:
    """Asserts every relabelled goal is a future achieved goal of the same episode; returns the mask."""
    goal = sample[goal_key]
    achieved = sample["achieved_goal"]
    relabelled = goal[..., 0] != SENTINEL
    assert ((goal == SENTINEL).all(-1) | relabelled).all()
    ahead = goal[..., 1] - achieved[..., 1]  # = k + 1 with k the offset from the next achieved goal
    assert (goal[..., 0][relabelled] == achieved[..., 0][relabelled]).all(), "goal from another episode"
    assert (ahead[relabelled] >= 1).all()
    if window_len is not None:
        assert (ahead[relabelled] <= window_len[relabelled]).all(), "goal beyond the window / stored data"
    return relabelled


def sparse_reward(achieved: torch.Tensor, goal: torch.Tensor, threshold: float = 0.5) -> torch.Tensor:
    distance = (achieved.double() - goal.double()).pow(2).sum(-1, keepdim=True).sqrt()
    return torch.where(distance > threshold, -1.0, 0.0)


def filled_buffer(
    stream: GoalStream, capacity: int, cycles: int, horizon: int, *relabel
) -> RelabelReplayBuffer:
    rb = RelabelReplayBuffer(storage=LazyTensorStorage(capacity, ndim=2), relabel=relabel, batch_size=512)
    for _ in range(cycles):
        rb.extend(stream.batch(horizon))
    return rb


def relabelled(rb: RelabelReplayBuffer, relabel: FutureGoalRelabel, batch_size: int | None = None):
    """A sample of ``rb`` relabelled by ``relabel`` called directly, as the buffer calls its steps."""
    sample, info = rb.sample(batch_size, return_info=True)
    return relabel.relabel_sample(sample, info["index"], rb.storage, newest_index=rb.newest_index)


# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("window", [1, 7, 150])
def test_goals_same_episode_within_window_multi_env(window):
    torch.manual_seed(0)
    stream = GoalStream(num_envs=4, min_len=5, max_len=40, seed=1)
    relabel = FutureGoalRelabel(window=window)
    rb = RelabelReplayBuffer(storage=LazyTensorStorage(4 * 64, ndim=2), relabel=[relabel], batch_size=1024)
    for _ in range(12):  # 12 x 16 steps on a 64-step circular time line: wraps around twice
        rb.extend(stream.batch(16))
        sample = rb.sample()
        expected = stream.expected_window(sample["achieved_goal"], window)
        coords = sample["index"]
        assert torch.equal(relabel.window_lengths(coords, rb.storage, rb.newest_index), expected)
        for key in ("goal", "graph_goal"):
            check_goals(sample, key, expected)
            assert torch.equal(sample["next", key], sample[key])


def test_her_ratio_binomial():
    torch.manual_seed(1)
    stream = GoalStream(num_envs=3, min_len=10, max_len=30, seed=2)
    relabel = FutureGoalRelabel(
        her_ratio=(0.8, 1.0, 0.3, 0.0), out_keys=["a", "b", "c", "d"], reward_keys=None
    )
    rb = filled_buffer(stream, 3 * 200, 5, 30, relabel)
    n = 20_000
    sample = rb.sample(n)
    for key, ratio in (("a", 0.8), ("c", 0.3)):
        fraction = check_goals(sample, key).double().mean().item()
        sigma = math.sqrt(ratio * (1 - ratio) / n)
        assert abs(fraction - ratio) < 4 * sigma, (key, fraction)
    assert check_goals(sample, "b").all()
    assert not check_goals(sample, "d").any()


def test_rewards_match_relabelled_goals():
    torch.manual_seed(2)
    stream = GoalStream(num_envs=2, min_len=3, max_len=12, seed=3)
    rb = filled_buffer(stream, 2 * 100, 4, 25, FutureGoalRelabel(window=5))
    sample = rb.sample(4096)
    for goal_key, reward_key in (("goal", "reward"), ("graph_goal", "graph_reward")):
        expected = sparse_reward(sample["next", "achieved_goal"], sample[goal_key]).float()
        assert torch.equal(sample["next", reward_key], expected)
        # a goal k = 0 steps ahead is the next achieved goal itself: success
        ahead = sample[goal_key][..., 1] - sample["achieved_goal"][..., 1]
        relabelled = sample[goal_key][..., 0] != SENTINEL
        assert (sample["next", reward_key][relabelled & (ahead == 1)] == 0).all()
        assert (sample["next", reward_key][relabelled & (ahead > 1)] == -1).all()
        assert (sample["next", reward_key][~relabelled] == -1).all()


def test_custom_reward_fn():
    stream = GoalStream(num_envs=2, min_len=3, max_len=12, seed=4)

    def negative_distance(achieved, goal):
        return -(achieved - goal).norm(dim=-1)  # [B]: the transform adds the trailing dim

    relabel = FutureGoalRelabel(negative_distance, her_ratio=1.0, out_keys=["goal"], reward_keys=["r"])
    rb = filled_buffer(stream, 2 * 50, 2, 20, relabel)
    sample = rb.sample(256)
    ahead = sample["goal"][..., 1] - sample["next", "achieved_goal"][..., 1]
    torch.testing.assert_close(sample["r"], -ahead.unsqueeze(-1))


@pytest.mark.parametrize("n_valid", [10, 4])
def test_offsets_uniform_on_support(n_valid):
    torch.manual_seed(3)
    window = 10
    # one env, one long episode stored; transition t has min(T_t, W) = n_valid future records
    stream = GoalStream(num_envs=1, min_len=40, max_len=40, seed=5)
    rb = filled_buffer(stream, 64, 1, 40)
    relabel = FutureGoalRelabel(window=window, her_ratio=1.0, out_keys=["goal"], reward_keys=None)
    t = 40 - n_valid
    draws = 40_000
    index = torch.tensor([[t, 0]]).expand(draws, 2)
    sample = rb.storage.get((index[:, 0], index[:, 1]))
    out = relabel.relabel_sample(sample, index, rb.storage, newest_index=rb.newest_index)
    offset = (out["goal"][:, 1] - out["next", "achieved_goal"][:, 1]).long()
    counts = torch.bincount(offset, minlength=window)
    assert counts[n_valid:].sum() == 0 and (counts[:n_valid] > 0).all()
    assert stats.chisquare(counts[:n_valid].numpy()).pvalue > 1e-4


def test_flat_storage_pitfall_and_traj_ids():
    """rb.extend(batch.reshape(-1)) interleaves envs: done flags alone let goals cross episodes."""
    torch.manual_seed(4)
    stream = GoalStream(num_envs=4, min_len=20, max_len=60, seed=6)
    rb = RelabelReplayBuffer(storage=LazyTensorStorage(10_000), batch_size=4096)
    for _ in range(6):
        rb.extend(stream.batch(25).reshape(-1))
    naive = FutureGoalRelabel(her_ratio=1.0, out_keys=["goal"], traj_key=None, step_count_key=None)
    sample = relabelled(rb, naive)
    crossed = sample["goal"][:, 0] != sample["achieved_goal"][:, 0]
    assert crossed.double().mean() > 0.05  # the pitfall is real
    # trajectory ids tell interleaved chunks apart (step counts alone can coincide across envs)
    for markers in ({}, {"step_count_key": None, "done_key": None}):
        relabel = FutureGoalRelabel(her_ratio=1.0, out_keys=["goal"], **markers)
        sample = relabelled(rb, relabel)
        check_goals(sample, "goal")
        uid, step = sample["achieved_goal"][:, 0].long(), sample["achieved_goal"][:, 1].long()
        remaining = torch.tensor([stream.episode_length[int(u)] for u in uid]) - step
        assert (sample["goal"][:, 1] - step <= remaining.clamp(max=150)).all()


def test_wrap_around_seam_without_trajectory_ids():
    """Aligned episodes make the oldest record look like the continuation of the newest one."""
    torch.manual_seed(5)
    stream = GoalStream(num_envs=2, min_len=4, max_len=4, seed=7)
    # 12 time slots = 3 episodes; 5-step batches leave the newest episode of each env unfinished
    relabel = FutureGoalRelabel(window=4, her_ratio=1.0, out_keys=["goal"], traj_key=None)
    rb = RelabelReplayBuffer(storage=LazyTensorStorage(2 * 12, ndim=2), relabel=[relabel], batch_size=2048)
    seen_seam = False
    for _ in range(9):
        rb.extend(stream.batch(5))
        sample = rb.sample()
        expected = stream.expected_window(sample["achieved_goal"], 4)
        check_goals(sample, "goal", expected)
        assert rb.newest_index == rb.storage._last_cursor_index  # tracked from extend's indices
        if not rb.storage._is_full:
            continue
        newest = rb.newest_index
        following = rb.storage.get(((newest + 1) % 12, 0))
        newest_td = rb.storage.get((newest, 0))
        if not newest_td["next", "done"].item():
            seen_seam |= bool(following["step_count"] == newest_td["step_count"] + 1)
    assert seen_seam  # the markers alone could not have told the seam apart


def test_seam_after_load_state_dict_uses_the_saved_newest_index():
    torch.manual_seed(6)
    stream = GoalStream(num_envs=2, min_len=4, max_len=4, seed=8)
    rb = filled_buffer(stream, 2 * 12, 7, 5)
    state = rb.state_dict()
    relabel = FutureGoalRelabel(window=4, her_ratio=1.0, out_keys=["goal"], traj_key=None)
    restored = RelabelReplayBuffer(
        storage=LazyTensorStorage(2 * 12, ndim=2), relabel=[relabel], batch_size=2048
    )
    restored.load_state_dict(state)
    assert restored.storage._is_full and restored.storage._last_cursor_index is None
    newest = 34 % 12  # 35 steps written: the newest record (step 2 of 4) is followed by an old step 3
    assert restored.newest_index == newest  # saved by the buffer, not read from the storage
    assert (
        restored.storage.get((newest + 1, 0))["step_count"]
        == restored.storage.get((newest, 0))["step_count"] + 1
    )
    sample = restored.sample()
    check_goals(sample, "goal", stream.expected_window(sample["achieved_goal"], 4))
    # a plain TensorDictReplayBuffer's state: the position is unknown, the markers alone guard the seam
    plain = TensorDictReplayBuffer(storage=LazyTensorStorage(2 * 12, ndim=2))
    plain.load_state_dict(state)
    restored.load_state_dict(plain.state_dict())
    assert restored.newest_index is None
    with pytest.warns(UserWarning, match="newest write position is unknown"):
        restored.sample()


@pytest.mark.parametrize("batch_size", [[], [4], [6, 4]])
@pytest.mark.parametrize("ndim", [1, 2])
def test_batch_shapes_without_buffer(batch_size, ndim):
    torch.manual_seed(7)
    stream = GoalStream(num_envs=3, min_len=5, max_len=15, seed=9)
    if ndim == 2:
        storage = LazyTensorStorage(3 * 40, ndim=2)
        data = stream.batch(30)
        storage.set(range(30), data.transpose(0, 1))
        index = torch.stack([torch.randint(30, batch_size), torch.randint(3, batch_size)], -1)
        sample = storage.get((index[..., 0], index[..., 1]))
    else:
        storage = LazyTensorStorage(200)
        data = stream.batch(40)[0]
        storage.set(range(40), data)
        index = torch.randint(40, batch_size)
        sample = storage.get(index)
    assert sample.batch_size == torch.Size(batch_size)
    out = FutureGoalRelabel(window=6).relabel_sample(sample, index, storage)
    assert out["goal"].shape == torch.Size([*batch_size, 2])
    assert out["next", "graph_reward"].shape == torch.Size([*batch_size, 1])
    check_goals(out, "graph_goal")
    assert check_goals(out, "graph_goal").all()


def test_inside_replay_buffer_and_composed():
    torch.manual_seed(8)
    stream = GoalStream(num_envs=2, min_len=5, max_len=15, seed=10)
    pipeline = Compose(
        FutureGoalRelabel(window=8),
        RenameTransform([("next", "graph_reward")], [("next", "reward")]),
    )
    rb = RelabelReplayBuffer(storage=LazyTensorStorage(2 * 50, ndim=2), relabel=pipeline, batch_size=128)
    assert len(rb.relabel) == 2  # a Compose is unpacked into steps
    # a buffer transform runs at sampling time, before the relabel
    rb.append_transform(RenameTransform(["observation"], ["state"], create_copy=True))
    rb.extend(stream.batch(30))
    out = rb.sample()
    assert "state" in out.keys() and ("next", "reward") in out.keys(True)
    assert ("next", "graph_reward") not in out.keys(True)
    check_goals(out, "graph_goal", stream.expected_window(out["achieved_goal"], 8))
    torch.testing.assert_close(
        out["next", "reward"], sparse_reward(out["next", "achieved_goal"], out["graph_goal"]).float()
    )
    # appended as a transform it cannot see the sample's storage coordinates: a clear error
    rb.append_transform(FutureGoalRelabel())
    with pytest.raises(RuntimeError, match=r"RelabelReplayBuffer\(storage=..., relabel="):
        rb.sample()
    plain = ReplayBuffer(storage=LazyTensorStorage(100), batch_size=8)
    plain.extend(stream.batch(10)[0])
    plain.append_transform(FutureGoalRelabel())
    with pytest.raises(RuntimeError, match="relabel_sample"):
        plain.sample()
    with pytest.raises(RuntimeError, match="relabel_sample"):
        pipeline(out)


def test_in_place_relabel_key():
    stream = GoalStream(num_envs=2, min_len=5, max_len=15, seed=11)
    relabel = FutureGoalRelabel(
        her_ratio=1.0, out_keys=["desired_goal"], reward_keys=[("next", "reward")], window=3
    )
    out = filled_buffer(stream, 2 * 50, 1, 30, relabel).sample(64)
    assert check_goals(out, "desired_goal").all()
    assert torch.equal(out["next", "desired_goal"], out["desired_goal"])
    assert torch.equal(
        out["next", "reward"], SparseGoalReward(0.5)(out["next", "achieved_goal"], out["desired_goal"])
    )


def test_errors():
    stream = GoalStream(num_envs=2, min_len=5, max_len=15, seed=12)
    rb = filled_buffer(stream, 2 * 50, 1, 10)
    storage = rb.storage
    sample = rb.sample(8)
    index = sample["index"]
    with pytest.raises(TypeError, match="TensorStorage"):
        FutureGoalRelabel().relabel_sample(sample.clone(), index, ListStorage(10))
    with pytest.raises(TypeError, match="does not take the replay buffer"):
        FutureGoalRelabel(rb)  # the former signature
    with pytest.raises(ValueError, match="her_ratio"):
        FutureGoalRelabel(her_ratio=(0.8, 1.2))
    with pytest.raises(ValueError, match="one out_key per her_ratio"):
        FutureGoalRelabel(her_ratio=0.8)
    with pytest.raises(ValueError, match="one reward key"):
        FutureGoalRelabel(reward_keys=["r"])
    with pytest.raises(ValueError, match="window"):
        FutureGoalRelabel(window=0)
    with pytest.raises(TypeError, match="callable"):
        FutureGoalRelabel(reward_fn=3)
    with pytest.raises(ValueError, match="At least one"):
        FutureGoalRelabel(traj_key=None, done_key=None, step_count_key=None)
    relabel = FutureGoalRelabel()
    with pytest.raises(ValueError, match="storage coordinates"):
        relabel.relabel_sample(sample.clone(), index[:, :1], storage)
    with pytest.raises(TypeError, match="integer storage coordinates"):
        relabel.relabel_sample(sample.clone(), index.float(), storage)
    with pytest.raises(KeyError, match="desired_goal"):
        relabel.relabel_sample(sample.exclude("desired_goal"), index, storage)
    with pytest.raises(KeyError, match="none of the episode markers"):
        FutureGoalRelabel(traj_key="missing", step_count_key=None, done_key=None).relabel_sample(
            sample.clone(), index, storage
        )
    empty = TensorDictReplayBuffer(storage=LazyTensorStorage(10, ndim=2))
    with pytest.raises(RuntimeError, match="empty"):
        relabel.relabel_sample(sample.clone(), index, empty.storage)
    with pytest.raises(RuntimeError, match="not inside an environment"):
        relabel._call(sample)
    with pytest.raises(RuntimeError, match="relabel_sample"):
        relabel(sample.clone())
    with pytest.raises(ValueError, match="reward_fn must return"):
        FutureGoalRelabel(lambda a, g: a).relabel_sample(sample.clone(), index, storage)


def test_plain_replay_buffer_is_accepted():
    stream = GoalStream(num_envs=1, min_len=5, max_len=15, seed=13)
    rb = ReplayBuffer(storage=LazyTensorStorage(100), batch_size=16)
    rb.extend(stream.batch(50)[0])
    sample, info = rb.sample(return_info=True)
    check_goals(FutureGoalRelabel(window=5).relabel_sample(sample, info["index"], rb.storage), "graph_goal")


class TraceableGoalEnv(EnvBase):
    """Episodes of random length whose achieved goal is ``(episode uid, step)``; uids are unique."""

    def __init__(self, env_index: int, num_envs: int, min_len: int, max_len: int, seed: int) -> None:
        super().__init__()
        self.env_index, self.num_envs = env_index, num_envs
        self.min_len, self.max_len = min_len, max_len
        self.rng = torch.Generator().manual_seed(seed)
        self.episode = -1
        self.observation_spec = Composite(
            observation=Unbounded((3,)), achieved_goal=Unbounded((2,)), desired_goal=Unbounded((2,))
        )
        self.action_spec = Bounded(-1.0, 1.0, (1,))
        self.reward_spec = Unbounded((1,))

    def _observation(self) -> TensorDict:
        achieved = torch.tensor([self.env_index + self.num_envs * self.episode, self.t], dtype=torch.float32)
        return TensorDict(
            observation=torch.cat([achieved, torch.tensor([float(self.env_index)])]),
            achieved_goal=achieved,
            desired_goal=torch.full((2,), -1000.0),
        )

    def _reset(self, tensordict=None, **kwargs) -> TensorDict:
        self.episode += 1
        self.t = 0
        self.length = int(torch.randint(self.min_len, self.max_len + 1, (), generator=self.rng))
        out = self._observation()
        out["done"] = out["terminated"] = torch.zeros(1, dtype=torch.bool)
        return out

    def _step(self, tensordict) -> TensorDict:
        self.t += 1
        out = self._observation()
        out["reward"] = torch.zeros(1)
        out["done"] = torch.tensor([self.t >= self.length])
        out["terminated"] = torch.zeros(1, dtype=torch.bool)
        return out

    def _set_seed(self, seed):
        self.rng.manual_seed(seed)


@pytest.mark.parametrize("layout", ["ndim2", "flat_with_traj_ids"])
def test_collector_batches_never_cross_episodes(layout):
    torch.manual_seed(0)
    num_envs, horizon, window = 3, 16, 10
    env = TransformedEnv(
        SerialEnv(
            num_envs, [lambda i=i: TraceableGoalEnv(i, num_envs, 5, 30, seed=i) for i in range(num_envs)]
        ),
        StepCounter(),
    )
    collector = Collector(
        env, None, frames_per_batch=num_envs * horizon, total_frames=num_envs * horizon * 10
    )
    relabel = FutureGoalRelabel(window=window)
    storage = LazyTensorStorage(num_envs * 64, ndim=2 if layout == "ndim2" else 1)
    rb = RelabelReplayBuffer(storage=storage, relabel=[relabel], batch_size=2048)
    last_step: dict[int, int] = {}
    try:
        for batch in collector:
            assert batch.batch_size == torch.Size([num_envs, horizon])
            for uid, step in batch["next", "achieved_goal"].reshape(-1, 2).long().tolist():
                last_step[uid] = max(step, last_step.get(uid, 0))
            rb.extend(batch if layout == "ndim2" else batch.reshape(-1))
            sample = rb.sample()
            for key in ("goal", "graph_goal"):
                goal, achieved = sample[key], sample["achieved_goal"]
                relabelled = goal[:, 0] != -1000.0
                assert (goal[relabelled, 0] == achieved[relabelled, 0]).all()
                ahead = (goal[:, 1] - achieved[:, 1])[relabelled]
                assert (ahead >= 1).all() and (ahead <= window).all()
                stored = torch.tensor([last_step[int(u)] for u in achieved[relabelled, 0]])
                assert (goal[relabelled, 1] <= stored).all()
            if layout == "ndim2":  # episode-contiguous lanes: the full window is used
                uid, step = sample["achieved_goal"].long().unbind(-1)
                expected = (torch.tensor([last_step[int(u)] for u in uid]) - step).clamp(max=window)
                assert torch.equal(
                    relabel.window_lengths(sample["index"], rb.storage, rb.newest_index), expected
                )
    finally:
        collector.shutdown()


MESSAGE = "is not an environment transform"


def sample_transforms():
    return {
        "future": FutureGoalRelabel(),
        "hindsight": HindsightSubgoalRelabel(),
        "builder": HighLevelTransitionBuilder(),
    }


def point_maze():
    return make_env("PointMaze", num_envs=1, seed=0)


@pytest.mark.parametrize("name", ["future", "hindsight", "builder"])
def test_transformed_env_raises_the_clear_error(name):
    transform = sample_transforms()[name]
    with pytest.raises(RuntimeError, match=f"{type(transform).__name__} {MESSAGE}"):
        TransformedEnv(point_maze(), transform)
    # the transform was left without a container: still usable on samples / in a replay buffer
    assert transform.container is None and transform.parent is None


@pytest.mark.parametrize("name", ["future", "hindsight", "builder"])
def test_composed_or_appended_in_an_env_raises_the_clear_error(name):
    transform = sample_transforms()[name]
    with pytest.raises(RuntimeError, match=MESSAGE):
        TransformedEnv(point_maze(), Compose(StepCounter(), transform))
    transform = sample_transforms()[name]
    env = TransformedEnv(point_maze(), StepCounter())
    with pytest.raises(RuntimeError, match=MESSAGE):
        env.append_transform(transform)
    # a Compose built first and attached later
    compose = Compose(sample_transforms()[name])
    with pytest.raises(RuntimeError, match=MESSAGE):
        TransformedEnv(point_maze(), compose)


def test_still_fine_outside_an_environment():
    transforms = sample_transforms()
    compose = Compose(StepCounter(), transforms["hindsight"])  # a Compose without env is fine
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(8), transform=transforms["builder"])
    assert len(rb) == 0
    sample = TensorDict(
        {
            "subgoal": torch.ones(4, 2),
            "desired_goal": torch.zeros(4, 2),
            ("next", "achieved_goal"): torch.zeros(4, 2),
        },
        batch_size=[4],
    )
    out = compose[1](sample)
    assert out["next", "reward"].shape == (4, 1)
    with pytest.raises(RuntimeError, match=MESSAGE):
        transforms["hindsight"]._call(sample)
