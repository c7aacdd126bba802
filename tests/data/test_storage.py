"""CompactLazyTensorStorage: checkpoints hold the written rows only and round-trip exactly; the recipe's
buffers hold ``buffer_size`` transitions whatever ``num_envs``."""

import io

import pytest
import torch
from _recipe import recipe_config
from dhrl_utils import build_agent, build_replay_buffers
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_dhrl.data import CompactLazyTensorStorage


def _batch(num_envs, steps, start):
    """A collector-shaped ``[num_envs, T]`` batch whose entries say where they came from."""
    step = torch.arange(start, start + steps).expand(num_envs, steps)
    env = torch.arange(num_envs).unsqueeze(-1).expand(num_envs, steps)
    return TensorDict(
        observation=torch.stack([env, step], -1).float(),
        next=TensorDict(done=step.unsqueeze(-1) % 7 == 6, batch_size=[num_envs, steps]),
        batch_size=[num_envs, steps],
    )


def _buffer(storage_cls, capacity, ndim):
    return TensorDictReplayBuffer(storage=storage_cls(capacity, ndim=ndim), batch_size=16)


def _fill(rb, batches, num_envs=3, steps=10):
    for k in range(batches):
        data = _batch(num_envs, steps, k * steps)
        rb.extend(data if rb.storage.ndim == 2 else data.reshape(-1))


def _nbytes(obj):
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    return buffer.getbuffer().nbytes


@pytest.mark.parametrize("ndim", [1, 2])
def test_state_dict_holds_written_rows_and_round_trips(ndim):
    torch.manual_seed(0)
    rb = _buffer(CompactLazyTensorStorage, 3000, ndim)
    _fill(rb, 4)  # 120 of 3000 transitions
    written = 40 if ndim == 2 else 120
    state = rb.state_dict()
    assert state["_storage"]["_storage"]["observation"].shape[0] == written
    plain = _buffer(LazyTensorStorage, 3000, ndim)
    _fill(plain, 4)
    assert _nbytes(state) * 10 < _nbytes(plain.state_dict())

    restored = _buffer(CompactLazyTensorStorage, 3000, ndim)
    restored.load_state_dict(state)
    assert restored.storage._storage.shape == rb.storage._storage.shape and len(restored) == len(rb) == 120
    torch.testing.assert_close(restored.storage._storage[:written], rb.storage._storage[:written])
    # the same writes and the same sampler RNG give the same contents and samples after the round trip
    for buffer in (rb, restored):
        _fill(buffer, 3)
    assert len(restored) == len(rb) == 210
    rows = 70 if ndim == 2 else 210
    torch.testing.assert_close(restored.storage._storage[:rows], rb.storage._storage[:rows])
    torch.manual_seed(1)
    expected = rb.sample()
    torch.manual_seed(1)
    torch.testing.assert_close(restored.sample(), expected)


def test_full_buffer_saves_everything_and_plain_states_load():
    rb = _buffer(CompactLazyTensorStorage, 60, 2)
    _fill(rb, 5)  # 150 transitions into 60: wrapped around
    state = rb.state_dict()
    assert "_allocated_rows" not in state["_storage"]
    assert state["_storage"]["_storage"]["observation"].shape[:2] == (20, 3)
    # a plain LazyTensorStorage's state (what earlier checkpoints hold) loads unchanged
    plain = _buffer(LazyTensorStorage, 3000, 2)
    _fill(plain, 2)
    restored = _buffer(CompactLazyTensorStorage, 3000, 2)
    restored.load_state_dict(plain.state_dict())
    rows = (
        len(plain) // plain.storage._storage.shape[1]
    )  # the written rows (the rest is uninitialised memory)
    torch.testing.assert_close(restored.storage._storage[:rows], plain.storage._storage[:rows])
    assert rows == 20 and len(restored) == 60


def test_empty_buffer_round_trips():
    rb = _buffer(CompactLazyTensorStorage, 100, 2)
    restored = _buffer(CompactLazyTensorStorage, 100, 2)
    restored.load_state_dict(rb.state_dict())
    assert len(restored) == 0
    _fill(restored, 1)
    assert len(restored) == 30


@pytest.mark.parametrize("num_envs", [1, 4])
def test_recipe_buffers_hold_buffer_size_transitions(num_envs):
    cfg = recipe_config("env=PointMaze", "preset=smoke", f"num_envs={num_envs}", "low.buffer_size=400")
    device = torch.device("cpu")
    agent = build_agent(cfg, device)
    low_rb, _ = build_replay_buffers(cfg, agent, device)
    for k in range(12):  # 12 x 40 steps per env: past capacity for every num_envs
        low_rb.extend(_batch(num_envs, 40, 40 * k))
    assert len(low_rb) == 400
    observation = low_rb.storage._storage["observation"]
    assert observation.shape[:2] == (400 // num_envs, num_envs)
    # the newest batch overwrote the oldest rows, every env keeps its own column
    assert observation[..., 0].eq(torch.arange(num_envs).float()).all()
    assert observation[..., 1].max() == 479


def _disk_bytes(path):
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def test_training_checkpoint_holds_the_written_rows_only(tmp_path):
    """``make_checkpoint`` saves the buffers through their ``state_dict``: on disk, the written rows only (the
    default adapter of a replay buffer, ``dump``, writes the whole allocated capacity)."""
    from torchrl.checkpoint import Checkpoint
    from torchrl.collectors import Collector
    from torchrl_dhrl.envs import make_env

    from torchrl_dhrl.recipe import load_checkpoint, make_checkpoint, save_checkpoint

    rb = _buffer(CompactLazyTensorStorage, 300_000, 2)
    _fill(rb, 4)  # 120 of 300k transitions
    env = make_env("PointMaze", num_envs=1, seed=0, max_episode_steps=4)
    collector = Collector(env, None, frames_per_batch=4, total_frames=-1)
    net = torch.nn.Linear(2, 1)
    registry = make_checkpoint(
        config={},
        agent=net,
        low_updater=net,
        high_updater=net,
        low_rb=rb,
        high_rb=rb,
        train_env=env,
        eval_env=env,
        collector=collector,
        counters={},
        history=[],
    )
    path = save_checkpoint(registry, tmp_path / "checkpoint")
    payload = path / Checkpoint.manifest(path)["components"]["low_rb"]["path"]
    rb.dumps(tmp_path / "dumped")  # what the default adapter of a replay buffer writes
    assert _disk_bytes(payload) * 100 < _disk_bytes(tmp_path / "dumped")
    assert load_checkpoint(path)["low_rb"]["_storage"]["_storage"]["observation"].shape[:2] == (40, 3)
