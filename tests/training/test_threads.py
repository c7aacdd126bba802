"""Intra-op threads: the CPUs this process may run on, ``OMP_NUM_THREADS``, the one-line report, and the
count that follows other processes' load (:class:`AdaptiveThreads`, against analytic counts and a real busy loop)."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from _batches import sqgc_transitions

from torchrl_dhrl.training import (
    AdaptiveThreads,
    available_cpus,
    cpu_busy_seconds,
    resolve_threads,
    set_threads,
    start_threads,
)


def test_threads(monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert resolve_threads(None) == (
        available_cpus(),
        f"threads=null: the {available_cpus()} CPU core(s) this process may run on",
    )
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert resolve_threads(None)[0] == 1 and resolve_threads(3)[0] == 3
    if hasattr(os, "sched_getaffinity"):
        assert available_cpus() == len(os.sched_getaffinity(0))
    before = torch.get_num_threads()
    try:
        line = set_threads(1)
        assert torch.get_num_threads() == 1 and line.startswith("Threads: 1 intra-op") and "\n" not in line
    finally:
        torch.set_num_threads(before)


def test_start_threads(monkeypatch):
    """``threads=null`` without ``OMP_NUM_THREADS`` adapts to the load; any explicit count is kept."""
    before = torch.get_num_threads()
    try:
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
        line, adaptive = start_threads(None)
        assert isinstance(adaptive, AdaptiveThreads) and adaptive.cores == available_cpus()
        assert line.startswith(f"Threads: {available_cpus()} intra-op") and "re-checked every 2 s" in line
        assert line.endswith(").") and line.count("(") == line.count(")") and "\n" not in line
        assert start_threads(1)[1] is None
        monkeypatch.setenv("OMP_NUM_THREADS", "1")
        line, adaptive = start_threads(None)
        assert adaptive is None and "OMP_NUM_THREADS=1" in line and torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


class FakeLoad:
    """Counters of a machine whose other processes use ``others`` cores while this one uses ``own``."""

    def __init__(self):
        self.now = self.busy = self.own = 0.0
        self.applied = []

    def advance(self, seconds, own, others):
        self.now += seconds
        self.own += own * seconds
        self.busy += (own + others) * seconds

    def threads(self, cores, **kwargs):
        return AdaptiveThreads(
            cores,
            busy_seconds=lambda: self.busy,
            own_seconds=lambda: self.own,
            clock=lambda: self.now,
            set_num_threads=self.applied.append,
            **kwargs,
        )


def test_adaptive_threads_follow_the_load():
    """Over many random windows: the count is ``cores - ceil(others - threshold)`` (at least 1), decided only
    once ``interval_s`` has passed (over the whole window since the last decision), applied only when it changes."""
    rng = np.random.default_rng(0)
    for _ in range(300):
        cores = int(rng.integers(1, 9))
        threshold = float(rng.choice([0.0, 0.25, 0.5]))
        load = FakeLoad()
        adaptive = load.threads(cores, interval_s=2.0, busy_threshold=threshold)
        assert adaptive.adaptive and adaptive.threads == cores and load.applied == [cores]
        expected, window, window_others = cores, 0.0, 0.0
        for _ in range(12):
            seconds = float(rng.choice([0.5, 1.0, 2.0, 3.0]))
            # whole quarters of a core, so that ties with the threshold occur exactly
            others = float(rng.integers(0, 4 * cores + 5)) / 4
            load.advance(seconds, own=float(rng.uniform(0, cores)), others=others)
            window += seconds
            window_others += others * seconds
            count = adaptive.poll()
            if window >= 2.0:
                mean = window_others / window
                taken = max(0, int(np.ceil(round(mean - threshold, 9))))
                expected = min(cores, max(1, cores - taken))
                assert adaptive.others == pytest.approx(mean)
                window = window_others = 0.0
            assert count == adaptive.threads == expected
        assert len(load.applied) == 1 + adaptive.changes  # applied once at the start, then only on a change
        assert all(a != b for a, b in zip(load.applied, load.applied[1:], strict=False))


def test_adaptive_threads_two_cores_one_busy_process():
    """The 2-core case of ``bench_threads.py``: one busy process -> 1 thread; it stops -> 2 again; a process
    using a fifth of a core is not counted; without readable load the count is kept."""
    load = FakeLoad()
    adaptive = load.threads(2)
    load.advance(1.0, own=2.0, others=0.0)
    assert adaptive.poll() == 2 and load.applied == [2]  # under interval_s: no decision yet
    load.advance(1.5, own=1.33, others=0.67)  # three runnable threads on two cores
    assert adaptive.poll() == 1 and adaptive.others == pytest.approx(0.67 * 1.5 / 2.5)
    load.advance(3.0, own=1.0, others=1.0)
    assert adaptive.poll() == 1
    load.advance(3.0, own=1.0, others=0.2)
    assert adaptive.poll() == 2 and load.applied == [2, 1, 2] and adaptive.changes == 2
    unknown = AdaptiveThreads(2, busy_seconds=lambda: None, set_num_threads=lambda n: None)
    assert not unknown.adaptive and unknown.poll() == 2 and "cannot be read" in unknown.describe()
    with pytest.raises(ValueError, match="`busy_threshold`"):
        AdaptiveThreads(2, busy_threshold=1.0)
    with pytest.raises(ValueError, match="`cores`"):
        AdaptiveThreads(0)


def test_cpu_busy_seconds(tmp_path):
    """``/proc/stat`` columns: user nice system idle iowait irq softirq steal guest guest_nice, in clock ticks."""
    stat = tmp_path / "stat"
    stat.write_text(
        "cpu  900 900 900 900 900 900 900 900 0 0\n"
        "cpu0 100 10 20 5000 7 1 2 3 50 0\n"
        "cpu1 200 0 40 4000 0 0 0 0 0 0\n"
        "cpu10 1 1 1 1 1 1 1 1 0 0\n"
        "intr 12345\n"
    )
    tick = os.sysconf("SC_CLK_TCK")
    assert cpu_busy_seconds([0], path=str(stat)) == pytest.approx((100 + 10 + 20 + 1 + 2 + 3) / tick)
    assert cpu_busy_seconds([0], count_niced=False, path=str(stat)) == pytest.approx(126 / tick)
    assert cpu_busy_seconds([0, 1], path=str(stat)) == pytest.approx((136 + 240) / tick)
    assert cpu_busy_seconds([5], path=str(stat)) is None
    assert cpu_busy_seconds([0], path=str(tmp_path / "missing")) is None


@pytest.mark.skipif(
    not (hasattr(os, "sched_setaffinity") and os.path.exists("/proc/stat")), reason="Linux CPU accounting"
)
def test_adaptive_threads_see_a_real_busy_process():
    """A busy loop pinned to one of our CPUs is seen as another process's load, and takes that core."""
    cpu = sorted(os.sched_getaffinity(0))[-1]
    burner = subprocess.Popen(
        [sys.executable, "-c", "while True: pass"], preexec_fn=lambda: os.sched_setaffinity(0, {cpu})
    )
    try:
        time.sleep(0.3)
        applied = []
        adaptive = AdaptiveThreads(2, cpus=[cpu], interval_s=1.0, set_num_threads=applied.append)
        time.sleep(1.2)  # this process sleeps: the CPU's busy time is the burner's (and other tests')
        assert adaptive.poll() == 1, adaptive.others
        assert adaptive.others > 0.4 and applied == [2, 1]
    finally:
        burner.kill()
        burner.wait()


def test_thread_count_does_not_change_updates():
    """The adaptive default may change the count mid-run: SQGC updates at the quick preset's shape (2x256, batch
    256) give the same parameters bit for bit with 1 and 2 threads (docs/training.md states it for this CPU)."""
    from torchrl_dhrl.modules import GoalConditionedCritic, LowLevelActor
    from torchrl_dhrl.objectives import SQGCLoss, make_optimizers

    def train(threads):
        torch.manual_seed(0)
        actor = LowLevelActor(
            6, 2, action_max=1.0, action_dim=2, goal_key="goal", num_cells=(256, 256), goal_indices=(0, 1)
        )

        def critic():
            return GoalConditionedCritic(
                6,
                2,
                action_max=1.0,
                action_dim=2,
                num_cells=(256, 256),
                relative_goal=True,
                goal_indices=(0, 1),
            )

        loss = SQGCLoss(actor, critic(), critic())
        optims = make_optimizers(loss)
        batch = sqgc_transitions(256, 6, 2, 2, 1.0)
        before = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            for i in range(20):
                out = loss.loss_terms(batch, update_actor=i % 2 == 1)
                total = sum(v for k, v in out.items() if k.startswith("loss_"))
                for optim in optims.values():
                    optim.zero_grad(set_to_none=True)
                total.backward()
                for optim in optims.values():
                    optim.step()
        finally:
            torch.set_num_threads(before)
        return [p.detach().clone() for p in loss.parameters()]

    for a, b in zip(train(1), train(2), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
