"""Env steps per second of the real recipe loop, before and after, in one run on one machine.

Runs ``recipes/dhrl_antmaze.py`` for ``--steps`` env steps (graph phase included) as separate processes,
interleaved over ``--repeats`` rounds so that every variant sees the same background load:

* ``base@<ref>`` (with ``--baseline <ref>``): the recipe at a git ref, checked out in a temporary worktree
  and installed into a temporary folder (``pip install --no-deps --target``), so before and after run the
  same loop on the same machine in the same session;
* ``tree`` and ``tree <overrides>`` (``--variants``): the working tree, with each override string (e.g.
  ``"compile=true"``, ``"update_dtype=bfloat16"``).

Each process writes its ``metrics.csv``; the loop rate is taken over the epochs after the warm-up (the
warm-up trains nothing, faithful to the reference, and would flatter every variant alike): env steps
divided by the collection + update seconds between the first epoch row after the warm-up and the last row.
``--parts`` also runs ``benchmarks/profile_train.py`` on the working tree (every phase alone) and prints
the rate the sum of its parts predicts next to the measured loop. ``process s`` is each process's whole
wall clock (start-up, warm-up, compilation, evaluations and graph rebuilds included).

Run::

    python benchmarks/bench_train.py --baseline HEAD --variants "" "compile=true"       # PointMaze quick
    python benchmarks/bench_train.py --env AntMazeSmall --steps 30000 --baseline 82e65d3
    python benchmarks/bench_train.py --env AntMaze --preset paper --steps 6000 --variants "update_dtype=bfloat16"
    python benchmarks/bench_train.py --threads default --competitors 0 1 --variants "" "threads=2"

Threads: ``--threads`` (default 1) is passed to every run (``threads=`` and ``OMP_NUM_THREADS``); ``--threads
default`` passes neither, so each run uses the recipe's default (``threads=null``: every core this process may
use, fewer while other processes keep some busy). ``--competitors 0 1`` runs every variant alone and next to
one CPU-bound busy loop (started with the run, stopped after it), and prints each variant's slowdown.

Several seeds at once: ``--seeds-at-once 1 4`` runs every variant as one process (seed 0) and as 4 processes
started together (seeds 0-3, each with ``--threads``; on one GPU they share it), and prints the aggregate env
steps/s (the sum of the processes' rates), its ratio to one run's, and whether seed 0's metrics (every
non-timing column) are identical to its run alone::

    python benchmarks/bench_train.py --seeds-at-once 1 2 --threads 1 --repeats 1          # 2 cores: 2 seeds
    python benchmarks/bench_train.py --env AntMaze --preset paper --steps 6000 --threads 4 --seeds-at-once 1 4 \
        --variants "device=cuda"                                                             # 4 seeds on one GPU
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from _recipe import TIMING_COLUMNS, recipe_config  # noqa: E402 - the tests' helpers: config, timing columns


def prepare_baseline(ref: str, workdir: Path) -> tuple[Path, dict[str, str]]:
    """A worktree of ``ref`` installed into ``workdir/site``: ``(recipe path, environment additions)``."""
    tree = workdir / "tree"
    subprocess.run(
        ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), ref],
        check=True,
        capture_output=True,
    )
    site = workdir / "site"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "-q",
            "--no-deps",
            "--no-build-isolation",
            "--target",
            str(site),
            str(tree),
        ],
        check=True,
        capture_output=True,
    )
    return tree / "recipes" / "dhrl_antmaze.py", {"PYTHONPATH": str(site)}


def remove_baseline(workdir: Path) -> None:
    subprocess.run(
        ["git", "-C", str(ROOT), "worktree", "remove", "--force", str(workdir / "tree")], capture_output=True
    )


def untimed_rows(rows: list[dict]) -> list[dict]:
    """A run's metrics rows without the columns that measure time (what must not differ between equal runs)."""
    return [{k: v for k, v in row.items() if not k.startswith(TIMING_COLUMNS)} for row in rows]


def compare_rows(rows: list[dict], alone: list[dict]) -> str:
    """How a run's untimed metrics compare with the same seed's run alone: identical, equal to float round-off
    (reductions split over another number of threads, e.g. ``threads=null`` adapting to the other seeds), or
    different (the first row and columns that differ)."""
    if rows == alone:
        return "identical"
    if len(rows) != len(alone) or any(a.keys() != b.keys() for a, b in zip(rows, alone, strict=True)):
        return f"DIFFERENT ({len(rows)} rows against {len(alone)})"
    worst, columns, far = 0.0, set(), False
    for a, b in zip(rows, alone, strict=True):
        for key in a:
            if a[key] == b[key]:
                continue
            try:
                x, y = float(a[key]), float(b[key])
            except ValueError:
                return f"DIFFERENT ({key} at {a.get('env_steps')} env steps)"
            worst = max(worst, abs(x - y))
            columns.add(key)
            # round-off: relative to the value, or absolute near 0 (e.g. a speed from two close positions)
            far |= not math.isclose(x, y, rel_tol=1e-5, abs_tol=1e-6)
    named = ", ".join(sorted(columns)[:4]) + (", ..." if len(columns) > 4 else "")
    what = f"absolute difference up to {worst:.1e} in {len(columns)} column(s): {named}"
    return f"DIFFERENT ({what})" if far else f"equal to float round-off ({what})"


def run_recipe(
    recipe: Path,
    env_add: dict,
    overrides: list[str],
    run_dir: Path,
    threads: int | None,
    competitors: int = 0,
    seeds: list[int] | None = None,
) -> list[dict]:
    """Runs the recipe (``threads=None``: its default) next to ``competitors`` busy loops, once, or once per seed
    of ``seeds`` as processes started together (``run_dir/seed_<k>``); returns each run's metrics rows and wall
    clock."""
    env = {**os.environ, **env_add}
    if threads is None:
        env.pop("OMP_NUM_THREADS", None)
        env.pop("MKL_NUM_THREADS", None)
    else:
        env.update(OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    if "PYTHONPATH" not in env_add:  # the working tree: its own editable install, not a baseline's copy
        env.pop("PYTHONPATH", None)
    dirs = [run_dir] if seeds is None else [run_dir / f"seed_{seed}" for seed in seeds]
    seeds = seeds or [None]
    commands = [
        [
            sys.executable,
            str(recipe),
            *([] if threads is None else [f"threads={threads}"]),
            *overrides,
            *([] if seed is None else [f"seed={seed}"]),
            f"run_dir={folder}",
            f"hydra.run.dir={folder}/hydra",
            "logger.backend=none",
            "plots.every_epochs=0",
            "progress=false",
        ]
        for seed, folder in zip(seeds, dirs, strict=True)
    ]
    burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(competitors)]
    logs = [tempfile.TemporaryFile(mode="w+") for _ in commands]
    try:
        start = time.perf_counter()
        procs = [
            subprocess.Popen(
                cmd, env=env, cwd=recipe.parents[1], stdout=subprocess.DEVNULL, stderr=log, text=True
            )
            for cmd, log in zip(commands, logs, strict=True)
        ]
        walls: list[float | None] = [None] * len(procs)
        while None in walls:
            for i, proc in enumerate(procs):
                if walls[i] is None and proc.poll() is not None:
                    walls[i] = time.perf_counter() - start
            time.sleep(0.05)
    finally:
        for burner in burners:
            burner.kill()
            burner.wait()
    for cmd, proc, log in zip(commands, procs, logs, strict=True):
        log.seek(0)
        if proc.returncode != 0:
            raise RuntimeError(f"{shlex.join(cmd)} failed:\n{log.read()[-3000:]}")
        log.close()
    return [
        {"rows": list(csv.DictReader(open(folder / "metrics.csv"))), "process_s": wall}
        for folder, wall in zip(dirs, walls, strict=True)
    ]


def loop_rate(rows: list[dict], warmup_steps: int) -> dict[str, float]:
    """Env steps/s of collection + updates over the rows after the warm-up, and the phase shares."""
    trained = [r for r in rows if float(r["env_steps"]) > warmup_steps]
    if len(trained) < 2:
        raise ValueError(
            f"{len(trained)} epoch(s) after the warm-up ({warmup_steps:g} env steps): nothing to time; raise --steps."
        )
    first, last = trained[0], trained[-1]

    def f(row, key):
        return float(row.get(key) or 0.0)

    steps = f(last, "env_steps") - f(first, "env_steps")
    collect = f(last, "time/collect_s") - f(first, "time/collect_s")
    update = f(last, "time/update_s") - f(first, "time/update_s")
    wall = f(last, "time/wall_s") - f(first, "time/wall_s")
    return {
        "env_steps_per_s": steps / max(collect + update, 1e-9),
        "wall_steps_per_s": steps / max(wall, 1e-9),  # evaluation and graph rebuilds included
        "update_ms_per_step": 1e3 * update / max(steps, 1),
        "collect_ms_per_step": 1e3 * collect / max(steps, 1),
        "steps": steps,
    }


def parts_rate(overrides: list[str], threads: int | None) -> float:
    """The env steps/s that ``profile_train.py`` (every phase alone) predicts for the working tree."""
    threads = threads or (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1)
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    out = subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmarks" / "profile_train.py"),
            "--threads",
            str(threads),
            *overrides,
        ],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    last = [line for line in out.splitlines() if "env steps/s" in line][-1]
    return float(last.split("->")[-1].split()[0])


def cell_name(variant: str, competitors: int, seeds: int) -> str:
    """A table row's name: the variant, the busy loops beside it and the seeds run at once."""
    return (
        variant + (f" x{seeds} seeds" if seeds > 1 else "") + (f" +{competitors} busy" if competitors else "")
    )


def combine(rates: list[dict]) -> dict[str, float]:
    """Several runs at once as one row: their rates summed (aggregate throughput), their per-step costs
    averaged (what one run paid), the longest process."""
    return {
        "env_steps_per_s": sum(r["env_steps_per_s"] for r in rates),
        "wall_steps_per_s": sum(r["wall_steps_per_s"] for r in rates),
        "update_ms_per_step": statistics.mean(r["update_ms_per_step"] for r in rates),
        "collect_ms_per_step": statistics.mean(r["collect_ms_per_step"] for r in rates),
        "process_s": max(r["process_s"] for r in rates),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--env", default="PointMaze")
    parser.add_argument("--preset", default="quick")
    parser.add_argument("--steps", type=int, default=21000, help="env steps per run (warm-up included)")
    parser.add_argument(
        "--epoch-episodes",
        type=int,
        default=5,
        help="schedule.epoch_episodes (short epochs: more rows to time)",
    )
    parser.add_argument("--baseline", default=None, help="a git ref to compare against (temporary worktree)")
    parser.add_argument("--variants", nargs="*", default=[""], help="override strings for the working tree")
    parser.add_argument(
        "--repeats", type=int, default=2, help="interleaved rounds (median and best reported)"
    )
    parser.add_argument(
        "--threads",
        type=lambda v: None if v == "default" else int(v),
        default=1,
        help="threads of every run, or 'default' for the recipe's own choice (default: 1)",
    )
    parser.add_argument(
        "--competitors",
        type=int,
        nargs="+",
        default=[0],
        help="run every variant next to each of these numbers of busy-loop processes (default: 0)",
    )
    parser.add_argument(
        "--seeds-at-once",
        type=int,
        nargs="+",
        default=[1],
        help="run every variant as each of these numbers of seeds started together (default: 1)",
    )
    parser.add_argument("--parts", action="store_true", help="also run profile_train.py (sum of the parts)")
    parser.add_argument("--keep", default=None, help="folder to keep the runs' directories in")
    parser.add_argument("overrides", nargs="*", help="recipe overrides for every variant (key=value)")
    args = parser.parse_args()
    common = [
        f"env={args.env}",
        f"preset={args.preset}",
        f"total_steps={args.steps}",
        f"schedule.epoch_episodes={args.epoch_episodes}",
        *args.overrides,
    ]

    cfg = recipe_config(*common)
    warmup_episodes = cfg["schedule"]["warmup_episodes"]
    from torchrl_dhrl.envs import get_env_spec  # noqa: PLC0415

    # the rate is taken between the first and the last epoch after the warm-up: at least two of them
    episode_length = get_env_spec(cfg["env_name"]).episode_length
    needed = (warmup_episodes + 2 * args.epoch_episodes) * episode_length
    if args.steps < needed:
        raise SystemExit(
            f"--steps {args.steps} is too short for {cfg['env_name']}: the rate is measured between the first "
            f"and the last epoch after the {warmup_episodes}-episode warm-up, so it needs at least "
            f"{needed} env steps (warm-up + 2 epochs of {args.epoch_episodes} episodes of "
            f"{episode_length} steps)."
        )

    work = Path(args.keep or tempfile.mkdtemp(prefix="bench_train_"))
    work.mkdir(parents=True, exist_ok=True)
    variants: dict[str, tuple[Path, dict, list[str]]] = {}
    if args.baseline:
        recipe, env_add = prepare_baseline(args.baseline, work / "baseline")
        variants[f"base@{args.baseline}"] = (recipe, env_add, [])
    for text in args.variants:
        name = f"tree {text}".strip()
        variants[name] = (ROOT / "recipes" / "dhrl_antmaze.py", {}, shlex.split(text))
    base_seed = int(cfg["seed"])
    cells = {  # every variant next to each number of competitors, as each number of seeds at once
        cell_name(name, n, k): (name, *variant, n, k)
        for name, variant in variants.items()
        for n in args.competitors
        for k in args.seeds_at_once
    }
    results: dict[str, list[dict]] = {name: [] for name in cells}
    identical: dict[str, list[str]] = {name: [] for name in cells}
    try:
        for round_ in range(args.repeats):
            alone_rows: dict[str, list[dict]] = {}  # seed 0's metrics run alone, per variant and competitors
            for i, (name, (variant, recipe, env_add, extra, competitors, k)) in enumerate(cells.items()):
                run_dir = work / f"r{round_}_v{i}"
                seeds = list(range(base_seed, base_seed + k))
                outs = run_recipe(
                    recipe, env_add, [*common, *extra], run_dir, args.threads, competitors, seeds
                )
                rates = []
                for out in outs:
                    rows = out["rows"]
                    warmup_steps = warmup_episodes * float(rows[0]["env_steps"]) / float(rows[0]["episodes"])
                    rates.append(loop_rate(rows, warmup_steps) | {"process_s": out["process_s"]})
                rate = combine(rates)
                results[name].append(rate)
                alone = cell_name(variant, competitors, 1)
                first = untimed_rows(outs[0]["rows"])
                if k == 1:
                    alone_rows[alone] = first
                elif alone in alone_rows:
                    identical[name].append(compare_rows(first, alone_rows[alone]))
                print(
                    f"round {round_ + 1} {name:<40} {rate['env_steps_per_s']:7.2f} env steps/s"
                    + (f" (sum of {k} seeds)" if k > 1 else ""),
                    flush=True,
                )
    finally:
        if args.baseline:
            remove_baseline(work / "baseline")
    parts = (
        parts_rate([f"env={args.env}", f"preset={args.preset}", *args.overrides], args.threads)
        if args.parts
        else None
    )

    print(
        f"\nenv={args.env} preset={args.preset} {' '.join(args.overrides)}: {args.steps} env steps per run, "
        f"{'the default' if args.threads is None else args.threads} thread(s), {args.epoch_episodes}-episode epochs, rates over the epochs after the "
        f"{warmup_episodes}-episode warm-up, "
        f"median (best) of {args.repeats} interleaved rounds"
    )
    names = list(cells)
    ref = names[0]
    header = f"{'variant':<40} {'env steps/s':>16} {'ratio':>6} {'update ms/step':>15} {'collect ms/step':>16} {'wall steps/s':>13} {'process s':>10}"
    print(header)
    med = {n: statistics.median(r["env_steps_per_s"] for r in results[n]) for n in names}
    for n in names:
        rs = results[n]
        best = max(r["env_steps_per_s"] for r in rs)
        print(
            f"{n:<40} {med[n]:>8.2f} ({best:6.2f}) {med[n] / med[ref]:>6.2f} "
            f"{statistics.median(r['update_ms_per_step'] for r in rs):>15.2f} "
            f"{statistics.median(r['collect_ms_per_step'] for r in rs):>16.2f} "
            f"{statistics.median(r['wall_steps_per_s'] for r in rs):>13.2f} "
            f"{statistics.median(r['process_s'] for r in rs):>10.1f}"
        )
    for name, (variant, _, _, _, n, k) in cells.items():
        if n and cell_name(variant, 0, k) in med:
            alone = cell_name(variant, 0, k)
            print(f"{alone}: {med[alone] / med[name]:.2f}x slower next to {n} busy process(es)")
        one = cell_name(variant, n, 1)
        if k > 1 and one in med:
            verdicts = identical[name]
            verdict = "; ".join(sorted(set(verdicts))) if verdicts else "not compared (no single run)"
            print(
                f"{name}: {med[name] / med[one]:.2f}x the env steps/s of one run ({med[name]:.2f} against "
                f"{med[one]:.2f}); seed {base_seed}'s metrics against its run alone: {verdict}"
            )
    if parts is not None:
        tree = next(n for n in names if n.startswith("tree"))
        print(
            f"sum of the parts (profile_train.py, eager): {parts:.2f} env steps/s; measured loop ({tree}): {med[tree]:.2f}"
        )


if __name__ == "__main__":
    main()
