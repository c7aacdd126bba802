"""An oracle graph distance for ablations: straight-line steps, blocked by obstacles."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

__all__ = ["LineOfSightDistance"]


class LineOfSightDistance:
    """``d(s -> g) = ||g - ag(s)|| / speed`` when the segment ``ag(s) -> g`` is free, else ``blocked``.

    The oracle counterpart of :class:`~torchrl_dhrl.modules.GoalDistance` (same contract,
    ``(states[..., obs_dim], goals[..., goal_dim]) -> steps[...]`` with broadcasting), for the
    "oracle graph distance" ablation and for tests. A plain Euclidean distance would let graph
    edges cross the mazes' walls (a 30-step cutoff spans the point agent's 4-unit wall), so
    segments that intersect an obstacle box (inflated by ``margin``) cost ``blocked`` instead.
    Intersection uses the slab test, vectorised over pairs and boxes.

    Args:
        speed (float): goal units covered per env step.

    Keyword Args:
        boxes (Tensor or sequence, optional): ``[W, 2, goal_dim]`` axis-aligned obstacle boxes
            (``boxes[:, 0]`` lower corners, ``boxes[:, 1]`` upper corners). Defaults to none.
        margin (float): inflation of every box (e.g. the agent's radius). Defaults to ``0.0``.
        goal_indices (sequence of int): where the achieved goal sits in the state. Defaults to
            ``(0, 1)``.
        blocked (float): the distance of a blocked pair. Defaults to ``1e4``.
        chunk_size (int): pairs per evaluation chunk. Defaults to ``65536``.

    Examples:
        >>> import torch
        >>> wall = torch.tensor([[[1.0, -5.0], [2.0, 5.0]]])  # a wall between x=1 and x=2
        >>> d = LineOfSightDistance(0.5, boxes=wall)
        >>> d(torch.zeros(2, 2), torch.tensor([[0.0, 3.0], [3.0, 0.0]])).tolist()
        [6.0, 10000.0]
    """

    def __init__(
        self,
        speed: float,
        *,
        boxes: Tensor | Sequence | None = None,
        margin: float = 0.0,
        goal_indices: Sequence[int] = (0, 1),
        blocked: float = 1e4,
        chunk_size: int = 65536,
    ) -> None:
        if not speed > 0:
            raise ValueError(f"`speed` must be > 0, got {speed}.")
        if margin < 0:
            raise ValueError(f"`margin` must be >= 0, got {margin}.")
        self.speed = float(speed)
        self.goal_indices = list(goal_indices)
        dim = len(self.goal_indices)
        boxes = torch.zeros(0, 2, dim) if boxes is None else torch.as_tensor(boxes, dtype=torch.float32)
        if boxes.ndim != 3 or boxes.shape[1:] != (2, dim):
            raise ValueError(f"`boxes` must be [W, 2, {dim}], got {tuple(boxes.shape)}.")
        self.boxes = torch.stack([boxes[:, 0] - margin, boxes[:, 1] + margin], 1)
        self.blocked = float(blocked)
        self.chunk_size = int(chunk_size)

    def crosses_obstacle(self, start: Tensor, end: Tensor) -> Tensor:
        """``[n]`` bool: does the segment ``start -> end`` (``[n, dim]``) cross any (inflated) box?"""
        boxes = self.boxes.to(start.device, start.dtype)
        if boxes.shape[0] == 0:
            return torch.zeros(start.shape[0], dtype=torch.bool, device=start.device)
        direction = (end - start).unsqueeze(1)  # [n, 1, dim]
        origin = start.unsqueeze(1)
        parallel = direction.abs() < 1e-12
        safe = torch.where(parallel, torch.ones_like(direction), direction)
        t0 = (boxes[:, 0] - origin) / safe  # [n, W, dim]
        t1 = (boxes[:, 1] - origin) / safe
        t_near = torch.minimum(t0, t1)
        t_far = torch.maximum(t0, t1)
        inside = (origin >= boxes[:, 0]) & (origin <= boxes[:, 1])  # for axes the segment is parallel to
        t_near = torch.where(parallel, torch.where(inside, -torch.inf, torch.inf), t_near)
        t_far = torch.where(parallel, torch.where(inside, torch.inf, -torch.inf), t_far)
        enter = t_near.amax(-1).clamp_min(0.0)
        leave = t_far.amin(-1).clamp_max(1.0)
        return (enter <= leave).any(-1)

    def __call__(self, states: Tensor, goals: Tensor) -> Tensor:
        achieved = states[..., self.goal_indices]
        shape = torch.broadcast_shapes(achieved.shape[:-1], goals.shape[:-1])
        dim = goals.shape[-1]
        start = achieved.expand(*shape, dim).reshape(-1, dim)
        end = goals.to(achieved.dtype).expand(*shape, dim).reshape(-1, dim)
        out = torch.empty(start.shape[0], dtype=achieved.dtype, device=achieved.device)
        for lo in range(0, start.shape[0], self.chunk_size):
            s, e = start[lo : lo + self.chunk_size], end[lo : lo + self.chunk_size]
            steps = (e - s).norm(dim=-1) / self.speed
            out[lo : lo + self.chunk_size] = torch.where(self.crosses_obstacle(s, e), self.blocked, steps)
        return out.reshape(shape)
