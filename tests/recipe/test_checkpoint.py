"""The run's checkpoint (one ``torchrl.checkpoint`` registry): round trip, atomic saves, RNG states, errors."""

from __future__ import annotations

import random

import numpy as np
import pytest
import torch
from torchrl_dhrl.envs import make_env

from torchrl_dhrl.recipe import (
    CHECKPOINT_COMPONENTS,
    CheckpointError,
    load_checkpoint,
    make_checkpoint,
    restore_checkpoint,
    save_checkpoint,
)


def _registry(weight: float, counters: dict, history: list):
    """A checkpoint registry of small stand-ins: a linear layer for the state-dict components."""
    from torchrl.collectors import Collector

    net = torch.nn.Linear(3, 1)
    torch.nn.init.constant_(net.weight, weight)
    env = make_env("PointMaze", num_envs=1, seed=0, max_episode_steps=4)
    collector = Collector(env, None, frames_per_batch=4, total_frames=-1)
    parts = dict.fromkeys(("agent", "low_updater", "high_updater", "low_rb", "high_rb"), net)
    registry = make_checkpoint(
        config={"seed": 0},
        train_env=env,
        eval_env=env,
        collector=collector,
        counters=counters,
        history=history,
        **parts,
    )
    return registry, net


def test_checkpoint_round_trip_and_atomicity(tmp_path, monkeypatch):
    path = tmp_path / "run" / "checkpoint"
    counters, history = {"step": 1}, [{"loss": 0.5}]
    registry, net = _registry(1.0, counters, history)
    save_checkpoint(registry, path)
    loaded = load_checkpoint(path)
    assert sorted(loaded) == sorted(CHECKPOINT_COMPONENTS)
    assert loaded["counters"]["step"] == 1 and torch.equal(loaded["agent"]["weight"], torch.ones(1, 3))

    from torchrl.checkpoint import StateDictCheckpointAdapter

    real_save = StateDictCheckpointAdapter.save
    calls = {"n": 0}

    def crash(self, component, path, **kwargs):  # writes some components, then dies
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real_save(self, component, path, **kwargs)

    counters["step"] = 2
    torch.nn.init.constant_(net.weight, 2.0)
    monkeypatch.setattr(StateDictCheckpointAdapter, "save", crash)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(registry, path)
    monkeypatch.undo()
    loaded = load_checkpoint(path)  # the previous checkpoint survives, whole
    assert loaded["counters"]["step"] == 1 and torch.equal(loaded["agent"]["weight"], torch.ones(1, 3))
    assert [p.name for p in path.parent.iterdir()] == ["checkpoint"]  # no staging directory left
    restore_checkpoint(registry, path)
    assert counters == {"step": 1} and torch.equal(net.weight, torch.ones(1, 3))
    with pytest.raises(FileNotFoundError, match="No checkpoint"):
        load_checkpoint(tmp_path / "missing.pt")


def test_rng_state_round_trip(tmp_path):
    registry, _ = _registry(1.0, {}, [])
    path = save_checkpoint(registry, tmp_path / "checkpoint")
    first = (random.random(), np.random.rand(), torch.rand(3))
    restore_checkpoint(registry, path)
    second = (random.random(), np.random.rand(), torch.rand(3))
    assert first[0] == second[0] and first[1] == second[1] and torch.equal(first[2], second[2])


def test_load_checkpoint_errors(tmp_path):
    path = tmp_path / "x.pt"
    path.write_bytes(b"\x00" * 10)
    with pytest.raises(CheckpointError, match="x.pt.* is not a readable checkpoint"):
        load_checkpoint(path)
    torch.save({"agent": 1}, path)
    assert load_checkpoint(path, required_keys=("agent",)) == {"agent": 1}
    with pytest.raises(CheckpointError, match="lacks 'counters'"):
        load_checkpoint(path, required_keys=("agent", "counters"))
    with pytest.raises(FileNotFoundError):
        load_checkpoint(tmp_path / "nothing.pt")
