"""Nothing is lost on a crash: a process killed with SIGKILL while it saves checkpoints, or while it trains, leaves
a complete checkpoint that the next start finds (recover_checkpoint) and loads: the previous one or the new one,
never none and never a mixture."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time

import pytest
import torch
from _recipe import RECIPES, TIMING_COLUMNS, load_recipe, metrics_rows, recipe_config
from torch import nn
from torchrl.checkpoint import Checkpoint, JSONCheckpointAdapter, StateDictCheckpointAdapter

from torchrl_dhrl.recipe import CHECKPOINT_NAME, recover_checkpoint, save_checkpoint

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")


def _registry(module: nn.Module, counters: dict) -> Checkpoint:
    checkpoint = Checkpoint()
    checkpoint.register("weights", module, adapter=StateDictCheckpointAdapter())
    checkpoint.register("counters", counters, adapter=JSONCheckpointAdapter())
    return checkpoint


def _save_forever(run_dir, start: int) -> None:
    """The child: saves checkpoints k = start, start + 1, ... whose two components both hold k."""
    torch.set_num_threads(1)
    module, counters = nn.Linear(512, 512), {"k": start}
    checkpoint = _registry(module, counters)
    k = start
    while True:
        with torch.no_grad():
            module.weight.fill_(k)
            module.bias.fill_(k)
        counters["k"] = k
        save_checkpoint(checkpoint, run_dir / CHECKPOINT_NAME)
        k += 1


def _load(run_dir) -> int:
    module, counters = nn.Linear(512, 512), {}
    _registry(module, counters).load(run_dir / CHECKPOINT_NAME)
    k = counters["k"]
    assert torch.all(module.weight == k) and torch.all(module.bias == k), "a checkpoint mixing two saves"
    return k


def test_checkpoints_survive_sigkill_during_their_writes_and_swaps(tmp_path):
    rng = random.Random(0)
    last, kills, recovered = 0, 0, 0
    while kills < 200:
        pid = os.fork()
        if pid == 0:  # pragma: no cover - the child never returns
            try:
                _save_forever(tmp_path, last + 1)
            finally:
                os._exit(1)
        time.sleep(rng.uniform(0.0, 0.03))
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        kills += 1
        recovered += recover_checkpoint(tmp_path) is not None
        if not (tmp_path / CHECKPOINT_NAME).exists():
            assert last == 0, f"kill {kills}: no checkpoint, although checkpoint {last} was complete"
            continue  # killed before the first save ended: nothing to lose yet
        k = _load(tmp_path)
        assert k >= last, f"kill {kills}: checkpoint {k} after {last}"
        last = k
        leftovers = [p.name for p in tmp_path.iterdir() if p.name != CHECKPOINT_NAME]
        assert leftovers == [], leftovers
    assert last > 10  # the children did save between the kills


def test_a_swap_interrupted_between_its_renames_is_completed(tmp_path):
    module, counters = nn.Linear(512, 512), {"k": 1}
    checkpoint = _registry(module, counters)
    with torch.no_grad():
        module.weight.fill_(1)
        module.bias.fill_(1)
    save_checkpoint(checkpoint, tmp_path / CHECKPOINT_NAME)
    # the state a kill between the two renames leaves: the old checkpoint renamed away, the new one staged
    os.replace(tmp_path / CHECKPOINT_NAME, tmp_path / f".{CHECKPOINT_NAME}.backup-deadbeef")
    assert "previous" in recover_checkpoint(tmp_path)
    assert _load(tmp_path) == 1 and sorted(p.name for p in tmp_path.iterdir()) == [CHECKPOINT_NAME]


@pytest.mark.parametrize("cut", [0, 1, 0.5, -2])
def test_a_stage_killed_while_writing_its_manifest_is_not_taken_for_a_checkpoint(tmp_path, cut):
    """A kill between the manifest's ``open("w")`` and its last byte leaves it empty or truncated."""
    module, counters = nn.Linear(512, 512), {"k": 1}
    checkpoint = _registry(module, counters)
    with torch.no_grad():
        module.weight.fill_(1)
        module.bias.fill_(1)
    save_checkpoint(checkpoint, tmp_path / "full")
    manifest = (tmp_path / "full" / "manifest.json").read_text()
    length = int(cut * len(manifest)) if isinstance(cut, float) else cut % len(manifest)
    stage = tmp_path / f".{CHECKPOINT_NAME}.stage-cafe"
    os.replace(tmp_path / "full", stage)
    (stage / "manifest.json").write_text(manifest[:length])
    # the first save of a run killed so: no checkpoint yet, and the partial stage is not one
    assert recover_checkpoint(tmp_path) is None and list(tmp_path.iterdir()) == []
    # a later save killed so, after the previous checkpoint was renamed away: the previous one comes back
    save_checkpoint(checkpoint, tmp_path / CHECKPOINT_NAME)
    os.replace(tmp_path / CHECKPOINT_NAME, tmp_path / f".{CHECKPOINT_NAME}.backup-beef")
    stage.mkdir()
    (stage / "manifest.json").write_text(manifest[:length])
    assert "previous" in recover_checkpoint(tmp_path)
    assert _load(tmp_path) == 1 and sorted(p.name for p in tmp_path.iterdir()) == [CHECKPOINT_NAME]


@pytest.mark.slow
@pytest.mark.recipe
def test_a_run_killed_while_training_resumes_to_the_straight_runs_metrics(tmp_path):
    """The recipe killed (SIGKILL) at random moments and restarted with resume=auto ends with the metrics of a
    run that was never killed."""
    overrides = [
        "env=PointMaze", "preset=smoke", "total_steps=720", "device=cpu", "logger.backend=none",
        "plots.every_epochs=0", "threads=1",
    ]
    straight = tmp_path / "straight"
    load_recipe().train(recipe_config(*overrides), run_dir=straight)
    killed = tmp_path / "killed"
    command = [sys.executable, str(RECIPES / "dhrl_antmaze.py"), *overrides, f"run_dir={killed}", "resume=auto"]
    environment = {**os.environ, "OMP_NUM_THREADS": "1"}
    rng = random.Random(1)
    manifest = killed / CHECKPOINT_NAME / "manifest.json"
    kills = 0
    for _ in range(3):
        process = subprocess.Popen(command, env=environment, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        before = manifest.stat().st_mtime_ns if manifest.exists() else None
        while process.poll() is None and (not manifest.exists() or manifest.stat().st_mtime_ns == before):
            time.sleep(0.05)  # until this process has saved a checkpoint of its own (it is training)
        time.sleep(rng.uniform(0.0, 1.5))  # then at a random moment: acting, updating or saving the next one
        if process.poll() is None:
            process.send_signal(signal.SIGKILL)
            kills += 1
        process.wait()
    assert kills >= 2  # the run was killed while it trained, not after it ended
    done = subprocess.run(command, env=environment, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert metrics_rows(killed, TIMING_COLUMNS) == metrics_rows(straight, TIMING_COLUMNS)
    assert json.loads((killed / CHECKPOINT_NAME / "manifest.json").read_text())
