"""The results protocol (:mod:`torchrl_dhrl.recipe.protocol`) against direct computations on hand-made runs."""

from __future__ import annotations

import math
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from torchrl_dhrl.recipe.aggregate import RunRecord
from torchrl_dhrl.recipe.protocol import (
    Protocol,
    ReportPoint,
    episodes_succeeded,
    first_at_least,
    paired_windows,
    report_points,
    summarize_point,
    window_success,
)


def _run(steps, successes, episodes=10, name="run"):
    """A run whose evaluations at ``steps`` had ``successes`` whole episodes of ``episodes``, stored as float32."""
    rows = [
        {"env_steps": float(s), "eval/success": float(np.float32(k / episodes))}
        for s, k in zip(steps, successes, strict=True)
    ]
    rows.insert(0, {"env_steps": 0.0, "eval/success": math.nan})  # a row without an evaluation is skipped
    return RunRecord(Path(name), {"schedule.eval_episodes": episodes}, rows)


@pytest.mark.parametrize("episodes", [1, 3, 7, 10, 20, 50, 100])
def test_whole_episodes_from_float32_rates(episodes):
    # every k of n survives float32 storage: 9 of 10 is 0.8999999761..., which `>= 0.9` misses
    for k in range(episodes + 1):
        stored = float(np.float32(k / episodes))
        assert episodes_succeeded(stored, episodes) == k
    assert float(np.float32(0.9)) < 0.9  # the float trap this guards against


@pytest.mark.parametrize("rate", [0.55, -0.1, 1.1, math.nan])
def test_a_rate_that_is_no_whole_number_of_episodes_is_refused(rate):
    with pytest.raises(ValueError, match="whole number of 10 test episodes"):
        episodes_succeeded(rate, 10)


def test_protocol_window_and_bad_budgets():
    assert Protocol((250_000, 500_000)).window == 25_000
    assert Protocol((2_500_000, 4_000_000)).window == 250_000
    assert Protocol((27_000,), window=9_000).window == 9_000
    for bad in [(), (500_000, 250_000), (0,), (100, 100)]:
        with pytest.raises(ValueError, match="budgets"):
            Protocol(bad)
    with pytest.raises(ValueError, match="window"):
        Protocol((100,), window=0)


@pytest.mark.parametrize("seed", range(20))
def test_window_success_matches_a_direct_count(seed):
    # random evaluation steps (repeated spacings, windows that start or end on an evaluation) and successes
    rng = np.random.default_rng(seed)
    episodes = int(rng.choice([5, 10, 20]))
    steps = np.cumsum(rng.choice([1000, 1500, 3000], size=60))
    successes = rng.integers(0, episodes + 1, size=60)
    run = _run(steps, successes, episodes)
    for _ in range(10):
        end = int(rng.choice([*steps[5:], *(rng.integers(steps[5], steps[-1], size=3))]))
        window = int(rng.choice([1000, 3000, 7500, 25_000]))
        inside = [k for s, k in zip(steps, successes, strict=True) if end - window < s <= end]
        if not inside:
            with pytest.raises(ValueError, match="no evaluation"):
                window_success(run, end, window)
            continue
        got = window_success(run, end, window)
        assert (got.successes, got.episodes, got.evaluations) == (
            sum(inside),
            episodes * len(inside),
            len(inside),
        )
        assert Fraction(got.successes, got.episodes) == Fraction(int(sum(inside)), episodes * len(inside))
        # the window is half-open: an evaluation exactly `window` before the end is out, one at the end is in
        assert got.first_step > end - window and got.last_step <= end


def test_an_empty_window_is_refused():
    with pytest.raises(ValueError, match=r"no evaluation in \(100, 200\]"):
        window_success(_run([50, 300], [1, 1]), 200, 100)


def test_report_points_all_seeds_reach_every_budget():
    a = _run(range(9000, 1_000_001, 9000), [5] * 111, name="a")  # last evaluation 999k
    b = _run(
        range(3000, 994_000, 9000), [5] * 111, name="b"
    )  # last evaluation 993k: within one interval of 1M
    points = report_points([a, b], Protocol((500_000, 1_000_000)))
    assert [(p.steps, p.kind, len(m)) for p, m in points] == [
        (500_000, "budget", 2),
        (1_000_000, "budget", 2),
    ]


def test_report_points_a_seed_stopping_short_adds_the_last_common_point():
    a = _run(range(9000, 1_000_001, 9000), [5] * 111, name="a")
    b = _run(range(9000, 820_000, 9000), [5] * 91, name="b")  # stopped at 819k
    points = report_points([a, b], Protocol((500_000, 1_000_000)))
    assert [(p.steps, p.kind, [r.path.name for r in m]) for p, m in points] == [
        (500_000, "budget", ["a", "b"]),
        (819_000, "last common", ["a", "b"]),
        (1_000_000, "budget", ["a"]),
    ]


def test_report_points_no_budget_reached():
    a, b = _run([9000, 18000, 27000], [0, 5, 10], name="a"), _run([9000, 18000], [0, 3], name="b")
    points = report_points([a, b], Protocol((250_000, 500_000)))
    assert points == [(ReportPoint(18_000, "last common"), [a, b])]


def test_summary_over_seeds_matches_numpy_and_the_interquartile_mean():
    steps = list(range(1000, 51_000, 1000))
    rng = np.random.default_rng(3)
    runs = [_run(steps, rng.integers(0, 11, size=len(steps)), name=f"s{i}") for i in range(4)]
    protocol = Protocol((50_000,))
    summary = summarize_point(runs, ReportPoint(50_000, "budget"), protocol)
    rates = np.array([w.successes / w.episodes for w in summary["seeds"]])
    for run, w in zip(runs, summary["seeds"], strict=True):  # the window: the last 5 evaluations (5k of 50k)
        direct = sum(round(r["eval/success"] * 10) for r in run.rows[-5:])
        assert (w.successes, w.episodes) == (direct, 50)
    assert summary["mean"] == pytest.approx(rates.mean())
    assert summary["std"] == pytest.approx(rates.std(ddof=1))
    middle = np.sort(rates)[1:3]  # IQM of 4 runs: the mean of the middle two
    assert summary["iqm"] == pytest.approx(middle.mean())
    low, high = summary["iqm_ci"]
    assert rates.min() <= low <= summary["iqm"] <= high <= rates.max()
    one = summarize_point(runs[:1], ReportPoint(50_000, "budget"), protocol)
    assert one["std"] == 0.0 and one["mean"] == one["iqm"]


def test_first_at_least_counts_whole_episodes():
    run = _run([1000, 2000, 3000, 4000], [8, 9, 10, 9])
    assert first_at_least(run, 9) == 2000  # stored 0.8999999761, which `>= 0.9` would have skipped
    assert first_at_least(run, 10) == 3000
    assert first_at_least(_run([1000], [3]), 9) is None


def _seeded(seed, steps, successes, name):
    run = _run(steps, successes, name=name)
    run.config["seed"] = seed
    return run


@pytest.mark.parametrize("trial", range(25))
def test_paired_windows_against_a_direct_count(trial):
    """Random runs of two configurations, some seeds in one only, some stopping short of a budget, ties in the
    rates: each budget pairs exactly the seeds whose two runs reached it, over the same window, counted directly."""
    rng = np.random.default_rng(trial)
    budgets, window, interval = (60, 120), 30, 10

    def make(seeds, prefix):
        runs = []
        for seed in seeds:
            last = int(rng.choice([40, 60, 90, 120]))  # some stop short of a budget
            steps = list(range(interval, last + 1, interval))
            runs.append(_seeded(seed, steps, rng.integers(0, 11, len(steps)).tolist(), f"{prefix}{seed}"))
        return runs

    ours = make(rng.permutation(5)[: rng.integers(1, 6)].tolist(), "a")
    theirs = make(rng.permutation(5)[: rng.integers(1, 6)].tolist(), "b")
    points = paired_windows(ours, theirs, Protocol(budgets, window=window))

    def direct(run, budget):  # successes over (budget - window, budget], read off the stored rates
        return sum(round(10 * r["eval/success"]) for r in run.rows if budget - window < r["env_steps"] <= budget)

    def last(run):
        return max(r["env_steps"] for r in run.rows)

    expected = {}
    for budget in budgets:
        pairs = [
            (a, b)
            for a in ours
            for b in theirs
            if a.seed == b.seed and last(a) > budget - interval and last(b) > budget - interval
        ]
        if pairs:
            expected[budget] = pairs
    assert [p.steps for p in points] == list(expected)
    for point in points:
        pairs = expected[point.steps]
        assert point.seeds == tuple(a.seed for a, _ in pairs)
        rates = [(direct(a, point.steps) / 30, direct(b, point.steps) / 30) for a, b in pairs]
        assert [w.successes for w in point.windows] == [direct(a, point.steps) for a, _ in pairs]
        assert [w.successes for w in point.other_windows] == [direct(b, point.steps) for _, b in pairs]
        assert all(w.episodes == 30 for w in (*point.windows, *point.other_windows))
        diffs = np.array([x - y for x, y in rates])
        assert point.mean_difference == pytest.approx(diffs.mean())
        assert point.std_difference == pytest.approx(diffs.std(ddof=1) if len(diffs) > 1 else 0.0)
        assert point.mean - point.other_mean == pytest.approx(diffs.mean())


def test_paired_windows_refuses_a_seed_twice():
    a, b = _seeded(0, [10, 20], [5, 5], "a"), _seeded(0, [10, 20], [1, 2], "b")
    with pytest.raises(ValueError, match="`others` holds more than one run of seed 0"):
        paired_windows([a], [b, b], Protocol((20,), window=20))
    assert paired_windows([a], [_seeded(1, [10, 20], [1, 2], "c")], Protocol((20,), window=20)) == []
