"""Many runs: ``resume=auto`` (a re-run sweep continues or skips its runs), sweep defaults, a joblib sweep aggregated."""

from __future__ import annotations

import csv
import gc
import importlib.util
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from _recipe import RECIPES, TIMING_COLUMNS, load_recipe, metrics_rows, recipe_config
from omegaconf import OmegaConf

from torchrl_dhrl.recipe import CONFIG_NAME, load_checkpoint

recipe = load_recipe()
SUBMITIT_LOCAL = "hydra_plugins.hydra_submitit_launcher.submitit_launcher.LocalLauncher"
RAY = "hydra_plugins.hydra_ray_launcher.ray_launcher.RayLauncher"
SMOKE = ("env=PointMaze", "preset=smoke", "plots.every_epochs=0", "device=cpu", "logger.backend=none")


@pytest.mark.recipe
def test_resume_auto_starts_continues_and_skips_a_finished_run(tmp_path, capsys):
    run = tmp_path / "job"
    recipe.train(recipe_config(*SMOKE, "total_steps=160", "resume=auto"), run_dir=run)  # nothing there: fresh
    assert gc.get_freeze_count() == 0  # the loop's frozen objects are handed back to the collector
    first = (run / "metrics.csv").read_bytes()
    assert [int(r["env_steps"]) for r in metrics_rows(run)] == [80, 160]
    saved = yaml.safe_load((run / CONFIG_NAME).read_text())
    assert saved["total_steps"] == 160 and saved["resume"] is None  # auto resolved to "no checkpoint"
    capsys.readouterr()
    # the same command again (a re-launched sweep): finished, so nothing is collected, trained or rewritten
    summary = recipe.train(recipe_config(*SMOKE, "total_steps=160", "resume=auto"), run_dir=run)
    assert "Already finished: 160 env steps" in capsys.readouterr().out
    assert (run / "metrics.csv").read_bytes() == first and summary["env_steps"] == 160
    # a longer budget continues the run's own checkpoint
    recipe.train(recipe_config(*SMOKE, "total_steps=320", "resume=auto"), run_dir=run)
    assert [int(r["env_steps"]) for r in metrics_rows(run)] == [80, 160, 240, 320]
    assert load_checkpoint(run, components=("counters",))["counters"]["env_steps"] == 320


def _hydra(mode, sweep_dir, **launcher):
    from hydra.types import RunMode

    return OmegaConf.create(
        {
            "mode": RunMode.MULTIRUN if mode == "multirun" else RunMode.RUN,
            "sweep": {"dir": str(sweep_dir)},
            "launcher": launcher,
        }
    )


@pytest.mark.parametrize(
    "mode, launcher, cpus, threads",
    [
        ("run", {"n_jobs": 2}, 2, None),  # one run: untouched
        ("multirun", {}, 2, None),  # the basic launcher runs one job at a time: all cores
        ("multirun", {"n_jobs": 2}, 2, 1),
        ("multirun", {"n_jobs": -1}, 8, 1),
        ("multirun", {"n_jobs": 3}, 8, 2),
        ("multirun", {"n_jobs": 16}, 8, 1),
        ("multirun", {"cpus_per_task": 4}, 8, 4),  # submitit
        ("multirun", {"_target_": SUBMITIT_LOCAL, "cpus_per_task": None}, 8, 1),  # Slurm's default: 1 CPU
        ("multirun", {"ray": {"remote": {"num_cpus": 3}}}, 8, 3),  # ray
        ("multirun", {"_target_": RAY, "ray": {"remote": {}}}, 8, 1),  # a Ray task reserves 1 CPU
    ],
)
def test_sweep_defaults(mode, launcher, cpus, threads, monkeypatch, tmp_path):
    import dhrl_utils

    monkeypatch.setattr(dhrl_utils, "available_cpus", lambda: cpus)
    cfg = OmegaConf.create(recipe_config("env=PointMaze"))
    dhrl_utils.sweep_defaults(cfg, _hydra(mode, tmp_path / "sweep_17", **launcher))
    assert cfg.threads == threads
    assert cfg.logger.group == (None if mode == "run" else "sweep_17")
    cfg = OmegaConf.create(recipe_config("env=PointMaze", "threads=2", "logger.group=mine"))
    dhrl_utils.sweep_defaults(cfg, _hydra(mode, tmp_path / "sweep_17", **launcher))
    assert (cfg.threads, cfg.logger.group) == (2, "mine")  # set by the user: kept


def test_wandb_logger_gets_the_group(monkeypatch, tmp_path):
    import torchrl.record.loggers as loggers

    from torchrl_dhrl.recipe import make_logger

    made = []
    monkeypatch.setattr(loggers, "WandbLogger", lambda *a, **k: made.append((a, k)) or SimpleNamespace())
    make_logger("wandb", "dhrl", tmp_path, project="p", group="sweep_17")
    make_logger("wandb", "dhrl", tmp_path, project="p")
    assert made[0][1]["group"] == "sweep_17" and made[0][1]["offline"] is True
    assert "group" not in made[1][1]


def _has(plugin):
    return importlib.util.find_spec(f"hydra_plugins.{plugin}") is not None


@pytest.fixture(scope="module")
def ray_cluster():
    """A Ray cluster on this machine for the test: head node at 127.0.0.1, 2 CPUs, token authentication, stopped
    at the end. Yields its address and the environment variables a client needs."""
    with socket.socket() as free:
        free.bind(("127.0.0.1", 0))
        port = free.getsockname()[1]
    temp = tempfile.mkdtemp(prefix="ray", dir="/tmp")  # Ray's socket paths must stay short
    # token authentication with a token of the test's own: the cluster does not depend on (or write) ~/.ray
    auth = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32), "RAY_USAGE_STATS_ENABLED": "0"}
    env = {**os.environ, **auth}
    ray = Path(sys.executable).with_name("ray")
    command = [str(ray), "start", "--head", "--block", "--node-ip-address=127.0.0.1", f"--port={port}"]
    command += ["--num-cpus=2", "--include-dashboard=false", f"--temp-dir={temp}", "--disable-usage-stats"]
    log = open(Path(temp) / "head.log", "w+")
    head = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while "--block" not in (Path(temp) / "head.log").read_text():  # printed once the node is up
            assert head.poll() is None and time.monotonic() < deadline, (Path(temp) / "head.log").read_text()
            time.sleep(0.5)
        yield f"127.0.0.1:{port}", auth
    finally:
        os.killpg(head.pid, signal.SIGTERM)  # --block: the head stops the node's processes on SIGTERM
        try:
            head.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(head.pid, signal.SIGKILL)
        log.close()
        shutil.rmtree(temp, ignore_errors=True)


LAUNCHERS = {
    # launcher: (plugin, its overrides, threads per job on this machine)
    "joblib": ("hydra_joblib_launcher", ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"], None),
    "ray": ("hydra_ray_launcher", ["hydra/launcher=ray_cluster"], 1),
    "submitit_local": (
        "hydra_submitit_launcher",
        ["hydra/launcher=submitit_local", "hydra.launcher.timeout_min=10"],
        1,
    ),
}


#: the sweep's settings, shared by the runs alone they are compared with
SWEEP_RUN = (
    "env=PointMaze",
    "preset=smoke",
    "total_steps=240",
    "plots.every_epochs=0",
    "device=cpu",
    "logger.backend=csv",
)


@pytest.fixture(scope="module")
def runs_alone(tmp_path_factory):
    """Seeds 0 and 1 of the sweep, each run alone (one process, one thread): their untimed metrics rows."""
    rows = {}
    for seed in (0, 1):
        folder = tmp_path_factory.mktemp(f"alone_{seed}")
        out = subprocess.run(
            [
                sys.executable,
                str(RECIPES / "dhrl_antmaze.py"),
                *SWEEP_RUN,
                f"seed={seed}",
                "threads=1",
                f"run_dir={folder}",
                f"hydra.run.dir={folder}/hydra",
            ],
            env={**os.environ, "OMP_NUM_THREADS": "1"},
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert out.returncode == 0, out.stderr[-3000:]
        rows[seed] = metrics_rows(folder, drop=TIMING_COLUMNS)
    return rows


@pytest.mark.recipe
@pytest.mark.slow
@pytest.mark.parametrize("launcher", list(LAUNCHERS))
def test_sweep_runs_two_seeds_and_aggregates(launcher, request, runs_alone, tmp_path):
    """A 2-seed sweep through each launcher: both runs, their seeds, threads and group, each run's metrics
    identical to the same seed run alone (jobs running at once do not change each other's results), the
    aggregate against numpy on the same files, and the sweep re-run skipping both finished jobs."""
    plugin, overrides, threads = LAUNCHERS[launcher]
    if not _has(plugin):
        pytest.skip(f"needs {plugin.replace('_', '-')} (pip install -e '.[sweeps]')")
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    if launcher == "ray":
        address, auth = request.getfixturevalue("ray_cluster")
        overrides = [*overrides, f"hydra.launcher.ray.init.address={address}"]
        env.update(auth)
    if threads is None:  # joblib: the machine's cores shared by its 2 jobs
        cpus = len(os.sched_getaffinity(0))
        threads = max(1, cpus // min(2, cpus))
    sweep = tmp_path / "sweep_pm"
    command = [
        sys.executable,
        str(RECIPES / "dhrl_antmaze.py"),
        "-m",
        *SWEEP_RUN,
        "seed=0,1",
        "resume=auto",
        *overrides,
        f"hydra.sweep.dir={sweep}",
    ]
    # Ray's driver prints every job's lines (it folds identical lines of several jobs into one otherwise)
    env["RAY_DEDUP_LOGS"] = "0"
    out = subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    runs = sorted(p for p in sweep.iterdir() if p.is_dir() and not p.name.startswith("."))
    assert [p.name for p in runs] == ["0", "1"]
    configs = [yaml.safe_load((p / CONFIG_NAME).read_text()) for p in runs]
    assert [c["seed"] for c in configs] == [0, 1]
    assert all(c["threads"] == threads for c in configs)
    assert all(c["logger"]["group"] == "sweep_pm" for c in configs)
    rows = [metrics_rows(p) for p in runs]
    assert [int(r["env_steps"]) for r in rows[0]] == [80, 160, 240] == [int(r["env_steps"]) for r in rows[1]]
    losses = [
        [float(r["low/loss_graph_qvalue"]) for r in run if r.get("low/loss_graph_qvalue")] for run in rows
    ]
    assert losses[0] != losses[1]  # two seeds, two runs
    # each job's losses, success and graph figures are its seed's run alone, to the last digit
    for seed, run in zip((0, 1), runs, strict=True):
        assert metrics_rows(run, drop=TIMING_COLUMNS) == runs_alone[seed]

    # aggregate the sweep and check the statistics against numpy on the same files
    table_out = subprocess.run(
        [sys.executable, str(RECIPES / "aggregate.py"), str(sweep), "--reps", "300"],
        capture_output=True,
        text=True,
    )
    assert table_out.returncode == 0, table_out.stderr
    table = list(csv.DictReader(open(sweep / "aggregate.csv")))
    assert [(r["env"], r["variant"], int(r["env_steps"]), int(r["n"])) for r in table] == [
        ("PointMaze", "default", s, 2) for s in (80, 160, 240)
    ]
    for i, row in enumerate(table):
        assert float(row["mean"]) == pytest.approx(np.mean([float(run[i]["eval/success"]) for run in rows]))
    distance = subprocess.run(
        [
            sys.executable,
            str(RECIPES / "aggregate.py"),
            str(sweep),
            "--metric",
            "eval/final_distance",
            "--reps",
            "300",
            "--out",
            str(tmp_path / "distance"),
        ],
        capture_output=True,
        text=True,
    )
    assert distance.returncode == 0, distance.stderr
    for i, row in enumerate(csv.DictReader(open(tmp_path / "distance" / "aggregate.csv"))):
        x = np.array([float(run[i]["eval/final_distance"]) for run in rows])
        assert float(row["mean"]) == pytest.approx(x.mean()) and float(row["std"]) == pytest.approx(
            x.std(ddof=1)
        )

    # the same sweep again: both runs are finished, so both jobs skip (metrics untouched)
    before = [(p / "metrics.csv").read_bytes() for p in runs]
    again = subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr[-3000:]
    finished = "Already finished: 240 env steps"
    if launcher == "submitit_local":  # the jobs' output goes to submitit's logs
        printed = "".join(p.read_text() for p in (sweep / ".submitit").rglob("*_log.out"))
        assert printed.count(finished) == 2
    else:
        assert (again.stdout + again.stderr).count(finished) == 2
    assert [(p / "metrics.csv").read_bytes() for p in runs] == before
