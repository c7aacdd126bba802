"""Aggregates many recipe runs into one table and one figure, the way the paper reports them.

Usage::

    python recipes/aggregate.py <run dir or sweep dir> [...] [--out <folder>] [--metric eval/success]

Every folder with a ``metrics.csv`` under the given paths is a run; its configuration is read from
``config.yaml`` (written by the recipe), else Hydra's ``.hydra/config.yaml``. Runs are grouped by task and
variant (the configuration keys that differ between runs of the same task; seeds, paths, thread counts and
the like never make a variant). For every evaluation point that all runs of a group reached, the table
holds the mean and standard deviation over seeds (the paper's convention), the interquartile mean with a
95% percentile-bootstrap interval (rliable's IQM), the range and each seed's value. Written to ``--out``
(default: the first path): ``aggregate.csv``, ``aggregate.png`` (the paper's points overlaid) and
``aggregate.md`` (a summary at each group's last common evaluation point and at the paper's step counts).

``--metric`` takes one or more ``metrics.csv`` columns (default ``eval/success``), e.g. ``--metric eval/success
train/frontier diag/landmark_coverage``: the first writes ``aggregate.csv``/``.png``, every other one
``aggregate_<column>.csv``/``.png`` (``/`` as ``_``), and ``aggregate.md`` has one table per column. Only success
columns are printed as percentages, and only ``eval/success`` (final-state success) is set against the paper's.
``--smooth K`` takes each run's value at a point as the mean of its last K evaluations (10 test episodes make a coarse
rate; the paper's curves are smoothed too).

``--ignore KEY [...]`` adds configuration keys (``fnmatch`` patterns) that make no variant, to pool runs known to
be alike in them: e.g. runs written with ``update_dtype=auto`` before the run directory recorded what ``auto``
resolved to (``provenance.yaml``) with runs that set the value it resolved to. Each pattern must match a key.
"""

from __future__ import annotations

import argparse
import fnmatch
import sys
from pathlib import Path

from dhrl_utils import PAPER_SUCCESS

from torchrl_dhrl.recipe import IGNORED_KEYS, aggregate_runs, find_runs, plot_aggregate, write_aggregate_csv
from torchrl_dhrl.recipe.aggregate import variant_of

PAPER_METRIC = "eval/success"  # the paper's measure: final-state success over the test episodes


def is_success(metric: str) -> bool:
    """Whether ``metric`` is a success rate in [0, 1] (printed as a percentage)."""
    return metric.rsplit("/", 1)[-1].endswith("success")


def summary_markdown(table: list[dict], reference: dict, metric: str = "eval/success") -> str:
    """A markdown table: per task and variant, the last common evaluation point and the paper's points.

    The paper's success rates (``reference``) are only set against ``eval/success`` (final-state success, the
    paper's measure); success columns are printed as percentages, others (the frontier, the landmark coverage,
    ...) as numbers, at the last common point and at the paper's step counts.
    """
    success = is_success(metric)

    def fmt(v: float) -> str:
        return f"{100 * v:.1f}%" if success else f"{v:.4g}"

    def spread(v: float) -> str:
        return f"{100 * v:.1f}" if success else f"{v:.3g}"

    lines = [
        "| task | variant | env steps | runs | mean ± std | IQM [95% CI] | per seed | paper |",
        "|---|---|---|---|---|---|---|---|",
    ]
    keys = sorted({(row["env"], row["variant"]) for row in table})
    for env, variant in keys:
        rows = sorted(
            (r for r in table if (r["env"], r["variant"]) == (env, variant)), key=lambda r: r["env_steps"]
        )
        paper = reference.get(env, {})
        picked = [rows[-1]]
        for steps in paper:  # the evaluation point nearest each of the paper's step counts, if reached
            near = min(rows, key=lambda r: abs(r["env_steps"] - steps))
            if abs(near["env_steps"] - steps) <= 0.05 * steps and near not in picked:
                picked.append(near)
        ref = (
            ", ".join(f"{100 * v:.1f}% at {s / 1e6:g}M" for s, v in paper.items())
            if metric == PAPER_METRIC
            else ""
        )
        for r in sorted(picked, key=lambda r: r["env_steps"]):
            lines.append(
                f"| {env} | {variant} | {r['env_steps']} | {r['n']} | {fmt(r['mean'])} ± {spread(r['std'])} | "
                f"{fmt(r['iqm'])} [{spread(r['iqm_ci_low'])}, {spread(r['iqm_ci_high'])}] | "
                f"{r['values']} | {ref or '-'} |"
            )
    return "\n".join(lines) + "\n"


def output_name(metric: str, first: bool) -> str:
    """``aggregate`` for the first column, ``aggregate_<column>`` (``/`` as ``_``) for the others."""
    return "aggregate" if first else "aggregate_" + metric.replace("/", "_")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("paths", nargs="+", help="run directories or folders holding them")
    parser.add_argument("--out", default=None, help="output folder (default: the first path)")
    parser.add_argument(
        "--metric",
        nargs="+",
        default=["eval/success"],
        help="metrics.csv columns (default eval/success); the first names aggregate.csv/.png",
    )
    parser.add_argument("--reps", type=int, default=2000, help="bootstrap resamples")
    parser.add_argument(
        "--smooth",
        type=int,
        default=1,
        help="each run's value at a point: the mean of its last K evaluations (default 1: none)",
    )
    parser.add_argument(
        "--ignore",
        nargs="+",
        default=[],
        metavar="KEY",
        help="configuration keys (fnmatch patterns) that make no variant, besides the run bookkeeping",
    )
    args = parser.parse_args(argv)
    runs = find_runs(args.paths)
    if not runs:
        print(f"aggregate.py: no metrics.csv under {' '.join(args.paths)}", file=sys.stderr)
        return 2
    if args.smooth < 1:
        print(
            f"aggregate.py: --smooth {args.smooth}: must be >= 1 (evaluations per trailing mean)",
            file=sys.stderr,
        )
        return 2
    present = {key for run in runs for row in run.rows for key in row}
    missing = [m for m in args.metric if m not in present]
    if missing:
        print(
            f"aggregate.py: --metric {' '.join(missing)}: no such column in any metrics.csv "
            f"(columns: {' '.join(sorted(present))})",
            file=sys.stderr,
        )
        return 2
    keys = {key for run in runs for key in run.config}
    unmatched = [p for p in args.ignore if not any(fnmatch.fnmatchcase(key, p) for key in keys)]
    if unmatched:
        print(
            f"aggregate.py: --ignore {' '.join(unmatched)}: matches no configuration key of the runs "
            "(dotted keys such as update_dtype or planner.build_dtype)",
            file=sys.stderr,
        )
        return 2
    ignored = (*IGNORED_KEYS, *args.ignore)
    out = Path(args.out or args.paths[0])
    reference = {env: dict(points) for env, points in PAPER_SUCCESS.items()}
    print(
        f"{len(runs)} runs: "
        + ", ".join(f"{r.env} seed {r.seed} ({r.path.name}, {variant_of(r, runs, ignored)})" for r in runs)
    )
    sections, written = [], []
    for i, metric in enumerate(args.metric):
        table = aggregate_runs(runs, metric=metric, ignored=ignored, reps=args.reps, smooth=args.smooth)
        name = output_name(metric, first=i == 0)
        success = is_success(metric)
        written.append(write_aggregate_csv(table, out / f"{name}.csv"))
        written.append(
            plot_aggregate(
                table,
                out / f"{name}.png",
                reference=reference if metric == PAPER_METRIC else None,
                metric_label=("final-state success" if metric == PAPER_METRIC else metric)
                + (f", mean of the last {args.smooth}" if args.smooth > 1 else ""),
                ylim=(-0.02, 1.02) if success else None,
            )
        )
        heading = f"## {metric}\n\n" if len(args.metric) > 1 else ""
        if args.smooth > 1:
            heading += f"Each run's value: the mean of its last {args.smooth} evaluations (`--smooth {args.smooth}`).\n\n"
        sections.append(heading + summary_markdown(table, reference, metric))
    markdown = "\n".join(sections)
    (out / "aggregate.md").write_text(markdown)
    print(markdown)
    print("Written: " + ", ".join(str(p) for p in [*written, out / "aggregate.md"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
