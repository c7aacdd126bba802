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
    goals, graph_seen = [], []
    real = evaluation.evaluate

    def recording(env_, policy, steps, **kwargs):
        result = real(env_, policy, steps, **kwargs)
        goals.append(result.rollout["desired_goal"][:, 0].clone())
        graph_seen.append(agent.planner.has_graph)
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
        "no graph",
        "flat",
    ]
    assert all(r["episodes"] == 2 * env.batch_size.numel() for r in rows)
    for r in rows:
        assert 0.0 <= r["success"] <= r["any_success"] <= 1.0 and r["final_distance"] > 0
    # every variant meets the same two batches of goals (Reacher3D draws them at random per episode)
    assert len(goals) == 10
    for k in range(2, 10, 2):
        torch.testing.assert_close(goals[k], goals[0], rtol=0, atol=0)
        torch.testing.assert_close(goals[k + 1], goals[1], rtol=0, atol=0)
    assert not torch.equal(goals[0], goals[1])
    assert graph_seen == [True] * 6 + [False] * 2 + [True] * 2  # the graph is gone only for "no graph"
    # left as it was
    torch.testing.assert_close(agent.planner.graph.landmark_goals, landmarks, rtol=0, atol=0)
    assert agent.planner.reach_radius == radius
    after = env.base_env.state_dict()
    assert set(after) == set(state)


def test_cli_prints_a_row_per_variant(run_dir, capsys):
    rows = load_recipe("diagnose_planning").main([str(run_dir), "--reach-radii", "0.3", "--repeats", "1"])
    out = capsys.readouterr().out
    assert len(rows) == 4 and "no graph" in out and "flat" in out and "reach_radius=0.3" in out


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
