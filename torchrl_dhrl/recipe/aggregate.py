"""Many runs, reported the way the paper reports them: success per evaluation point over seeds.

:func:`find_runs` collects run directories (each with the recipe's ``metrics.csv`` and its configuration),
:func:`aggregate_runs` groups them by task and variant (the configuration keys that differ between runs of
the same task, seeds and run bookkeeping aside) and computes, at every evaluation point all the group's
runs reached: the mean and standard deviation over seeds (the paper's convention) and the interquartile
mean (IQM) with a percentile-bootstrap 95% confidence interval over seeds (Agarwal et al., 2021, as
``rliable`` computes them: ``scipy.stats.trim_mean(x, 0.25)`` and resampled seeds).
:func:`plot_aggregate` draws success against env steps per task, one line per variant, with the paper's
points. ``recipes/aggregate.py`` is the command line.
"""

from __future__ import annotations

import csv
import fnmatch
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from matplotlib.figure import Figure
from scipy.stats import trim_mean

from .run import read_provenance, write_csv
from .schema import IGNORED_KEYS, RESOLVED_KEYS, with_implied_keys

__all__ = [
    "RunRecord",
    "aggregate_runs",
    "bootstrap_iqm_ci",
    "find_runs",
    "iqm",
    "plot_aggregate",
    "write_aggregate_csv",
]

#: Where a run directory may keep its configuration, in the order they are tried.
CONFIG_FILES = ("config.yaml", ".hydra/config.yaml", "hydra/.hydra/config.yaml")


@dataclass
class RunRecord:
    """One run: its directory, configuration (flattened dotted keys) and evaluation rows."""

    path: Path
    config: dict[str, Any]
    rows: list[dict[str, float]] = field(repr=False)

    @property
    def env(self) -> str:
        return str(self.config.get("env_name", "unknown"))

    @property
    def seed(self) -> Any:
        return self.config.get("seed", self.path.name)


def _flatten(cfg: Mapping, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in cfg.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out |= _flatten(value, f"{name}.")
        else:
            out[name] = tuple(value) if isinstance(value, list) else value
    return out


def _number(text: str) -> float:
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan


def read_run(path: str | Path) -> RunRecord:
    """The run in directory ``path``: ``metrics.csv`` and the first configuration file of :data:`CONFIG_FILES`.

    A run without a configuration file gets ``{"env_name": "unknown"}`` (grouped on its own by directory).
    A key of :data:`RESOLVED_KEYS` set to ``auto`` takes the value it resolved to, where the run's
    :data:`~torchrl_dhrl.recipe.PROVENANCE_NAME` records one value for every start (``auto`` stays for a run
    without that record, or resumed on machines that resolved it differently).
    """
    path = Path(path)
    with open(path / "metrics.csv", newline="") as file:
        rows = [{k: _number(v) for k, v in row.items()} for row in csv.DictReader(file)]
    config: dict[str, Any] = {"env_name": "unknown"}
    for name in CONFIG_FILES:
        if (path / name).is_file():
            # an older run's configuration lacks the keys added since: the values it was trained with
            config = _flatten(with_implied_keys(yaml.safe_load((path / name).read_text()) or {}))
            break
    starts = read_provenance(path)
    for key in RESOLVED_KEYS:
        values = {str(start.get("precision", {}).get(key)) for start in starts}
        if config.get(key) == "auto" and len(values) == 1 and "None" not in values:
            config[key] = values.pop()
    return RunRecord(path, config, rows)


def find_runs(roots: Iterable[str | Path]) -> list[RunRecord]:
    """Every run directory (a folder with ``metrics.csv``) under ``roots`` (searched recursively), sorted."""
    found = set()
    for root in roots:
        root = Path(root)
        candidates = [root / "metrics.csv"] if (root / "metrics.csv").is_file() else []
        found.update(p.parent.resolve() for p in [*candidates, *root.rglob("metrics.csv")])
    return [read_run(p) for p in sorted(found)]


def _ignored(key: str, patterns: Sequence[str]) -> bool:
    return any(fnmatch.fnmatchcase(key, pattern) for pattern in patterns)


def variant_of(run: RunRecord, runs: Sequence[RunRecord], ignored: Sequence[str] = IGNORED_KEYS) -> str:
    """The keys of ``run``'s configuration that differ between the runs of its task, as ``k=v`` text.

    ``"default"`` when the task's runs differ only in ignored keys (seeds, paths, ...).
    """
    same_task = [r for r in runs if r.env == run.env]
    keys = sorted({k for r in same_task for k in r.config} - {"env_name"})
    differing = [
        k for k in keys if not _ignored(k, ignored) and len({repr(r.config.get(k)) for r in same_task}) > 1
    ]
    if not differing:
        return "default"
    return " ".join(f"{k}={_text(run.config.get(k))}" for k in differing)


def _text(value: Any) -> str:
    if isinstance(value, tuple):
        return "[" + ",".join(_text(v) for v in value) + "]"
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    return str(value)


def iqm(values: Sequence[float] | np.ndarray) -> float:
    """Interquartile mean: the mean of the middle 50% (``scipy.stats.trim_mean(x, 0.25)``, as rliable).

    Examples:
        >>> iqm([0.0, 0.5, 0.7, 1.0])  # the lowest and the highest of four runs are dropped
        0.6
    """
    return float(trim_mean(np.asarray(values, dtype=float), 0.25))


def bootstrap_iqm_ci(
    values: Sequence[float] | np.ndarray, *, reps: int = 2000, confidence: float = 0.95, seed: int = 0
) -> tuple[float, float]:
    """Percentile-bootstrap confidence interval of the IQM, resampling the runs with replacement.

    Examples:
        >>> low, high = bootstrap_iqm_ci([0.2, 0.5, 0.9, 1.0], reps=1000)
        >>> 0.2 <= low <= iqm([0.2, 0.5, 0.9, 1.0]) <= high <= 1.0
        True
    """
    x = np.asarray(values, dtype=float)
    rng = np.random.default_rng(seed)
    samples = x[rng.integers(0, len(x), size=(reps, len(x)))]
    stats = trim_mean(samples, 0.25, axis=1)
    alpha = (1.0 - confidence) / 2.0
    low, high = np.quantile(stats, [alpha, 1.0 - alpha])
    return float(low), float(high)


def _column(run: RunRecord, metric: str) -> dict[float, float]:
    """``run``'s evaluation points (env steps) -> value of ``metric``, where the value is present."""
    return {row["env_steps"]: row[metric] for row in run.rows if not math.isnan(row.get(metric, math.nan))}


def _trailing_mean(points: dict[float, float], window: int) -> dict[float, float]:
    """Each point's value replaced by the mean of the last ``window`` values up to it, in env-step order."""
    if window == 1:
        return points
    steps = sorted(points)
    values = np.array([points[s] for s in steps])
    sums = np.concatenate([[0.0], np.cumsum(values)])
    lows = np.maximum(np.arange(len(steps)) + 1 - window, 0)
    means = (sums[1:] - sums[lows]) / (np.arange(len(steps)) + 1 - lows)
    return dict(zip(steps, means.tolist(), strict=True))


def aggregate_runs(
    runs: Sequence[RunRecord],
    *,
    metric: str = "eval/success",
    ignored: Sequence[str] = IGNORED_KEYS,
    reps: int = 2000,
    smooth: int = 1,
) -> list[dict[str, Any]]:
    """One row per task, variant and evaluation point that every run of the group reached.

    Columns: ``env``, ``variant``, ``env_steps``, ``n`` (runs), ``mean``, ``std`` (sample standard deviation
    over runs, ``ddof=1``; 0 for one run), ``iqm``, ``iqm_ci_low``, ``iqm_ci_high`` (95% percentile
    bootstrap), ``min``, ``max``, ``seeds`` and ``values`` (per run, in seed order).

    ``smooth=k`` replaces each run's value at an evaluation point by the mean of its last ``k`` evaluations
    (that one included; fewer at the run's start) before the statistics over runs: a 10-episode success rate
    is a coarse estimate, and the paper's curves are smoothed too.
    """
    if int(smooth) != smooth or smooth < 1:
        raise ValueError(f"smooth must be an integer >= 1 (evaluations per trailing mean), got {smooth!r}.")
    groups: dict[tuple[str, str], list[RunRecord]] = {}
    for run in runs:
        groups.setdefault((run.env, variant_of(run, runs, ignored)), []).append(run)
    table = []
    for (env, variant), members in sorted(groups.items()):
        members = sorted(members, key=lambda r: repr(r.seed))
        per_run = [_trailing_mean(_column(r, metric), int(smooth)) for r in members]
        common = sorted(set.intersection(*(set(p) for p in per_run))) if per_run else []
        for steps in common:
            values = np.array([p[steps] for p in per_run])
            low, high = bootstrap_iqm_ci(values, reps=reps)
            table.append(
                {
                    "env": env,
                    "variant": variant,
                    "env_steps": int(steps),
                    "n": len(values),
                    "mean": float(values.mean()),
                    "std": float(values.std(ddof=1)) if len(values) > 1 else 0.0,
                    "iqm": iqm(values),
                    "iqm_ci_low": low,
                    "iqm_ci_high": high,
                    "min": float(values.min()),
                    "max": float(values.max()),
                    "seeds": " ".join(_text(r.seed) for r in members),
                    "values": " ".join(f"{v:g}" for v in values),
                }
            )
    return table


def write_aggregate_csv(table: Sequence[Mapping[str, Any]], path: str | Path) -> Path:
    """Writes the rows of :func:`aggregate_runs` as CSV (atomically: a temporary file, then renamed)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    columns = list(table[0]) if table else ["env", "variant", "env_steps", "n", "mean", "std", "iqm"]
    return write_csv(table, columns, path)


def plot_aggregate(
    table: Sequence[Mapping[str, Any]],
    path: str | Path,
    *,
    reference: Mapping[str, Mapping[float, float]] | None = None,
    metric_label: str = "final-state success",
    ylim: tuple[float, float] | None = (-0.02, 1.02),
) -> Path:
    """Saves success against env steps, one panel per task and one line per variant: the mean with a band of
    one standard deviation, the IQM dashed with its bootstrap interval shaded lightly and each seed's curve
    faintly where a variant has several seeds (one seed: its curve alone). The x-axis spans the runs' own
    steps; the paper's points (``reference[env]``: steps -> success) are drawn by
    :func:`~torchrl_dhrl.recipe.plots.draw_paper_reference` (crosses within those steps, a labelled horizontal
    line for a budget beyond them), and each panel's legend sits below it. ``ylim``: the value axis' limits
    (``None``: fitted to the data, for columns that are not rates)."""
    from .plots import draw_paper_reference  # here: plots imports the env and planner packages

    envs = sorted({row["env"] for row in table})
    fig = Figure(figsize=(5.5 * max(len(envs), 1), 5), layout="constrained")
    panels = fig.subfigures(1, max(len(envs), 1), squeeze=False)[0]
    for panel, env in zip(panels, envs, strict=False):
        ax = panel.subplots()
        rows = [row for row in table if row["env"] == env]
        for variant in sorted({row["variant"] for row in rows}):
            sel = sorted((row for row in rows if row["variant"] == variant), key=lambda r: r["env_steps"])
            x = np.array([r["env_steps"] for r in sel])
            n = sel[-1]["n"]
            mean, std = np.array([r["mean"] for r in sel]), np.array([r["std"] for r in sel])
            label = f"{variant} (n={n}): mean ± std" if n > 1 else f"{variant} (n=1)"
            line = ax.plot(x, mean, marker="o", ms=3, label=label, zorder=3)[0]
            if n > 1:  # the spread over seeds, and each seed faintly: few seeds' spread hides which did what
                ax.fill_between(x, mean - std, mean + std, color=line.get_color(), alpha=0.2)
                iqm_line = [r["iqm"] for r in sel]
                ax.plot(x, iqm_line, ls="--", color=line.get_color(), alpha=0.8, label="IQM, 95% CI")
                per_seed = np.array([[float(v) for v in r["values"].split()] for r in sel])
                ax.plot(x, per_seed, lw=0.7, color=line.get_color(), alpha=0.35)
                ax.fill_between(
                    x,
                    [r["iqm_ci_low"] for r in sel],
                    [r["iqm_ci_high"] for r in sel],
                    color=line.get_color(),
                    alpha=0.07,
                )
        draw_paper_reference(
            ax, (reference or {}).get(env), [row["env_steps"] for row in rows], label="paper (DHRL)"
        )
        ax.set_title(env, fontsize=10)
        ax.set_xlabel("env steps (warm-up included)")
        ax.set_ylabel(metric_label)
        if ylim is not None:
            ax.set_ylim(*ylim)
        ax.grid(alpha=0.3)
        panel.legend(loc="outside lower center", fontsize=7, frameon=False)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    return path
