"""``recipes/aggregate.py`` and :mod:`torchrl_dhrl.recipe.aggregate` against numpy on hand-made run folders."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
import yaml
from _recipe import load_recipe

from torchrl_dhrl.recipe import aggregate_runs, bootstrap_iqm_ci, find_runs, iqm
from torchrl_dhrl.recipe.aggregate import variant_of

aggregate_cli = load_recipe("aggregate")


def _run(root, name, config, success, steps=None, extra_files=True, frontier=None):
    path = root / name
    path.mkdir(parents=True)
    steps = steps or [3000 * (i + 1) for i in range(len(success))]
    frontier = [math.nan] * len(success) if frontier is None else frontier
    with open(path / "metrics.csv", "w", newline="") as file:
        writer = csv.DictWriter(file, ["env_steps", "epoch", "eval/success", "train/frontier", "time/wall_s"])
        writer.writeheader()
        for i, (s, v, f) in enumerate(zip(steps, success, frontier, strict=True)):
            row = {"env_steps": s, "epoch": i + 1, "eval/success": v, "time/wall_s": 10.0 * i}
            row["train/frontier"] = "" if math.isnan(f) else f
            writer.writerow(row)
    if extra_files:
        (path / "config.yaml").write_text(yaml.safe_dump(config))
    return path


def _config(env, seed, sqgc=True, **extra):
    return {
        "env_name": env,
        "seed": seed,
        "run_dir": f"/somewhere/{env}_{seed}",
        "threads": seed % 2 + 1,
        "total_steps": 9000 + seed,  # bookkeeping keys differ between seeds: never a variant
        "low": {"sqgc": sqgc, "hidden": [256, 256]},
        "logger": {"exp_name": f"run{seed}"},
        **extra,
    }


@pytest.fixture
def sweep(tmp_path):
    rng = np.random.default_rng(0)
    values = {}
    for seed in range(4):
        for sqgc in (True, False):
            success = rng.integers(0, 11, size=3) / 10
            values[("PointMaze", sqgc, seed)] = success
            _run(tmp_path / "sweep", f"pm_{sqgc}_{seed}", _config("PointMaze", seed, sqgc), success)
    for seed in range(2):  # another task, one variant, runs of different lengths
        success = rng.integers(0, 11, size=4 - seed) / 10
        values[("AntMaze", True, seed)] = success
        _run(tmp_path / "sweep", f"am_{seed}", _config("AntMaze", seed), success)
    return tmp_path / "sweep", values


@pytest.mark.recipe
def test_table_matches_numpy(sweep, tmp_path):
    root, values = sweep
    assert aggregate_cli.main([str(root), "--out", str(tmp_path / "out"), "--reps", "500"]) == 0
    rows = list(csv.DictReader(open(tmp_path / "out" / "aggregate.csv")))
    groups = {(r["env"], r["variant"]) for r in rows}
    assert groups == {("PointMaze", "low.sqgc=true"), ("PointMaze", "low.sqgc=false"), ("AntMaze", "default")}
    for row in rows:
        sqgc = row["variant"] != "low.sqgc=false"
        seeds = range(4) if row["env"] == "PointMaze" else range(2)
        index = int(row["env_steps"]) // 3000 - 1
        x = np.array([values[(row["env"], sqgc, s)][index] for s in seeds])
        assert int(row["n"]) == len(x)
        assert float(row["mean"]) == pytest.approx(x.mean())
        assert float(row["std"]) == pytest.approx(x.std(ddof=1))
        middle = np.sort(x)[1:-1] if len(x) == 4 else x  # 4 runs: the IQM drops the lowest and the highest
        assert float(row["iqm"]) == pytest.approx(middle.mean())
        assert float(row["iqm_ci_low"]) <= float(row["iqm"]) + 1e-12 <= float(row["iqm_ci_high"]) + 2e-12
        assert x.min() <= float(row["iqm_ci_low"]) and float(row["iqm_ci_high"]) <= x.max()
        assert [float(v) for v in row["values"].split()] == pytest.approx(list(x))
    # AntMaze: seed 1 stopped one evaluation earlier, so only the common points are reported
    assert sorted(int(r["env_steps"]) for r in rows if r["env"] == "AntMaze") == [3000, 6000, 9000]
    assert (tmp_path / "out" / "aggregate.png").stat().st_size > 10_000
    summary = (tmp_path / "out" / "aggregate.md").read_text()
    assert "| PointMaze | low.sqgc=false | 9000 | 4 |" in summary and "96.9% at 0.25M" in summary


@pytest.mark.recipe
def test_several_metrics_each_against_numpy_and_only_success_against_the_paper(tmp_path):
    rng = np.random.default_rng(3)
    success = {seed: rng.integers(0, 11, size=3) / 10 for seed in range(3)}
    frontier = {seed: rng.uniform(5.0, 25.0, size=3) for seed in range(3)}
    frontier[2][0] = math.nan  # an epoch without the column (e.g. before the first training episode)
    for seed in range(3):
        _run(
            tmp_path / "runs",
            f"bn_{seed}",
            _config("AntMazeBottleneck", seed),
            success[seed],
            frontier=frontier[seed],
        )
    out = tmp_path / "out"
    argv = [
        str(tmp_path / "runs"),
        "--out",
        str(out),
        "--reps",
        "300",
        "--metric",
        "eval/success",
        "train/frontier",
    ]
    assert aggregate_cli.main(argv) == 0
    rows = list(csv.DictReader(open(out / "aggregate_train_frontier.csv")))
    assert [int(r["env_steps"]) for r in rows] == [6000, 9000]  # seed 2 has no frontier at 3000
    for row in rows:
        x = np.array([frontier[s][int(row["env_steps"]) // 3000 - 1] for s in range(3)])
        assert float(row["mean"]) == pytest.approx(x.mean())
        assert float(row["std"]) == pytest.approx(x.std(ddof=1))
        assert float(row["iqm"]) == pytest.approx(x.mean())  # three runs: trim_mean(0.25) drops none
    success_rows = list(csv.DictReader(open(out / "aggregate.csv")))  # the first metric keeps the plain names
    assert [int(r["env_steps"]) for r in success_rows] == [3000, 6000, 9000]
    assert (out / "aggregate.png").is_file() and (
        out / "aggregate_train_frontier.png"
    ).stat().st_size > 10_000
    summary = (out / "aggregate.md").read_text()
    head, tail = summary.split("## train/frontier")
    assert "## eval/success" in head and "16.5% at 0.5M" in head
    last = np.array([frontier[s][2] for s in range(3)])
    frontier_row = next(line for line in tail.splitlines() if line.startswith("| AntMazeBottleneck"))
    assert f"| 9000 | 3 | {last.mean():.4g} ± {last.std(ddof=1):.3g} |" in frontier_row
    assert "%" not in frontier_row and frontier_row.endswith(
        "| - |"
    )  # a number, not a rate, and no paper point


@pytest.mark.recipe
def test_an_unknown_metric_exits_2_naming_it_and_the_columns(tmp_path, capsys):
    _run(tmp_path, "a", _config("PointMaze", 0), [0.1, 0.2])
    assert aggregate_cli.main([str(tmp_path), "--metric", "eval/success", "eval/sucess"]) == 2
    err = capsys.readouterr().err
    assert "--metric eval/sucess: no such column" in err and "eval/success" in err and "train/frontier" in err
    assert not (tmp_path / "aggregate.csv").exists()  # nothing written before the check


@pytest.mark.parametrize("window", [1, 2, 3, 7, 50])
def test_smooth_is_each_runs_trailing_mean_before_the_statistics(tmp_path, window):
    rng = np.random.default_rng(window)
    values, steps = {}, {}
    for seed in range(3):
        n = 12 - seed  # runs of different lengths, on the same evaluation grid
        values[seed] = rng.integers(0, 11, size=n) / 10
        steps[seed] = [1500 * (i + 1) for i in range(n)]
        _run(tmp_path, f"r{seed}", _config("Reacher3D", seed), values[seed], steps=steps[seed])
    table = aggregate_runs(find_runs([tmp_path]), reps=100, smooth=window)
    assert [r["env_steps"] for r in table] == steps[2]  # the points every run reached
    for row in table:
        i = row["env_steps"] // 1500 - 1
        x = np.array([values[s][max(0, i + 1 - window) : i + 1].mean() for s in range(3)])  # direct, per run
        assert row["mean"] == pytest.approx(x.mean()) and row["std"] == pytest.approx(x.std(ddof=1))
        assert [float(v) for v in row["values"].split()] == pytest.approx(list(x), rel=1e-5)  # printed with %g
    with pytest.raises(ValueError, match="smooth must be an integer >= 1"):
        aggregate_runs(find_runs([tmp_path]), smooth=0)


@pytest.mark.recipe
def test_smooth_on_the_command_line(tmp_path, capsys):
    _run(tmp_path / "runs", "a", _config("Reacher3D", 0), [0.0, 1.0, 0.5, 0.0])
    assert (
        aggregate_cli.main([str(tmp_path / "runs"), "--out", str(tmp_path), "--smooth", "2", "--reps", "50"])
        == 0
    )
    rows = list(csv.DictReader(open(tmp_path / "aggregate.csv")))
    assert [float(r["mean"]) for r in rows] == pytest.approx([0.0, 0.5, 0.75, 0.25])
    assert "the mean of its last 2 evaluations" in (tmp_path / "aggregate.md").read_text()
    assert aggregate_cli.main([str(tmp_path / "runs"), "--smooth", "0"]) == 2
    assert "--smooth 0: must be >= 1" in capsys.readouterr().err


def test_iqm_and_bootstrap_against_direct_computation():
    rng = np.random.default_rng(1)
    for n in (1, 2, 3, 4, 5, 8, 13):
        x = rng.random(n)
        lo, hi = np.quantile(x, [0.25, 0.75])
        k = int(np.floor(0.25 * n))  # scipy's trim_mean cuts floor(0.25 n) values from each end
        assert iqm(x) == pytest.approx(np.sort(x)[k : n - k].mean())
        low, high = bootstrap_iqm_ci(x, reps=3000, seed=2)
        assert x.min() - 1e-12 <= low <= high <= x.max() + 1e-12
        assert bootstrap_iqm_ci(x, reps=3000, seed=2) == (low, high)  # seeded: reproducible
    assert bootstrap_iqm_ci([0.7, 0.7, 0.7]) == pytest.approx((0.7, 0.7))  # no spread, no interval


def test_variants_ignore_bookkeeping_and_configless_runs_group_alone(tmp_path):
    _run(tmp_path, "a", _config("PointMaze", 0, compile=True, device="cpu"), [0.1, 0.2])
    _run(tmp_path, "b", _config("PointMaze", 1, compile=False, device="cuda"), [0.3, 0.4])
    _run(tmp_path, "c", {}, [0.5, 0.6], extra_files=False)
    runs = find_runs([tmp_path])
    assert [variant_of(r, runs) for r in runs] == ["default", "default", "default"]
    table = aggregate_runs(runs, reps=200)
    assert {(r["env"], r["n"]) for r in table} == {("PointMaze", 2), ("unknown", 1)}


@pytest.mark.recipe
def test_no_runs_exits_2(tmp_path, capsys):
    assert aggregate_cli.main([str(tmp_path)]) == 2
    assert "no metrics.csv" in capsys.readouterr().err


def test_an_older_run_is_labelled_with_the_distance_output_it_was_trained_with(tmp_path):
    from torchrl_dhrl.recipe import find_runs
    from torchrl_dhrl.recipe.aggregate import variant_of

    for name, low in (("old", {"gamma": 0.99}), ("new", {"gamma": 0.99, "distance_output": "linear"})):
        run = tmp_path / name
        run.mkdir()
        (run / "metrics.csv").write_text("env_steps,eval/success\n9000,0.5\n")
        (run / "config.yaml").write_text(yaml.safe_dump({"env_name": "PointMaze", "seed": 0, "low": low}))
    runs = find_runs([tmp_path])
    assert [variant_of(r, runs) for r in runs] == [
        "low.distance_output=linear",
        "low.distance_output=softplus",
    ]


def _provenance(path, *precisions):
    """A run's provenance.yaml: one start per ``(update_dtype, build_dtype)`` resolved."""
    starts = [
        {"env_steps": 3000 * i, "precision": {"update_dtype": u, "planner.build_dtype": b}}
        for i, (u, b) in enumerate(precisions)
    ]
    (path / "provenance.yaml").write_text(yaml.safe_dump(starts))


def test_auto_precision_makes_the_variant_it_resolved_to(tmp_path):
    """``update_dtype=auto``: the run's provenance says what it ran with; alike for every start, that is its
    variant, so it pools with runs that set that value and splits from runs where auto chose otherwise."""
    auto = {"update_dtype": "auto", "planner": {"build_dtype": "auto"}}
    fp32 = {"update_dtype": "float32", "planner": {"build_dtype": "float32"}}
    _provenance(_run(tmp_path, "a", _config("AntMaze", 0, **auto), [0.1]), ("float32", "float32"))
    _run(tmp_path, "b", _config("AntMaze", 1, **fp32), [0.2])
    _provenance(_run(tmp_path, "c", _config("AntMaze", 2, **auto), [0.3]), ("bfloat16", "bfloat16"))
    _provenance(
        _run(tmp_path, "d", _config("AntMaze", 3, **auto), [0.4]),
        ("float32", "float32"),
        ("bfloat16", "float32"),
    )
    _run(tmp_path, "e", _config("AntMaze", 4, **auto), [0.5])  # no provenance: auto stays
    runs = find_runs([tmp_path])
    assert [(r.config["update_dtype"], r.config["planner.build_dtype"]) for r in runs] == [
        ("float32", "float32"),
        ("float32", "float32"),
        ("bfloat16", "bfloat16"),
        ("auto", "float32"),  # resumed where auto chose otherwise: not one value
        ("auto", "auto"),
    ]
    groups = {}
    for r in runs:
        groups.setdefault(variant_of(r, runs), []).append(r.path.name)
    assert sorted(groups.values()) == [["a", "b"], ["c"], ["d"], ["e"]]


@pytest.mark.recipe
def test_ignore_pools_runs_and_an_unknown_key_exits_2(tmp_path, capsys):
    _run(tmp_path, "a", _config("AntMaze", 0, update_dtype="auto"), [0.0, 1.0])
    _run(tmp_path, "b", _config("AntMaze", 1, update_dtype="float32"), [0.5, 0.5])
    assert aggregate_cli.main([str(tmp_path), "--reps", "50"]) == 0
    table = list(csv.DictReader(open(tmp_path / "aggregate.csv")))
    assert (
        sorted((r["variant"], r["n"]) for r in table)
        == [("update_dtype=auto", "1")] * 2 + [("update_dtype=float32", "1")] * 2
    )
    assert aggregate_cli.main([str(tmp_path), "--reps", "50", "--ignore", "update_*"]) == 0
    table = list(csv.DictReader(open(tmp_path / "aggregate.csv")))
    assert [(r["variant"], r["n"], float(r["mean"])) for r in table] == [
        ("default", "2", 0.25),
        ("default", "2", 0.75),
    ]
    capsys.readouterr()
    assert aggregate_cli.main([str(tmp_path), "--ignore", "update_dtype", "planner.nothing"]) == 2
    err = capsys.readouterr().err
    assert "--ignore planner.nothing: matches no configuration key" in err and "update_dtype:" not in err


def test_an_unreadable_provenance_names_its_file(tmp_path):
    from torchrl_dhrl.recipe import read_provenance

    (tmp_path / "provenance.yaml").write_text("- started: [unclosed\n")
    with pytest.raises(ValueError, match=r"provenance.yaml: not readable as YAML; move it aside"):
        read_provenance(tmp_path)
    (tmp_path / "provenance.yaml").write_text("just text\n")  # not a list of starts: none recorded
    assert read_provenance(tmp_path) == []
