"""Test-time switches over a task's seeds: each run's paired ``variants_eval.yaml`` (``recipes/evaluate.py
--variant``) side by side, pooled over the runs, with the verdict of a rule fixed beforehand.

    python recipes/evaluate.py ~/runs/bn_s0 --episodes 50 --variant planner.edge_rule=connected \\
        --variant high.critic_candidates=8      # the same for every seed, then:
    python recipes/variants_summary.py ~/runs/bn_s{0,1,2,3} --out results/antmazebottleneck_cps/switches.md

One row per variant (its changed keys): per run, the agent as trained and the variant on the same test episodes
(successes of episodes) with the episodes only the variant / only the agent as trained succeeded in; then the
runs pooled (:func:`~torchrl_dhrl.recipe.pooled_comparison`: the counts summed, the exact McNemar p-value of the
summed discordant episodes) and the verdict: **helps** where the pooled discordant episodes favour the variant
with ``p < --alpha`` (0.05), **hurts** where they favour the agent as trained with ``p < --alpha``, **no clear
effect** otherwise. Every run must hold the same variants (refused otherwise, before any table, naming the run).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

import yaml
from dhrl_utils import print_table

from torchrl_dhrl.recipe import PairedComparison, pooled_comparison

#: The record ``recipes/evaluate.py --variant`` writes in a run directory.
VARIANTS_EVAL_NAME = "variants_eval.yaml"


def variant_name(changes: dict) -> str:
    """``{"high.critic_candidates": 8}`` -> ``high.critic_candidates=8`` (keys sorted, space-separated)."""
    return " ".join(f"{key}={yaml.safe_dump(value, default_flow_style=True).strip().removesuffix('...').strip()}"
                    for key, value in sorted(changes.items()))


def read_record(path: str | Path) -> dict:
    """A run's ``variants_eval.yaml`` (``path``: the run directory or the file); ``SystemExit`` naming the run
    where it has none or it holds no variant."""
    path = Path(path)
    file = path / VARIANTS_EVAL_NAME if path.is_dir() else path
    if not file.is_file():
        raise SystemExit(
            f"{path}: no {VARIANTS_EVAL_NAME}; write it with `python recipes/evaluate.py {path} --variant KEY=VALUE`."
        )
    record = yaml.safe_load(file.read_text())
    if not record.get("variants"):
        raise SystemExit(f"{file}: holds no variant (recipes/evaluate.py was run without --variant).")
    return record


def comparisons(record: dict) -> dict[str, PairedComparison]:
    """The record's variants by :func:`variant_name`, each as a :class:`~torchrl_dhrl.recipe.PairedComparison`
    against the agent as trained."""
    return {
        variant_name(v["changes"]): PairedComparison(
            episodes=record["episodes"],
            reference=record["successes"],
            variant=v["successes"],
            only_variant=v["only_variant"],
            only_reference=v["only_reference"],
            p_value=v["p_value"],
        )
        for v in record["variants"]
    }


def verdict(pooled: PairedComparison, alpha: float = 0.05) -> str:
    """``helps``, ``hurts`` or ``no clear effect`` (see the module's docstring).

    Examples:
        >>> from torchrl_dhrl.recipe import paired_comparison
        >>> verdict(paired_comparison([0] * 10, [1] * 10)), verdict(paired_comparison([0, 1], [1, 0]))
        ('helps', 'no clear effect')
    """
    if pooled.p_value >= alpha or pooled.only_variant == pooled.only_reference:
        return "no clear effect"
    return "helps" if pooled.only_variant > pooled.only_reference else "hurts"


def summarize(paths: Sequence[str | Path], alpha: float = 0.05) -> list[dict]:
    """One row per variant: ``variant``, ``runs`` (per run, its :class:`PairedComparison`), ``pooled`` and
    ``verdict``. Every run is read and checked first."""
    records = [read_record(path) for path in paths]
    per_run = [comparisons(record) for record in records]
    names = list(per_run[0])
    for path, runs in zip(paths, per_run, strict=True):
        if sorted(runs) != sorted(names):
            raise SystemExit(
                f"{path}: its variants ({', '.join(sorted(runs))}) differ from {paths[0]}'s ({', '.join(sorted(names))}); "
                "evaluate every run with the same --variant options."
            )
    rows = []
    for name in names:
        runs = [run[name] for run in per_run]
        pooled = pooled_comparison(runs)
        rows.append({"variant": name, "runs": runs, "pooled": pooled, "verdict": verdict(pooled, alpha)})
    return rows


def markdown(rows: Sequence[dict], paths: Sequence[str | Path], alpha: float) -> str:
    """The table: a line per variant, a column per run, then the pooled counts, p-value and verdict."""
    names = [Path(p).name if Path(p).is_dir() else Path(p).parent.name for p in paths]
    head = ["variant", *(f"{n}: as trained -> variant (only variant / only as trained)" for n in names)]
    head += ["pooled: as trained -> variant", "only variant / only as trained", "McNemar p", f"verdict (p < {alpha:g})"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in rows:
        cells = [f"`{row['variant']}`"]
        cells += [
            f"{c.reference}/{c.episodes} -> {c.variant}/{c.episodes} ({c.only_variant} / {c.only_reference})"
            for c in row["runs"]
        ]
        pooled = row["pooled"]
        cells += [
            f"{pooled.reference}/{pooled.episodes} -> {pooled.variant}/{pooled.episodes}",
            f"{pooled.only_variant} / {pooled.only_reference}",
            f"{pooled.p_value:.3g}",
            f"**{row['verdict']}**",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help=f"run directories (or their {VARIANTS_EVAL_NAME})")
    parser.add_argument("--alpha", type=float, default=0.05, help="the verdict's significance level")
    parser.add_argument("--out", default=None, help="also write the table to this file")
    args = parser.parse_args(argv)
    if not 0 < args.alpha < 1:
        parser.error("--alpha must lie in (0, 1)")
    rows = summarize(args.runs, args.alpha)
    print_table(markdown(rows, args.runs, args.alpha), args.out)
    return rows


if __name__ == "__main__":
    main()
