"""planning_ablations: the oracle variants plan with the oracle on the same landmarks and restore the agent."""

import math
import sys

import pytest
import torch

from torchrl_dhrl.diagnostics import planning_ablations
from torchrl_dhrl.training import evaluation


def _pointmaze_agent_with_graph(**graph):
    """A small PointMaze agent and its evaluation env, its graph (``graph``: LandmarkGraph settings, 12
    landmarks) built with a stand-in for a trained critic's distance (an untrained one is about 0 everywhere:
    one landmark)."""
    from torchrl_dhrl.factory import make_agent, make_environment

    torch.manual_seed(0)
    spec_env = make_environment("PointMaze", "cpu", num_envs=1, max_episode_steps=20)
    agent = make_agent(
        spec_env,
        "cpu",
        high_policy={"subgoal_low": [-2.0, -2.0], "subgoal_high": [10.0, 10.0], "interval": 5, "num_cells": (16,)},
        high_critic={"num_cells": (16,)},
        low_actor={"num_cells": (16,), "relative_goal": False},
        low_critic={"num_cells": (16,)},
        graph={"max_landmarks": 12, **graph},
    )
    env = make_environment(
        "PointMaze", "cpu", num_envs=2, seed=0, eval=True, max_episode_steps=20, agent=agent
    )
    goals = torch.rand(200, 2) * 12 - 2
    states = torch.cat([goals, torch.zeros(200, 4)], -1)  # PointMaze: the achieved goal is obs[:2]
    agent.planner.distance = lambda s, g: (g - s[..., :2]).norm(dim=-1) / 0.15
    agent.planner.build(states, goals)
    return agent, env


def test_oracle_variants_plan_with_the_oracle_on_the_same_landmarks_and_restore(monkeypatch):
    from torchrl_dhrl.envs.geometry import obstacle_boxes

    from torchrl_dhrl.planner import LineOfSightDistance

    agent, env = _pointmaze_agent_with_graph()
    assert agent.planner.num_landmarks == 12
    learned, saved = agent.planner.distance, agent.planner.graph.state_dict()
    oracle = LineOfSightDistance(0.15, boxes=obstacle_boxes("PointMaze"), margin=0.5, goal_indices=(0, 1))
    seen = []
    real = evaluation.evaluate

    def recording(env_, policy, steps, **kwargs):
        seen.append((agent.planner.distance, agent.planner.landmark_goals.clone()))
        return real(env_, policy, steps, **kwargs)

    monkeypatch.setattr(sys.modules["torchrl_dhrl.diagnostics.planning_ablations"], "evaluate", recording)
    rows = planning_ablations(agent, env, 20, oracle=oracle)
    names = [r["variant"] for r in rows]
    assert names == [
        "as trained",
        "goal as subgoal",
        "unreachable=subgoal",
        "oracle graph",
        "oracle graph, goal",
        "no graph",
        "flat",
    ]
    distances = [d for d, _ in seen]
    assert distances == [learned, learned, learned, oracle, oracle, learned, learned]
    # the oracle graph is rebuilt on the trained graph's landmarks (FPS keeps a subset of them)
    trained = saved["landmark_goals"]
    for _, landmarks in seen[3:5]:
        assert len(landmarks) >= 2 and (torch.cdist(landmarks, trained).min(-1).values == 0).all()
    assert agent.planner.distance is learned
    for key, value in agent.planner.graph.state_dict().items():
        torch.testing.assert_close(value, saved[key], rtol=0, atol=0)


def test_cutoff_variants_redo_the_edges_of_the_same_landmarks_and_restore(monkeypatch):
    """Each ``cutoff=c`` variant plans on the trained landmarks and learned distances with the edges of
    DHRL's rule at ``c`` (checked by direct loops) and scipy's shortest paths over them; the cutoff and the
    graph are restored afterwards."""
    from scipy.sparse.csgraph import shortest_path

    agent, env = _pointmaze_agent_with_graph(cutoff=40.0)
    graph = agent.planner.graph
    saved = {k: v.clone() for k, v in graph.state_dict().items()}
    seen = []
    real = evaluation.evaluate

    def recording(env_, policy, steps, **kwargs):
        seen.append(
            (
                graph.cutoff,
                graph.landmark_goals.clone(),
                graph.landmark_distances.clone(),
                graph.edge_mask.clone(),
                graph.shortest_distances.clone(),
            )
        )
        return real(env_, policy, steps, **kwargs)

    monkeypatch.setattr(sys.modules["torchrl_dhrl.diagnostics.planning_ablations"], "evaluate", recording)
    rows = planning_ablations(agent, env, 20, cutoffs=[10, 60.5])
    assert [r["variant"] for r in rows] == [
        "as trained",
        "cutoff=10",
        "cutoff=60.5",
        "goal as subgoal",
        "unreachable=subgoal",
        "no graph",
        "flat",
    ]
    assert [c for c, *_ in seen[:3]] == [40.0, 10.0, 60.5] and all(c == 40.0 for c, *_ in seen[3:])
    counts = []
    for cutoff, goals, distances, mask, shortest in seen[:3]:
        torch.testing.assert_close(goals, saved["landmark_goals"], rtol=0, atol=0)
        torch.testing.assert_close(distances, saved["landmark_distances"], rtol=0, atol=0)
        d = distances.tolist()
        k = len(d)
        expected = [[False] * k for _ in range(k)]
        for i in range(k):
            nearest = min(d[i][j] for j in range(k) if j != i)
            for j in range(k):
                expected[i][j] = j != i and (d[i][j] < cutoff or d[i][j] < 1.2 * nearest)
        assert mask.tolist() == expected
        weights = torch.where(mask, distances, torch.zeros_like(distances)).double().numpy()
        reference = shortest_path(weights, method="FW", directed=True)
        torch.testing.assert_close(shortest.double(), torch.from_numpy(reference), rtol=1e-5, atol=1e-4)
        counts.append(int(mask.sum()))
    assert counts[1] < counts[0] < counts[2]  # the cutoffs change the graph: fewer edges at 10, more at 60.5
    assert graph.cutoff == 40.0
    for key, value in graph.state_dict().items():
        torch.testing.assert_close(value, saved[key], rtol=0, atol=0)


@pytest.mark.parametrize("cutoffs", [[0.0], [-5.0], [math.nan], [math.inf], [True], [30.0, "40"]])
def test_bad_cutoffs_are_refused_before_any_episode(monkeypatch, cutoffs):
    agent, env = _pointmaze_agent_with_graph(cutoff=40.0)

    def never(*args, **kwargs):
        raise AssertionError("an episode ran before the cutoffs were checked")

    monkeypatch.setattr(sys.modules["torchrl_dhrl.diagnostics.planning_ablations"], "evaluate", never)
    with pytest.raises(ValueError, match="`cutoffs` must be finite numbers > 0"):
        planning_ablations(agent, env, 20, cutoffs=cutoffs)
    assert agent.planner.graph.cutoff == 40.0
