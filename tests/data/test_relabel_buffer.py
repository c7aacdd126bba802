"""Tests of RelabelReplayBuffer: relabelled samples, the newest write position, checkpoints, prefetching.

Capture-safe sampling (``RelabelReplayBuffer.capturable_sampler`` and ``FutureGoalRelabel.capturable_relabel``)
reads the whole preallocated storage with device-side counters, so that a CUDA graph
(``LossUpdater(cudagraphs=True)``) can replay sampling and relabelling with the update. Checked here on the CPU:
it relabels exactly as ``relabel_sample`` does (same coordinates, same random state) on storages that are
partly filled, full and wrapped, 1-D and ``[T, num_envs]``; it draws uniformly from the written records
(chi-square); it sees later writes without being rebuilt; ``torch.compile(fullgraph=True)`` traces it without a
graph break and never recompiles as the storage fills and wraps (the CPU's proxy for "no host synchronisation,
static shapes"); bad buffers are refused with the reason."""

from __future__ import annotations

import threading

import pytest
import torch
from scipy import stats
from tensordict import TensorDict, assert_close
from torchrl.data import LazyTensorStorage, SamplerWithoutReplacement, TensorDictReplayBuffer
from torchrl.envs import RenameTransform

from tests.data.test_future_goals import SENTINEL, GoalStream, check_goals
from torchrl_dhrl.data import (
    CompactLazyTensorStorage,
    FutureGoalRelabel,
    HindsightSubgoalRelabel,
    RelabelReplayBuffer,
)
from torchrl_dhrl.factory import make_high_level_buffer, make_low_level_buffer


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


OUT_KEYS = (
    "goal",
    "graph_goal",
    ("next", "goal"),
    ("next", "graph_goal"),
    ("next", "reward"),
    ("next", "graph_reward"),
)


def _filled_buffer(
    num_envs: int, capacity_rows: int, writes: int, horizon: int, window: int, seed: int, device="cpu"
):
    stream = GoalStream(num_envs=num_envs, min_len=2, max_len=30, seed=seed)
    ndim = 2 if num_envs > 1 else 1
    relabel = FutureGoalRelabel(window=window)
    rb = RelabelReplayBuffer(
        storage=LazyTensorStorage(capacity_rows * num_envs, ndim=ndim, device=device),
        relabel=[relabel],
        batch_size=128,
    )
    for _ in range(writes):
        batch = stream.batch(horizon)
        rb.extend((batch if ndim == 2 else batch.reshape(-1)).to(device))
    return rb, relabel, stream


@pytest.mark.parametrize("num_envs", [1, 3])
@pytest.mark.parametrize(
    "writes", [1, 3, 5, 9], ids=["partly-filled", "nearly-full", "wrapped", "wrapped-twice"]
)
def test_capturable_relabel_matches_relabel_sample(num_envs, writes):
    """Same coordinates and random state: the capture-safe relabelling writes exactly what ``relabel_sample``
    writes (windows, offsets, ratios, rewards), whether the storage is partly filled, full or wrapped."""
    for seed in range(4):
        rb, relabel, stream = _filled_buffer(num_envs, 40, writes, 11, window=7 + seed, seed=seed)
        index, _ = rb._sampler.sample(rb.storage, 512)  # the buffer's own draws
        index = torch.stack(index, -1) if isinstance(index, tuple) else index
        data = rb.storage[index.unbind(-1) if index.ndim > 1 else index]
        coords2d = index if index.ndim > 1 else index.unsqueeze(-1)
        torch.manual_seed(seed)
        expected = relabel.relabel_sample(data.clone(), index, rb.storage, newest_index=rb.newest_index)
        torch.manual_seed(seed)
        newest = torch.tensor(rb.newest_index)
        tensor_newest = relabel.relabel_sample(data.clone(), index, rb.storage, newest_index=newest)
        torch.manual_seed(seed)
        captured = relabel.capturable_relabel(rb.storage)(data.clone(), coords2d, newest)
        for key in OUT_KEYS:
            assert torch.equal(captured[key], expected[key]), key
            assert torch.equal(tensor_newest[key], expected[key]), key
        window = stream.expected_window(data["achieved_goal"], relabel.window)
        assert torch.equal(relabel.window_lengths(coords2d, rb.storage, newest), window)
        check_goals(captured, "graph_goal", window)
        assert check_goals(captured, "graph_goal").all()  # ratio 1.0: every graph goal relabelled


@pytest.mark.parametrize("num_envs", [1, 3])
def test_capturable_sampler_draws_written_records_uniformly(num_envs):
    rb, _, _ = _filled_buffer(num_envs, 64, 1, 37, window=5, seed=0)  # 37 of 64 rows written
    sample = rb.capturable_sampler(batch_size=4096)
    torch.manual_seed(0)
    index = torch.cat([sample()["index"] for _ in range(10)])
    time = index[:, 0] if num_envs > 1 else index
    assert int(time.min()) == 0 and int(time.max()) == 36  # every written row reachable, no unwritten one
    cells = time * num_envs + (index[:, 1] if num_envs > 1 else 0)
    counts = torch.bincount(cells, minlength=37 * num_envs).double()
    assert counts.numel() == 37 * num_envs
    assert stats.chisquare(counts.numpy()).pvalue > 1e-3


def test_capturable_sampler_follows_later_writes_and_the_seam():
    rb, relabel, stream = _filled_buffer(3, 40, 1, 10, window=9, seed=3)
    sample = rb.capturable_sampler(batch_size=512)
    rows, newest = rb._device_counters
    assert (int(rows), int(newest)) == (10, 9)
    for write in range(1, 9):  # fills the 40 rows at write 4, then wraps
        rb.extend(stream.batch(10))
        assert int(newest) == rb.newest_index and int(rows) == min(10 * (write + 1), 40)
        batch = sample()
        time = batch["index"][:, 0]
        assert int(time.max()) < int(rows)
        if write == 3:
            assert int(time.max()) >= 30  # the new rows are drawn without rebuilding the sampler
        window = stream.expected_window(batch["achieved_goal"], 9)  # ground truth, seam included
        assert torch.equal(relabel.window_lengths(batch["index"], rb.storage, rb.newest_index), window)
        check_goals(batch, "goal", window)
        relabelled = check_goals(batch, "graph_goal", window)
        assert relabelled.all()
        assert 0.7 < check_goals(batch, "goal").float().mean() < 0.9  # her_ratio 0.8
        assert (batch["desired_goal"] == SENTINEL).all()  # the stored goal is not overwritten


@pytest.mark.slow
def test_capturable_sampler_compiles_whole_without_recompiling():
    """``torch.compile(fullgraph=True)``: no graph break (no host synchronisation) and no recompilation while the
    storage fills and wraps (nothing read on the host changes); with ``fallback_random`` the compiled sampler
    draws the eager one's batches."""
    from torchrl_dhrl.training import compile_available

    if compile_available() is not None:
        pytest.skip(f"torch.compile unavailable here: {compile_available()}")
    rb, _, stream = _filled_buffer(2, 30, 1, 8, window=6, seed=5)
    sample = rb.capturable_sampler(batch_size=64)
    torch._dynamo.reset()
    compiled = torch.compile(sample, fullgraph=True, options={"fallback_random": True})
    with torch._dynamo.config.patch(error_on_recompile=True):
        for _ in range(6):  # 8, 16, ..., 48 rows written into 30: fills, then wraps
            rb.extend(stream.batch(8))
            torch.manual_seed(1)
            got = compiled()
            torch.manual_seed(1)
            expected = sample()
            for key in ("index", "graph_goal", "goal", ("next", "reward"), "observation"):
                assert torch.equal(got[key], expected[key]), key


def test_capturable_sampler_refuses_what_it_cannot_capture():
    stream = GoalStream(num_envs=2, min_len=3, max_len=9, seed=0)

    def buffer(**kwargs):
        kwargs.setdefault("relabel", [FutureGoalRelabel(window=4)])
        rb = RelabelReplayBuffer(storage=LazyTensorStorage(100, ndim=2), batch_size=8, **kwargs)
        return rb

    with pytest.raises(RuntimeError, match="written to"):
        buffer().capturable_sampler()
    rb = buffer()
    rb.extend(stream.batch(5))
    with pytest.raises(ValueError, match="batch_size must be a positive int, got 0"):
        rb.capturable_sampler(batch_size=0)
    without = buffer(sampler=SamplerWithoutReplacement())
    without.extend(stream.batch(5))
    with pytest.raises(RuntimeError, match="this buffer's sampler is SamplerWithoutReplacement"):
        without.capturable_sampler()
    class Identity:  # a relabel step without a capture-safe form (no capturable_relabel)
        def __call__(self, tensordict):
            return tensordict

    custom = buffer(relabel=[Identity()])
    custom.extend(stream.batch(5))
    with pytest.raises(RuntimeError, match="the relabel step Identity has no capture-safe form"):
        custom.capturable_sampler()
    restored = buffer()
    restored.load_state_dict({k: v for k, v in rb.state_dict().items() if k != "_newest_index"})
    with pytest.raises(RuntimeError, match="newest written row is unknown"):
        restored.capturable_sampler()
    restored.extend(stream.batch(2))  # writing once more makes it known
    assert restored.capturable_sampler()()["index"].shape == (8, 2)


def test_capturable_sampler_after_a_restore():
    """A sampler built after ``load_state_dict`` draws from the restored rows with the restored seam."""
    rb, relabel, stream = _filled_buffer(2, 20, 5, 10, window=5, seed=2)  # wrapped: the seam matters
    restored = RelabelReplayBuffer(
        storage=LazyTensorStorage(40, ndim=2), relabel=[FutureGoalRelabel(window=5)], batch_size=256
    )
    restored.load_state_dict(rb.state_dict())
    torch.manual_seed(4)
    got = restored.capturable_sampler(batch_size=256)()
    torch.manual_seed(4)
    expected = rb.capturable_sampler(batch_size=256)()
    for key in ("index", "goal", "graph_goal", ("next", "graph_reward")):
        assert torch.equal(got[key], expected[key]), key
    window = stream.expected_window(got["achieved_goal"], 5)
    check_goals(got, "graph_goal", window)


def test_recipe_buffers_offer_capture_safe_sampling():
    """Both levels' recipe buffers offer the capture-safe sampler: the high level's (its transition builder acts on
    writes only) with subgoal testing, and with the gradual penalty only where the planner's graph query has a
    capture-safe form (a fixed-size graph; refused on a plain one, saying why)."""
    from tests.data.test_high_level_transitions import SubgoalStream
    from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph

    low = make_low_level_buffer(buffer_size=200, batch_size=16, reward_threshold=0.5)
    stream = GoalStream(num_envs=1, min_len=3, max_len=9, seed=0)
    batch = stream.batch(20).rename_key_("desired_goal", "waypoint")
    low.extend(batch)
    out = low.capturable_sampler()()
    assert out["index"].shape == (16, 2) and out["goal"].shape == (16, 2)
    segments = SubgoalStream(num_envs=3, min_len=8, max_len=40, flag_prob=0.2, seed=11)
    plain = GraphPlanner(LandmarkGraph(), lambda s, g: (s[..., :2] - g).norm(dim=-1), 2)
    for planner in (None, plain):
        high = make_high_level_buffer(
            buffer_size=100, batch_size=8, reward_threshold=0.5, her_window=3, planner=planner
        )
        for _ in range(3):
            high.extend(segments.batch(12))
        if planner is None:  # no graph query: subgoal tests and hindsight only
            out = high.capturable_sampler()()
            assert out["index"].shape == (8,) and out["subgoal_test"].shape == (8, 1)
            tested = out["subgoal_test"].squeeze(-1)
            assert torch.equal(out["subgoal"][~tested], out["next", "achieved_goal"][~tested])
        else:
            with pytest.raises(RuntimeError, match="distance_from_graph has no capture-safe form here"):
                high.capturable_sampler()
