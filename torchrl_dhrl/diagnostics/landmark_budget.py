"""How the graph's quality depends on the landmark budget: the graph rebuilt from one buffer with several
numbers of landmarks.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Sequence

import torch
from torch import Tensor

from torchrl_dhrl.envs.geometry import MazeGeometry, furthest_progress

from .coverage import landmark_coverage

__all__ = ["landmark_budget_sweep"]


@torch.no_grad()
def landmark_budget_sweep(
    geometry: MazeGeometry,
    planner,
    replay_buffer,
    budgets: Sequence[tuple[int, int]],
    *,
    draws: int = 3,
    coverage_radius: float,
    start: Tensor | None = None,
    observation_key: str = "observation",
    achieved_goal_key: str = "achieved_goal",
    generator: torch.Generator | None = None,
) -> tuple[list[dict], float]:
    """Does the graph's size limit how far it reaches? Rebuilds with other landmark and candidate budgets.

    For each ``(max_landmarks, candidates)`` of ``budgets`` a copy of ``planner``'s graph is rebuilt
    ``draws`` times from ``candidates`` states drawn uniformly (with replacement, as the recipe's
    :func:`~torchrl_dhrl.recipe.rebuild_graph` does) from ``replay_buffer``'s storage, with the planner's
    learned distance, and the rebuilt landmarks' ``landmark_progress`` (:func:`furthest_progress`) and
    ``landmark_coverage`` are measured. The same draw index uses the same candidates in every budget with
    the same candidate count. The planner itself is left as it was.

    The second return value is the progress of the whole buffer (every stored achieved goal): when a budget's
    progress is close to it, the graph reaches as far as the data does, and a larger graph cannot help;
    exploration is what limits it.

    Args:
        geometry (MazeGeometry): the maze.
        planner (GraphPlanner): the planner whose graph (settings and distance) is copied.
        replay_buffer (ReplayBuffer): the low-level buffer the recipe builds its graph from.
        budgets (sequence of (int, int)): ``(max_landmarks, candidates)`` pairs.

    Keyword Args:
        draws (int): rebuilds per budget. Defaults to ``3``.
        coverage_radius (float): see :func:`landmark_coverage`.
        start (Tensor, optional): where progress is measured from (default: the origin).
        observation_key, achieved_goal_key (str): the storage's entries. Default to ``"observation"`` and
            ``"achieved_goal"``.
        generator (torch.Generator, optional): the candidates' random draws.

    Returns:
        one row per budget (``max_landmarks``, ``candidates``, ``landmarks`` (mean built), ``progress_mean``,
        ``progress_min``, ``progress_max``, ``coverage_mean``, ``build_s``) and the buffer's progress.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, ReplayBuffer
        >>> from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph
        >>> geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
        >>> xy = torch.stack([torch.linspace(0.0, 8.0, 40), torch.zeros(40)], -1)  # the first corridor
        >>> rb = ReplayBuffer(storage=LazyTensorStorage(40))
        >>> _ = rb.extend(TensorDict(observation=xy, achieved_goal=xy, batch_size=[40]))
        >>> planner = GraphPlanner(LandmarkGraph(cutoff=3.0, early_stop=0.0),
        ...                        lambda s, g: (s[..., :2] - g).norm(dim=-1), goal_dim=2)
        >>> rows, buffer_progress = landmark_budget_sweep(geometry, planner, rb, [(2, 400), (40, 400)],
        ...                                               coverage_radius=2.0, generator=torch.Generator().manual_seed(0))
        >>> [row["landmarks"] for row in rows], rows[1]["progress_min"], buffer_progress
        ([2.0, 40.0], 8.0, 8.0)
        >>> planner.num_landmarks  # the planner's own graph is untouched
        0
    """
    if isinstance(draws, bool) or not isinstance(draws, int) or draws < 1:
        raise ValueError(f"`draws` must be a positive int, got {draws!r}.")
    budgets = [tuple(budget) for budget in budgets]
    for budget in budgets:
        if len(budget) != 2 or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in budget):
            raise ValueError(
                f"`budgets` must hold (max_landmarks, candidates) pairs of positive ints, got {budget!r}."
            )
    storage = replay_buffer.storage
    if len(storage) == 0:
        raise ValueError("`replay_buffer` is empty: there is nothing to build a graph from.")
    data = storage[:].reshape(-1)  # the written entries (every env lane of a multi-dimensional storage)
    goals = data.get(achieved_goal_key)
    states = data.get(observation_key)
    buffer_progress = furthest_progress(geometry, goals.float().cpu()[..., :2], start)
    seeds = torch.randint(0, 2**62, (draws,), generator=generator).tolist()
    rows = []
    for max_landmarks, candidates in budgets:
        graph = copy.deepcopy(planner.graph)
        graph.max_landmarks = max_landmarks
        graph.min_landmarks = min(graph.min_landmarks, max_landmarks)
        progress, coverage, built, seconds = [], [], [], []
        for seed in seeds:
            index = torch.randint(
                0, goals.shape[0], (candidates,), generator=torch.Generator().manual_seed(seed)
            )
            begin = time.perf_counter()
            graph.build(states[index.to(states.device)], goals[index.to(goals.device)], planner.distance)
            seconds.append(time.perf_counter() - begin)
            landmarks = graph.landmark_goals.detach().float().cpu()[..., :2]
            progress.append(furthest_progress(geometry, landmarks, start))
            coverage.append(landmark_coverage(geometry, landmarks, coverage_radius))
            built.append(graph.num_landmarks)
        rows.append(
            {
                "max_landmarks": max_landmarks,
                "candidates": candidates,
                "landmarks": sum(built) / draws,
                "progress_mean": sum(progress) / draws,
                "progress_min": min(progress),
                "progress_max": max(progress),
                "coverage_mean": sum(coverage) / draws,
                "build_s": sum(seconds) / draws,
            }
        )
    return rows, buffer_progress
