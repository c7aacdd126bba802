"""Goal-conditioned rewards recomputed from goals at relabelling time."""

from __future__ import annotations

import torch

__all__ = ["SparseGoalReward"]


class SparseGoalReward:
    """Sparse goal-reaching reward: ``0`` within ``distance_threshold`` of the goal, ``-1`` otherwise.

    This is the reward both DHRL levels train on (the learner recomputes it from goals; the environment's
    own reward is never used): ``0`` when ``||achieved_goal - goal||_2 <= distance_threshold`` and ``-1``
    otherwise, with a threshold of ``0.5`` for the mazes.

    Args:
        distance_threshold (float, optional): Euclidean distance at or below which the goal counts as
            reached. Must be ``> 0``. Defaults to ``0.5``.

    Keyword Args:
        success_reward (float, optional): reward when the goal is reached. Defaults to ``0.0``.
        failure_reward (float, optional): reward otherwise. Defaults to ``-1.0``.

    Calling the object with ``(achieved_goal, goal)``, two tensors of shape ``[..., goal_dim]`` that
    broadcast together, returns a tensor of shape ``[..., 1]`` (TorchRL's reward layout) with the dtype of
    ``achieved_goal`` (float32 if it is not floating point) on its device.

    Examples:
        >>> import torch
        >>> reward_fn = SparseGoalReward(distance_threshold=0.5)
        >>> achieved = torch.tensor([[0.0, 0.0], [3.0, 4.0]])
        >>> goal = torch.tensor([[0.3, 0.4], [0.0, 0.0]])
        >>> reward_fn(achieved, goal)
        tensor([[ 0.],
                [-1.]])
    """

    def __init__(
        self,
        distance_threshold: float = 0.5,
        *,
        success_reward: float = 0.0,
        failure_reward: float = -1.0,
    ) -> None:
        if not distance_threshold > 0:
            raise ValueError(f"distance_threshold must be > 0, got {distance_threshold}.")
        self.distance_threshold = float(distance_threshold)
        self.success_reward = float(success_reward)
        self.failure_reward = float(failure_reward)

    def __call__(self, achieved_goal: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        if not isinstance(achieved_goal, torch.Tensor) or not isinstance(goal, torch.Tensor):
            raise TypeError(
                "SparseGoalReward expects two tensors (achieved_goal, goal), got "
                f"{type(achieved_goal).__name__} and {type(goal).__name__}."
            )
        if achieved_goal.ndim == 0 or goal.ndim == 0 or achieved_goal.shape[-1] != goal.shape[-1]:
            raise ValueError(
                "achieved_goal and goal must have the same trailing goal dimension, got shapes "
                f"{tuple(achieved_goal.shape)} and {tuple(goal.shape)}."
            )
        dtype = achieved_goal.dtype if achieved_goal.is_floating_point() else torch.float32
        distance = torch.linalg.vector_norm(achieved_goal.to(dtype) - goal.to(dtype), dim=-1, keepdim=True)
        reached = distance <= self.distance_threshold
        return torch.where(
            reached,
            torch.full((), self.success_reward, dtype=dtype, device=distance.device),
            torch.full((), self.failure_reward, dtype=dtype, device=distance.device),
        )

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(distance_threshold={self.distance_threshold}, "
            f"success_reward={self.success_reward}, failure_reward={self.failure_reward})"
        )
