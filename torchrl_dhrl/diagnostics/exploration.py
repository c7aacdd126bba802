"""How far a maze run's training episodes get, goal by goal: is exploration what holds it back?

The frontier of a maze run moves only when training episodes reach beyond it. :func:`episode_progress`
measures, for the episodes stored in a high-level replay buffer, how far along the maze each episode's goal
is and how far the agent got, both as obstacle-free path lengths from the start (``MazeGeometry.path_length``),
next to the furthest point the stored data has ever reached. ``recipes/diagnose_exploration.py`` prints it for
a saved run; :func:`episodes_in_boxes` says which stored episodes ever entered given regions (a bottleneck's gap, the
corridor past it), step by step. :class:`TrainingEpisodeLog` follows the training episodes while a run trains: per epoch, how many
reached their goal, how many goals frontier-based goal shifting moved, and (mazes) how far along the maze they got.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor

from torchrl_dhrl.envs.geometry import MazeGeometry, furthest_progress

__all__ = ["EpisodeProgress", "TrainingEpisodeLog", "episode_progress", "episodes_in_boxes", "upside_down_by_episode"]


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
def episodes_in_boxes(positions: Tensor, episode_ids: Tensor, boxes: Tensor) -> tuple[Tensor, Tensor]:
    """Which episodes ever had a position inside each of ``boxes``.

    Args:
        positions (Tensor): ``[N, 2]`` the agent's x, y at every stored step (e.g. a low-level buffer's
            ``observation[..., :2]``).
        episode_ids (Tensor): ``[N]`` the episode of each step (e.g. the collector's ``traj_ids``), any integers.
        boxes (Tensor): ``[B, 4]`` closed boxes ``(x_min, x_max, y_min, y_max)``; an empty box (min > max) holds nothing.

    Returns:
        ``(ids, inside)``: ``ids [E]`` the distinct episodes in increasing order (the collector numbers them as
        they start, so oldest first) and ``inside [E, B]`` whether episode ``e`` had a step in box ``b``.

    Examples:
        >>> import torch
        >>> positions = torch.tensor([[0.0, 0.0], [16.0, 7.5], [1.0, 1.0], [16.2, 9.2]])
        >>> ids, inside = episodes_in_boxes(
        ...     positions, torch.tensor([0, 0, 1, 1]), torch.tensor([[15.4, 17.0, 7.0, 9.0], [12.0, 20.0, 9.0, 16.0]])
        ... )
        >>> ids.tolist(), inside.tolist()
        ([0, 1], [[True, False], [False, True]])
    """
    positions = torch.as_tensor(positions).reshape(-1, 2).float()
    episode_ids = torch.as_tensor(episode_ids).reshape(-1)
    boxes = torch.as_tensor(boxes, dtype=torch.float32).reshape(-1, 4)
    if positions.shape[0] != episode_ids.shape[0]:
        raise ValueError(
            f"positions ({positions.shape[0]} steps) and episode_ids ({episode_ids.shape[0]}) must match."
        )
    x, y = positions[:, None, 0], positions[:, None, 1]  # [N, 1]
    hit = (x >= boxes[:, 0]) & (x <= boxes[:, 1]) & (y >= boxes[:, 2]) & (y <= boxes[:, 3])  # [N, B]
    ids, inverse = torch.unique(episode_ids, return_inverse=True)
    inside = torch.zeros(len(ids), boxes.shape[0], dtype=torch.long)
    inside.scatter_reduce_(0, inverse[:, None].expand_as(hit), hit.long(), "amax")
    return ids, inside.bool()


def upside_down_by_episode(
    flipped: Tensor, episode_ids: Tensor, step_count: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """Per episode, the share of its stored steps the agent spent upside down and whether its last one was.

    Args:
        flipped (Tensor): ``[N]`` bool, whether the agent was upside down after each stored step (e.g. the ant's
            :meth:`~torchrl_dhrl.envs.AntAgent.is_upside_down` of a low-level buffer's ``("next", "observation")``).
        episode_ids (Tensor): ``[N]`` the episode of each step (e.g. the collector's ``traj_ids``), any integers.
        step_count (Tensor, optional): ``[N]`` each step's place in its episode; an episode's last step is the one
            of highest count. Defaults to ``None``: the last in storage order.

    Returns:
        ``(ids, share, ended)``: ``ids [E]`` the distinct episodes in increasing order (oldest first), ``share
        [E]`` the fraction of each one's stored steps upside down, ``ended [E]`` bool, upside down at its last step.

    Examples:
        >>> import torch
        >>> ids, share, ended = upside_down_by_episode(
        ...     torch.tensor([False, True, True, False, False]), torch.tensor([3, 3, 3, 5, 5])
        ... )
        >>> ids.tolist(), share.tolist(), ended.tolist()
        ([3, 5], [0.6666666865348816, 0.0], [True, False])
    """
    flipped = torch.as_tensor(flipped).reshape(-1).bool()
    episode_ids = torch.as_tensor(episode_ids).reshape(-1)
    if flipped.shape[0] != episode_ids.shape[0]:
        raise ValueError(f"flipped ({flipped.shape[0]} steps) and episode_ids ({episode_ids.shape[0]}) must match.")
    order = torch.arange(flipped.shape[0]) if step_count is None else torch.as_tensor(step_count).reshape(-1)
    if order.shape[0] != flipped.shape[0]:
        raise ValueError(f"step_count ({order.shape[0]} steps) and flipped ({flipped.shape[0]}) must match.")
    ids, inverse = torch.unique(episode_ids, return_inverse=True)
    steps = torch.zeros(len(ids)).index_add_(0, inverse, torch.ones(flipped.shape[0]))
    share = torch.zeros(len(ids)).index_add_(0, inverse, flipped.float()) / steps
    # the last step of each episode: the highest order, ties to the later stored step
    rank = order.double() * flipped.shape[0] + torch.arange(flipped.shape[0], dtype=torch.float64)
    last = torch.full((len(ids),), -1.0, dtype=torch.float64).scatter_reduce_(0, inverse, rank, "amax")
    ended = torch.zeros(len(ids), dtype=torch.bool)
    is_last = rank == last[inverse]
    ended[inverse[is_last]] = flipped[is_last]
    return ids, share, ended


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


class TrainingEpisodeLog:
    """Per-epoch statistics of the training episodes, from the collector's batches of whole episodes.

    :meth:`update` takes a batch ``[num_envs, T]`` holding one whole episode per env (the recipe's collector
    yields them) and counts, per episode:

    * ``train/success``: the fraction whose final step is a success (``success_key``, the env's own goal: under
      frontier-based goal shifting the agent chases a shifted goal, the env still judges the real one);
    * ``train/any_success``: the fraction with a success at any step;
    * ``train/goal_shifted``: the fraction whose goal frontier-based goal shifting moved (``shifted_key``; only
      reported when the batches hold it, i.e. with FGS);
    * with a maze ``geometry``: ``train/max_progress``, the furthest obstacle-free path length from ``start``
      that an episode of the epoch reached (:meth:`MazeGeometry.path_length`, goal units), and
      ``train/frontier``, the furthest since the run began: the exploration frontier as a curve;
    * with an ``upside_down`` test (the ant's :meth:`~torchrl_dhrl.envs.AntAgent.is_upside_down`):
      ``train/upside_down``, the fraction of the epoch's training steps the agent spent upside down, and
      ``train/ended_upside_down``, the fraction of episodes that ended so. By default nothing rights a flipped
      ant (as in the reference; see the env's ``right_flipped_after``), so the rest of such an episode explores
      nothing.

    :meth:`pop_metrics` returns them for the episodes since the last call (``train/episodes`` their number) and
    starts a new epoch; the frontier is kept. The state is a small JSON-able dict (:meth:`state_dict`), so a
    checkpoint taken in the middle of an epoch resumes its counts exactly.

    Args:
        geometry (MazeGeometry, optional): the maze; ``None`` (arm envs) skips the progress.
        start (Tensor, optional): ``[2]`` where progress is measured from. Defaults to the origin (every
            maze's start).
        upside_down (callable, optional): maps observations ``[..., obs_dim]`` to a bool tensor ``[...]``,
            ``True`` where the agent lies upside down. ``None`` (the default) skips the two metrics.

    Keyword Args:
        success_key (NestedKey): per-step success flag. Defaults to ``("next", "is_success")``.
        shifted_key (NestedKey): per-step bool, ``True`` in episodes whose goal FGS shifted. Defaults to
            ``"goal_shifted"``.
        achieved_goal_key (NestedKey): where the agent got to. Defaults to ``("next", "achieved_goal")``.
        observation_key (NestedKey): the observations ``upside_down`` reads. Defaults to
            ``("next", "observation")``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
        >>> log = TrainingEpisodeLog(geometry)
        >>> x = torch.tensor([[1.0, 2.0, 3.0], [1.0, 5.0, 2.0]])  # two episodes of 3 steps along y = 0
        >>> batch = TensorDict({
        ...     ("next", "achieved_goal"): torch.stack([x, torch.zeros_like(x)], -1),
        ...     ("next", "is_success"): torch.tensor([[False, False, True], [False, True, False]]).unsqueeze(-1),
        ... }, [2, 3])
        >>> log.update(batch)
        >>> metrics = log.pop_metrics()
        >>> metrics["train/episodes"], metrics["train/success"], metrics["train/any_success"]
        (2, 0.5, 1.0)
        >>> metrics["train/max_progress"], metrics["train/frontier"], "train/goal_shifted" in metrics
        (5.0, 5.0, False)
        >>> log.pop_metrics()["train/episodes"], log.state_dict()["frontier"]  # a new epoch; the frontier stays
        (0, 5.0)
    """

    def __init__(
        self,
        geometry: MazeGeometry | None = None,
        start: Tensor | None = None,
        *,
        success_key: NestedKey = ("next", "is_success"),
        shifted_key: NestedKey = "goal_shifted",
        achieved_goal_key: NestedKey = ("next", "achieved_goal"),
        upside_down: Callable[[Tensor], Tensor] | None = None,
        observation_key: NestedKey = ("next", "observation"),
    ) -> None:
        self.geometry = geometry
        self.start = start
        self.success_key = success_key
        self.shifted_key = shifted_key
        self.achieved_goal_key = achieved_goal_key
        self.upside_down = upside_down
        self.observation_key = observation_key
        self._state = self._empty_epoch() | {"frontier": -math.inf}

    @staticmethod
    def _empty_epoch() -> dict[str, Any]:
        return {
            "episodes": 0,
            "success": 0,
            "any_success": 0,
            "shifted": None,
            "max_progress": -math.inf,
            "steps": 0,
            "upside_down_steps": 0,
            "ended_upside_down": 0,
        }

    @torch.no_grad()
    def update(self, batch: TensorDictBase) -> None:
        """Counts the episodes of ``batch`` (``[num_envs, T]``, or ``[T]`` for one env), one episode per row."""
        if batch.ndim not in (1, 2) or batch.batch_size.numel() == 0:
            raise ValueError(
                f"TrainingEpisodeLog.update expects a non-empty [num_envs, T] batch of whole episodes, got "
                f"{tuple(batch.shape)}."
            )
        if batch.ndim == 1:
            batch = batch.unsqueeze(0)
        success = batch.get(self.success_key, None)
        if success is None:
            raise KeyError(f"TrainingEpisodeLog: {self.success_key!r} is not in the batch.")
        success = success.reshape(*batch.shape, -1).any(-1).cpu()  # [E, T]
        state = self._state
        state["episodes"] += batch.shape[0]
        state["success"] += int(success[:, -1].sum())
        state["any_success"] += int(success.any(-1).sum())
        shifted = batch.get(self.shifted_key, None)
        if shifted is not None:
            shifted = shifted.reshape(*batch.shape, -1).any(-1).any(-1)
            state["shifted"] = (state["shifted"] or 0) + int(shifted.sum())
        if self.geometry is not None:
            achieved = batch.get(self.achieved_goal_key, None)
            if achieved is None:
                raise KeyError(f"TrainingEpisodeLog: {self.achieved_goal_key!r} is not in the batch.")
            furthest = furthest_progress(self.geometry, achieved[..., :2], self.start)
            state["max_progress"] = max(state["max_progress"], furthest)
            state["frontier"] = max(state["frontier"], furthest)
        if self.upside_down is not None:
            observation = batch.get(self.observation_key, None)
            if observation is None:
                raise KeyError(f"TrainingEpisodeLog: {self.observation_key!r} is not in the batch.")
            flipped = torch.as_tensor(self.upside_down(observation)).reshape(batch.shape).cpu()  # [E, T]
            state["steps"] += flipped.numel()
            state["upside_down_steps"] += int(flipped.sum())
            state["ended_upside_down"] += int(flipped[:, -1].sum())

    def pop_metrics(self) -> dict[str, float]:
        """The ``train/...`` metrics of the episodes since the last call; starts a new epoch."""
        state = self._state
        episodes = state["episodes"]
        ratio = (lambda n: n / episodes) if episodes else (lambda n: math.nan)
        out: dict[str, float] = {
            "train/episodes": episodes,
            "train/success": ratio(state["success"]),
            "train/any_success": ratio(state["any_success"]),
        }
        if state["shifted"] is not None:
            out["train/goal_shifted"] = ratio(state["shifted"])
        if self.geometry is not None:
            finite = lambda v: v if math.isfinite(v) else math.nan  # noqa: E731
            out["train/max_progress"] = finite(state["max_progress"])
            out["train/frontier"] = finite(state["frontier"])
        if self.upside_down is not None:
            out["train/upside_down"] = (
                state["upside_down_steps"] / state["steps"] if state["steps"] else math.nan
            )
            out["train/ended_upside_down"] = ratio(state["ended_upside_down"])
        self._state = self._empty_epoch() | {"frontier": state["frontier"]}
        return out

    def state_dict(self) -> dict[str, Any]:
        """The counts of the current epoch and the frontier (JSON-able; ``-inf`` stored as ``None``)."""
        return {k: (None if isinstance(v, float) and math.isinf(v) else v) for k, v in self._state.items()}

    def load_state_dict(self, state_dict: Mapping[str, Any]) -> None:
        state = self._empty_epoch() | {"frontier": -math.inf}
        for key, value in state_dict.items():
            if key not in state:
                raise KeyError(
                    f"TrainingEpisodeLog.load_state_dict: unknown entry {key!r} (expected {sorted(state)})."
                )
            if key in ("max_progress", "frontier"):
                value = -math.inf if value is None else float(value)
            state[key] = value
        self._state = state
