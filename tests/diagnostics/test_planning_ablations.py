"""planning_ablations: the oracle variants plan with the oracle on the same landmarks and restore the agent."""

import sys

import torch

from torchrl_dhrl.diagnostics import planning_ablations
from torchrl_dhrl.training import evaluation


def test_oracle_variants_plan_with_the_oracle_on_the_same_landmarks_and_restore(monkeypatch):
    from torchrl_dhrl.envs.geometry import obstacle_boxes

    from torchrl_dhrl.planner import LineOfSightDistance
    from torchrl_dhrl.recipe import make_agent, make_environment

    torch.manual_seed(0)
    spec_env = make_environment("PointMaze", "cpu", num_envs=1, max_episode_steps=20)
    agent = make_agent(
        spec_env,
        "cpu",
        high_policy={"subgoal_low": [-2.0, -2.0], "subgoal_high": [10.0, 10.0], "interval": 5, "num_cells": (16,)},
        high_critic={"num_cells": (16,)},
        low_actor={"num_cells": (16,)},
        low_critic={"num_cells": (16,)},
        graph={"max_landmarks": 12},
    )
    env = make_environment(
        "PointMaze", "cpu", num_envs=2, seed=0, eval=True, max_episode_steps=20, agent=agent
    )
    goals = torch.rand(200, 2) * 12 - 2
    states = torch.cat([goals, torch.zeros(200, 4)], -1)  # PointMaze: the achieved goal is obs[:2]
    # a stand-in for a trained critic's distance (an untrained one is about 0 everywhere: one landmark)
    agent.planner.distance = lambda s, g: (g - s[..., :2]).norm(dim=-1) / 0.15
    agent.planner.build(states, goals)
    assert agent.planner.num_landmarks == 12
    learned, saved = agent.planner.distance, agent.planner.graph.state_dict()
    oracle = LineOfSightDistance(0.15, boxes=obstacle_boxes("PointMaze"), margin=0.5)
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
        "oracle graph",
        "oracle graph, goal",
        "no graph",
        "flat",
    ]
    distances = [d for d, _ in seen]
    assert distances == [learned, learned, oracle, oracle, learned, learned]
    # the oracle graph is rebuilt on the trained graph's landmarks (FPS keeps a subset of them)
    trained = saved["landmark_goals"]
    for _, landmarks in seen[2:4]:
        assert len(landmarks) >= 2 and (torch.cdist(landmarks, trained).min(-1).values == 0).all()
    assert agent.planner.distance is learned
    for key, value in agent.planner.graph.state_dict().items():
        torch.testing.assert_close(value, saved[key], rtol=0, atol=0)
