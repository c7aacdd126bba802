"""Shared pytest configuration."""

import os
import sys
from pathlib import Path

import torch

# The test modules import their helpers (``_recipe``, ``_batches``) by name, from this folder, wherever they live:
# the folders below it mirror the package and are packages of ``tests`` (whose parent pytest puts on sys.path), so
# this folder goes last on sys.path, where its subpackages (``tests.data``, ...) shadow no installed module.
HERE = str(Path(__file__).resolve().parent)
if HERE not in sys.path:
    sys.path.append(HERE)

# Under pytest-xdist every worker is a process of its own: one intra-op thread each keeps the
# 2-core CI machine from being oversubscribed, and so does one thread for the processes the tests start
# (the recipe's command line, benchmarks): two 2-thread processes on 2 cores run many times slower.
if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
