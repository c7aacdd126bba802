"""recipes/diagnose_planning.py (planning_ablations: paired goals, the agent left as it was) and diagnose_observations.py."""

import sys

import pytest
import torch
from _recipe import load_recipe, recipe_config

from torchrl_dhrl.training import evaluation, planning_ablations


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    path = tmp_path_factory.mktemp("run")
    load_recipe().train(
        recipe_config("env=Reacher3D", "preset=smoke", "logger.backend=none", "plots.every_epochs=0"),
        run_dir=path,
    )
    return path


def test_variants_are_paired_and_leave_the_agent_unchanged(run_dir, monkeypatch):
    dhrl_utils = load_recipe("dhrl_utils")
    cfg, agent = dhrl_utils.agent_from_checkpoint(run_dir)
    env = dhrl_utils.build_environment(cfg, torch.device("cpu"), eval=True, agent=agent)
    assert agent.planner.has_graph
    landmarks = agent.planner.graph.landmark_goals.clone()
    radius = agent.planner.reach_radius
    state = env.base_env.state_dict()
    goals, graph_seen, subgoal_is_goal = [], [], []
    real = evaluation.evaluate

    def recording(env_, policy, steps, **kwargs):
        result = real(env_, policy, steps, **kwargs)
        goals.append(result.rollout["desired_goal"][:, 0].clone())
        graph_seen.append(agent.planner.has_graph)
        subgoal_is_goal.append(torch.equal(result.rollout["subgoal"], result.rollout["desired_goal"]))
        return result

    module = sys.modules[
        "torchrl_dhrl.training.planning_ablations"
    ]  # the package exports the function by that name
    monkeypatch.setattr(module, "evaluate", recording)
    rows = planning_ablations(agent, env, 40, reach_radii=[0.5, 2.0], repeats=2)
    assert [r["variant"] for r in rows] == [
        "as trained",
        "reach_radius=0.5",
        "reach_radius=2",
        "goal as subgoal",
        "no graph",
        "flat",
    ]
    assert all(r["episodes"] == 2 * env.batch_size.numel() for r in rows)
    for r in rows:
        assert 0.0 <= r["success"] <= r["any_success"] <= 1.0 and r["final_distance"] > 0
    # every variant meets the same two batches of goals (Reacher3D draws them at random per episode)
    assert len(goals) == 12
    for k in range(2, 12, 2):
        torch.testing.assert_close(goals[k], goals[0], rtol=0, atol=0)
        torch.testing.assert_close(goals[k + 1], goals[1], rtol=0, atol=0)
    assert not torch.equal(goals[0], goals[1])
    assert graph_seen == [True] * 8 + [False] * 2 + [True] * 2  # the graph is gone only for "no graph"
    # the planner is handed the real goal only in "goal as subgoal"
    assert subgoal_is_goal == [False] * 6 + [True] * 2 + [False] * 4
    # left as it was
    torch.testing.assert_close(agent.planner.graph.landmark_goals, landmarks, rtol=0, atol=0)
    assert agent.planner.reach_radius == radius
    after = env.base_env.state_dict()
    assert set(after) == set(state)


def test_cli_prints_a_row_per_variant(run_dir, capsys):
    rows = load_recipe("diagnose_planning").main([str(run_dir), "--reach-radii", "0.3", "--repeats", "1"])
    out = capsys.readouterr().out
    assert (
        len(rows) == 5
        and "goal as subgoal" in out
        and "no graph" in out
        and "flat" in out
        and "reach_radius=0.3" in out
    )


def test_bad_repeats(run_dir):
    dhrl_utils = load_recipe("dhrl_utils")
    cfg, agent = dhrl_utils.agent_from_checkpoint(run_dir)
    env = dhrl_utils.build_environment(cfg, torch.device("cpu"), eval=True, agent=agent)
    with pytest.raises(ValueError, match="repeats"):
        planning_ablations(agent, env, 40, repeats=0)


def test_observation_ranges_against_the_buffer(run_dir, capsys):
    """diagnose_observations: the maximum and the quantiles of |observation| over the stored states."""
    script = load_recipe("diagnose_observations")
    ranges = script.observation_ranges(run_dir, quantiles=(0.5, 1.0))
    dhrl_utils = load_recipe("dhrl_utils")
    cfg, agent = dhrl_utils.agent_from_checkpoint(run_dir)
    low_rb, _ = dhrl_utils.build_replay_buffers(cfg, agent, torch.device("cpu"))
    from torchrl_dhrl.training import load_checkpoint

    low_rb.load_state_dict(load_checkpoint(run_dir, components=("low_rb",))["low_rb"])
    obs = low_rb[:]["observation"].reshape(-1, 17).abs()
    assert ranges["entries"] == obs.shape[0] == len(low_rb)
    torch.testing.assert_close(ranges["max"], obs.max(0).values)
    torch.testing.assert_close(ranges["quantiles"][1.0], obs.max(0).values)  # all rows: fewer than SAMPLE
    torch.testing.assert_close(ranges["quantiles"][0.5], obs.quantile(0.5, dim=0))
    script.main([str(run_dir)])
    assert "stored states" in capsys.readouterr().out


def test_goal_as_subgoal_needs_the_policy_planner(run_dir):
    dhrl_utils = load_recipe("dhrl_utils")
    _, agent = dhrl_utils.agent_from_checkpoint(run_dir)
    with pytest.raises(ValueError, match="planner"):
        evaluation.goal_as_subgoal(agent.policy, agent.low_actor)
    policy = evaluation.goal_as_subgoal(agent.policy, agent.planner)
    assert [type(m).__name__ for m in policy.module][1:3] == ["TensorDictModule", "GraphPlanner"]
    assert len(agent.policy.module) == 3  # the agent's own policy is left as it was


def test_oracle_variants_plan_with_the_oracle_on_the_same_landmarks_and_restore(monkeypatch):
    from torchrl_dhrl.planner import LineOfSightDistance
    from torchrl_dhrl.training import make_agent, make_environment, obstacle_boxes

    torch.manual_seed(0)
    spec_env = make_environment("PointMaze", "cpu", num_envs=1, max_episode_steps=20)
    agent = make_agent(
        spec_env,
        "cpu",
        subgoal_low=[-2.0, -2.0],
        subgoal_high=[10.0, 10.0],
        subgoal_interval=5,
        low_num_cells=(16,),
        high_num_cells=(16,),
        max_landmarks=12,
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

    monkeypatch.setattr(sys.modules["torchrl_dhrl.training.planning_ablations"], "evaluate", recording)
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
