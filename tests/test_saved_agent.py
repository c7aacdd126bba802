"""The saved agent of a run (``<run dir>/agent``, :func:`~torchrl_dhrl.recipe.save_agent`): written by the recipe
with each checkpoint (and on SIGTERM), small, the same agent as the checkpoint's; re-evaluated by
``recipes/evaluate.py`` (success in whole episodes, as a direct evaluation with the same seeds); written
atomically."""

from __future__ import annotations

import math
import os
import re
import shutil
import signal

import numpy as np
import pytest
import torch
import yaml
from _recipe import load_recipe, recipe_config
from torch.utils._pytree import tree_flatten_with_path
from torchrl.checkpoint import Checkpoint, JSONCheckpointAdapter, StateDictCheckpointAdapter
from torchrl_dhrl.envs.simulation import GoalSimulation

from torchrl_dhrl.planner import ConnectedEdgeRule, CutoffEdgeRule, LandmarkGraph
from torchrl_dhrl.recipe import (
    AGENT_COMPONENTS,
    AGENT_NAME,
    CHECKPOINT_NAME,
    CheckpointError,
    ConfigError,
    load_checkpoint,
    recover_checkpoint,
    save_agent,
)
from torchrl_dhrl.training import evaluate

pytestmark = pytest.mark.recipe

#: Two epochs of the smoke preset on Reacher3D (random test goals: the episodes differ), the graph built in the
#: second; the test episodes in batches of 10 envs.
OVERRIDES = (
    "env=Reacher3D",
    "preset=smoke",
    "total_steps=160",
    "schedule.eval_episodes=10",
    "schedule.eval_flat=false",
    "logger.backend=none",
    "plots.every_epochs=0",
)
#: A success radius (m) at which this tiny agent succeeds in some test episodes and fails in others (0.25 as trained).
WIDE_SUCCESS = 0.85


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    path = tmp_path_factory.mktemp("run")
    load_recipe().train(recipe_config(*OVERRIDES), run_dir=path)
    return path


def _size(path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def _assert_same_states(a, b) -> None:
    """Equal leaf for leaf: the same keys, tensors of the same dtype and values, the same other values."""
    (leaves_a, _), (leaves_b, _) = tree_flatten_with_path(a), tree_flatten_with_path(b)
    assert [k for k, _ in leaves_a] == [k for k, _ in leaves_b]
    for (key, x), (_, y) in zip(leaves_a, leaves_b, strict=True):
        if torch.is_tensor(x):
            torch.testing.assert_close(x, y, rtol=0, atol=0, equal_nan=True, msg=str(key))  # dtype too
        else:
            assert x == y or (x != x and y != y), key  # NaN metrics in the history


def test_the_recipe_writes_a_small_saved_agent_equal_to_the_checkpoints(run_dir, tmp_path):
    agent_dir = run_dir / AGENT_NAME
    assert sorted(load_checkpoint(agent_dir)) == sorted(AGENT_COMPONENTS)
    assert 2 * _size(agent_dir) < _size(run_dir / CHECKPOINT_NAME)  # no buffers, envs, optimisers
    full = load_checkpoint(run_dir, components=AGENT_COMPONENTS)  # a run directory: its full checkpoint
    saved = load_checkpoint(agent_dir)
    for name in AGENT_COMPONENTS:
        _assert_same_states(saved[name], full[name])
    assert saved["counters"]["env_steps"] == 160
    dhrl_utils = load_recipe("dhrl_utils")
    _, from_saved = dhrl_utils.agent_from_checkpoint(agent_dir)
    _, from_full = dhrl_utils.agent_from_checkpoint(run_dir / CHECKPOINT_NAME)
    assert from_saved.planner.has_graph and from_saved.planner.num_landmarks > 0
    _assert_same_states(from_saved.state_dict(), from_full.state_dict())
    # from the checkpoint on disk (a run saved before the agent was): the same states
    copy = save_agent(run_dir, out=tmp_path / AGENT_NAME)
    _assert_same_states(load_checkpoint(copy), saved)
    # a run directory kept with its saved agent only (results committed without the checkpoint)
    kept = tmp_path / "kept"
    shutil.copytree(agent_dir, kept / AGENT_NAME)
    _, from_kept = dhrl_utils.agent_from_checkpoint(kept)
    _assert_same_states(from_kept.state_dict(), from_full.state_dict())


def _wide_success(monkeypatch) -> None:
    """Success within WIDE_SUCCESS of the goal, for every env built from now on (the reward is left as it is)."""
    real = GoalSimulation.evaluate

    def evaluate_wide(self):
        reward, _ = real(self)
        return reward, np.linalg.norm(self.achieved_goal - self.desired_goal, axis=-1) <= WIDE_SUCCESS

    monkeypatch.setattr(GoalSimulation, "evaluate", evaluate_wide)


def test_evaluate_script_counts_whole_episodes_as_a_direct_evaluation(run_dir, tmp_path, monkeypatch):
    _wide_success(monkeypatch)
    record = load_recipe("evaluate").main([str(run_dir / AGENT_NAME), "--episodes", "20", "--seed", "3"])
    written = yaml.safe_load((run_dir / "final_eval.yaml").read_text())
    assert written == record
    assert written["episodes"] == 20 and isinstance(written["successes"], int)
    assert written["success"] == written["successes"] / 20 and written["env_steps"] == 160
    assert written["seed"] == 3 and "--episodes 20" in written["command"]
    assert {"commit", "modified"} <= set(written["code"]) and written["versions"]["torch"] and written["date"]
    # independently: the full checkpoint's agent, the recipe's test env, batch k of 10 envs seeded with 3 + k
    dhrl_utils = load_recipe("dhrl_utils")
    cfg, agent = dhrl_utils.agent_from_checkpoint(run_dir / CHECKPOINT_NAME)
    env = dhrl_utils.build_environment(cfg, torch.device("cpu"), eval=True, agent=agent)
    assert env.batch_size.numel() == cfg["schedule"]["eval_episodes"] == 10
    rates = []
    for k in range(2):
        dhrl_utils.seed_everything(3 + k, env)
        rates.append(evaluate(env, agent.policy, env.max_episode_steps).success)
    successes = round(sum(rates) * 10)  # the rates are float32 means of 10 episodes
    assert math.isclose(sum(rates) * 10, successes, abs_tol=1e-4)
    assert 0 < successes < 20  # a count that can be wrong
    assert written["successes"] == successes
    # at least --episodes, in whole batches; the low level alone recorded with --flat; --out
    out = tmp_path / "eval.yaml"
    flat = load_recipe("evaluate").main([str(run_dir), "--episodes", "1", "--flat", "--out", str(out)])
    assert (
        flat["episodes"] == 10 and isinstance(flat["flat_successes"], int) and 0 <= flat["flat_success"] <= 1
    )
    assert flat["agent"] == str((run_dir / CHECKPOINT_NAME).resolve())  # a run directory: its checkpoint
    assert yaml.safe_load(out.read_text()) == flat


def _final_first_entries(run_dir, changes=None) -> torch.Tensor:
    """Independently of the script: the first observation entry at the end of each of 20 test episodes of the run's
    agent (with ``changes``), two batches of the recipe's test env seeded with 5 and 6."""
    dhrl_utils = load_recipe("dhrl_utils")
    cfg, agent = dhrl_utils.agent_from_checkpoint(run_dir / CHECKPOINT_NAME, changes=changes)
    env = dhrl_utils.build_environment(cfg, torch.device("cpu"), eval=True, agent=agent)
    final = []
    for k in range(2):
        dhrl_utils.seed_everything(5 + k, env)
        final.append(evaluate(env, agent.policy, env.max_episode_steps).rollout["next", "observation"][:, -1, 0])
    return torch.cat(final)


def test_evaluate_script_counts_the_test_episodes_that_end_upside_down(run_dir, tmp_path, monkeypatch):
    """On the ant mazes the record counts the test episodes that ended with the ant on its back: here with a stand-in
    test on this Reacher3D run (its first observation entry past the median of the episodes' final ones), against
    the final observations of the same episodes computed independently; other envs record no count."""
    final = _final_first_entries(run_dir)
    threshold = final.median()
    script = load_recipe("evaluate")
    monkeypatch.setattr(script, "upside_down_test", lambda cfg: lambda obs: obs[..., 0] > threshold)
    record = script.main([str(run_dir / AGENT_NAME), "--episodes", "20", "--seed", "5", "--out", str(tmp_path / "a.yaml")])
    assert record["ended_upside_down"] == int((final > threshold).sum()) and 0 < record["ended_upside_down"] < 20
    # a variant's episodes counted the same way: the same agent acting otherwise ends elsewhere
    argv = [str(run_dir / AGENT_NAME), "--episodes", "20", "--seed", "5", "--out", str(tmp_path / "v.yaml")]
    varied = script.main([*argv, "--variant", "high.critic_candidates=4"])
    assert varied["ended_upside_down"] == record["ended_upside_down"]
    final = _final_first_entries(run_dir, {"high.critic_candidates": 4})
    assert varied["variants"][0]["ended_upside_down"] == int((final > threshold).sum())
    monkeypatch.setattr(script, "upside_down_test", lambda cfg: None)
    record = script.main([str(run_dir / AGENT_NAME), "--episodes", "1", "--out", str(tmp_path / "b.yaml")])
    assert "ended_upside_down" not in record


def _final_successes(cfg, agent, batches: int, seed: int) -> torch.Tensor:
    """Independently of the script: each episode's final success, batch k of the recipe's test env seeded
    with seed + k."""
    dhrl_utils = load_recipe("dhrl_utils")
    env = dhrl_utils.build_environment(cfg, torch.device("cpu"), eval=True, agent=agent)
    out = []
    for k in range(batches):
        dhrl_utils.seed_everything(seed + k, env)
        rollout = evaluate(env, agent.policy, env.max_episode_steps).rollout
        out.append(rollout["next", "is_success"].reshape(*rollout.shape, -1).any(-1)[:, -1])
    return torch.cat(out)


def test_evaluate_script_compares_test_time_variants_on_the_same_episodes(run_dir, monkeypatch):
    """``--variant``: the same trained agent with keys no checkpointed state holds changed, on the same episodes
    as the agent as trained; the counts paired episode by episode (an unchanged variant differs in none), the
    graph's edges redone with a changed edge rule; the protocol's final_eval.yaml left alone."""
    _wide_success(monkeypatch)
    final = run_dir / "final_eval.yaml"
    before = final.read_bytes() if final.exists() else None
    critic = ["high.critic_candidates=8", "high.candidate_noise=0.5", "high.landmark_candidates=true"]
    record = load_recipe("evaluate").main(
        [
            str(run_dir / AGENT_NAME),
            "--episodes",
            "20",
            "--seed",
            "3",
            "--variant",
            "high.critic_candidates=0",
            "--variant",
            *critic,
            "--variant",
            "planner.edge_rule=connected",
        ]
    )
    assert (final.read_bytes() if final.exists() else None) == before
    assert yaml.safe_load((run_dir / "variants_eval.yaml").read_text()) == record
    same, guided, connected = record["variants"]
    assert same["changes"] == {"high.critic_candidates": 0}
    assert guided["changes"] == {
        "high.critic_candidates": 8,
        "high.candidate_noise": 0.5,
        "high.landmark_candidates": True,
    }
    assert 0 < record["successes"] < 20  # outcomes that pairing the episodes wrongly would change
    assert (same["successes"], same["only_variant"], same["only_reference"], same["p_value"]) == (
        record["successes"],
        0,
        0,
        1.0,
    )
    # the critic-guided variant, independently: its agent rebuilt from the checkpoint with the keys changed
    dhrl_utils = load_recipe("dhrl_utils")
    cfg, agent = dhrl_utils.agent_from_checkpoint(run_dir / AGENT_NAME)
    trained = _final_successes(cfg, agent, 2, 3)
    changed = dict(cfg)
    changed["high"] = cfg["high"] | {
        "critic_candidates": 8,
        "candidate_noise": 0.5,
        "landmark_candidates": True,
    }
    variant_agent = dhrl_utils.build_agent(changed, torch.device("cpu"))
    variant_agent.load_state_dict(agent.state_dict())
    assert variant_agent.high_policy.selector is not None and agent.high_policy.selector is None
    outcome = _final_successes(changed, variant_agent, 2, 3)
    assert int(trained.sum()) == record["successes"]
    assert (guided["successes"], guided["only_variant"], guided["only_reference"]) == (
        int(outcome.sum()),
        int((outcome & ~trained).sum()),
        int((trained & ~outcome).sum()),
    )
    assert guided["success"] == guided["successes"] / 20 and 0 <= guided["p_value"] <= 1
    assert connected["changes"] == {"planner.edge_rule": "connected"} and 0 <= connected["successes"] <= 20
    # the record as recipes/variants_summary.py reads it: one run pooled is the run itself
    rows = load_recipe("variants_summary").summarize([run_dir])
    assert [row["variant"] for row in rows] == [
        "high.critic_candidates=0",
        "high.candidate_noise=0.5 high.critic_candidates=8 high.landmark_candidates=true",
        "planner.edge_rule=connected",
    ]
    for row, variant in zip(rows, record["variants"], strict=True):
        assert (row["pooled"].variant, row["pooled"].only_variant, row["pooled"].only_reference) == (
            variant["successes"], variant["only_variant"], variant["only_reference"]
        )
        assert row["pooled"].p_value == pytest.approx(variant["p_value"])


def test_a_changed_edge_rule_redoes_the_loaded_graphs_edges(run_dir, monkeypatch):
    """A saved graph cut in two by the cutoff (its distances across set above it, its edges the cutoff rule's,
    as saved): rebuilt as saved it stays cut; with ``planner.edge_rule=connected`` its edges are
    ConnectedEdgeRule's on the same landmarks and distances, and every landmark reaches every other."""
    dhrl_utils = load_recipe("dhrl_utils")
    real_load = dhrl_utils.load_checkpoint

    def load_cut_graph(*args, **kwargs):
        state = real_load(*args, **kwargs)
        agent = state["agent"]
        distances = agent["planner"]["graph.landmark_distances"]
        num, cutoff = distances.shape[0], state["config"]["planner"]["cutoff"]
        half = torch.arange(num) < num // 2
        across = half[:, None] != half[None, :]
        ties = torch.arange(num)[:, None] + torch.arange(num)[None, :]  # distinct lengths across, some tied
        cut = torch.where(across, 2 * cutoff + 0.5 * (ties % 3), torch.ones(num, num)).fill_diagonal_(0.0)
        saved = LandmarkGraph(cutoff=cutoff).set_distance_matrix(  # the graph the cutoff rule saves
            agent["planner"]["graph.landmark_states"], agent["planner"]["graph.landmark_goals"], cut
        )
        for name, value in saved.state_dict().items():
            if name in ("landmark_distances", "edge_weights", "shortest_distances", "next_hop", "hop_counts"):
                agent["planner"][f"graph.{name}"] = value
        return state

    monkeypatch.setattr(dhrl_utils, "load_checkpoint", load_cut_graph)
    _, saved = dhrl_utils.agent_from_checkpoint(run_dir / AGENT_NAME)
    _, rewired = dhrl_utils.agent_from_checkpoint(
        run_dir / AGENT_NAME, changes={"planner.edge_rule": "connected"}
    )
    old, graph = saved.planner.graph, rewired.planner.graph
    assert isinstance(graph.edge_rule, ConnectedEdgeRule) and isinstance(old.edge_rule, CutoffEdgeRule)
    torch.testing.assert_close(graph.landmark_distances, old.landmark_distances, rtol=0, atol=0)
    torch.testing.assert_close(graph.landmark_goals, old.landmark_goals, rtol=0, atol=0)
    off_diag = graph.landmark_distances.clone().fill_diagonal_(math.inf)
    connected_edges = ConnectedEdgeRule()(off_diag, graph.cutoff).fill_diagonal_(False)
    assert torch.equal(graph.edge_mask, connected_edges)
    assert torch.equal(old.edge_mask, CutoffEdgeRule()(off_diag, old.cutoff).fill_diagonal_(False))
    assert not torch.equal(graph.edge_mask, old.edge_mask)
    assert graph.shortest_distances.isfinite().all() and not old.shortest_distances.isfinite().all()


def test_the_unreachable_rule_reaches_the_graph_and_is_a_test_time_switch(run_dir, tmp_path):
    """``planner.unreachable``: the recipe's graph takes it, a configuration saved before the key rebuilds the
    reference's fallback, a saved agent takes another rule at load (the same graph state), and a bad value stops
    the recipe before its run directory exists."""
    from torchrl_dhrl.recipe import ConfigError

    dhrl_utils = load_recipe("dhrl_utils")
    cfg, saved = dhrl_utils.agent_from_checkpoint(run_dir / AGENT_NAME)
    assert cfg["planner"]["unreachable"] == "nearest_landmark" == saved.planner.graph.unreachable
    _, switched = dhrl_utils.agent_from_checkpoint(run_dir / AGENT_NAME, changes={"planner.unreachable": "subgoal"})
    assert switched.planner.graph.unreachable == "subgoal"
    for name in ("landmark_goals", "landmark_distances", "edge_weights", "shortest_distances", "next_hop"):
        assert torch.equal(getattr(switched.planner.graph, name), getattr(saved.planner.graph, name)), name
    del cfg["planner"]["unreachable"]
    assert dhrl_utils.build_agent(cfg, torch.device("cpu")).planner.graph.unreachable == "nearest_landmark"
    bad = recipe_config("env=PointMaze", "preset=smoke", "device=cpu", "planner.unreachable=nearest")
    message = r"^`planner.unreachable` must be one of \('nearest_landmark', 'subgoal'\), got 'nearest'.$"
    with pytest.raises(ConfigError, match=message):
        load_recipe().train(bad, run_dir=tmp_path / "run")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    "variant, error",
    [
        (
            ["high.actor_lr=0.1"],
            r"`high\.actor_lr` cannot change on a trained agent.*accepted: .*high\.critic_candidates",
        ),
        (["high.critic_candidates=-1"], r"high\.critic_candidates"),
        (["planner.edge_rule=shortest"], r"planner\.edge_rule"),
        (["high.critic_candidate=8"], r"`high\.critic_candidate` is not a key of the saved configuration"),
    ],
)
def test_evaluate_script_refuses_a_bad_variant_before_any_episode(run_dir, monkeypatch, capsys, variant, error):
    """One line on stderr naming the key and what is accepted (exit status 2), before any episode."""
    evaluate_script = load_recipe("evaluate")

    def no_episodes(*args, **kwargs):
        raise AssertionError("an episode ran before the variants were checked")

    monkeypatch.setattr(evaluate_script, "episode_outcomes", no_episodes)
    with pytest.raises(SystemExit) as refused:
        evaluate_script.main([str(run_dir / AGENT_NAME), "--episodes", "10", "--variant", *variant])
    message = capsys.readouterr().err.strip().splitlines()[-1]
    assert refused.value.code == 2 and re.search(r"error: --variant: `?" + error.removeprefix("`"), message)
    with pytest.raises(SystemExit):  # not KEY=VALUE
        evaluate_script.main([str(run_dir / AGENT_NAME), "--variant", "high.critic_candidates"])


def test_sigterm_writes_the_saved_agent_with_the_checkpoint(tmp_path, monkeypatch):
    recipe = load_recipe()
    real_end_epoch = recipe.end_epoch

    def end_epoch_then_sigterm(*args, **kwargs):
        metrics = real_end_epoch(*args, **kwargs)
        os.kill(os.getpid(), signal.SIGTERM)  # GracefulStop: stop after this batch, with a checkpoint
        return metrics

    monkeypatch.setattr(recipe, "end_epoch", end_epoch_then_sigterm)
    with pytest.raises(KeyboardInterrupt):
        # no checkpoint of the schedule before the stop
        recipe.train(recipe_config(*OVERRIDES, "checkpoint.every_epochs=100"), run_dir=tmp_path)
    saved, full = (
        load_checkpoint(tmp_path / AGENT_NAME),
        load_checkpoint(tmp_path, components=AGENT_COMPONENTS),
    )
    assert saved["counters"]["env_steps"] == full["counters"]["env_steps"] == 80
    _assert_same_states(saved["agent"], full["agent"])
    # a saved agent does not resume
    with pytest.raises(ConfigError, match="low_rb"):
        load_recipe("dhrl_utils").start_up(
            recipe_config(*OVERRIDES, f"resume={tmp_path / AGENT_NAME}"), tmp_path / "resumed", write=False
        )


def test_a_failing_save_leaves_the_previous_saved_agent(run_dir, tmp_path, monkeypatch):
    run = tmp_path / "run"
    shutil.copytree(run_dir / CHECKPOINT_NAME, run / CHECKPOINT_NAME)
    path = save_agent(run)
    assert path == run / AGENT_NAME
    before = {p.relative_to(path): p.read_bytes() for p in path.rglob("*") if p.is_file()}

    def crash(self, component, path, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(StateDictCheckpointAdapter, "save", crash)
    with pytest.raises(RuntimeError, match="disk full"):
        save_agent(run)
    monkeypatch.undo()
    assert {p.relative_to(path): p.read_bytes() for p in path.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in run.iterdir()) == [AGENT_NAME, CHECKPOINT_NAME]  # no stage left behind
    # killed between its two renames: the next start puts it back
    os.replace(path, run / f".{AGENT_NAME}.backup-feed")
    assert "saved agent" in recover_checkpoint(run)
    assert sorted(p.name for p in run.iterdir()) == [AGENT_NAME, CHECKPOINT_NAME]
    _assert_same_states(load_checkpoint(path), load_checkpoint(run, components=AGENT_COMPONENTS))
    registry = Checkpoint()
    registry.register("config", {"seed": 0}, adapter=JSONCheckpointAdapter())
    with pytest.raises(ValueError, match="`out` is required"):
        save_agent(registry)
    with pytest.raises(ValueError, match="no 'agent' component"):
        save_agent(registry, tmp_path / AGENT_NAME)
    with pytest.raises(CheckpointError, match="lacks 'agent'"):  # a checkpoint without the agent
        save_agent(registry.save(tmp_path / "config_only"))
