"""The committed results tables are what ``recipes/report.py`` renders from the committed runs; every run folder
of ``results/index.yaml`` carries its provenance; every relative link of the docs resolves."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest
import yaml
from _recipe import load_recipe

import torchrl_dhrl.recipe.protocol as protocol_module

ROOT = Path(__file__).resolve().parents[1]
report = load_recipe("report")


def test_committed_tables_are_the_rendered_ones():
    stale = [str(p.relative_to(ROOT)) for p, text in report.render(ROOT).items() if p.read_text() != text]
    assert not stale, f"run `python recipes/report.py`: {stale} differ from what it renders"


def test_check_mode_names_a_table_edited_by_hand(tmp_path, capsys):
    (tmp_path / "docs").mkdir()
    shutil.copy(ROOT / "README.md", tmp_path / "README.md")
    shutil.copy(ROOT / "docs" / "results.md", tmp_path / "docs" / "results.md")
    shutil.copytree(ROOT / "results", tmp_path / "results")
    assert report.main(["--check"], root=tmp_path) == 0
    readme = tmp_path / "README.md"
    readme.write_text(readme.read_text().replace("| AntMaze |", "| AntMaze (typed by hand) |", 1))
    assert report.main(["--check"], root=tmp_path) == 1
    assert "README.md: differs" in capsys.readouterr().err
    assert report.main([], root=tmp_path) == 0 and report.main(["--check"], root=tmp_path) == 0


def test_every_indexed_run_has_metrics_config_and_provenance():
    for entry in yaml.safe_load((ROOT / "results" / "index.yaml").read_text()):
        folder = ROOT / "results" / entry["folder"]
        for name in [*entry["runs"], *(entry.get("baseline") or {}).get("runs", [])]:
            run = folder / name
            assert (run / "metrics.csv").is_file(), run
            starts = yaml.safe_load((run / "provenance.yaml").read_text())
            assert starts and all(s["code"]["commit"] and s["command"] for s in starts), run
            if not name.startswith("sac"):
                assert (run / "config.yaml").is_file(), run


def test_results_holds_only_indexed_folders():
    indexed = {entry["folder"] for entry in yaml.safe_load((ROOT / "results" / "index.yaml").read_text())}
    folders = {p.name for p in (ROOT / "results").iterdir() if p.is_dir()}
    assert folders == indexed


@pytest.mark.parametrize("doc", ["README.md", "docs", "results", "benchmarks/README.md", "CHANGELOG.md"])
def test_relative_links_resolve(doc):
    paths = [ROOT / doc] if doc.endswith(".md") else sorted((ROOT / doc).rglob("*.md"))
    broken = []
    for path in paths:
        text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)  # links inside code blocks are code
        for target in re.findall(r"\]\(([^)\s#]+)", text):
            if (
                "://" not in target
                and not target.startswith("mailto:")
                and not (path.parent / target).exists()
            ):
                broken.append(f"{path.relative_to(ROOT)}: {target}")
    assert not broken, broken


def test_a_baseline_runs_final_evaluation_is_reported(tmp_path):
    """A baseline run with a ``final_eval.yaml`` (benchmarks/sac_her_baseline.py writes one) shows its count in the
    results table, as a DHRL run's; one without it reads "agent not kept"."""
    (tmp_path / "docs").mkdir()
    shutil.copy(ROOT / "README.md", tmp_path / "README.md")
    shutil.copy(ROOT / "docs" / "results.md", tmp_path / "docs" / "results.md")
    shutil.copytree(ROOT / "results", tmp_path / "results")
    sac = tmp_path / "results" / "pointmaze_umaze_dhrl_vs_sac" / "sac_s1"
    (sac / "final_eval.yaml").write_text(yaml.safe_dump({"env_steps": 30000, "episodes": 100, "successes": 87}))
    doc = report.render(tmp_path)[tmp_path / "docs" / "results.md"]
    table = doc.split("<!-- report:results -->")[1].split("<!-- /report:results -->")[0]
    rows = [line for line in table.splitlines() if line.startswith("| gymnasium:PointMaze_UMaze-v3 | SAC + HER")]
    assert rows and all("| agent not kept, 87/100 (87.0%) at 30k, agent not kept |" in row for row in rows)


def test_the_runs_table_names_a_baseline_run_by_its_agent():
    """docs/results.md's provenance table: a DHRL run's row holds its entry's configuration, a baseline run's the
    baseline's name (it did not run that configuration)."""
    entries = report.read_entries(ROOT)
    table = report.runs_table(entries, ROOT / "docs")
    checked = 0
    for entry in (e for e in entries if e.baseline):
        for name, _ in entry.named_runs():
            row = next(line for line in table.splitlines() if f"[{entry.spec['folder']}/{name}](" in line)
            configuration = row.split(" | ")[1]
            if name in entry.spec["baseline"]["runs"]:
                assert configuration == entry.baseline_name, row
                checked += 1
            else:
                assert configuration == f"`{entry.spec['configuration']}`", row
    assert checked >= 2


def test_the_provenance_column_says_what_was_reconstructed_and_from_what():
    recorded = {"started": "2026-01-01T00:00:00+00:00", "env_steps": 0}
    docs = {**recorded, "provenance": "reconstructed: ... as docs/results.md stated them when the run was reported"}
    notes = {**recorded, "provenance": "reconstructed: commit from the snapshot, command from the run notes"}
    assert report.reconstruction_text([recorded, recorded]) == "recorded by the recipe"
    assert report.reconstruction_text([docs, docs]) == "reconstructed from the docs"
    assert report.reconstruction_text([docs, notes]) == "reconstructed from run notes"
    assert report.reconstruction_text([notes, recorded, recorded]) == "reconstructed from run notes for 1 of 3 starts"


def test_the_readme_sets_each_baseline_beside_dhrl_at_every_reporting_point(tmp_path):
    """README's "against a flat agent" table: a row per point either agent's runs reach, the other agent's cell
    ``-`` where its runs do not reach it, and the final agents pooled over the runs that kept one."""
    (tmp_path / "docs").mkdir()
    shutil.copy(ROOT / "README.md", tmp_path / "README.md")
    shutil.copy(ROOT / "docs" / "results.md", tmp_path / "docs" / "results.md")
    shutil.copytree(ROOT / "results", tmp_path / "results")
    folder = tmp_path / "results" / "pointmaze_umaze_dhrl_vs_sac"
    for name, successes in (("sac_s1", 87), ("sac_s2", 90)):
        (folder / name / "final_eval.yaml").write_text(
            yaml.safe_dump({"env_steps": 27000, "episodes": 100, "successes": successes})
        )
    entry = next(e for e in report.read_entries(tmp_path) if e.folder.name == "pointmaze_umaze_dhrl_vs_sac")
    table = report.render(tmp_path)[tmp_path / "README.md"]
    rows = [line for line in table.splitlines() if line.startswith(f"| {entry.task} |")]
    ours = {report.steps_text(p["steps"]): p for p in entry.points(entry.runs)}
    theirs = {report.steps_text(p["steps"]): p for p in entry.points(entry.baseline)}
    steps_of = {report.steps_text(p["steps"]): p["steps"] for p in [*ours.values(), *theirs.values()]}
    assert [row.split(" | ")[1] for row in rows] == sorted(steps_of, key=steps_of.get)
    for row in rows:
        steps = row.split(" | ")[1]
        for points, agent_cell in ((ours, row.split(" | ")[2]), (theirs, row.split(" | ")[3])):
            if steps in points:
                assert f"**{report.over_seeds(points[steps])}**" in agent_cell, row
            else:
                assert agent_cell.endswith("-"), row
        assert "| not kept; 88.5% (2 of 3 runs, 100 episodes each) |" in row


def _first_reaching(run_dir: Path, successes: int) -> str:
    """The first evaluation's env steps with at least ``successes`` of 10, read off metrics.csv directly."""
    import csv

    with open(run_dir / "metrics.csv", newline="") as file:
        rows = [r for r in csv.DictReader(file) if r.get("eval/success") not in (None, "", "nan")]
    steps = [float(r["env_steps"]) for r in rows if round(10 * float(r["eval/success"])) >= successes]
    return report.steps_text(min(steps)) if steps else "never"


@pytest.mark.parametrize("first_at, successes", [(None, 9), (0.8, 8), (0.25, 3)])
def test_an_entry_names_the_success_its_runs_first_reach(tmp_path, first_at, successes):
    """report.md lists per run the first evaluation with at least ``first_at`` of its test episodes (0.9 unless the
    entry says), counted in whole episodes; a value outside (0, 1] is refused in one line naming the entry."""
    shutil.copytree(ROOT / "results", tmp_path / "results")
    index = tmp_path / "results" / "index.yaml"
    entries = yaml.safe_load(index.read_text())
    spec = next(e for e in entries if e["folder"] == "pointmaze_umaze_dhrl_vs_sac")
    if first_at is not None:
        spec["first_at"] = first_at
    index.write_text(yaml.safe_dump(entries))
    entry = next(e for e in report.read_entries(tmp_path) if e.spec["folder"] == spec["folder"])
    text = report.folder_report(entry)
    assert f"| first evaluation with >= {successes} of 10 |" in text
    for name in [*spec["runs"], *spec["baseline"]["runs"]]:
        row = next(line for line in text.splitlines() if line.startswith(f"| [{name}]({name}) |"))
        assert row.split(" | ")[2] == _first_reaching(entry.folder / name, successes), row
    spec["first_at"] = 1.5
    index.write_text(yaml.safe_dump(entries))
    with pytest.raises(ValueError, match="pointmaze_umaze_dhrl_vs_sac.*first_at 1.5"):
        report.read_entries(tmp_path)


def test_an_entry_compared_to_another_sets_its_seeds_beside_theirs(tmp_path):
    """``compare_to``: report.md holds each seed both entries ran, its two windows and their difference, with the
    means; a folder that is not another entry of the same task is refused in one line naming the choices."""
    shutil.copytree(ROOT / "results", tmp_path / "results")
    index = tmp_path / "results" / "index.yaml"
    entries = yaml.safe_load(index.read_text())
    spec = next(e for e in entries if e.get("compare_to"))
    entry = next(e for e in report.read_entries(tmp_path) if e.spec["folder"] == spec["folder"])
    other = entry.compared
    assert other is not None and other.spec["folder"] == spec["compare_to"]
    text = report.folder_report(entry)
    protocol = entry.protocol
    others = {r.seed: r for r in other.runs}
    rows = [line for line in text.splitlines() if line.startswith("| ") and " | mean over " not in line]
    paired = 0
    for run in entry.runs:
        if run.seed not in others:
            continue
        for budget in protocol.budgets:
            if not (protocol_module.reached(run, budget) and protocol_module.reached(others[run.seed], budget)):
                continue
            ours = protocol_module.window_success(run, budget, protocol.window)
            theirs = protocol_module.window_success(others[run.seed], budget, protocol.window)
            expected = (
                f"| {report.steps_text(budget)} | {run.seed} | {ours.successes}/{ours.episodes} "
                f"({report.pct(ours.rate)}) | {theirs.successes}/{theirs.episodes} ({report.pct(theirs.rate)}) | "
                f"{100 * (ours.rate - theirs.rate):+.1f} |"
            )
            assert expected in rows, (expected, rows)
            paired += 1
    assert paired and sum(" | mean over " in line for line in text.splitlines()) >= 1
    for bad in (spec["folder"], "antmaze_cpu", "no_such_folder"):
        spec["compare_to"] = bad
        index.write_text(yaml.safe_dump(entries))
        with pytest.raises(ValueError, match=f"compare_to '{bad}': must name another entry's folder of the same task"):
            report.read_entries(tmp_path)


def test_the_machine_column_says_whether_the_cpu_has_native_bfloat16():
    """What `update_dtype=auto` resolved by: recorded with the machine, shown unless the CPU's name already says it."""
    recorded = {"machine": {"cpu": "AMD EPYC", "cores": 2, "native_bfloat16": False}}
    assert report.machine_text(recorded) == "AMD EPYC (no native bfloat16), 2 cores"
    recorded["machine"]["native_bfloat16"] = True
    assert report.machine_text(recorded) == "AMD EPYC (native bfloat16), 2 cores"
    named = {"machine": {"cpu": "AMD EPYC (AVX2, no AVX512)", "cores": 2, "native_bfloat16": False}}
    assert report.machine_text(named) == "AMD EPYC (AVX2, no AVX512), 2 cores"
    assert report.machine_text({"machine": {"cpu": "Intel Xeon"}, "device": "cuda"}) == "Intel Xeon, cuda"
    trademarked = {"machine": {"cpu": "Intel(R) Xeon(R) Processor", "cores": 2, "native_bfloat16": True}}
    assert report.machine_text(trademarked) == "Intel(R) Xeon(R) Processor (native bfloat16), 2 cores"


def test_a_docs_page_holding_the_against_flat_block_gets_readmes_table_with_its_own_links(tmp_path):
    """README's against-flat table, rendered into a ``docs/*.md`` page that holds its block (docs/goal_env.md), with
    the links relative to that page; a page without the block is left out."""
    (tmp_path / "docs").mkdir()
    shutil.copy(ROOT / "README.md", tmp_path / "README.md")
    shutil.copy(ROOT / "docs" / "results.md", tmp_path / "docs" / "results.md")
    shutil.copytree(ROOT / "results", tmp_path / "results")
    (tmp_path / "docs" / "page.md").write_text("# A page\n\n<!-- report:against-flat -->\nold\n<!-- /report:against-flat -->\n")
    (tmp_path / "docs" / "other.md").write_text("# No block\n")
    out = report.render(tmp_path)
    assert tmp_path / "docs" / "other.md" not in out

    def block(text):
        return text.split("<!-- report:against-flat -->\n")[1].split("<!-- /report:against-flat -->")[0]

    page, readme = block(out[tmp_path / "docs" / "page.md"]), block(out[tmp_path / "README.md"])
    assert "old" not in page and "](results/" in readme
    assert page == readme.replace("](results/", "](../results/")
    assert out[tmp_path / "docs" / "page.md"].startswith("# A page\n\n")


def test_agents_stopped_apart_short_of_a_budget_are_also_set_side_by_side_where_both_got(tmp_path):
    """DHRL's runs stop at 28.5k and 42k, the baseline's at 27k and 36k, all short of the budget: the table keeps
    each agent's own last point (the other's cell ``-``) and sets both at 27k, the last evaluation every run of both
    reached, each seed's window read off its metrics.csv directly."""
    import csv

    (tmp_path / "docs").mkdir()
    shutil.copy(ROOT / "README.md", tmp_path / "README.md")
    shutil.copy(ROOT / "docs" / "results.md", tmp_path / "docs" / "results.md")
    shutil.copytree(ROOT / "results", tmp_path / "results")
    index = tmp_path / "results" / "index.yaml"
    specs = yaml.safe_load(index.read_text())
    spec = next(e for e in specs if e["folder"] == "pointmaze_umaze_dhrl_vs_sac")
    spec["budgets"] = [60000]  # beyond every run
    index.write_text(yaml.safe_dump(specs, sort_keys=False))
    table = report.render(tmp_path)[tmp_path / "README.md"]
    rows = {row.split(" | ")[1]: row.split(" | ") for row in table.splitlines()
            if row.startswith("| gymnasium:PointMaze_UMaze-v3 |")}
    assert list(rows) == ["27k", "28.5k"]
    folder = tmp_path / "results" / "pointmaze_umaze_dhrl_vs_sac"

    def per_seed(run):  # the 9k window ending at 27k: successes over its test episodes
        with open(folder / run / "metrics.csv", newline="") as file:
            evals = [float(r["eval/success"]) for r in csv.DictReader(file)
                     if r.get("eval/success") not in (None, "", "nan") and 18000 < float(r["env_steps"]) <= 27000]
        return f"{100 * sum(evals) / len(evals):.1f}%"

    dhrl, sac = rows["27k"][2], rows["27k"][3]
    assert "the last point every run of both agents reached; short of 60k" in dhrl
    assert ", ".join(per_seed(f"dhrl_s{k}") for k in range(3)) in dhrl
    assert sac.startswith("SAC + HER: **") and ", ".join(per_seed(f"sac_s{k}") for k in range(3)) in sac
    assert rows["28.5k"][3] == "SAC + HER: -" and "the last point every seed reached" in rows["28.5k"][2]
