"""Shared pytest configuration."""

import os

import torch

# Under pytest-xdist every worker is a process of its own: one intra-op thread each keeps the
# 2-core CI machine from being oversubscribed.
if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)
