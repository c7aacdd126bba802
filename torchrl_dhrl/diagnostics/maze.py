"""The ``diag/...`` metrics of a maze run's subgoals and graph against the maze's true geometry.

When a run does not learn, these numbers say whether the high level proposes impossible subgoals
(inside walls, outside the arena: the main criticism of DHRL in the later literature), whether the
graph's edges cut through walls, whether the learned distances rank landmark pairs like the true
obstacle-free path lengths do, and how much of the free space the landmarks cover.
:func:`maze_epoch_diagnostics` gathers the ``diag/...`` metrics the recipe logs after every evaluation,
:func:`graph_diagnosis` computes them for a trained agent (``recipes/diagnose_graph.py`` rebuilds a saved
run's).
"""

from __future__ import annotations

import math
import time
from typing import NamedTuple

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import Tensor

from torchrl_dhrl.envs.geometry import MazeGeometry, cached_maze_geometry

from .coverage import default_coverage_radius
from .feasibility import feasibility_fractions
from .graph_quality import graph_quality
from .reachability import graph_reach
from .subgoal_landscape import landscape_summary, subgoal_box, subgoal_landscape

__all__ = [
    "DIAG_KEYS",
    "LANDSCAPE_DIAG_KEYS",
    "start_subgoal",
    "maze_epoch_diagnostics",
    "maze_geometry",
    "GraphDiagnosis",
    "graph_diagnosis",
]


#: The ``diag/...`` metrics :func:`maze_epoch_diagnostics` writes (every one, NaN where undefined).
DIAG_KEYS = (
    "diag/subgoals_in_walls",
    "diag/subgoals_outside",
    "diag/waypoints_in_walls",
    "diag/waypoints_outside",
    "diag/edges_crossing_walls",
    "diag/edges_shortcut",
    "diag/distance_rank_corr",
    "diag/graph_distance_rank_corr",
    "diag/landmark_coverage",
    "diag/landmark_progress",
    "diag/reachable_landmarks",
    "diag/reachable_progress",
    "diag/goal_to_reachable",
    "diag/start_subgoal_x",
    "diag/start_subgoal_y",
    "diag/start_subgoal_feasible",
)


#: The keys :func:`maze_epoch_diagnostics` adds with ``high_loss`` (the high level's critic at the first test
#: start, :func:`~torchrl_dhrl.diagnostics.landscape_summary` over a grid of the subgoal box).
LANDSCAPE_DIAG_KEYS = (
    "diag/start_q_range",
    "diag/start_best_subgoal_in_wall",
    "diag/start_top_subgoals_in_walls",
    "diag/start_actor_q_gap",
)


@torch.no_grad()
def start_subgoal(high_actor: TensorDictModuleBase, observation: Tensor, desired_goal: Tensor) -> Tensor:
    """The subgoal the deterministic high-level actor proposes at ``observation`` for ``desired_goal``.

    ``high_actor`` is the bare network (:class:`~torchrl_dhrl.modules.HighLevelActor`, e.g.
    ``agent.high_policy.actor``): no exploration noise, no ``c_h`` cadence.

    Examples:
        >>> import torch
        >>> from torchrl_dhrl.modules import HighLevelActor
        >>> actor = HighLevelActor(6, 2, [-2.0, -2.0], [10.0, 10.0], num_cells=(8,))
        >>> start_subgoal(actor, torch.zeros(6), torch.tensor([0.0, 8.0])).shape
        torch.Size([2])
    """
    td = TensorDict(
        {
            high_actor.in_keys[0]: observation.reshape(1, -1),
            high_actor.in_keys[1]: desired_goal.reshape(1, -1),
        },
        batch_size=[1],
    )
    return high_actor(td)[high_actor.out_keys[0]][0].detach().float().cpu()


def maze_epoch_diagnostics(
    env_name: str | MazeGeometry,
    planner,
    rollout: TensorDictBase,
    high_actor: TensorDictModuleBase,
    *,
    margin: float = 0.5,
    coverage_radius: float | None = None,
    max_sources: int | None = 64,
    resolution: float | None = None,
    high_loss=None,
) -> dict:
    """The ``diag/...`` metrics of an evaluation: subgoals and graph against the maze's true geometry.

    Empty for the arm envs (not a maze). Every entry of :data:`DIAG_KEYS` otherwise, with
    ``time/diag_s``, its own cost:

    * ``diag/subgoals_in_walls``, ``diag/subgoals_outside``: fractions of the rollout's subgoal proposals
      strictly inside a wall box, outside the arena (:func:`feasibility_fractions`);
    * ``diag/waypoints_in_walls``, ``diag/waypoints_outside``: the same for the waypoints of all steps;
    * ``diag/edges_crossing_walls``, ``diag/edges_shortcut``, ``diag/distance_rank_corr``,
      ``diag/graph_distance_rank_corr``, ``diag/landmark_coverage``, ``diag/landmark_progress``:
      :func:`graph_quality` (``NaN`` without a graph), the true path lengths on the grid of
      :meth:`MazeGeometry.from_maze` (cells of ``resolution``) around walls inflated by ``margin``;
    * ``diag/reachable_landmarks``, ``diag/reachable_progress``, ``diag/goal_to_reachable``:
      :func:`graph_reach` from the start state of the rollout's first episode, for its goal: the part of the
      graph its plans can use (``NaN`` without a graph);
    * ``diag/start_subgoal_x``, ``diag/start_subgoal_y``, ``diag/start_subgoal_feasible``: the deterministic
      high-level proposal at the start state of the rollout's first episode, for its goal
      (:func:`start_subgoal`), and whether it is feasible (``1.0``/``0.0``).

    Args:
        env_name (str or MazeGeometry): the environment, or the geometry of its maze (:func:`maze_geometry`: a
            gymnasium-robotics maze's; ``margin`` and ``resolution`` are then the geometry's own).
        planner (GraphPlanner): the planner whose graph is evaluated.
        rollout (TensorDictBase): ``[B, T]`` evaluation rollout (``observation``, ``desired_goal``,
            ``subgoal``, ``new_subgoal``, ``waypoint``).
        high_actor (TensorDictModuleBase): the deterministic high-level actor.

    Keyword Args:
        margin (float): wall inflation of the true path lengths (the agent's radius; the recipe passes
            ``planner.oracle_margin``). Defaults to ``0.5``.
        coverage_radius (float, optional): defaults to half the maze scale, half a corridor width (2 for
            PointMaze and AntMazeSmall, 4 for the others): a free cell farther from every landmark lies in
            a stretch of corridor the graph does not reach. A fixed fraction of the maze rather than the
            graph's own resolution (``early_stop`` x oracle speed: 2 for PointMaze, 1 for the ant mazes),
            so that the number compares across runs and configurations.
        max_sources (int, optional): see :func:`graph_quality`. Defaults to ``64``.
        resolution (float, optional): the grid cell size. Defaults to :meth:`MazeGeometry.from_maze`'s.
        high_loss (HighLevelLoss, optional): with it, the high level's critic at the first episode's start
            (:data:`LANDSCAPE_DIAG_KEYS`: :func:`~torchrl_dhrl.diagnostics.landscape_summary` of its Q over a
            49 x 49 grid of the subgoal box): ``diag/start_q_range``, ``diag/start_best_subgoal_in_wall``,
            ``diag/start_top_subgoals_in_walls`` (the best 5%) and ``diag/start_actor_q_gap``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_dhrl.modules import HighLevelActor
        >>> from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph
        >>> planner = GraphPlanner(LandmarkGraph(), lambda s, g: (g - s[..., :2]).norm(dim=-1), goal_dim=2)  # no graph
        >>> actor = HighLevelActor(6, 2, [-2.0, -2.0], [10.0, 10.0], num_cells=(8,))
        >>> rollout = TensorDict(observation=torch.zeros(1, 3, 6), desired_goal=torch.zeros(1, 3, 2),
        ...                      subgoal=torch.zeros(1, 3, 2), waypoint=torch.zeros(1, 3, 2),
        ...                      new_subgoal=torch.ones(1, 3, 1, dtype=torch.bool), batch_size=[1, 3])
        >>> out = maze_epoch_diagnostics("PointMaze", planner, rollout, actor)
        >>> out["diag/subgoals_in_walls"], out["diag/distance_rank_corr"]
        (0.0, nan)
        >>> maze_epoch_diagnostics("Reacher3D", planner, rollout, actor)
        {}
    """
    geometry = maze_geometry(env_name, margin, resolution)
    if geometry is None:
        return {}
    start = time.perf_counter()
    if coverage_radius is None:
        coverage_radius = default_coverage_radius(geometry)
    metrics = {f"diag/{k}": v for k, v in feasibility_fractions(geometry, rollout).items()}
    quality = graph_quality(geometry, planner, coverage_radius=coverage_radius, max_sources=max_sources)
    metrics.update({f"diag/{k}": v for k, v in quality.items()})
    first = rollout.reshape(-1, rollout.shape[-1])[0, 0]
    reach = graph_reach(geometry, planner, first["observation"], first["desired_goal"])
    for key in ("reachable_landmarks", "reachable_progress", "goal_to_reachable"):
        metrics[f"diag/{key}"] = reach[key]
    subgoal = start_subgoal(high_actor, first["observation"], first["desired_goal"])
    metrics["diag/start_subgoal_x"], metrics["diag/start_subgoal_y"] = subgoal[:2].tolist()
    metrics["diag/start_subgoal_feasible"] = float(geometry.feasible(subgoal[:2]).item())
    if high_loss is not None:
        low, high = subgoal_box(high_loss)
        step = max(h - lo for lo, h in zip(low, high, strict=True)) / 48
        land = subgoal_landscape(
            high_loss, high_actor, first["observation"], first["desired_goal"], low, high, step
        )
        summary = landscape_summary(land, geometry.in_walls(land.points()))
        metrics["diag/start_q_range"] = summary["q_range"]
        metrics["diag/start_best_subgoal_in_wall"] = summary["best_in_wall"]
        metrics["diag/start_top_subgoals_in_walls"] = summary["top_in_walls"]
        metrics["diag/start_actor_q_gap"] = summary["actor_q_gap"]
    metrics["time/diag_s"] = time.perf_counter() - start
    return metrics


def maze_geometry(maze: str | MazeGeometry, margin: float = 0.5, resolution: float | None = None) -> MazeGeometry | None:
    """The geometry the maze diagnostics measure against: ``maze`` itself when it is a :class:`MazeGeometry` (a
    gymnasium-robotics maze's, :meth:`~torchrl_dhrl.envs.GymnasiumGoalEnv.maze_geometry`), a built-in maze's by
    name (walls inflated by ``margin``, cached), ``None`` for any other env.

    Examples:
        >>> maze_geometry("PointMaze").scale, maze_geometry("Reacher3D")
        (4.0, None)
    """
    if isinstance(maze, MazeGeometry):
        return maze
    from torchrl_dhrl.envs import MAZE_NAMES

    return cached_maze_geometry(maze, float(margin), resolution) if maze in MAZE_NAMES else None


class GraphDiagnosis(NamedTuple):
    """Outcome of :func:`graph_diagnosis`.

    Attributes:
        metrics (dict): the ``diag/...`` metrics (:func:`maze_epoch_diagnostics`), with ``graph/landmarks``
            and ``graph/edges``.
        pairs (dict): ``rows``, ``cols`` (landmark indices), ``true`` (path length, goal units),
            ``learned`` (``landmark_distances``, steps) and ``graph`` (all-pairs shortest distances, steps)
            of the landmark pairs entering the rank correlations; empty tensors without a graph.
        landmark_goals (Tensor): ``[K, 2]``.
        reach (dict): :func:`graph_reach` from the first test episode's start state, for its goal (with
            ``bridge_distance``, which the ``diag/...`` metrics leave out), and that ``start`` and ``goal``
            (``[2]`` tensors).
    """

    metrics: dict
    pairs: dict
    landmark_goals: Tensor
    reach: dict


def graph_diagnosis(
    agent,
    eval_env,
    env_name: str | MazeGeometry,
    *,
    oracle_margin: float = 0.5,
    rollout: bool = True,
    max_sources: int | None = 64,
    resolution: float | None = None,
) -> GraphDiagnosis:
    """:func:`maze_epoch_diagnostics` for the graph and the high level of a trained agent.

    With ``rollout`` a deterministic evaluation on the test goals of ``eval_env`` is run (as the recipe does
    after each epoch) for the subgoal and waypoint fractions; without it they are ``NaN`` and the start
    state is the first evaluation env's reset state.

    Args:
        agent (DHRLAgent): the agent, its graph built (or not).
        eval_env (EnvBase): the evaluation env with the agent's primers.
        env_name (str or MazeGeometry): the maze, or its geometry (:func:`maze_geometry`).

    Keyword Args:
        oracle_margin (float): the agent's radius (walls are inflated by it). Defaults to ``0.5``.
        rollout (bool): run the evaluation episodes. Defaults to ``True``.
        max_sources (int, optional): see :func:`graph_quality`. Defaults to ``64``.
        resolution (float, optional): the grid cell size (default: the recipe's, see
            :meth:`MazeGeometry.from_maze`).

    Raises:
        ValueError: when ``env_name`` is not a maze.

    Examples:
        >>> import torch
        >>> from torchrl_dhrl.factory import make_agent, make_environment
        >>> _ = torch.manual_seed(0)
        >>> cells = {"num_cells": (8,)}
        >>> agent = make_agent(make_environment("PointMaze"), goal_indices=[0, 1], high_policy={"subgoal_low": [-2.0, -2.0],
        ...     "subgoal_high": [10.0, 10.0], "interval": 5, **cells}, high_critic=cells, low_actor=cells,
        ...     low_critic=cells)
        >>> env = make_environment("PointMaze", eval=True, max_episode_steps=10, agent=agent)
        >>> diagnosis = graph_diagnosis(agent, env, "PointMaze", rollout=False)
        >>> diagnosis.metrics["graph/landmarks"], diagnosis.pairs["true"].numel()
        (0, 0)
    """
    from torchrl_dhrl.training import evaluate

    geometry = maze_geometry(env_name, oracle_margin, resolution)
    if geometry is None:
        raise ValueError(f"The graph diagnostics need a maze; this run is on {env_name}.")
    if rollout:
        length = eval_env.max_episode_steps
        td = evaluate(eval_env, agent.policy, length).rollout
    else:
        td = eval_env.reset().unsqueeze(-1)
        nan = torch.full_like(td["achieved_goal"], math.nan)
        td.set("subgoal", nan).set("waypoint", nan).set("new_subgoal", torch.zeros_like(nan[..., :1]).bool())
    metrics = maze_epoch_diagnostics(
        geometry,
        agent.planner,
        td,
        agent.high_policy.actor,
        margin=oracle_margin,
        max_sources=max_sources,
        resolution=resolution,
    )
    if not rollout:
        for key in ("subgoals", "waypoints"):
            metrics[f"diag/{key}_in_walls"] = metrics[f"diag/{key}_outside"] = math.nan
    graph = agent.planner.graph
    metrics["graph/landmarks"] = graph.num_landmarks
    metrics["graph/edges"] = int(graph.edges.shape[0]) if graph.has_graph else 0
    _, pairs = graph_quality(geometry, graph, coverage_radius=1.0, max_sources=max_sources, return_pairs=True)
    names = ("rows", "cols", "true", "learned", "graph")
    pairs = (
        dict(zip(names, pairs, strict=True))
        if pairs is not None
        else {name: torch.zeros(0) for name in names}
    )
    first = td.reshape(-1, td.shape[-1])[0, 0]
    reach = graph_reach(geometry, agent.planner, first["observation"], first["desired_goal"])
    reach["start"] = first["achieved_goal"].detach().float().cpu()[:2]
    reach["goal"] = first["desired_goal"].detach().float().cpu()[:2]
    return GraphDiagnosis(metrics, pairs, graph.landmark_goals.detach().cpu(), reach)
