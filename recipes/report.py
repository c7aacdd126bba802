"""Renders the results tables of README.md, docs/results.md and each results folder's report.md from the
committed runs, under the protocol of docs/results.md (:mod:`torchrl_dhrl.recipe.protocol`).

    python recipes/report.py            # rewrite the tables
    python recipes/report.py --curves   # and draw each folder's success.png (the protocol's curve over seeds)
    python recipes/report.py --check    # exit 1, naming each file, where a committed table differs

The entries come from ``results/index.yaml`` (a folder of seeds per task and configuration); every figure
comes from a run's ``metrics.csv``, ``config.yaml``, ``provenance.yaml`` and, where its agent was kept,
``final_eval.yaml`` (``recipes/evaluate.py``). In README.md and docs/results.md the tables sit between
``<!-- report:NAME -->`` and ``<!-- /report:NAME -->``; the text around them is not touched. README's
``against-flat`` table is also rendered into any other ``docs/*.md`` page that holds its block.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

import yaml
from dhrl_utils import PAPER_SUCCESS

from torchrl_dhrl.recipe.aggregate import RunRecord, plot_aggregate, read_run
from torchrl_dhrl.recipe.protocol import (
    Protocol,
    ReportPoint,
    eval_episodes,
    evaluation_steps,
    first_at_least,
    paired_windows,
    report_points,
    summarize_point,
)
from torchrl_dhrl.recipe.run import read_provenance

ROOT = Path(__file__).resolve().parents[1]
INDEX = Path("results") / "index.yaml"
FINAL_EVAL = "final_eval.yaml"


def steps_text(steps: float) -> str:
    """Env steps as the tables print them: ``84k``, ``249.5k``, ``1M``, ``2.5M``.

    Examples:
        >>> [steps_text(s) for s in (84_000, 249_500, 1_000_000, 2_500_000, 993_000)]
        ['84k', '249.5k', '1M', '2.5M', '993k']
    """
    if steps >= 1_000_000 and steps % 100_000 == 0:
        return f"{steps / 1e6:g}M"
    return f"{steps / 1e3:g}k"


def pct(rate: float) -> str:
    return f"{100 * rate:.1f}%"


class Entry:
    """One entry of ``results/index.yaml``: its runs (and baseline runs) read, its protocol and paper figures."""

    def __init__(self, spec: Mapping, root: Path) -> None:
        self.spec = dict(spec)
        self.task = str(spec["task"])
        self.root = root
        self.folder = root / "results" / str(spec["folder"])
        self.paper = dict(PAPER_SUCCESS.get(self.task, {}))
        budgets = spec.get("budgets") or sorted(self.paper)
        if not budgets:
            raise ValueError(f"{INDEX}: {self.task} has no paper budgets; give `budgets:` in its entry.")
        self.protocol = Protocol(tuple(budgets), spec.get("window"))
        self.first_at = float(spec.get("first_at", 0.9))
        if not 0 < self.first_at <= 1:
            raise ValueError(
                f"{INDEX}: {self.task} ({spec['folder']}): first_at {spec.get('first_at')!r}: must be a fraction "
                "of an evaluation's test episodes in (0, 1] (0.9: 9 of 10)."
            )
        self.runs = [read_run(self.folder / name) for name in spec["runs"]]
        baseline = spec.get("baseline") or {}
        self.baseline_name = baseline.get("name")
        self.baseline = [read_run(self.folder / name) for name in baseline.get("runs", [])]
        self.compared: Entry | None = None  # the entry its `compare_to` names, set by read_entries

    def first_successes(self, run: RunRecord) -> int:
        """The successes of ``first_at`` of ``run``'s test episodes per evaluation, whole (0.8 of 10 is 8)."""
        return math.ceil(self.first_at * eval_episodes(run) - 1e-9)

    def named_runs(self) -> list[tuple[str, RunRecord]]:
        """Every run of the entry, the baseline's after, with its folder's name."""
        names = [*self.spec["runs"], *(self.spec.get("baseline") or {}).get("runs", [])]
        return list(zip(names, [*self.runs, *self.baseline], strict=True))

    def points(self, runs: Sequence[RunRecord]) -> list[dict]:
        return [
            summarize_point(members, point, self.protocol)
            for point, members in report_points(runs, self.protocol)
        ]


def last_step(run: RunRecord) -> float:
    """The env steps of ``run``'s last row."""
    return max(r["env_steps"] for r in run.rows)


def seeds_text(point: Mapping) -> str:
    return ", ".join(f"{w.successes}/{w.episodes}" for w in point["seeds"])


def point_label(point: Mapping, entry: Entry, runs: Sequence[RunRecord] | None = None) -> str:
    """``84k (the last point every seed reached; short of 250k)``, ``1M (seed1 only)``, ``500k``."""
    notes = []
    if point["kind"] in ("last common", "both agents"):
        short = [b for b in entry.protocol.budgets if b > point["steps"]]
        which = "every seed" if point["kind"] == "last common" else "every run of both agents"
        notes.append(f"the last point {which} reached" + (f"; short of {steps_text(short[0])}" if short else ""))
    runs = entry.runs if runs is None else runs
    if len(point["seeds"]) < len(runs):
        notes.append(f"{len(point['seeds'])} of {len(runs)} seeds")
    return steps_text(point["steps"]) + (f" ({'; '.join(notes)})" if notes else "")


def iqm_text(point: Mapping) -> str:
    """``72.2% [30.0, 100.0]``: the IQM over seeds and its 95% bootstrap interval."""
    low, high = point["iqm_ci"]
    return f"{pct(point['iqm'])} [{100 * low:.1f}, {100 * high:.1f}]"


def over_seeds(point: Mapping) -> str:
    """``72.2% ± 37.2`` over several seeds, ``64.0%`` for one."""
    return (
        f"{pct(point['mean'])} ± {100 * point['std']:.1f}" if len(point["seeds"]) > 1 else pct(point["mean"])
    )


def paper_text(entry: Entry) -> str:
    if not entry.paper:
        return "-"
    return ", ".join(f"{pct(v)} at {steps_text(s)}" for s, v in sorted(entry.paper.items()))


def machine_text(start: Mapping) -> str:
    machine = start.get("machine") or {}
    text = str(machine.get("cpu", "?"))
    says_it = "AVX" in text or "bfloat16" in text.lower()  # names reconstructed from the docs carry it
    if machine.get("native_bfloat16") is not None and not says_it:  # what update_dtype=auto resolves by
        text += " (native bfloat16)" if machine["native_bfloat16"] else " (no native bfloat16)"
    if machine.get("cores"):
        text += f", {machine['cores']} cores"
    device = start.get("device")
    return f"{text}, {device}" if device and device != "cpu" else text


def provenance_rows(run: RunRecord) -> dict[str, str]:
    starts = read_provenance(run.path)
    if not starts:
        return {"code": "unknown", "machine": "unknown", "provenance": "none: cannot be established"}
    commits = []
    for start in starts:
        commit = (start.get("code") or {}).get("commit")
        short = commit[:7] if commit else "not a git checkout"
        if (start.get("code") or {}).get("modified"):
            short += " (modified)"
        if short not in commits:
            commits.append(short)
    machines = list(dict.fromkeys(machine_text(s) for s in starts))
    status = reconstruction_text(starts)
    resumes = len(starts) - 1
    if resumes:
        status += f"; {resumes} resume{'s' if resumes > 1 else ''}"
    return {"code": ", then ".join(commits), "machine": "; ".join(machines), "provenance": status}


def reconstruction_text(starts: list[dict]) -> str:
    """"recorded by the recipe", or where a start's record was filled in afterwards (its ``provenance`` note says
    how): from what, and for how many of the run's starts where not all."""
    notes = [start["provenance"] for start in starts if "provenance" in start]
    if not notes:
        return "recorded by the recipe"
    source = "the docs" if all("docs/" in note for note in notes) else "run notes"
    share = "" if len(notes) == len(starts) else f" for {len(notes)} of {len(starts)} starts"
    return f"reconstructed from {source}{share}"


def final_eval_text(run: RunRecord) -> str:
    path = run.path / FINAL_EVAL
    if not path.is_file():
        return "agent not kept"
    record = yaml.safe_load(path.read_text())
    return (
        f"{record['successes']}/{record['episodes']} ({pct(record['successes'] / record['episodes'])}) "
        f"at {steps_text(record['env_steps'])}"
    )


def folder_report(entry: Entry) -> str:
    """The entry's ``report.md``: every reporting point, per seed and over seeds, and each run's provenance."""
    p = entry.protocol
    lines = [
        f"# {entry.task}: `{entry.spec['configuration']}`",
        "",
        "Generated by `python recipes/report.py` from the runs of this folder (do not edit). Protocol "
        "([docs/results.md]("
        + _rel(entry.folder, entry.root / "docs" / "results.md")
        + ")): per seed, the test episodes "
        f"that succeeded over the evaluations in the {steps_text(p.window)} env steps up to each point; over "
        "seeds, mean ± std and the IQM with its 95% bootstrap interval.",
        "",
        f"Paper (4 seeds): {paper_text(entry)}. Reporting budgets: "
        + ", ".join(steps_text(b) for b in p.budgets)
        + ". The same success at every evaluation all seeds reached, mean ± std over seeds: "
        "[success.png](success.png) (`python recipes/report.py --curves`).",
        "",
    ]
    lines += _points_table(entry, entry.runs, entry.spec["runs"])
    if entry.baseline:
        lines += ["", f"Baseline, {entry.baseline_name}, evaluated the same way:", ""]
        lines += _points_table(entry, entry.baseline, entry.spec["baseline"]["runs"])
    if entry.compared is not None:
        lines += ["", *comparison_lines(entry, entry.compared)]
    lines += [
        "",
        f"| run | last evaluation | first evaluation with >= {entry.first_successes(entry.runs[0])} of "
        f"{eval_episodes(entry.runs[0])} | final agent re-evaluated | "
        "code | machine | provenance |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, run in entry.named_runs():
        prov = provenance_rows(run)
        first = first_at_least(run, entry.first_successes(run))
        lines.append(
            f"| [{name}]({name}) | {steps_text(last_step(run))} | {steps_text(first) if first is not None else 'never'} | "
            f"{final_eval_text(run)} | {prov['code']} | {prov['machine']} | {prov['provenance']} |"
        )
    return "\n".join(lines) + "\n"


def comparison_lines(entry: Entry, other: Entry) -> list[str]:
    """``entry``'s runs against ``other``'s seed by seed (:func:`paired_windows`, ``entry``'s windows): per seed the
    successes of each over the same window, the difference in points, and over the paired seeds the mean of each and
    the mean ± std of the differences."""
    link = f"[{other.spec['folder']}]({_rel(entry.folder, other.folder / 'report.md')})"
    points = paired_windows(entry.runs, other.runs, entry.protocol)
    lines = [
        f"Seed by seed against {link} (`{other.spec['configuration']}`): each seed's runs over the same window, at "
        "each budget both reached.",
        "",
    ]
    if not points:
        return [*lines, "No seed of both has reached a budget yet."]
    lines += [
        f"| env steps | seed | this folder: successes / episodes | {other.spec['folder']} | difference (points) |",
        "|---|---|---|---|---|",
    ]
    for point in points:
        label = steps_text(point.steps)
        for seed, ours, theirs, diff in zip(
            point.seeds, point.windows, point.other_windows, point.differences, strict=True
        ):
            lines.append(
                f"| {label} | {seed} | {ours.successes}/{ours.episodes} ({pct(ours.rate)}) | "
                f"{theirs.successes}/{theirs.episodes} ({pct(theirs.rate)}) | {100 * diff:+.1f} |"
            )
        lines.append(
            f"| {label} | mean over {len(point.seeds)} seed{'s' if len(point.seeds) > 1 else ''} | "
            f"{pct(point.mean)} | {pct(point.other_mean)} | "
            f"{100 * point.mean_difference:+.1f} ± {100 * point.std_difference:.1f} |"
        )
    return lines


def _points_table(entry: Entry, runs: Sequence[RunRecord], names: Sequence[str]) -> list[str]:
    lines = [
        f"| env steps | evaluations per seed | per seed ({', '.join(names)}): successes / episodes | mean ± std | IQM [95% CI] | paper |",
        "|---|---|---|---|---|---|",
    ]
    for point in entry.points(runs):
        paper = entry.paper.get(point["steps"]) if point["kind"] == "budget" else None
        evals = sorted({w.evaluations for w in point["seeds"]})
        lines.append(
            f"| {point_label(point, entry, runs)} | {evals[0] if len(evals) == 1 else f'{evals[0]}-{evals[-1]}'} | "
            f"{seeds_text(point)} | {over_seeds(point)} | "
            f"{iqm_text(point)} | {pct(paper) if paper is not None else '-'} |"
        )
    return lines


def _rel(frm: Path, to: Path) -> str:
    return os.path.relpath(to, frm)


def glance_table(entries: Sequence[Entry], frm: Path) -> str:
    """README's "Results at a glance": one row per task, its entry marked ``glance``."""
    lines = [
        "| task | paper (4 seeds) | ours: mean ± std over seeds (per seed) | seeds | configuration | details |",
        "|---|---|---|---|---|---|",
    ]
    for entry in entries:
        if not entry.spec.get("glance"):
            continue
        ours = "; ".join(
            f"**{over_seeds(pt)}** at {point_label(pt, entry)}"
            + (f": {', '.join(pct(w.rate) for w in pt['seeds'])}" if len(pt["seeds"]) > 1 else "")
            for pt in entry.points(entry.runs)
        )
        lines.append(
            f"| {entry.task} | {paper_text(entry)} | {ours} | {len(entry.runs)} | `{entry.spec['configuration']}` | "
            f"[report]({_rel(frm, entry.folder / 'report.md')}) |"
        )
    return "\n".join(lines)


def against_flat_table(entries: Sequence[Entry], frm: Path) -> str:
    """README's "Against a flat agent": every entry with a baseline, both agents at each of its reporting points
    (a point only one of them reached reads ``-`` for the other), and where the two stopped at different points
    short of a budget, both at the last evaluation every run of both reached; with their final agents'
    re-evaluations."""
    lines = [
        "| task | env steps | DHRL: mean ± std over seeds (per seed) | flat agent, the same protocol | "
        "final agents re-evaluated (DHRL; flat) | seeds | details |",
        "|---|---|---|---|---|---|---|",
    ]

    def cell(point: Mapping | None, runs: Sequence[RunRecord], entry: Entry) -> str:
        if point is None:
            return "-"
        label = point_label(point, entry, runs)
        note = label[len(steps_text(point["steps"])) :].strip()  # "(the last point every seed reached ...)"
        per_seed = f": {', '.join(pct(w.rate) for w in point['seeds'])}" if len(point["seeds"]) > 1 else ""
        return f"**{over_seeds(point)}**{per_seed}" + (f" {note}" if note else "")

    def finals(runs: Sequence[RunRecord]) -> str:
        kept = [yaml.safe_load((r.path / FINAL_EVAL).read_text()) for r in runs if (r.path / FINAL_EVAL).is_file()]
        if not kept:
            return "not kept"
        rate = sum(k["successes"] for k in kept) / sum(k["episodes"] for k in kept)
        return f"{pct(rate)} ({len(kept)} of {len(runs)} runs, {kept[0]['episodes']} episodes each)"

    for entry in entries:
        if not entry.baseline:
            continue
        ours = {pt["steps"]: pt for pt in entry.points(entry.runs)}
        theirs = {pt["steps"]: pt for pt in entry.points(entry.baseline)}
        # the protocol's last common point over the runs of both agents, side by side where both got
        for joint, _ in report_points([*entry.runs, *entry.baseline], entry.protocol):
            if joint.kind == "last common" and not (joint.steps in ours and joint.steps in theirs):
                point = ReportPoint(joint.steps, "both agents")
                ours[joint.steps] = summarize_point(entry.runs, point, entry.protocol)
                theirs[joint.steps] = summarize_point(entry.baseline, point, entry.protocol)
        flat = entry.baseline_name.split(" (")[0]
        for steps in sorted(ours.keys() | theirs.keys()):
            lines.append(
                f"| {entry.task} | {steps_text(steps)} | {cell(ours.get(steps), entry.runs, entry)} | "
                f"{flat}: {cell(theirs.get(steps), entry.baseline, entry)} | "
                f"{finals(entry.runs)}; {finals(entry.baseline)} | {len(entry.runs)}, {len(entry.baseline)} | "
                f"[report]({_rel(frm, entry.folder / 'report.md')}) |"
            )
    return "\n".join(lines)


def results_table(entries: Sequence[Entry], frm: Path) -> str:
    """docs/results.md's table: every entry at every reporting point."""
    lines = [
        "| task | configuration | env steps | per seed: successes / episodes | mean ± std | IQM [95% CI] | paper | final agents | report |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for entry in entries:
        link = f"[{entry.spec['folder']}]({_rel(frm, entry.folder / 'report.md')})"
        agents = [(f"`{entry.spec['configuration']}`", entry.runs)]
        if entry.baseline:
            agents.append((entry.baseline_name, entry.baseline))
        for name, runs in agents:
            finals = ", ".join(final_eval_text(r) for r in runs)  # the baseline's final models too
            for point in entry.points(runs):
                paper = (
                    entry.paper.get(point["steps"])
                    if point["kind"] == "budget" and runs is entry.runs
                    else None
                )
                lines.append(
                    f"| {entry.task} | {name} | {point_label(point, entry, runs)} | {seeds_text(point)} | "
                    f"{over_seeds(point)} | {iqm_text(point)} | "
                    f"{pct(paper) if paper is not None else '-'} | {finals} | {link} |"
                )
    return "\n".join(lines)


def runs_table(entries: Sequence[Entry], frm: Path) -> str:
    """docs/results.md's provenance table: each run's code, machine and how its provenance is known."""
    lines = [
        "| task | configuration | run | last evaluation | code | machine | provenance |",
        "|---|---|---|---|---|---|---|",
    ]
    for entry in entries:
        baseline = (entry.spec.get("baseline") or {}).get("runs", [])
        for name, run in entry.named_runs():
            # a baseline's run is named by its agent, as in the results table, not by DHRL's configuration
            configuration = entry.baseline_name if name in baseline else f"`{entry.spec['configuration']}`"
            prov = provenance_rows(run)
            lines.append(
                f"| {entry.task} | {configuration} | [{entry.spec['folder']}/{name}]({_rel(frm, run.path)}) | "
                f"{steps_text(last_step(run))} | {prov['code']} | {prov['machine']} | {prov['provenance']} |"
            )
    return "\n".join(lines)


def main_job_text(entries: Sequence[Entry]) -> str:
    """README's expectation for its first command (PointMaze, ``preset=quick``), from the committed seeds."""
    entry = next(e for e in entries if e.task == "PointMaze" and e.spec.get("glance"))
    firsts = [first_at_least(r, 9) for r in entry.runs]
    machines = {provenance_rows(r)["machine"] for r in entry.runs}
    point = entry.points(entry.runs)[0]
    reached = [steps_text(f) for f in firsts if f is not None]
    minutes = [
        next(r["time/wall_s"] for r in run.rows if r["env_steps"] == point["steps"]) / 60
        for run in entry.runs
    ]
    return (
        f"Over the {len(entry.runs)} committed seeds of this command ({len(machines)} kinds of 2-core CPU, one thread, "
        f"another run on the other core), {steps_text(point['steps'])} env steps took {min(minutes):.0f}-"
        f"{max(minutes):.0f} min of wall clock; the first "
        f"evaluation with at least 9 of 10 test goals reached came at {', '.join(reached)} env steps, and success "
        f"over the evaluations of the last {steps_text(entry.protocol.window)} up to {steps_text(point['steps'])} was "
        f"{', '.join(pct(w.rate) for w in point['seeds'])} (seeds {', '.join(str(r.seed) for r in entry.runs)}); "
        "a run on another CPU gives other numbers from its first update on."
    )


def curve_table(entry: Entry) -> list[dict]:
    """The protocol's success at every evaluation all of the entry's seeds reached (each seed's window ending
    there), per agent, as rows of :func:`~torchrl_dhrl.recipe.plot_aggregate`."""
    rows = []
    for name, runs in [("DHRL", entry.runs), (entry.baseline_name, entry.baseline)]:
        if not runs:
            continue
        common = sorted(set.intersection(*(set(evaluation_steps(r)) for r in runs)))
        for steps in common:
            if steps <= entry.protocol.window // 2:  # a window that would hold too little of itself
                continue
            point = summarize_point(runs, ReportPoint(steps, "curve"), entry.protocol, reps=200)
            low, high = point["iqm_ci"]
            rows.append(
                {
                    "env": entry.task,
                    "variant": name,
                    "env_steps": steps,
                    "n": len(runs),
                    "mean": point["mean"],
                    "std": point["std"],
                    "iqm": point["iqm"],
                    "iqm_ci_low": low,
                    "iqm_ci_high": high,
                    "values": " ".join(f"{w.rate:g}" for w in point["seeds"]),
                }
            )
    return rows


def write_curves(entries: Sequence[Entry]) -> None:
    """Each entry's ``success.png``: the protocol's per-seed window success at every common evaluation."""
    for entry in entries:
        label = f"final-state success over the last {steps_text(entry.protocol.window)}"
        plot_aggregate(
            curve_table(entry),
            entry.folder / "success.png",
            reference={entry.task: entry.paper},
            metric_label=label,
        )


def replace_block(text: str, name: str, body: str, path: Path) -> str:
    pattern = re.compile(rf"(<!-- report:{name} -->\n).*?(<!-- /report:{name} -->)", re.S)
    if not pattern.search(text):
        raise SystemExit(f"{path}: no `<!-- report:{name} -->` ... `<!-- /report:{name} -->` block.")
    return pattern.sub(lambda m: m.group(1) + body + "\n" + m.group(2), text)


def read_entries(root: Path = ROOT) -> list[Entry]:
    """The entries of ``results/index.yaml``, each ``compare_to`` resolved to the entry of that folder (same task)."""
    entries = [Entry(spec, root) for spec in yaml.safe_load((root / INDEX).read_text())]
    by_folder = {str(e.spec["folder"]): e for e in entries}
    for entry in entries:
        target = entry.spec.get("compare_to")
        if target is None:
            continue
        other = by_folder.get(str(target))
        if other is None or other is entry or other.task != entry.task:
            raise ValueError(
                f"{INDEX}: {entry.spec['folder']}: compare_to {target!r}: must name another entry's folder of the same "
                f"task ({entry.task}): "
                + (", ".join(f for f, e in by_folder.items() if e.task == entry.task and e is not entry) or "none")
            )
        entry.compared = other
    return entries


def render(root: Path = ROOT) -> dict[Path, str]:
    """Every generated file's new text: ``{path: text}``."""
    entries = read_entries(root)
    out: dict[Path, str] = {e.folder / "report.md": folder_report(e) for e in entries}
    readme = root / "README.md"
    text = replace_block(readme.read_text(), "glance", glance_table(entries, root), readme)
    text = replace_block(text, "against-flat", against_flat_table(entries, root), readme)
    out[readme] = replace_block(text, "main-job", main_job_text(entries), readme)
    results = root / "docs" / "results.md"
    text = replace_block(results.read_text(), "results", results_table(entries, results.parent), results)
    out[results] = replace_block(text, "runs", runs_table(entries, results.parent), results)
    for page in sorted((root / "docs").glob("*.md")):  # pages that quote the against-flat table
        text = page.read_text()
        if page != results and "<!-- report:against-flat -->" in text:
            out[page] = replace_block(text, "against-flat", against_flat_table(entries, page.parent), page)
    return out


def main(argv: list[str] | None = None, root: Path = ROOT) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 where a committed table differs")
    parser.add_argument("--curves", action="store_true", help="also draw each folder's success.png")
    args = parser.parse_args(argv)
    if args.curves and not args.check:
        write_curves(read_entries(root))
    stale = []
    for path, text in render(root).items():
        if path.is_file() and path.read_text() == text:
            continue
        if args.check:
            stale.append(path)
        else:
            path.write_text(text)
            print(f"wrote {path.relative_to(root)}")
    for path in stale:
        print(
            f"{path.relative_to(root)}: differs from what recipes/report.py renders; run it.", file=sys.stderr
        )
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main())
