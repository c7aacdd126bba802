"""The end of a DHRL epoch (Appendix A): rebuild the graph from the replay buffer, evaluate, draw.

:func:`epoch_of` counts the epochs of the schedule, :func:`rebuild_graph` rebuilds the planner's graph from
states sampled from a buffer, :func:`evaluate_epoch` runs the test episodes with the diagnostics the recipe
logs and :func:`plot_epoch` draws the graph with a test episode.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.data import RandomSampler, ReplayBuffer
from torchrl.envs import EnvBase

from torchrl_dhrl.diagnostics import hierarchy_diagnostics, maze_epoch_diagnostics
from torchrl_dhrl.envs.geometry import MazeGeometry
from torchrl_dhrl.planner import GraphPlanner
from torchrl_dhrl.training import EvaluationResult, evaluate, goal_as_waypoint

from .plots import plot_episode

__all__ = ["epoch_of", "evaluate_epoch", "graph_metrics", "plot_epoch", "rebuild_graph", "upside_down_steps"]


def epoch_of(episodes: int, warmup_episodes: int, epoch_episodes: int) -> int:
    """The number of epochs completed after ``episodes`` training episodes.

    As in the reference, epochs of ``epoch_episodes`` start when the warm-up ends; the warm-up itself
    is cut into epochs of the same length (evaluated too, for the curve), the last one possibly
    shorter. For example with 200 warm-up episodes and 15 per epoch, epochs end after 15, 30, ...,
    195, 200, 215, 230, ... episodes.

    Examples:
        >>> [epoch_of(e, 200, 15) for e in (194, 195, 199, 200, 214, 215)]
        [12, 13, 13, 14, 14, 15]
    """
    if episodes < warmup_episodes:
        return episodes // epoch_episodes
    return -(-warmup_episodes // epoch_episodes) + (episodes - warmup_episodes) // epoch_episodes


@torch.no_grad()
def rebuild_graph(
    planner: GraphPlanner,
    replay_buffer: ReplayBuffer,
    candidates: int,
    *,
    observation_key: str = "observation",
    achieved_goal_key: str = "achieved_goal",
) -> dict[str, float]:
    """Rebuilds ``planner``'s graph from scratch from ``candidates`` states drawn uniformly from the buffer.

    The states are drawn (with replacement, as the reference does) from the buffer's storage, not through
    its sampler or relabelling, and handed to :meth:`~torchrl_dhrl.planner.GraphPlanner.build` (FPS
    landmarks, edges, shortest paths).

    Returns:
        ``{"graph/build_s": seconds}``: the rebuild's wall-clock time, sampling included.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, ReplayBuffer
        >>> from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph
        >>> _ = torch.manual_seed(0)
        >>> rb = ReplayBuffer(storage=LazyTensorStorage(100))
        >>> xy = torch.rand(100, 2) * 10
        >>> _ = rb.extend(TensorDict(observation=xy, achieved_goal=xy, batch_size=[100]))
        >>> graph = LandmarkGraph(cutoff=3.0, max_landmarks=8, early_stop=0.0)
        >>> planner = GraphPlanner(graph, lambda s, g: (s - g).norm(dim=-1), 2)
        >>> metrics = rebuild_graph(planner, rb, candidates=50)
        >>> planner.num_landmarks, list(metrics)
        (8, ['graph/build_s'])
    """
    start = time.perf_counter()
    index, _ = RandomSampler().sample(replay_buffer.storage, candidates)
    states = replay_buffer.storage[index]
    planner.build(states[observation_key], states[achieved_goal_key])
    return {"graph/build_s": time.perf_counter() - start}


def graph_metrics(planner: GraphPlanner) -> dict[str, int]:
    """``graph/landmarks`` and ``graph/edges`` of the planner's current graph (0 and 0 without one).

    Examples:
        >>> from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph
        >>> graph_metrics(GraphPlanner(LandmarkGraph(cutoff=3.0), lambda s, g: (s - g).norm(dim=-1), 2))
        {'graph/landmarks': 0, 'graph/edges': 0}
    """
    return {
        "graph/landmarks": planner.num_landmarks,
        "graph/edges": int(planner.edges.shape[0]) if planner.has_graph else 0,
    }


@torch.no_grad()
def evaluate_epoch(
    agent,
    eval_env: EnvBase,
    max_steps: int,
    *,
    env_name: str,
    reward_threshold: float,
    far_from_graph_threshold: float,
    oracle_margin: float = 0.5,
    flat: bool = True,
    policy: TensorDictModuleBase | None = None,
    maze: MazeGeometry | None = None,
    upside_down: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> tuple[dict[str, Any], EvaluationResult]:
    """The evaluation of an epoch: the test episodes with the agent's policy, and what the recipe logs of it.

    One deterministic episode per env of ``eval_env`` (:func:`~torchrl_dhrl.training.evaluate`), then:

    * ``eval/success`` (final state, the paper's), ``eval/any_success``, ``eval/final_distance``,
      ``eval/last10_success``, ``eval/final_speed`` and ``time/eval_s``;
    * with ``upside_down``, ``eval/upside_down`` (the share of the test steps the agent spent upside down) and
      ``eval/ended_upside_down`` (the share of the test episodes that ended so);
    * ``graph/mean_path_landmarks`` (planned path length) and ``graph/learned_distance_start_goal`` (the
      planner's distance from the first episode's start to its goal);
    * on the mazes, the subgoals and the graph against the true geometry
      (:func:`~torchrl_dhrl.diagnostics.maze_epoch_diagnostics`: ``maze``, else the built-in maze of
      ``env_name`` with ``oracle_margin`` as the agent's radius; and the high level's critic over the subgoal box
      at the first test start);
    * on every env, ``diag/...`` of :func:`~torchrl_dhrl.diagnostics.hierarchy` (with
      ``reward_threshold`` as the reach radius and ``far_from_graph_threshold`` for the gradual penalty's
      "far from the graph");
    * with ``flat``, ``eval/flat_success``, ``eval/flat_any_success`` and ``eval/flat_final_distance``: the
      low level alone chasing the goal (:func:`~torchrl_dhrl.training.goal_as_waypoint`) on the same test
      goals. ``eval_env.base_env``'s state is restored around it, so the next evaluations' goals are those
      of a run without it.

    Args:
        agent (DHRLAgent): the agent (``policy``, ``planner``, ``high_policy``, ``low_actor``).
        eval_env (TransformedEnv): the evaluation env with the agent's primers (its ``base_env`` has an exact
            ``state_dict``, as :func:`~torchrl_dhrl.envs.make_env`'s envs do).
        max_steps (int): the episode length.

    Keyword Args:
        policy (TensorDictModuleBase, optional): what acts in the test episodes, e.g. the agent's policy captured
            as a CUDA graph (:func:`~torchrl_dhrl.factory.make_eval_policy`). Defaults to ``agent.policy``.
        maze (MazeGeometry, optional): the geometry of an env's maze that is not built in (a gymnasium-robotics
            maze's, :meth:`~torchrl_dhrl.envs.GymnasiumGoalEnv.maze_geometry`). Defaults to the built-in maze of
            ``env_name`` (none for the arms and other envs).
        upside_down (callable, optional): maps the observations ``[..., obs_dim]`` after each test step to a bool
            tensor ``[...]`` (the ant's :meth:`~torchrl_dhrl.envs.AntAgent.is_upside_down`). Defaults to ``None``
            (not measured).

    Returns:
        ``(metrics, result)``: the metrics and the main evaluation's
        :class:`~torchrl_dhrl.training.EvaluationResult` (its rollout is what :func:`plot_epoch` draws).

    Examples:
        >>> import torch
        >>> from torchrl_dhrl.factory import make_agent, make_environment
        >>> _ = torch.manual_seed(0)
        >>> env = make_environment("PointMaze", max_episode_steps=20)
        >>> agent = make_agent(env, goal_indices=[0, 1], high_policy={"subgoal_low": [-2.0, -2.0], "subgoal_high": [10.0, 10.0], "interval": 5,
        ...     "num_cells": (16,)}, high_critic={"num_cells": (16,)}, low_actor={"num_cells": (16,)},
        ...     low_critic={"num_cells": (16,)}, graph={"cutoff": 5.0})
        >>> eval_env = make_environment("PointMaze", num_envs=2, eval=True, max_episode_steps=20, agent=agent)
        >>> metrics, result = evaluate_epoch(agent, eval_env, 20, env_name="PointMaze", reward_threshold=0.5,
        ...                                  far_from_graph_threshold=15.0)
        >>> result.rollout.shape, 0.0 <= metrics["eval/success"] <= metrics["eval/any_success"] <= 1.0
        (torch.Size([2, 20]), True)
        >>> "eval/flat_success" in metrics and "diag/subgoals_in_walls" in metrics
        True
    """
    planner = agent.planner
    start = time.perf_counter()
    before = eval_env.base_env.state_dict() if flat else None
    result = evaluate(eval_env, agent.policy if policy is None else policy, max_steps)
    metrics: dict[str, Any] = {"time/eval_s": time.perf_counter() - start}
    metrics["eval/success"] = result.success
    metrics["eval/any_success"] = result.any_success
    metrics["eval/final_distance"] = result.final_distance
    metrics["eval/last10_success"] = result.last_steps_success
    metrics["eval/final_speed"] = result.final_speed
    rollout = result.rollout
    if upside_down is not None:
        flipped = upside_down_steps(rollout, upside_down)
        metrics["eval/upside_down"] = flipped.float().mean().item()
        metrics["eval/ended_upside_down"] = flipped[..., -1].float().mean().item()
    metrics["graph/mean_path_landmarks"] = rollout["planner", "path_length"].float().mean().item()
    start_state, goal = rollout[0, 0]["observation"], rollout[0, 0]["desired_goal"]
    metrics["graph/learned_distance_start_goal"] = planner.distance(start_state, goal).item()
    # subgoals and graph against the maze's true geometry (diag/...; nothing for the arms)
    metrics.update(
        maze_epoch_diagnostics(
            env_name if maze is None else maze,
            planner,
            rollout,
            agent.high_policy.actor,
            margin=oracle_margin,
            high_loss=agent.high_loss,
        )
    )
    # the high level's subgoals vs the goal, and the low level's delivery of them (every env)
    hierarchy = hierarchy_diagnostics(
        rollout,
        reward_threshold,
        distance=planner.distance,
        distance_from_graph=planner.distance_from_graph,
        far_threshold=far_from_graph_threshold,
    )
    metrics.update({f"diag/{k}": v for k, v in hierarchy.items()})
    if flat:  # the low level alone chasing the goal, on the same test goals (diagnosis)
        after = eval_env.base_env.state_dict()
        eval_env.base_env.load_state_dict(before)
        flat_result = evaluate(eval_env, goal_as_waypoint(agent.low_actor), max_steps)
        eval_env.base_env.load_state_dict(after)  # the next evaluation's goals as without this one
        metrics["eval/flat_success"] = flat_result.success
        metrics["eval/flat_any_success"] = flat_result.any_success
        metrics["eval/flat_final_distance"] = flat_result.final_distance
    return metrics, result


def upside_down_steps(rollout, upside_down: Callable[[torch.Tensor], torch.Tensor]) -> torch.Tensor:
    """Whether the agent is upside down after each step of ``rollout`` (``[*B, T]`` bool), by ``upside_down`` on
    its ``("next", "observation")`` (the ant's :meth:`~torchrl_dhrl.envs.AntAgent.is_upside_down`); ``[..., -1]``
    says which episodes ended so.

    Examples:
        >>> from tensordict import TensorDict
        >>> rollout = TensorDict({"next": {"observation": torch.tensor([[[0.0], [2.0]], [[3.0], [0.5]]])}}, [2, 2])
        >>> upside_down_steps(rollout, lambda obs: obs[..., 0] > 1.0).tolist()
        [[False, True], [True, False]]
    """
    return torch.as_tensor(upside_down(rollout["next", "observation"])).reshape(rollout.shape).bool()


def plot_epoch(
    env_name: str,
    planner: GraphPlanner,
    result: EvaluationResult,
    directory: str | Path,
    *,
    epoch: int,
    env_steps: int,
    maze: MazeGeometry | None = None,
) -> Path:
    """Draws the graph, its route and the first test episode of ``result`` into
    ``directory/epoch_<epoch>.png`` (:func:`~torchrl_dhrl.recipe.plot_episode`), titled with the epoch, the
    env steps and the success rate, over ``maze`` (the geometry of a maze that is not built in); returns the file.

    Examples:
        >>> import tempfile, torch
        >>> from torchrl_dhrl.envs import make_env
        >>> from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph
        >>> from torchrl_dhrl.training import evaluate
        >>> planner = GraphPlanner(LandmarkGraph(cutoff=3.0), lambda s, g: (s - g).norm(dim=-1), 2)
        >>> env = make_env("PointMaze", num_envs=1, seed=0, eval=True, max_episode_steps=5)
        >>> still = lambda td: td.set("action", torch.zeros(1, 2))
        >>> path = plot_epoch("PointMaze", planner, evaluate(env, still, 5), tempfile.mkdtemp(), epoch=3, env_steps=80)
        >>> path.name
        'epoch_0003.png'
    """
    return plot_episode(
        env_name,
        planner,
        result.rollout,
        Path(directory) / f"epoch_{epoch:04d}.png",
        title=f"{env_name} epoch {epoch}, {env_steps} steps: success {result.success:.0%}",
        maze=maze,
    )
