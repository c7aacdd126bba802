"""Random low-level (SQGC) training batches shared by the update tests."""

from __future__ import annotations

import torch
from tensordict import TensorDict


def sqgc_transitions(
    n: int, obs_dim: int, goal_dim: int, action_dim: int, action_max: float, *, seed: int = 123
) -> TensorDict:
    """``n`` random transitions with both relabelled goals and -1/0 rewards, drawn from a seeded generator."""
    gen = torch.Generator().manual_seed(seed)
    return TensorDict(
        {
            "observation": torch.randn(n, obs_dim, generator=gen),
            "action": (torch.rand(n, action_dim, generator=gen) * 2 - 1) * action_max,
            "goal": torch.randn(n, goal_dim, generator=gen),
            "graph_goal": torch.randn(n, goal_dim, generator=gen),
            ("next", "observation"): torch.randn(n, obs_dim, generator=gen),
            ("next", "reward"): -(torch.rand(n, 1, generator=gen) > 0.3).float(),
            ("next", "graph_reward"): -(torch.rand(n, 1, generator=gen) > 0.5).float(),
        },
        [n],
    )
