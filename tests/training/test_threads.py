"""Intra-op threads: the CPUs this process may run on, ``OMP_NUM_THREADS`` and the one-line report."""

from __future__ import annotations

import os

import torch

from torchrl_dhrl.training import available_cpus, resolve_threads, set_threads


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
