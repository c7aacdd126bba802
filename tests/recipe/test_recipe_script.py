"""Smoke tests of ``recipes/dhrl_antmaze.py``: every phase on every maze with a tiny config, exact resume,
ablation switches and the command line."""

import importlib.metadata
import os
import shlex
import shutil
import signal
import subprocess
import sys
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
import torch
from _recipe import RECIPES, TIMING_COLUMNS, load_recipe, metrics_rows, recipe_config
from tensordict import TensorDict
from torchrl_dhrl.envs import ENV_NAMES

import torchrl_dhrl
from torchrl_dhrl.recipe import ConfigError, code_and_machine, load_checkpoint, read_provenance
from torchrl_dhrl.training import AdaptiveThreads

pytestmark = pytest.mark.recipe

recipe = load_recipe()

SMOKE = ("preset=smoke", "logger.backend=csv")


@pytest.mark.parametrize("env", ENV_NAMES)
def test_smoke_every_phase(env, tmp_path):
    """Warm-up (2 episodes), vanilla HRL (1 epoch), graph rebuilds, evaluations, checkpoints and pictures."""
    torch.manual_seed(0)
    cfg = recipe_config(f"env={env}", *SMOKE)
    summary = recipe.train(cfg, run_dir=tmp_path)
    rows = metrics_rows(tmp_path)
    # 480 steps of 2 envs x 40-step episodes = 6 batches, 2 episodes per epoch -> 6 epochs
    assert [int(r["env_steps"]) for r in rows] == [80 * k for k in range(1, 7)]
    landmarks = [int(r["graph/landmarks"]) for r in rows]
    assert landmarks[0] == 0  # warm-up epoch: no graph
    assert all(2 <= n <= 12 for n in landmarks[1:])  # graph from epoch 2 on, rebuilt every epoch
    assert all(r["graph/build_s"] for r in rows[1:])
    for i, r in enumerate(rows):
        assert 0.0 <= float(r["eval/success"]) <= float(r["eval/any_success"]) <= 1.0
        for key in ("low/loss_policy_qvalue", "low/loss_graph_qvalue", "high/loss_qvalue"):
            if i == 0:  # the warm-up epoch: no update (as the reference), hence no loss
                assert r[key] == ""
            else:
                assert torch.isfinite(torch.tensor(float(r[key])))
    assert summary["eval/success"] == float(rows[-1]["eval/success"])
    assert len(list((tmp_path / "episodes").glob("epoch_*.png"))) == 6
    assert (tmp_path / "success_curve.png").stat().st_size > 1000
    assert (tmp_path / "logs" / f"dhrl_{env}_seed0" / "scalars" / "eval" / "success.csv").exists()
    state = load_checkpoint(tmp_path / "checkpoint")
    assert state["counters"]["env_steps"] == 480 and state["counters"]["graph_builds"] == 5
    assert len(state["low_rb"]["_storage"]["_storage"]["observation"]) > 0


def test_default_threads_follow_the_load(tmp_path, monkeypatch):
    """``threads=null``: the loop polls :class:`AdaptiveThreads` after each training batch's updates, and
    ``time/threads`` logs the count it keeps."""
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    polls = []

    def poll(self):
        polls.append(self)
        self.threads = 1  # as if another process had taken a core
        torch.set_num_threads(1)
        return 1

    monkeypatch.setattr(AdaptiveThreads, "poll", poll)
    before = torch.get_num_threads()
    try:
        recipe.train(recipe_config("env=PointMaze", *SMOKE, "plots.every_epochs=0"), run_dir=tmp_path)
    finally:
        torch.set_num_threads(before)
    assert len(polls) == 6 and len({id(p) for p in polls}) == 1  # 6 batches, one policy for the run
    assert [r["time/threads"] for r in metrics_rows(tmp_path)] == ["1"] * 6


def _flat(state, prefix=""):
    out = {}
    for key, value in state.items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{key}."))
        elif isinstance(value, torch.Tensor):
            out[f"{prefix}{key}"] = value
    return out


def test_resume_continues_exactly(tmp_path):
    """K steps, checkpoint, resume, K more == 2K straight (CPU, fixed seed)."""
    overrides = ("env=PointMaze", *SMOKE, "plots.every_epochs=0", "device=cpu")
    straight = tmp_path / "straight"
    recipe.train(recipe_config(*overrides, "total_steps=480"), run_dir=straight)
    halves = tmp_path / "halves"
    recipe.train(recipe_config(*overrides, "total_steps=240"), run_dir=halves)
    recipe.train(recipe_config(*overrides, "total_steps=480", f"resume={halves}"), run_dir=halves)
    a, b = load_checkpoint(straight / "checkpoint"), load_checkpoint(halves / "checkpoint")
    assert {k: v for k, v in a["counters"].items() if k != "wall_s"} == {
        k: v for k, v in b["counters"].items() if k != "wall_s"
    }
    flat_a, flat_b = _flat(a["agent"]), _flat(b["agent"])
    assert flat_a.keys() == flat_b.keys()
    for key in flat_a:
        torch.testing.assert_close(flat_a[key], flat_b[key], rtol=0, atol=0, msg=key)
    untimed = metrics_rows(straight, drop=TIMING_COLUMNS)
    assert untimed == metrics_rows(halves, drop=TIMING_COLUMNS)  # losses, success, graph: all identical
    for row in metrics_rows(halves)[
        3:
    ]:  # after the resume the rate counts this process's steps and time only
        busy = float(row["time/collect_s"]) + float(row["time/update_s"])
        rate = (int(row["env_steps"]) - 240) / busy
        assert float(row["env_steps_per_s"]) == pytest.approx(rate, rel=1e-4)
    # the run directory records each start: the resume appended to the first, what they ran on and with
    assert [s["env_steps"] for s in read_provenance(straight)] == [0]
    starts = read_provenance(halves)
    assert [s["env_steps"] for s in starts] == [0, 240]
    assert datetime.fromisoformat(starts[0]["started"]) <= datetime.fromisoformat(starts[1]["started"])
    repo = Path(__file__).resolve().parents[2]
    git = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True, text=True)
    commit = git.stdout.strip() if (repo / ".git").exists() and git.returncode == 0 else None
    for start in starts:
        assert start["precision"] == {"update_dtype": "float32", "planner.build_dtype": "float32"}
        assert start["code"]["commit"] == commit
        assert start["code"]["version"] == torchrl_dhrl.__version__
        assert start["versions"]["torch"] == torch.__version__
        assert start["device"] == "cpu" and start["threads"] >= 1
        assert start["machine"]["cores"] == os.cpu_count() and start["machine"]["cpu"]
        # the command this process was started with, as a shell would split it again
        assert shlex.split(start["command"]) == [Path(sys.executable).name, *sys.argv]


def test_provenance_version_is_the_imported_code_s(monkeypatch):
    """The version a start records is the imported package's, not the installed distribution's metadata (an
    editable install leaves it stale; a ``PYTHONPATH`` snapshot of other code bypasses it)."""
    monkeypatch.setattr(importlib.metadata, "version", lambda name: "0.0.0-stale")
    record = code_and_machine("cpu")
    assert record["code"]["version"] == torchrl_dhrl.__version__
    assert record["versions"]["torch"] == "0.0.0-stale"  # the other packages still from their metadata


def test_a_0_2_0_checkpoint_resumes_exactly(tmp_path):
    """A 0.2.0 ``checkpoint.pt`` (one ``torch.save`` dictionary, with the collector's copy of the policy and the
    carrier apart) resumes to the straight run's parameters, bit for bit; new checkpoints hold the policy once."""
    overrides = ("env=PointMaze", *SMOKE, "plots.every_epochs=0", "device=cpu")
    straight, halves, old = tmp_path / "straight", tmp_path / "halves", tmp_path / "old"
    recipe.train(recipe_config(*overrides, "total_steps=480"), run_dir=straight)
    recipe.train(recipe_config(*overrides, "total_steps=240"), run_dir=halves)
    state = load_checkpoint(halves)
    assert "policy_state_dict" not in state["collector"]  # the agent's components hold the policy
    # the same state as 0.2.0 saved it
    collector = dict(state["collector"])
    carrier = TensorDict(collector.pop("carrier"), batch_size=[2])
    policy = {"module.0.weight": torch.zeros(1)}  # ignored: the agent's entry holds the policy
    rng = state["rng"]
    numpy_state = (rng["numpy"][0], rng["numpy"][1].numpy().astype(np.uint32), *rng["numpy"][2:])
    legacy = {
        **state,
        "collector": {**collector, "policy_state_dict": policy},
        "carrier": carrier,
        "rng": {"python": rng["python"], "numpy": numpy_state, "torch": rng["torch_cpu"]},
    }
    old.mkdir()
    shutil.copy(halves / "metrics.csv", old / "metrics.csv")
    torch.save(legacy, old / "checkpoint.pt")
    recipe.train(recipe_config(*overrides, "total_steps=480", f"resume={old}"), run_dir=old)
    a, b = _flat(load_checkpoint(straight)["agent"]), _flat(load_checkpoint(old / "checkpoint")["agent"])
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def _switch_reached_its_object(override: str, parts) -> bool:
    """Whether the override configured the object it names (not only ran): read off the built run."""
    agent = parts.agent
    subgoal_relabel = [step for step in parts.high_rb._relabel if type(step).__name__ == "HindsightSubgoalRelabel"]
    transforms = {type(t).__name__: t for t in parts.train_env.transform}
    return {
        "low.sqgc=false": agent.sqgc_loss.sqgc is False,
        "high.gradual_penalty=null": [step.gradual_penalty for step in subgoal_relabel] == [None],
        # no planner for the gradual penalty's distance from the graph, and (below) no graph ever built
        "planner.enabled=false": [step.distance_from_graph for step in subgoal_relabel] == [None],
        "planner.distance=oracle": type(agent.planner.distance).__name__ == "LineOfSightDistance",
        "fgs.enabled=true": "GoalShiftOnReset" in transforms,
        "high.c_h=5": agent.high_policy.scheduler.interval == 5,
        "planner.build_dtype=bfloat16": agent.planner.graph.build_autocast_dtype == torch.bfloat16,
        "angle_features=null": "AngleFeatures" not in transforms,  # Reacher3D's default is [4, 6]
    }[override]


@pytest.mark.parametrize(
    "env, override",
    [
        ("PointMaze", "low.sqgc=false"),
        ("PointMaze", "high.gradual_penalty=null"),
        ("PointMaze", "planner.enabled=false"),
        ("PointMaze", "planner.distance=oracle"),
        ("UR3Obstacle", "planner.distance=oracle"),
        ("PointMaze", "fgs.enabled=true"),
        ("PointMaze", "high.c_h=5"),
        ("PointMaze", "planner.build_dtype=bfloat16"),
        ("Reacher3D", "angle_features=null"),
    ],
)
def test_ablation_switches_run(env, override, tmp_path, monkeypatch):
    built = []
    build_run = recipe.build_run
    monkeypatch.setattr(recipe, "build_run", lambda *args: built.append(build_run(*args)) or built[-1])
    cfg = recipe_config(f"env={env}", *SMOKE, "total_steps=240", "plots.every_epochs=0", override)
    recipe.train(cfg, run_dir=tmp_path)
    (parts,) = built
    assert _switch_reached_its_object(override, parts)
    # and the defaults do not: the same check fails on a run built without the override
    default = build_run(recipe_config(f"env={env}", *SMOKE, "total_steps=240"), torch.device("cpu"))
    try:
        assert not _switch_reached_its_object(override, default)
    finally:
        default.collector.shutdown()
    rows = metrics_rows(tmp_path)
    landmarks = [int(r["graph/landmarks"]) for r in rows]
    fgs = override == "fgs.enabled=true"  # the share of training goals it moved is logged with it only
    assert ("train/goal_shifted" in rows[-1]) == fgs
    assert not fgs or all(0.0 <= float(r["train/goal_shifted"]) <= 1.0 for r in rows)
    assert ("train/frontier" in rows[-1]) == (env == "PointMaze")  # maze progress: mazes only
    if override == "planner.enabled=false":
        assert landmarks == [0, 0, 0]
    else:
        assert landmarks[-1] >= 2


def test_bfloat16_updates_reach_both_updaters(tmp_path, monkeypatch):
    """``update_dtype=bfloat16``: both levels' updates run under bf16 autocast, losses stay finite and
    differ from the float32 run's (same seed), and a bf16 run resumes exactly."""
    from torchrl_dhrl.training import LossUpdater

    seen = []
    real_step = LossUpdater._step

    def record(self):
        seen.append((type(self.loss).__name__, self.autocast_dtype, torch.is_autocast_enabled("cpu")))
        return real_step(self)

    monkeypatch.setattr(LossUpdater, "_step", record)
    overrides = ("env=PointMaze", *SMOKE, "plots.every_epochs=0", "device=cpu")
    recipe.train(
        recipe_config(*overrides, "total_steps=240", "update_dtype=bfloat16"), run_dir=tmp_path / "bf16"
    )
    assert {(name, dtype) for name, dtype, _ in seen} == {
        ("SQGCLoss", torch.bfloat16),
        ("HighLevelLoss", torch.bfloat16),
    }
    assert not any(enabled for *_, enabled in seen)  # autocast covers the loss only, not sampling
    assert read_provenance(tmp_path / "bf16")[0]["precision"]["update_dtype"] == "bfloat16"
    recipe.train(recipe_config(*overrides, "total_steps=240"), run_dir=tmp_path / "fp32")
    bf, fp = metrics_rows(tmp_path / "bf16"), metrics_rows(tmp_path / "fp32")
    for key in ("low/loss_policy_qvalue", "low/loss_graph_qvalue", "high/loss_qvalue"):
        assert all(
            torch.isfinite(torch.tensor(float(r[key]))) for r in bf[1:]
        )  # bf[0]: the warm-up, no update
    assert [r["low/loss_policy_qvalue"] for r in bf] != [r["low/loss_policy_qvalue"] for r in fp]
    # exact resume in bf16: 120 steps + resume to 240 == 240 straight
    halves = tmp_path / "halves"
    recipe.train(recipe_config(*overrides, "total_steps=120", "update_dtype=bfloat16"), run_dir=halves)
    recipe.train(
        recipe_config(*overrides, "total_steps=240", "update_dtype=bfloat16", f"resume={halves}"),
        run_dir=halves,
    )
    a, b = (
        _flat(load_checkpoint(tmp_path / "bf16" / "checkpoint")["agent"]),
        _flat(load_checkpoint(halves / "checkpoint")["agent"]),
    )
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_bad_config_fails_before_anything_is_written(tmp_path):
    cfg = recipe_config("env=PointMaze", *SMOKE, "planner.cutoff=-1")
    with pytest.raises(ConfigError, match="planner.cutoff"):
        recipe.train(cfg, run_dir=tmp_path / "run")
    assert not (tmp_path / "run").exists()
    # the maze diagnostics' agent radius closing every corridor of PointMaze (4 wide): refused, nothing written
    cfg = recipe_config("env=PointMaze", *SMOKE, "planner.oracle_margin=2.0")
    with pytest.raises(ConfigError, match=r"planner.oracle_margin=2 on env_name=PointMaze: margin=2 leaves no free cell"):
        recipe.train(cfg, run_dir=tmp_path / "run")
    assert not (tmp_path / "run").exists()
    with pytest.raises(ConfigError, match="oracle needs the achieved goal"):  # Reacher3D: goal not in obs
        recipe.train(
            recipe_config("env=Reacher3D", *SMOKE, "planner.distance=oracle"), run_dir=tmp_path / "r"
        )


@pytest.mark.slow
def test_command_line(tmp_path):
    """The script itself, through Hydra's command line (as in the README)."""
    result = subprocess.run(
        [
            sys.executable,
            str(RECIPES / "dhrl_antmaze.py"),
            "env=PointMaze",
            "preset=smoke",
            "total_steps=160",
            f"run_dir={tmp_path}",
            f"hydra.run.dir={tmp_path / 'hydra'}",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert "Done: 160 env steps" in result.stdout
    assert (tmp_path / "success_curve.png").exists()
    bad = subprocess.run(
        [
            sys.executable,
            str(RECIPES / "dhrl_antmaze.py"),
            "env=PointMaze",
            "high.c_h=0",
            f"hydra.run.dir={tmp_path / 'bad'}",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert bad.returncode != 0 and "high.c_h" in bad.stderr


def test_ctrl_c_saves_a_checkpoint_that_resumes(tmp_path, monkeypatch):
    from torchrl_dhrl.training import LossUpdater

    calls = {"n": 0}
    real_run = LossUpdater.run

    def interrupt_on_third_batch(self, num_updates):
        calls["n"] += 1
        if calls["n"] == 5:  # low and high updates of batches 1-2, then the low updates of batch 3
            raise KeyboardInterrupt
        return real_run(self, num_updates)

    monkeypatch.setattr(LossUpdater, "run", interrupt_on_third_batch)
    cfg = recipe_config("env=PointMaze", *SMOKE, "plots.every_epochs=0")
    with pytest.raises(KeyboardInterrupt):
        recipe.train(cfg, run_dir=tmp_path)
    state = load_checkpoint(tmp_path / "checkpoint")
    assert state["counters"]["env_steps"] == 240  # batch 3 was collected and stored before the interrupt
    assert (tmp_path / "success_curve.png").stat().st_size > 1000  # the curve so far is drawn too
    monkeypatch.setattr(LossUpdater, "run", real_run)
    summary = recipe.train(
        recipe_config("env=PointMaze", *SMOKE, "plots.every_epochs=0", f"resume={tmp_path}"), run_dir=tmp_path
    )
    assert summary["env_steps"] == 480


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_mid_update_stops_at_the_batch_end_and_resumes_exactly(signum, tmp_path, monkeypatch):
    """A signal inside an update (where an exception would cross ``TensorDict.to_module``) stops the run after
    the batch's updates: a clean checkpoint that resumes to the straight run's parameters, bit for bit."""
    from torchrl_dhrl.training import LossUpdater

    overrides = ("env=PointMaze", *SMOKE, "plots.every_epochs=0", "device=cpu")
    straight = tmp_path / "straight"
    recipe.train(recipe_config(*overrides, "total_steps=480"), run_dir=straight)
    real_step = LossUpdater._step
    calls = {"n": 0}

    def signal_inside_an_update(self):
        calls["n"] += 1
        if calls["n"] == 100:  # the 20th low-level update of batch 3 (batch 2: 80 low + 8 high)
            os.kill(os.getpid(), signum)
        return real_step(self)

    monkeypatch.setattr(LossUpdater, "_step", signal_inside_an_update)
    before = (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM))
    halves = tmp_path / "halves"
    with pytest.raises(KeyboardInterrupt):
        recipe.train(recipe_config(*overrides, "total_steps=480"), run_dir=halves)
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before  # handlers restored
    state = load_checkpoint(halves / "checkpoint")
    assert state["counters"]["env_steps"] == 240 and state["low_updater"]["num_updates"] == 160
    monkeypatch.setattr(LossUpdater, "_step", real_step)
    recipe.train(recipe_config(*overrides, "total_steps=480", f"resume={halves}"), run_dir=halves)
    a, b = (
        _flat(load_checkpoint(straight / "checkpoint")["agent"]),
        _flat(load_checkpoint(halves / "checkpoint")["agent"]),
    )
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_nan_stops_with_a_message_and_keeps_the_last_good_checkpoint(tmp_path, monkeypatch):
    from torchrl_dhrl.training import LossUpdater, NonFiniteLossError

    real_step = LossUpdater.step
    count = {"n": 0}

    def nan_later(self):
        count["n"] += 1
        if count["n"] > 200:  # in the 4th batch (none in the warm-up batch, then 80 low + 8 high per batch)
            raise NonFiniteLossError("SQGCLoss produced a non-finite loss")
        return real_step(self)

    monkeypatch.setattr(LossUpdater, "step", nan_later)
    cfg = recipe_config("env=PointMaze", *SMOKE, "plots.every_epochs=0")
    with pytest.raises(SystemExit, match="non-finite loss.*last good checkpoint"):
        recipe.train(cfg, run_dir=tmp_path)
    state = load_checkpoint(tmp_path / "checkpoint")
    assert state["counters"]["env_steps"] == 240  # the checkpoint of the 3rd batch's epoch


def test_flat_evaluation_uses_the_same_goals_and_changes_nothing_else(tmp_path, monkeypatch):
    """``schedule.eval_flat``: the low level alone on the main evaluation's test goals (Reacher3D draws them at
    random), and every other metric as without it."""
    from torchrl_dhrl.recipe import epoch as epoch_end

    goals = []
    evaluate = epoch_end.evaluate

    def recording(env, policy, steps, **kwargs):
        result = evaluate(env, policy, steps, **kwargs)
        goals.append(result.rollout["desired_goal"][:, 0].clone())
        return result

    monkeypatch.setattr(epoch_end, "evaluate", recording)
    # one thread: `threads=null` follows the machine's load, and another thread count rounds differently
    overrides = ("env=Reacher3D", *SMOKE, "total_steps=240", "plots.every_epochs=0", "device=cpu", "threads=1")
    recipe.train(recipe_config(*overrides, "schedule.eval_flat=true"), run_dir=tmp_path / "flat")
    with_flat, goals = goals, []
    recipe.train(recipe_config(*overrides, "schedule.eval_flat=false"), run_dir=tmp_path / "plain")
    assert len(with_flat) == 2 * len(goals) == 6
    for epoch, plain in enumerate(goals):
        main, flat = with_flat[2 * epoch], with_flat[2 * epoch + 1]
        torch.testing.assert_close(main, flat, rtol=0, atol=0)  # paired: the same test goals
        torch.testing.assert_close(main, plain, rtol=0, atol=0)  # the next evaluations' goals unchanged
    assert not torch.equal(goals[0], goals[1])  # the test goals are random per episode in Reacher3D
    drop = (*TIMING_COLUMNS, "eval/flat_")
    assert metrics_rows(tmp_path / "flat", drop) == metrics_rows(tmp_path / "plain", drop)
    rows_flat = metrics_rows(tmp_path / "flat")
    for row in rows_flat:
        assert 0.0 <= float(row["eval/flat_success"]) <= float(row["eval/flat_any_success"]) <= 1.0
        assert float(row["eval/flat_final_distance"]) > 0
        for key in ("subgoal_goal_distance", "subgoal_reached", "segment_progress", "graph_steps"):
            assert row[f"diag/{key}"] != ""
    # the learned distances: from the graph once there is one (NaN in the warm-up epoch without a graph)
    assert rows_flat[0]["diag/subgoal_graph_distance"] == "nan"
    for row in rows_flat[1:]:
        assert float(row["diag/subgoal_graph_distance"]) >= 0
        assert 0.0 <= float(row["diag/subgoals_far_from_graph"]) <= 1.0
        assert float(row["diag/subgoal_learned_distance"]) >= 0
    assert "eval/flat_success" not in metrics_rows(tmp_path / "plain")[0]
