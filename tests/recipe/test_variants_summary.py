"""recipes/variants_summary.py and ``pooled_comparison``: paired test-time comparisons of several runs pooled, against
the comparison of all their episodes at once (scipy), the verdict's rule at its boundaries, bad records refused before
any table."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from _recipe import load_recipe
from scipy.stats import binomtest

from torchrl_dhrl.recipe import paired_comparison, pooled_comparison


@pytest.fixture(scope="module")
def summary():
    return load_recipe("variants_summary")


def _record(reference, variants: dict) -> dict:
    """A ``variants_eval.yaml`` record as recipes/evaluate.py writes it, from per-episode successes."""
    out = {"episodes": len(reference), "successes": int(np.sum(reference)), "variants": []}
    for name, successes in variants.items():
        key, _, value = name.partition("=")
        paired = paired_comparison(reference, successes)
        out["variants"].append(
            {"changes": {key: yaml.safe_load(value)}, "successes": paired.variant, "success": paired.variant / len(reference),
             "only_variant": paired.only_variant, "only_reference": paired.only_reference, "p_value": paired.p_value}
        )
    return out


@pytest.mark.parametrize("seed", range(6))
def test_pooling_seeds_is_comparing_all_their_episodes_at_once(seed, summary, tmp_path):
    """Runs of random lengths and success rates (ties, all-concordant runs, a run where the variant never differs):
    the pooled counts are those of the concatenated episodes, the p-value scipy's exact binomial test of them."""
    rng = np.random.default_rng(seed)
    runs, all_reference, all_variant = [], [], []
    for k in range(int(rng.integers(1, 5))):
        n = int(rng.integers(1, 40))
        reference = rng.random(n) < rng.random()
        variant = reference.copy() if k == 0 else rng.random(n) < rng.random()
        path = tmp_path / f"seed{k}"
        path.mkdir()
        (path / "variants_eval.yaml").write_text(yaml.safe_dump(_record(reference, {"planner.edge_rule=connected": variant})))
        runs.append(path)
        all_reference.append(reference)
        all_variant.append(variant)
    (row,) = summary.summarize(runs)
    a, b = np.concatenate(all_reference), np.concatenate(all_variant)
    only_variant, only_reference = int((b & ~a).sum()), int((a & ~b).sum())
    pooled = row["pooled"]
    assert (pooled.episodes, pooled.reference, pooled.variant) == (a.size, int(a.sum()), int(b.sum()))
    assert (pooled.only_variant, pooled.only_reference) == (only_variant, only_reference)
    discordant = only_variant + only_reference
    expected = binomtest(only_variant, discordant, 0.5).pvalue if discordant else 1.0
    assert pooled.p_value == pytest.approx(expected)
    assert pooled_comparison(row["runs"]) == pooled and len(row["runs"]) == len(runs)


def test_the_verdict_and_the_table(summary, tmp_path, capsys):
    """6 of 6 discordant episodes for the variant: p = 1/32, helps at 0.05; 5 of 5 against: p = 1/16, no clear effect
    at 0.05, hurts at 0.1; an even split never has an effect."""
    ones, zeros = [True] * 6, [False] * 6
    for k, (reference, helps, hurts, even) in enumerate(
        [(zeros, ones, zeros, [True, False] * 3), (ones[:5], ones[:5], [False] * 5, [False, True] * 2 + [True])]
    ):
        path = tmp_path / f"seed{k}"
        path.mkdir()
        record = _record(reference, {"a=1": helps, "b=2": hurts, "c=3": even})
        (path / "variants_eval.yaml").write_text(yaml.safe_dump(record))
    rows = summary.main([str(tmp_path / "seed0"), str(tmp_path / "seed1")])
    assert [r["verdict"] for r in rows] == ["helps", "no clear effect", "no clear effect"]
    assert rows[0]["pooled"].p_value == pytest.approx(1 / 32) and rows[1]["pooled"].p_value == pytest.approx(1 / 16)
    table = capsys.readouterr().out
    assert "| `a=1` | 0/6 -> 6/6 (6 / 0) | 5/5 -> 5/5 (0 / 0) | 5/11 -> 11/11 | 6 / 0 | 0.0312 | **helps** |" in table
    rows = summary.main([str(tmp_path / "seed0"), str(tmp_path / "seed1"), "--alpha", "0.1", "--out", str(tmp_path / "t.md")])
    assert [r["verdict"] for r in rows] == ["helps", "hurts", "no clear effect"]
    assert (tmp_path / "t.md").read_text() == capsys.readouterr().out


def test_bad_records_are_refused_before_any_table(summary, tmp_path, capsys):
    good, other, empty = (tmp_path / n for n in ("good", "other", "empty"))
    for path, record in ((good, _record([True, False], {"a=1": [True, True]})),
                         (other, _record([True, False], {"b=1": [True, True]})),
                         (empty, {"episodes": 2, "successes": 1})):
        path.mkdir()
        (path / "variants_eval.yaml").write_text(yaml.safe_dump(record))
    with pytest.raises(SystemExit, match=r"no variants_eval.yaml; write it with `python recipes/evaluate.py"):
        summary.main([str(good), str(tmp_path)])
    with pytest.raises(SystemExit, match="holds no variant"):
        summary.main([str(good), str(empty)])
    with pytest.raises(SystemExit, match=r"its variants \(b=1\) differ from .*good's \(a=1\)"):
        summary.main([str(good), str(other)])
    assert capsys.readouterr().out == ""
    with pytest.raises(SystemExit):
        summary.main([str(good), "--alpha", "1.5"])
    with pytest.raises(ValueError, match="at least one comparison"):
        pooled_comparison([])
