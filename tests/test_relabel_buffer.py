"""Tests of RelabelReplayBuffer: relabelled samples, the newest write position, checkpoints, prefetching."""

from __future__ import annotations

import threading

import pytest
import torch
from tensordict import TensorDict, assert_close
from test_relabel_future import SENTINEL, GoalStream, check_goals
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import RenameTransform

from torchrl_dhrl.data import (
    CompactLazyTensorStorage,
    FutureGoalRelabel,
    HindsightSubgoalRelabel,
    RelabelReplayBuffer,
)


def low_level_buffer(capacity: int, window: int, **kwargs) -> RelabelReplayBuffer:
    return RelabelReplayBuffer(
        storage=LazyTensorStorage(capacity, ndim=2),
        relabel=[FutureGoalRelabel(window=window)],
        batch_size=256,
        **kwargs,
    )


def test_sample_is_relabelled_and_iterable():
    torch.manual_seed(0)
    stream = GoalStream(num_envs=3, min_len=5, max_len=20, seed=0)
    rb = low_level_buffer(3 * 40, window=6)
    rb.extend(stream.batch(30))
    for sample in (rb.sample(), next(iter(rb))):
        expected = stream.expected_window(sample["achieved_goal"], 6)
        for key in ("goal", "graph_goal"):
            check_goals(sample, key, expected)
        assert check_goals(sample, "graph_goal").all() and "index" in sample.keys()
    # the storage itself is untouched: relabelled entries only live in the samples
    assert "graph_goal" not in rb.storage.get(slice(None)).keys()
    assert (rb[:]["desired_goal"] == SENTINEL).all()


def test_single_step_and_plain_callables():
    torch.manual_seed(1)
    stream = GoalStream(num_envs=2, min_len=5, max_len=20, seed=1)
    rename = RenameTransform([("next", "graph_reward")], [("next", "distance_reward")])
    rb = RelabelReplayBuffer(
        storage=LazyTensorStorage(2 * 40, ndim=2), relabel=FutureGoalRelabel(window=4), batch_size=64
    )
    assert len(rb.relabel) == 1
    rb.extend(stream.batch(20))
    assert ("next", "graph_reward") in rb.sample().keys(True)
    both = RelabelReplayBuffer(
        storage=LazyTensorStorage(2 * 40, ndim=2),
        relabel=[FutureGoalRelabel(window=4), rename, lambda td: td.set("tag", torch.ones(td.shape))],
        batch_size=64,
    )
    both.extend(stream.batch(20))
    out = both.sample()
    assert ("next", "distance_reward") in out.keys(True) and (out["tag"] == 1).all()
    assert "RelabelReplayBuffer" in repr(both) and "FutureGoalRelabel" in repr(both)


def test_high_level_steps_after_the_goal_relabel():
    torch.manual_seed(2)
    stream = GoalStream(num_envs=1, min_len=30, max_len=30, seed=2)
    rb = RelabelReplayBuffer(
        storage=LazyTensorStorage(100),
        relabel=[
            FutureGoalRelabel(her_ratio=1.0, window=5, out_keys=["desired_goal"], reward_keys=None),
            HindsightSubgoalRelabel(goal_key="desired_goal", action_key="action", subgoal_test_ratio=0.0),
        ],
        batch_size=128,
    )
    batch = stream.batch(30)[0]
    batch["action"] = torch.zeros(30, 2)
    rb.extend(batch)
    sample = rb.sample()
    check_goals(sample, "desired_goal")
    assert torch.equal(sample["action"], sample["next", "achieved_goal"])  # HAC: after the new goal
    ahead = sample["desired_goal"][:, 1] - sample["next", "achieved_goal"][:, 1]
    assert torch.equal(sample["next", "reward"].squeeze(-1), torch.where(ahead == 0, 0.0, -1.0))


def test_newest_index_follows_the_writes():
    rb = RelabelReplayBuffer(storage=LazyTensorStorage(5), batch_size=2)
    assert rb.newest_index is None
    rb.extend(TensorDict(x=torch.arange(4.0), batch_size=[4]))
    assert rb.newest_index == 3
    rb.add(TensorDict(x=torch.tensor(4.0)))
    assert rb.newest_index == 4
    rb.extend(TensorDict(x=torch.arange(2.0), batch_size=[2]))  # wraps around
    assert rb.newest_index == 1 == rb.storage._last_cursor_index
    rb.empty()
    assert rb.newest_index is None and len(rb) == 0
    time_major = RelabelReplayBuffer(storage=LazyTensorStorage(3 * 6, ndim=2), batch_size=2)
    for k, newest in ((0, 3), (1, 1), (2, 5)):  # [num_envs=3, T=4] batches on 6 time rows
        time_major.extend(TensorDict(x=torch.full((3, 4), float(k)), batch_size=[3, 4]))
        assert time_major.newest_index == newest == time_major.storage._last_cursor_index


def test_state_dict_round_trip_samples_identically(tmp_path):
    stream = GoalStream(num_envs=2, min_len=4, max_len=9, seed=3)
    rb = RelabelReplayBuffer(
        storage=CompactLazyTensorStorage(2 * 20, ndim=2),
        relabel=[FutureGoalRelabel(window=5, traj_key=None)],
        batch_size=128,
    )
    for _ in range(7):  # wrapped around
        rb.extend(stream.batch(6))
    restored = RelabelReplayBuffer(
        storage=CompactLazyTensorStorage(2 * 20, ndim=2), relabel=rb.relabel, batch_size=128
    )
    restored.load_state_dict(rb.state_dict())
    from_disk = RelabelReplayBuffer(
        storage=CompactLazyTensorStorage(2 * 20, ndim=2), relabel=rb.relabel, batch_size=128
    )
    rb.dumps(tmp_path)
    from_disk.loads(tmp_path)
    assert restored.newest_index == from_disk.newest_index == rb.newest_index == 41 % 20
    samples = []
    for buffer in (rb, restored, from_disk):
        torch.manual_seed(4)
        samples.append(buffer.sample())
    assert_close(samples[0], samples[1])
    assert_close(samples[0], samples[2])


def test_prefetch_relabels_against_the_sampled_storage():
    torch.manual_seed(5)
    stream = GoalStream(num_envs=4, min_len=5, max_len=40, seed=5)
    rb = low_level_buffer(4 * 32, window=7, prefetch=2)
    rb.extend(stream.batch(16))
    for _ in range(12):  # 16-step batches on a 32-step time line: prefetched samples outlive their data
        sample = rb.sample()
        assert rb.stats()["prefetch_queue_size"] == 2
        rb.extend(stream.batch(16))
        expected = stream.expected_window(sample["achieved_goal"], 7)
        for key in ("goal", "graph_goal"):
            check_goals(sample, key, expected)
    # prefetched, already relabelled batches are part of the checkpoint
    restored = low_level_buffer(4 * 32, window=7, prefetch=2)
    restored.load_state_dict(rb.state_dict())
    assert_close(restored.sample(), rb.sample())
    rb.shutdown()
    restored.shutdown()


def test_concurrent_writer_never_splits_a_relabelled_sample():
    """A writer thread extends while prefetching threads sample: goals always come from the sampled episode."""
    torch.manual_seed(6)
    stream = GoalStream(num_envs=2, min_len=3, max_len=12, seed=6)
    batches = [stream.batch(8) for _ in range(200)]
    rb = RelabelReplayBuffer(  # no trajectory ids: an overwritten window would show as a wrong step
        storage=LazyTensorStorage(2 * 16, ndim=2),
        relabel=[FutureGoalRelabel(window=6, her_ratio=(1.0,), out_keys=["goal"], traj_key=None)],
        batch_size=64,
        prefetch=3,
    )
    rb.extend(batches[0])

    def write():
        for batch in batches[1:]:
            rb.extend(batch)

    writer = threading.Thread(target=write)
    writer.start()
    try:
        while writer.is_alive():
            sample = rb.sample()
            assert check_goals(sample, "goal").all()
            ahead = sample["goal"][:, 1] - sample["achieved_goal"][:, 1]
            assert (ahead <= 6).all()
            step = sample["achieved_goal"][:, 1].long()
            episode = torch.tensor([stream.episode_length[int(u)] for u in sample["achieved_goal"][:, 0]])
            assert (sample["goal"][:, 1].long() <= episode).all() and (step < episode).all()
    finally:
        writer.join()
        rb.shutdown()


def test_errors():
    with pytest.raises(ValueError, match="shared=True"):
        RelabelReplayBuffer(storage=LazyTensorStorage(10), shared=True)
    rb = RelabelReplayBuffer(storage=LazyTensorStorage(10))
    with pytest.raises(ValueError, match="shared=True"):
        rb.share()
    with pytest.raises(TypeError, match="relabel steps must be callables"):
        RelabelReplayBuffer(storage=LazyTensorStorage(10), relabel=[3])
    # the storage must be a TensorStorage for FutureGoalRelabel (the default storage is a ListStorage)
    rb = RelabelReplayBuffer(relabel=[FutureGoalRelabel()], batch_size=2)
    rb.extend(GoalStream(num_envs=1, min_len=5, max_len=5).batch(5)[0])
    with pytest.raises(TypeError, match="TensorStorage"):
        rb.sample()


def test_a_plain_buffer_state_loads():
    stream = GoalStream(num_envs=2, min_len=4, max_len=9, seed=7)
    plain = TensorDictReplayBuffer(storage=LazyTensorStorage(2 * 30, ndim=2), batch_size=16)
    plain.extend(stream.batch(10))  # not wrapped around: the newest row is the last written one
    rb = low_level_buffer(2 * 30, window=5)
    rb.load_state_dict(plain.state_dict())
    assert rb.newest_index is None
    sample = rb.sample()
    check_goals(sample, "goal", stream.expected_window(sample["achieved_goal"], 5))
    rb.extend(stream.batch(5))
    assert rb.newest_index == 14
