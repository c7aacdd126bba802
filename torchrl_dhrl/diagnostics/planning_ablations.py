"""Does the graph help? The same agent evaluated with and without its planner, on the same test goals."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torchrl.envs import EnvBase

from torchrl_dhrl.training import evaluate, goal_as_subgoal, goal_as_waypoint

from ..planner import TemporalDistance

__all__ = ["planning_ablations"]


@torch.no_grad()
def planning_ablations(
    agent: Any,
    env: EnvBase,
    max_steps: int,
    *,
    reach_radii: Sequence[float] = (),
    cutoffs: Sequence[float] = (),
    repeats: int = 1,
    oracle: TemporalDistance | None = None,
) -> list[dict]:
    """Evaluates ``agent`` as trained and with parts of its planning switched off, at evaluation time only.

    The variants, each on the same ``repeats`` batches of test episodes (``env``'s state is restored before
    each variant, so every variant meets the same goals and start states):

    * ``"as trained"``: the full agent (high level, graph waypoints, low level);
    * ``"reach_radius=r"`` for each ``r`` of ``reach_radii``: waypoints count as reached within ``r``;
    * ``"cutoff=c"`` for each ``c`` of ``cutoffs``: the graph's cutoff set to ``c`` (steps), its edges redone
      from the same landmarks and the same learned distances, and a plan's entry, exit and direct edges (state
      to landmark, landmark to subgoal, state to subgoal) allowed up to ``c``: whether the learned edges are
      merely too long for the cutoff, or missing;
    * ``"goal as subgoal"``: the high level bypassed, the graph planning to the real goal
      (:func:`goal_as_subgoal`; replans keep the high level's ``c_h`` cadence);
    * ``"unreachable=<rule>"``: the graph's other rule for subgoals it cannot reach
      (:attr:`~torchrl_dhrl.planner.LandmarkGraph.unreachable`: ``"subgoal"``, straight for them, for an agent
      trained with the reference's ``"nearest_landmark"``, and the other way round): whether the fallback's
      landmark leads the agent astray;
    * with ``oracle``: ``"oracle graph"`` and ``"oracle graph, goal"``, the agent as trained and the goal as
      subgoal with the graph rebuilt on the same landmarks with the oracle distance (FPS and edges redone,
      queries answered by the oracle): the learned distance's share of a failure;
    * ``"no graph"``: the high level and the low level, the planner passing the subgoal through;
    * ``"flat"``: the low level alone chasing the real goal (:func:`goal_as_waypoint`).

    A variant far better than ``"as trained"`` names the part that leads the agent astray (the graph's
    waypoints, the high level's subgoals); ``"goal as subgoal"`` failing too says that the graph cannot
    route to the goal either (e.g. a goal beyond the explored region: exploration, not the high level). The
    agent and ``env`` are left as they were (graph, cutoff, distance, radius, unreachable rule and the env's state
    restored).

    Args:
        agent (DHRLAgent): the agent (e.g. a checkpoint's, rebuilt by ``recipes/dhrl_utils.py``).
        env (EnvBase): the evaluation env with the agent's primers (``make_environment(..., eval=True, agent=...)``).
        max_steps (int): steps per episode.

    Keyword Args:
        reach_radii (sequence of float): waypoint radii to try. Defaults to none.
        cutoffs (sequence of float): graph cutoffs to try (steps, ``> 0``). Defaults to none.
        repeats (int): batches of ``env``'s episodes per variant. Defaults to ``1``.
        oracle (TemporalDistance, optional): a reference distance (e.g. the maze's
            :class:`~torchrl_dhrl.planner.LineOfSightDistance`) for the two oracle variants. Defaults to none.

    Returns:
        one dict per variant: ``variant``, ``episodes``, ``success`` (final state), ``any_success``,
        ``final_distance`` (means over the episodes).

    Examples:
        >>> import torch
        >>> from torchrl_dhrl.factory import make_agent, make_environment
        >>> spec_env = make_environment("PointMaze", "cpu", num_envs=1, max_episode_steps=20)
        >>> agent = make_agent(spec_env, "cpu", goal_indices=[0, 1], high_policy={"subgoal_low": [-2.0, -2.0], "subgoal_high": [10.0, 10.0], "interval": 5,
        ...     "num_cells": (16,)}, high_critic={"num_cells": (16,)}, low_actor={"num_cells": (16,)},
        ...     low_critic={"num_cells": (16,)}, graph={"max_landmarks": 8})
        >>> env = make_environment("PointMaze", "cpu", num_envs=2, seed=0, eval=True, max_episode_steps=20,
        ...     agent=agent)
        >>> rows = planning_ablations(agent, env, 20, reach_radii=[1.0])
        >>> [row["variant"] for row in rows], rows[0]["episodes"]
        (['as trained', 'reach_radius=1', 'goal as subgoal', 'unreachable=subgoal', 'no graph', 'flat'], 2)
    """
    if repeats < 1:
        raise ValueError(f"`repeats` must be >= 1, got {repeats}.")
    bad = [
        c
        for c in cutoffs
        if isinstance(c, bool) or not (isinstance(c, (int, float)) and math.isfinite(c) and c > 0)
    ]
    if bad:
        raise ValueError(f"`cutoffs` must be finite numbers > 0 (steps), got {bad}.")
    base = env.base_env if hasattr(env, "base_env") else env
    start = base.state_dict()
    planner, graph = agent.planner, agent.planner.graph
    radius, distance, cutoff, unreachable = planner.reach_radius, planner.distance, graph.cutoff, graph.unreachable
    other_rule = "subgoal" if unreachable == "nearest_landmark" else "nearest_landmark"
    saved_graph = graph.state_dict()
    to_goal = goal_as_subgoal(agent.policy, planner)

    def oracle_graph() -> None:  # the same landmarks, FPS and edges redone with the oracle distance
        landmark_states, landmark_goals = planner.landmark_states.clone(), planner.landmark_goals.clone()
        planner.distance = oracle
        planner.build(landmark_states, landmark_goals)

    def set_radius(r: float):
        def setup() -> None:
            planner.reach_radius = r

        return setup

    def set_cutoff(c: float):
        def setup() -> None:  # the same landmarks and learned distances, edges redone at the new cutoff
            graph.cutoff = c
            graph.redo_edges()

        return setup

    def set_unreachable() -> None:
        graph.unreachable = other_rule

    def restore() -> None:
        planner.reach_radius, planner.distance, graph.cutoff = radius, distance, cutoff
        graph.unreachable = unreachable
        graph.load_state_dict(saved_graph)

    variants = [("as trained", agent.policy, None)]
    variants += [(f"reach_radius={r:g}", agent.policy, set_radius(float(r))) for r in reach_radii]
    variants += [(f"cutoff={c:g}", agent.policy, set_cutoff(float(c))) for c in cutoffs]
    variants += [("goal as subgoal", to_goal, None), (f"unreachable={other_rule}", agent.policy, set_unreachable)]
    if oracle is not None:
        variants += [
            ("oracle graph", agent.policy, oracle_graph),
            ("oracle graph, goal", to_goal, oracle_graph),
        ]
    variants += [("no graph", agent.policy, graph.clear), ("flat", goal_as_waypoint(agent.low_actor), None)]
    rows = []
    try:
        for name, policy, setup in variants:
            base.load_state_dict(start)
            if setup is not None:
                setup()
            results = [evaluate(env, policy, max_steps) for _ in range(repeats)]
            episodes = repeats * int(math.prod(env.batch_size))
            rows.append(
                {
                    "variant": name,
                    "episodes": episodes,
                    "success": sum(r.success for r in results) / repeats,
                    "any_success": sum(r.any_success for r in results) / repeats,
                    "final_distance": sum(r.final_distance for r in results) / repeats,
                }
            )
            if setup is not None:
                restore()
    finally:
        restore()
        base.load_state_dict(start)
    return rows
