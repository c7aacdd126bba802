"""Yardsticks for one DHRL low-level update: a plain-PyTorch eager SQGC update, and its matrix products alone.

* :class:`PlainSQGCUpdate` is the same update as ``LossUpdater(SQGCLoss(...), actor_after_critic_step=True)``
  with the recipe's defaults, written the way one would write it by hand for speed in plain PyTorch:
  ``nn.Sequential`` MLPs of ``nn.Linear`` (one per critic member: policy twin + graph twin), no TensorDict,
  no ``to_module``; target actions with Gaussian noise for both goals in one batch, the clamped TD3
  targets, the sum of the members' MSE, one backward and fused Adam for the four critics; on every second
  update the actor loss on the updated critic (first policy member) with its own backward and fused Adam;
  Polyak averaging (``torch._foreach_lerp_``) every 10 updates. Optional bfloat16 autocast of the forward
  pass (hidden layers), as ``update_dtype=bfloat16``.
* :func:`matmul_floor` records every matrix product (``mm``, ``addmm``, ``bmm``, ``baddbmm``) that a
  function dispatches, forward and backward, with its shapes and dtype, and returns a callable that runs
  exactly those products on fresh tensors: the floor that any implementation of that update on this
  machine can only approach (elementwise work, Adam and Python add to it).

Used by ``bench_losses.py`` (columns ``plain`` and ``matmul floor``) and ``profile_train.py``.
"""

from __future__ import annotations

import copy

import torch
from torch import nn
from torch.utils._python_dispatch import TorchDispatchMode

_MATMULS = {
    torch.ops.aten.mm.default,
    torch.ops.aten.addmm.default,
    torch.ops.aten.bmm.default,
    torch.ops.aten.baddbmm.default,
}


def _mlp(widths: list[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (w_in, w_out) in enumerate(zip(widths[:-1], widths[1:], strict=True)):
        layers.append(nn.Linear(w_in, w_out))
        if i < len(widths) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class PlainSQGCUpdate:
    """One SQGC update in plain PyTorch (see the module docstring); call it with a batch dict of tensors.

    Args:
        obs_dim, goal_dim, action_dim (int): the env's sizes.
        num_cells (sequence of int): hidden widths of the actor and every critic.
        action_max (float): the action box half-width.

    Keyword Args:
        goal_indices (tuple): where the achieved goal sits in the observation (the actor's relative goal).
        autocast_dtype (torch.dtype, optional): ``torch.bfloat16`` for mixed-precision forward passes.
        device (torch.device): where everything lives.
    """

    def __init__(
        self,
        obs_dim: int,
        goal_dim: int,
        action_dim: int,
        num_cells,
        action_max: float,
        *,
        goal_indices=(0, 1),
        autocast_dtype: torch.dtype | None = None,
        device: torch.device | str = "cpu",
    ) -> None:
        cells = list(num_cells)
        self.device = torch.device(device)
        self.actor = _mlp([obs_dim + goal_dim, *cells, action_dim]).to(self.device)
        self.critics = nn.ModuleList(_mlp([obs_dim + goal_dim + action_dim, *cells, 1]) for _ in range(4)).to(
            self.device
        )  # policy twin (0, 1), graph twin (2, 3)
        self.target_actor = copy.deepcopy(self.actor).requires_grad_(False)
        self.target_critics = copy.deepcopy(self.critics).requires_grad_(False)
        self.action_max = float(action_max)
        self.goal_indices = list(goal_indices)
        self.gamma, self.clip_return, self.noise, self.action_l2 = 0.99, 80.0, 0.05, 0.01
        self.autocast_dtype = autocast_dtype
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=1e-4, fused=True)
        self.critic_opt = torch.optim.Adam(self.critics.parameters(), lr=1e-3, fused=True)
        self.online = list(self.actor.parameters()) + list(self.critics.parameters())
        self.targets = list(self.target_actor.parameters()) + list(self.target_critics.parameters())
        self.count = 0

    def _autocast(self):
        return torch.autocast(
            self.device.type,
            dtype=self.autocast_dtype or torch.bfloat16,
            enabled=self.autocast_dtype is not None,
        )

    def _pi(self, actor: nn.Module, obs: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        relative = goal - obs[:, self.goal_indices]
        return self.action_max * torch.tanh(actor(torch.cat([obs, relative], -1)).float())

    def _q(self, critic: nn.Module, obs, goal, action) -> torch.Tensor:
        return critic(torch.cat([obs, goal, action / self.action_max], -1)).float().squeeze(-1)

    def __call__(self, batch: dict[str, torch.Tensor]) -> None:
        obs, action, next_obs = batch["observation"], batch["action"], batch["next_observation"]
        goals = (batch["goal"], batch["graph_goal"])
        rewards = (batch["reward"], batch["graph_reward"])
        n = obs.shape[0]
        self.count += 1
        with self._autocast():
            with torch.no_grad():
                both_goals = torch.cat(goals, 0)
                next2 = next_obs.repeat(2, 1)
                next_action = self._pi(self.target_actor, next2, both_goals)
                next_action = next_action + torch.randn_like(next_action) * self.noise
                targets = []
                for pair, (goal, reward, nxt) in enumerate(
                    zip(goals, rewards, next_action.split(n), strict=True)
                ):
                    q1 = self._q(self.target_critics[2 * pair], next_obs, goal, nxt)
                    q2 = self._q(self.target_critics[2 * pair + 1], next_obs, goal, nxt)
                    low = -self.clip_return if pair == 0 else None
                    targets.append((reward + self.gamma * torch.minimum(q1, q2)).clamp(min=low, max=0.0))
            loss = 0.0
            for pair, (goal, target) in enumerate(zip(goals, targets, strict=True)):
                for member in (2 * pair, 2 * pair + 1):
                    loss = loss + (self._q(self.critics[member], obs, goal, action) - target).pow(2).mean()
        self.critic_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.critic_opt.step()
        if self.count % 2 == 0:  # TD3's delayed actor, on the updated critic
            with self._autocast():
                pi = self._pi(self.actor, obs, goals[0])
                q = self._q(self.critics[0], obs, goals[0], pi)
                actor_loss = -q.mean() + self.action_l2 * (pi / self.action_max).pow(2).mean()
            self.actor_opt.zero_grad(set_to_none=True)
            actor_loss.backward()
            self.actor_opt.step()
            for p in self.critics.parameters():  # the actor step leaves no gradient on the critics behind
                p.grad = None
        if self.count % 10 == 0:
            with torch.no_grad():
                torch._foreach_lerp_(self.targets, self.online, 1 - 0.995)


def plain_batch(batch) -> dict[str, torch.Tensor]:
    """The tensors :class:`PlainSQGCUpdate` reads, from an ``SQGCLoss`` input TensorDict."""
    return {
        "observation": batch["observation"],
        "action": batch["action"],
        "goal": batch["goal"],
        "graph_goal": batch["graph_goal"],
        "next_observation": batch["next", "observation"],
        "reward": batch["next", "reward"].reshape(-1),
        "graph_reward": batch["next", "graph_reward"].reshape(-1),
    }


class _RecordMatmuls(TorchDispatchMode):
    def __init__(self) -> None:
        super().__init__()
        self.calls: list[tuple] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if func in _MATMULS:
            self.calls.append(
                (func, [(a.shape, a.dtype, a.device) if isinstance(a, torch.Tensor) else a for a in args])
            )
        return func(*args, **(kwargs or {}))


def record_matmuls(fn, *args, **kwargs) -> list[tuple]:
    """The matrix products ``fn(*args, **kwargs)`` dispatches (forward and backward): ``[(op, args)]``."""
    with _RecordMatmuls() as mode:
        fn(*args, **kwargs)
    return mode.calls


def matmul_floor(calls: list[tuple]):
    """A callable that runs exactly the recorded matrix products on fresh random tensors (same shapes)."""
    prepared = []
    for func, spec in calls:
        args = [
            torch.randn(s[0], dtype=s[1], device=s[2]) if isinstance(s, tuple) and len(s) == 3 else s
            for s in spec
        ]
        prepared.append((func, args))

    def run() -> None:
        for func, args in prepared:
            func(*args)

    return run


def count_flops(calls: list[tuple]) -> float:
    """Floating-point operations of the recorded products (2 per multiply-add)."""
    total = 0.0
    for _, spec in calls:
        shapes = [s[0] for s in spec if isinstance(s, tuple) and len(s) == 3]
        a, b = shapes[-2], shapes[-1]  # (addmm/baddbmm: bias first)
        batch = a[0] if len(a) == 3 else 1
        total += 2.0 * batch * a[-2] * a[-1] * b[-1]
    return total
