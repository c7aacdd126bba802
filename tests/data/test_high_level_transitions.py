"""Tests of HighLevelTransitionBuilder against a plain-Python segmentation of the same stream."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_dhrl.data import HighLevelTransitionBuilder


class SubgoalStream:
    """Collector-shaped low-level batches ``[num_envs, T]`` with traceable segments.

    Episodes have random lengths; a subgoal is issued at the first step of each episode (unless
    ``flag_first=False``) and then with probability ``flag_prob`` per step. Entries encode their origin:
    ``observation = (lane, uid, step)``, ``achieved_goal = (uid, step)``, ``desired_goal = (uid, -1)``,
    ``subgoal = (uid, issuing step)``.
    """

    def __init__(self, num_envs, min_len, max_len, flag_prob=0.25, seed=0, flag_first=True):
        self.num_envs = num_envs
        self.min_len, self.max_len, self.flag_prob = min_len, max_len, flag_prob
        self.flag_first = flag_first
        self.generator = torch.Generator().manual_seed(seed)
        self.uid = torch.arange(num_envs)
        self.next_uid = num_envs
        self.step = torch.zeros(num_envs, dtype=torch.long)
        self.length = self._lengths(num_envs)
        self.issued = torch.full((num_envs,), -1)
        self.log: list[list[tuple[int, int, bool, bool]]] = [
            [] for _ in range(num_envs)
        ]  # (uid, step, flag, done)

    def _lengths(self, n):
        return torch.randint(self.min_len, self.max_len + 1, (n,), generator=self.generator)

    def batch(self, horizon: int) -> TensorDict:
        cols = []
        for _ in range(horizon):
            flag = torch.rand(self.num_envs, generator=self.generator) < self.flag_prob
            if self.flag_first:
                flag |= self.step == 0
            self.issued = torch.where(flag, self.step, self.issued)
            done = self.step + 1 == self.length
            cols.append((self.uid.clone(), self.step.clone(), flag, done, self.issued.clone()))
            for lane in range(self.num_envs):
                self.log[lane].append(
                    (int(self.uid[lane]), int(self.step[lane]), bool(flag[lane]), bool(done[lane]))
                )
            self.step = torch.where(done, 0, self.step + 1)
            if done.any():
                n = int(done.sum())
                self.uid[done] = torch.arange(self.next_uid, self.next_uid + n)
                self.next_uid += n
                self.length[done] = self._lengths(n)
                self.issued[done] = -1
        uid, step, flag, done, issued = (torch.stack(x, 1) for x in zip(*cols, strict=True))
        lane = torch.arange(self.num_envs)[:, None].expand_as(uid)
        f = torch.float32
        return TensorDict(
            {
                "observation": torch.stack([lane, uid, step], -1).to(f),
                "achieved_goal": torch.stack([uid, step], -1).to(f),
                "desired_goal": torch.stack([uid, torch.full_like(uid, -1)], -1).to(f),
                "subgoal": torch.stack([uid, issued], -1).to(f),
                "new_subgoal": flag.unsqueeze(-1),
                "step_count": step.unsqueeze(-1),
                "action": torch.zeros(*uid.shape, 3),
                ("next", "observation"): torch.stack([lane, uid, step + 1], -1).to(f),
                ("next", "achieved_goal"): torch.stack([uid, step + 1], -1).to(f),
                ("next", "done"): done.unsqueeze(-1),
                ("next", "terminated"): torch.zeros_like(done).unsqueeze(-1),
                ("next", "truncated"): done.unsqueeze(-1),
                ("next", "reward"): torch.zeros(*uid.shape, 1),
            },
            batch_size=list(uid.shape),
        )

    def reference_segments(self) -> dict[tuple, tuple]:
        """Completed segments fed so far: (lane, uid, start) -> (end step, segment index, episode done)."""
        segments = {}
        for lane, steps in enumerate(self.log):
            current, index, prev_uid = None, 0, None
            for position, (uid, step, flag, done) in enumerate(steps):
                if uid != prev_uid:
                    current, index, prev_uid = None, 0, uid
                if flag:
                    current = (lane, uid, step, index)
                    index += 1
                if current is not None:
                    # the segment ends here if the episode ends or the next logged step of the episode flags
                    nxt = steps[position + 1] if position + 1 < len(steps) else None
                    next_flag = nxt is not None and nxt[0] == uid and nxt[2]
                    if done or next_flag:
                        segments[current[:3]] = (step, current[3], done)
                        current = None
        return segments

    def finished_uids(self) -> set[int]:
        return {uid for steps in self.log for uid, _, _, done in steps if done}


def records_to_dict(records: TensorDict) -> dict[tuple, tuple]:
    out = {}
    for i in range(records.shape[0]):
        r = records[i]
        lane, uid, start = (int(v) for v in r["observation"].tolist())
        end_lane, end_uid, end_next = (int(v) for v in r["next", "observation"].tolist())
        assert (end_lane, end_uid) == (lane, uid)
        key = (lane, uid, start)
        assert key not in out, f"segment emitted twice: {key}"
        out[key] = (end_next - 1, int(r["segment_index"]), bool(r["next", "done"]))
        assert int(r["segment_length"]) == end_next - start
        assert r["achieved_goal"].tolist() == [uid, start]
        assert r["next", "achieved_goal"].tolist() == [uid, end_next]
        assert r["desired_goal"].tolist() == r["next", "desired_goal"].tolist() == [uid, -1]
        assert r["subgoal"].tolist() == [uid, start]  # the subgoal issued at the segment's first step
        assert "step_count" not in r.keys()  # the high-level step counter is segment_index
    return out


def split_points(total: int, generator: torch.Generator, max_len: int = 7) -> list[int]:
    sizes = []
    while sum(sizes) < total:
        sizes.append(min(int(torch.randint(1, max_len + 1, (), generator=generator)), total - sum(sizes)))
    return sizes


# ---------------------------------------------------------------------------------------------------
def test_single_episode_segments_exact():
    T, c_h = 10, 4
    step = torch.arange(T)
    position = torch.stack([step, 10 * step], -1).float()
    batch = TensorDict(
        {
            "observation": torch.cat([position, torch.ones(T, 1)], -1),
            "achieved_goal": position,
            "desired_goal": torch.tensor([[8.0, 80.0]]).expand(T, 2),
            "subgoal": (step // c_h * c_h + 100).float().unsqueeze(-1).expand(T, 2),
            "new_subgoal": (step % c_h == 0).unsqueeze(-1),
            ("next", "observation"): torch.cat([position + torch.tensor([1.0, 10.0]), torch.ones(T, 1)], -1),
            ("next", "achieved_goal"): position + torch.tensor([1.0, 10.0]),
            ("next", "done"): (step == T - 1).unsqueeze(-1),
        },
        batch_size=[T],
    )
    out = HighLevelTransitionBuilder(step_count_key=None).build(batch)
    assert out.batch_size == torch.Size([3])
    torch.testing.assert_close(out["observation"][:, 0], torch.tensor([0.0, 4.0, 8.0]))
    # s_{t+c_h}: the state at the next flag, or the final state for the segment cut by the episode end
    torch.testing.assert_close(out["next", "observation"][:, 0], torch.tensor([4.0, 8.0, 10.0]))
    torch.testing.assert_close(
        out["next", "achieved_goal"], torch.tensor([[4.0, 40.0], [8.0, 80.0], [10.0, 100.0]])
    )
    torch.testing.assert_close(out["subgoal"][:, 0], torch.tensor([100.0, 104.0, 108.0]))
    assert out["segment_length"].squeeze(-1).tolist() == [4, 4, 2]
    assert out["segment_index"].squeeze(-1).tolist() == [0, 1, 2]
    assert out["episode_id"].squeeze(-1).tolist() == [0, 0, 0]
    assert out["next", "done"].squeeze(-1).tolist() == [False, False, True]
    # sparse reward of (ag_{t+c}, g) at 0.5: only the second segment ends on the goal (8, 80)
    assert out["next", "reward"].squeeze(-1).tolist() == [-1.0, 0.0, -1.0]
    assert out["next", "reward"].shape == torch.Size([3, 1])


@pytest.mark.parametrize("emit", ["segment", "episode"])
def test_matches_reference_over_random_batch_splits(emit):
    torch.manual_seed(0)
    generator = torch.Generator().manual_seed(1)
    stream = SubgoalStream(num_envs=3, min_len=3, max_len=25, flag_prob=0.3, seed=2)
    builder = HighLevelTransitionBuilder(emit=emit)
    emitted = {}
    for size in split_points(200, generator):
        out = builder.build(stream.batch(size))
        new = records_to_dict(out)
        assert not set(new) & set(emitted)
        emitted.update(new)
        if emit == "episode":  # whole episodes, contiguous and in order
            episode = out["episode_id"].squeeze(-1)
            index = out["segment_index"].squeeze(-1)
            for eid in episode.unique():
                rows = (episode == eid).nonzero().squeeze(-1)
                assert torch.equal(rows, torch.arange(rows[0], rows[0] + rows.numel()))
                assert index[rows].tolist() == list(range(rows.numel()))
                assert bool(out["next", "done"][rows[-1]])
    expected = stream.reference_segments()
    if emit == "episode":
        finished = stream.finished_uids()
        expected = {k: v for k, v in expected.items() if k[1] in finished}
        assert builder.num_pending == len(stream.reference_segments()) - len(expected)
    assert emitted == expected
    assert len(expected) > 50


def test_episode_ids_consistent_and_unique():
    stream = SubgoalStream(num_envs=4, min_len=2, max_len=12, seed=3)
    builder = HighLevelTransitionBuilder(emit="segment")
    ids = {}
    for size in (1, 5, 3, 17, 2, 9):
        out = builder.build(stream.batch(size))
        for uid, eid in zip(
            out["achieved_goal"][:, 0].long().tolist(), out["episode_id"].squeeze(-1).tolist(), strict=True
        ):
            assert ids.setdefault(uid, eid) == eid
    assert len(set(ids.values())) == len(ids)


def test_state_dict_round_trip_mid_segment():
    stream_a = SubgoalStream(num_envs=2, min_len=4, max_len=20, flag_prob=0.1, seed=4)
    stream_b = SubgoalStream(num_envs=2, min_len=4, max_len=20, flag_prob=0.1, seed=4)
    sizes = [3, 5, 1, 8, 2, 6, 4, 7]
    uninterrupted = HighLevelTransitionBuilder()
    outputs_a = [uninterrupted.build(stream_a.batch(s)) for s in sizes]
    first = HighLevelTransitionBuilder()
    outputs_b = [first.build(stream_b.batch(s)) for s in sizes[:4]]
    state = first.state_dict()
    assert "_extra_state" in state
    resumed = HighLevelTransitionBuilder()
    resumed.load_state_dict(torch.load(_save(state), weights_only=False))
    outputs_b += [resumed.build(stream_b.batch(s)) for s in sizes[4:]]
    for out_a, out_b in zip(outputs_a, outputs_b, strict=True):
        assert (out_a == out_b).all()
    assert sum(o.shape[0] for o in outputs_a) > 0


def _save(state):
    import io

    buffer = io.BytesIO()
    torch.save(state, buffer)
    buffer.seek(0)
    return buffer


def test_unflagged_reset_cuts_the_segment():
    stream = SubgoalStream(num_envs=1, min_len=6, max_len=6, flag_prob=0.0, seed=5)
    first = stream.batch(4)  # steps 0..3 of an episode, one flag at step 0, no done
    builder = HighLevelTransitionBuilder(emit="segment")
    assert builder.build(first).shape[0] == 0
    restarted = SubgoalStream(num_envs=1, min_len=6, max_len=6, flag_prob=0.0, seed=6)
    restarted.uid[:] = 100
    out = builder.build(restarted.batch(6))  # the env was reset without a done flag
    cut = out[out["achieved_goal"][:, 0] == 0]
    assert cut.shape[0] == 1
    assert cut["segment_length"].item() == 4
    assert cut["next", "observation"].tolist() == [[0.0, 0.0, 4.0]]
    assert cut["next", "done"].item() and cut["next", "truncated"].item()
    assert not cut["next", "terminated"].item()
    assert out[out["achieved_goal"][:, 0] == 100]["segment_length"].tolist() == [[6]]


def test_steps_before_the_first_flag_are_dropped():
    stream = SubgoalStream(num_envs=1, min_len=10, max_len=10, flag_prob=0.0, seed=7, flag_first=False)
    batch = stream.batch(10)
    batch["new_subgoal"][0, 3] = True
    batch["subgoal"][0, 3:, 1] = 3
    out = HighLevelTransitionBuilder().build(batch)
    assert out.shape[0] == 1
    assert out["observation"][0, 2].item() == 3 and out["segment_length"].item() == 7
    assert out["segment_index"].item() == 0


def test_as_replay_buffer_transform():
    stream = SubgoalStream(num_envs=3, min_len=3, max_len=10, seed=8)
    builder = HighLevelTransitionBuilder()
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(1000), transform=builder, batch_size=16)
    total = 0
    for size in (4, 9, 1, 12):
        before = len(rb)
        rb.extend(stream.batch(size))
        total += len(rb) - before
    assert total == len(records_to_dict(rb[:])) > 0
    stored = rb[:]
    # whole episodes, contiguous in the 1-D storage
    episode, index = stored["episode_id"].squeeze(-1), stored["segment_index"].squeeze(-1)
    for eid in episode.unique():
        rows = (episode == eid).nonzero().squeeze(-1)
        assert torch.equal(rows, torch.arange(rows[0], rows[0] + rows.shape[0]))
        assert index[rows].tolist() == list(range(rows.shape[0]))
    sample = rb.sample()
    assert sample.batch_size == torch.Size([16]) and "segment_index" in sample.keys()
    assert any(k.endswith("_extra_state") for k in rb.state_dict()["_transforms"])


def test_batched_leading_dims_and_single_env():
    stream = SubgoalStream(num_envs=4, min_len=3, max_len=9, seed=9)
    batch = stream.batch(30)
    flat = HighLevelTransitionBuilder(emit="segment").build(batch)
    nested = HighLevelTransitionBuilder(emit="segment").build(batch.reshape(2, 2, 30))
    assert records_to_dict(flat) == records_to_dict(nested)
    single = HighLevelTransitionBuilder(emit="segment").build(batch[1])
    assert records_to_dict(single) == {k: v for k, v in records_to_dict(flat).items() if k[0] == 1}


def test_errors():
    stream = SubgoalStream(num_envs=2, min_len=3, max_len=9, seed=10)
    builder = HighLevelTransitionBuilder()
    builder.build(stream.batch(5))
    with pytest.raises(ValueError, match="lanes"):
        builder.build(stream.batch(5)[:1])
    builder.reset()
    builder.build(stream.batch(5)[:1])
    with pytest.raises(KeyError, match="missing"):
        HighLevelTransitionBuilder().build(stream.batch(5).exclude("new_subgoal"))
    with pytest.raises(KeyError, match="changed"):
        builder.build(stream.batch(5)[:1].exclude("step_count"))
    with pytest.raises(ValueError, match="time as the last batch dimension"):
        HighLevelTransitionBuilder().build(TensorDict(batch_size=[]))
    with pytest.raises(ValueError, match="emit"):
        HighLevelTransitionBuilder(emit="step")
    with pytest.raises(ValueError, match="achieved_goal_key"):
        HighLevelTransitionBuilder(observation_keys=["observation"])
    with pytest.raises(TypeError, match="TensorDict"):
        HighLevelTransitionBuilder().build(torch.zeros(3))
    with pytest.raises(RuntimeError, match="not inside an environment"):
        HighLevelTransitionBuilder()._call(stream.batch(1))
