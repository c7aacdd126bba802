"""Where does the high level's critic want the subgoal? Its Q over a grid of subgoals, next to the actor's choice.

A high level can fail in two ways that its success rate does not separate: its critic values the wrong subgoals
(e.g. points inside a wall, towards the goal as the crow flies), or its actor does not follow the critic (it
proposes a subgoal the critic itself values less than others). :func:`subgoal_landscape` evaluates the critic at
one state and goal for every subgoal of a grid over a 2-D subgoal box and records the actor's subgoal and value,
so both can be read off (``recipes/diagnose_high_level.py`` adds the maze's walls and a picture).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torch import Tensor

__all__ = ["SubgoalLandscape", "landscape_summary", "subgoal_box", "subgoal_landscape", "subgoal_values"]


@torch.no_grad()
def subgoal_values(
    high_loss, observation: Tensor, goal: Tensor, subgoals: Tensor, chunk_size: int = 4096
) -> Tensor:
    """Q of every member of ``high_loss``'s critic at ``(observation, goal)`` for each subgoal: ``[E, N]``.

    Args:
        high_loss (HighLevelLoss): the high level's loss (its critic's current parameters are used).
        observation (Tensor): ``[obs_dim]`` one state.
        goal (Tensor): ``[goal_dim]`` the final goal.
        subgoals (Tensor): ``[N, subgoal_dim]`` candidate subgoals (goal space, not scaled).
        chunk_size (int): subgoals per critic call. Defaults to ``4096``.

    Examples:
        >>> import torch
        >>> from torchrl_dhrl.modules import GoalConditionedCritic, HighLevelActor
        >>> from torchrl_dhrl.objectives import HighLevelLoss
        >>> actor = HighLevelActor(6, 2, [-2.0, -2.0], [10.0, 10.0], num_cells=(8,))
        >>> critic = GoalConditionedCritic(6, 2, action_low=[-2.0, -2.0], action_high=[10.0, 10.0],
        ...     goal_key="desired_goal", action_key="subgoal", relative_goal=False, num_cells=(8,))
        >>> loss = HighLevelLoss(actor, critic)
        >>> subgoal_values(loss, torch.zeros(6), torch.ones(2), torch.rand(5, 2)).shape
        torch.Size([2, 5])
    """
    if observation.ndim != 1 or goal.ndim != 1 or subgoals.ndim != 2:
        raise ValueError(
            "`observation` [obs_dim], `goal` [goal_dim] and `subgoals` [N, subgoal_dim] expected, got shapes "
            f"{tuple(observation.shape)}, {tuple(goal.shape)} and {tuple(subgoals.shape)}."
        )
    params = high_loss.critic_network_params
    device = next(iter(params.values(True, True))).device
    outs = []
    for start in range(0, subgoals.shape[0], chunk_size):
        block = subgoals[start : start + chunk_size].to(device)
        num = block.shape[0]
        outs.append(
            high_loss._critic_q(
                "critic_network",
                params,
                observation.to(device).expand(num, -1),
                goal.to(device).expand(num, -1),
                block,
            )
        )
    return torch.cat(outs, dim=-1)


class SubgoalLandscape(NamedTuple):
    """The high-level critic's Q over a grid of 2-D subgoals at one state and goal (:func:`subgoal_landscape`)."""

    xs: Tensor
    """``[W]`` the grid's x coordinates."""
    ys: Tensor
    """``[H]`` the grid's y coordinates."""
    q: Tensor
    """``[H, W]`` Q of the critic's first member (the one the actor maximises) at ``(xs[j], ys[i])``."""
    q_min: Tensor
    """``[H, W]`` the minimum over the critic's members (the clipped double-Q view)."""
    actor_subgoal: Tensor
    """``[2]`` the deterministic actor's subgoal."""
    actor_q: Tensor
    """0-d: the first member's Q at the actor's subgoal."""

    def points(self) -> Tensor:
        """``[H, W, 2]`` the grid's subgoals."""
        grid_y, grid_x = torch.meshgrid(self.ys, self.xs, indexing="ij")
        return torch.stack([grid_x, grid_y], -1)

    def best(self, mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """The grid subgoal of highest ``q`` (among ``mask``'s ``[H, W]`` cells, if given) and its value."""
        q = self.q if mask is None else self.q.masked_fill(~mask, -torch.inf)
        index = int(q.reshape(-1).argmax())
        return self.points().reshape(-1, 2)[index], q.reshape(-1)[index]


@torch.no_grad()
def subgoal_landscape(
    high_loss,
    high_actor: TensorDictModuleBase,
    observation: Tensor,
    goal: Tensor,
    low,
    high,
    resolution: float = 0.5,
) -> SubgoalLandscape:
    """The high-level critic's Q at ``(observation, goal)`` over a grid of the 2-D subgoal box ``[low, high]``.

    Args:
        high_loss (HighLevelLoss): the high level's loss (critic parameters).
        high_actor (TensorDictModuleBase): the bare deterministic high-level actor (e.g.
            ``agent.high_policy.actor``; no exploration noise, no ``c_h`` cadence).
        observation (Tensor): ``[obs_dim]`` one state, e.g. a test episode's start.
        goal (Tensor): ``[2]`` the final goal.
        low, high (sequence of 2 floats): the subgoal box.
        resolution (float): grid spacing (goal units). Defaults to ``0.5``.

    Raises:
        ValueError: a subgoal box that is not 2-D, or a resolution that is not positive.

    Examples:
        >>> import torch
        >>> from torchrl_dhrl.modules import GoalConditionedCritic, HighLevelActor
        >>> from torchrl_dhrl.objectives import HighLevelLoss
        >>> actor = HighLevelActor(6, 2, [-2.0, -2.0], [10.0, 10.0], num_cells=(8,))
        >>> critic = GoalConditionedCritic(6, 2, action_low=[-2.0, -2.0], action_high=[10.0, 10.0],
        ...     goal_key="desired_goal", action_key="subgoal", relative_goal=False, num_cells=(8,))
        >>> land = subgoal_landscape(HighLevelLoss(actor, critic), actor, torch.zeros(6), torch.ones(2),
        ...                          [-2.0, -2.0], [10.0, 10.0], resolution=1.0)
        >>> land.q.shape, land.actor_subgoal.shape
        (torch.Size([13, 13]), torch.Size([2]))
    """
    low, high = torch.as_tensor(low, dtype=torch.float32), torch.as_tensor(high, dtype=torch.float32)
    if low.shape != (2,) or high.shape != (2,):
        raise ValueError(
            f"subgoal_landscape needs a 2-D subgoal box, got low {tuple(low.tolist())} and high "
            f"{tuple(high.tolist())}."
        )
    if not resolution > 0:
        raise ValueError(f"`resolution` must be > 0, got {resolution!r}.")
    xs = torch.arange(float(low[0]), float(high[0]) + 1e-6, resolution)
    ys = torch.arange(float(low[1]), float(high[1]) + 1e-6, resolution)
    grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
    points = torch.stack([grid_x, grid_y], -1).reshape(-1, 2)
    values = subgoal_values(high_loss, observation, goal, points).float().cpu()  # [E, H*W]
    device = observation.device
    td = TensorDict(
        {
            high_actor.in_keys[0]: observation.reshape(1, -1),
            high_actor.in_keys[1]: goal.reshape(1, -1).to(device),
        },
        batch_size=[1],
    )
    actor_subgoal = high_actor(td)[high_actor.out_keys[0]][0].float()
    actor_q = subgoal_values(high_loss, observation, goal, actor_subgoal.reshape(1, -1))[0, 0].float().cpu()
    shape = (ys.numel(), xs.numel())
    return SubgoalLandscape(
        xs, ys, values[0].reshape(shape), values.min(0).values.reshape(shape), actor_subgoal.cpu(), actor_q
    )


def subgoal_box(high_loss) -> tuple[list[float], list[float]]:
    """The high level's subgoal box ``(low, high)``, read from its loss's action scaling."""
    loc, scale = high_loss.action_loc.float().cpu(), high_loss.action_scale.float().cpu()
    return (loc - scale).reshape(-1).tolist(), (loc + scale).reshape(-1).tolist()


def landscape_summary(land: SubgoalLandscape, in_walls: Tensor, top: float = 0.05) -> dict:
    """What a landscape says about the high level, given which grid subgoals lie in walls (``[H, W]`` bool).

    Returns a dict of floats: ``q_range`` (max - min of Q over the grid: how much the critic tells subgoals
    apart), ``best_in_wall`` (``1.0`` when the grid subgoal of highest Q is inside a wall), ``top_in_walls``
    (the share of the ``top`` best-valued grid subgoals inside walls), ``walls_share`` (the share of the grid
    inside walls, its chance level) and ``actor_q_gap`` (Q of the best free grid subgoal minus Q of the actor's
    subgoal: above zero, the actor does not reach its critic's best; NaN when no grid subgoal is free).

    Examples:
        >>> import torch
        >>> xs, ys = torch.arange(3.0), torch.arange(2.0)
        >>> q = torch.tensor([[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]])
        >>> land = SubgoalLandscape(xs, ys, q, q, torch.zeros(2), torch.tensor(1.0))
        >>> walls = torch.tensor([[False, False, False], [False, False, True]])
        >>> summary = landscape_summary(land, walls, top=0.5)
        >>> summary["q_range"], summary["best_in_wall"], round(summary["top_in_walls"], 3), summary["actor_q_gap"]
        (5.0, 1.0, 0.333, 3.0)
    """
    if in_walls.shape != land.q.shape:
        raise ValueError(
            f"`in_walls` must have the grid's shape {tuple(land.q.shape)}, got {tuple(in_walls.shape)}."
        )
    if not 0 < top <= 1:
        raise ValueError(f"`top` must be in (0, 1], got {top!r}.")
    q, walls = land.q.reshape(-1), in_walls.reshape(-1).bool()
    count = max(1, int(round(top * q.numel())))
    free = ~walls
    best_free = q[free].max() if bool(free.any()) else torch.tensor(float("nan"))
    return {
        "q_range": float(q.max() - q.min()),
        "best_in_wall": float(walls[q.argmax()]),
        "top_in_walls": float(walls[q.topk(count).indices].float().mean()),
        "walls_share": float(walls.float().mean()),
        "actor_q_gap": float(best_free - land.actor_q),
    }
