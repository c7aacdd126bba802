"""How far a maze run's training episodes get, goal by goal: is exploration what holds it back?

The frontier of a maze run moves only when training episodes reach beyond it. :func:`episode_progress`
measures, for the episodes stored in a high-level replay buffer, how far along the maze each episode's goal
is and how far the agent got, both as obstacle-free path lengths from the start (``MazeGeometry.path_length``),
next to the furthest point the stored data has ever reached. ``recipes/diagnose_exploration.py`` prints it for
a saved run.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor

from .maze_diagnostics import MazeGeometry

__all__ = ["EpisodeProgress", "episode_progress"]


class EpisodeProgress(NamedTuple):
    """Per-episode progress along a maze (path lengths from the start, goal units), as :func:`episode_progress` returns it.

    Attributes:
        episode_ids (Tensor): ``[E]`` the episodes, oldest first.
        goals (Tensor): ``[E, 2]`` each episode's goal.
        goal_progress (Tensor): ``[E]`` the goal's path length from the start.
        max_progress (Tensor): ``[E]`` the furthest progress the episode reached.
        end_progress (Tensor): ``[E]`` the progress at the episode's end.
        explored (float): the furthest progress of any achieved goal in the data (the frontier).
    """

    episode_ids: Tensor
    goals: Tensor
    goal_progress: Tensor
    max_progress: Tensor
    end_progress: Tensor
    explored: float


@torch.no_grad()
def episode_progress(
    geometry: MazeGeometry,
    transitions: TensorDictBase,
    start: Tensor,
    *,
    last: int | None = None,
    episode_key: NestedKey = "episode_id",
    achieved_goal_key: NestedKey = ("next", "achieved_goal"),
    goal_key: NestedKey = "desired_goal",
) -> EpisodeProgress:
    """How far each stored episode got along the maze, and how far its goal was.

    ``transitions`` are records tagged with their episode (e.g. the storage of the recipe's high-level buffer,
    one record per ``c_h``-step segment, in the order they were written): the progress of a record is the
    obstacle-free path length from ``start`` to its ``achieved_goal_key``; an episode's maximum and last
    progress come from its records, its goal from ``goal_key``. ``explored`` is the maximum over every record.

    Args:
        geometry (MazeGeometry): the maze's true geometry.
        transitions (TensorDictBase): ``[N]`` records with ``episode_key``, ``achieved_goal_key`` and
            ``goal_key``.
        start (Tensor): ``[2]`` the start position.

    Keyword Args:
        last (int, optional): keep the ``last`` most recent episodes (largest ids). Defaults to all.
        episode_key, achieved_goal_key, goal_key (NestedKey): where the records hold them.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
        >>> records = TensorDict({  # two episodes along the first corridor, two segments each
        ...     "episode_id": torch.tensor([[0], [0], [1], [1]]),
        ...     ("next", "achieved_goal"): torch.tensor([[2.0, 0.0], [5.0, 0.0], [3.0, 0.0], [1.0, 0.0]]),
        ...     "desired_goal": torch.tensor([[6.0, 0.0], [6.0, 0.0], [0.0, 8.0], [0.0, 8.0]]),
        ... }, [4])
        >>> out = episode_progress(geometry, records, torch.zeros(2))
        >>> out.max_progress.tolist(), out.end_progress.tolist(), out.explored
        ([5.0, 3.0], [5.0, 1.0], 5.0)
        >>> bool(out.goal_progress[1] > 16)  # (0, 8) is behind the U's inner wall
        True
    """
    if transitions.ndim != 1 or transitions.batch_size.numel() == 0:
        raise ValueError(
            f"`transitions` must be a non-empty 1-D batch of records, got {tuple(transitions.shape)}."
        )
    for key in (episode_key, achieved_goal_key, goal_key):
        if transitions.get(key, None) is None:
            raise KeyError(f"episode_progress: {key!r} is not in the records.")
    episodes = transitions.get(episode_key).reshape(-1).long().cpu()
    achieved = transitions.get(achieved_goal_key).reshape(len(episodes), -1).float().cpu()
    goals = transitions.get(goal_key).reshape(len(episodes), -1).float().cpu()
    start = torch.as_tensor(start, dtype=torch.float32).reshape(1, -1)
    progress = geometry.path_length(start, achieved)  # [N]
    ids, inverse = torch.unique(episodes, return_inverse=True)
    count = len(ids)
    order = torch.arange(len(episodes))
    max_progress = torch.full((count,), -torch.inf).scatter_reduce(0, inverse, progress, "amax")
    last_record = torch.full((count,), -1, dtype=torch.long).scatter_reduce(0, inverse, order, "amax")
    first_record = torch.full((count,), len(episodes), dtype=torch.long).scatter_reduce(
        0, inverse, order, "amin"
    )
    keep = slice(None) if last is None else slice(max(count - int(last), 0), None)
    episode_goals = goals[first_record][keep]
    return EpisodeProgress(
        episode_ids=ids[keep],
        goals=episode_goals,
        goal_progress=geometry.path_length(start, episode_goals),
        max_progress=max_progress[keep],
        end_progress=progress[last_record][keep],
        explored=float(progress.max()),
    )
