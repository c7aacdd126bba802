"""Shared pytest configuration."""

import os

import torch

# Under pytest-xdist every worker is a process of its own: one intra-op thread each keeps the
# 2-core CI machine from being oversubscribed, and so does one thread for the processes the tests start
# (the recipe's command line, benchmarks): two 2-thread processes on 2 cores run many times slower.
if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
