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
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from dhrl_utils import PAPER_SUCCESS

from torchrl_dhrl.recipe import aggregate_runs, find_runs, plot_aggregate, write_aggregate_csv


def summary_markdown(table: list[dict], reference: dict) -> str:
    """A markdown table: per task and variant, the last common evaluation point and the paper's points."""
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
        for r in sorted(picked, key=lambda r: r["env_steps"]):
            ref = ", ".join(f"{100 * v:.1f}% at {s / 1e6:g}M" for s, v in paper.items()) or "-"
            lines.append(
                f"| {env} | {variant} | {r['env_steps']} | {r['n']} | {100 * r['mean']:.1f}% ± {100 * r['std']:.1f} | "
                f"{100 * r['iqm']:.1f}% [{100 * r['iqm_ci_low']:.1f}, {100 * r['iqm_ci_high']:.1f}] | "
                f"{r['values']} | {ref} |"
            )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("paths", nargs="+", help="run directories or folders holding them")
    parser.add_argument("--out", default=None, help="output folder (default: the first path)")
    parser.add_argument("--metric", default="eval/success", help="metrics.csv column (default eval/success)")
    parser.add_argument("--reps", type=int, default=2000, help="bootstrap resamples")
    args = parser.parse_args(argv)
    runs = find_runs(args.paths)
    if not runs:
        print(f"aggregate.py: no metrics.csv under {' '.join(args.paths)}", file=sys.stderr)
        return 2
    table = aggregate_runs(runs, metric=args.metric, reps=args.reps)
    out = Path(args.out or args.paths[0])
    csv_path = write_aggregate_csv(table, out / "aggregate.csv")
    reference = {env: dict(points) for env, points in PAPER_SUCCESS.items()}
    png = plot_aggregate(table, out / "aggregate.png", reference=reference)
    markdown = summary_markdown(table, reference)
    (out / "aggregate.md").write_text(markdown)
    print(f"{len(runs)} runs: " + ", ".join(f"{r.env} seed {r.seed} ({r.path.name})" for r in runs))
    print(markdown)
    print(f"Table: {csv_path}, figure: {png}, summary: {out / 'aggregate.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
