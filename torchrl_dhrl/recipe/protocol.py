"""The results protocol: how one number per seed and one per task are read off the runs' evaluations.

The paper reports the mean of 4 seeds at fixed env-step budgets from curves "smoothed equally". A single
evaluation here is 10 test episodes, a rate known to about ±15 points; so, per seed, the success at a budget
``B`` is the fraction of the test episodes that succeeded over every evaluation in the window ``(B - W, B]``,
with ``W`` a tenth of the task's first budget (:attr:`Protocol.window`): for AntMaze's 0.5M and 1M, the
evaluations of the last 50k env steps before each. Successes are counted in whole episodes
(:func:`episodes_succeeded`: ``eval/success`` times the run's test episodes, rounded), never by comparing a
stored float with a threshold. Over seeds: the mean and sample standard deviation, and the interquartile mean
with its 95% percentile-bootstrap interval (:func:`~torchrl_dhrl.recipe.iqm`,
:func:`~torchrl_dhrl.recipe.bootstrap_iqm_ci`).

The reporting points (:func:`report_points`) are the budgets; a budget counts for the seeds that reached it
(their last evaluation within one evaluation interval of it). Where a seed stopped short of a budget, the
last evaluation every seed reached is reported too, labelled as such, so that no run is dropped and no point
is chosen after seeing the curves.

Two variants of one agent (as trained, and with a test-time switch) are compared on the same test episodes
(:func:`paired_comparison`): the episodes only one of them succeeded in, and the exact McNemar test on those. Two
configurations trained from the same seeds (without and with a switch) are compared seed by seed over the same
windows (:func:`paired_windows`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .aggregate import RunRecord, bootstrap_iqm_ci, iqm

__all__ = [
    "PairedComparison",
    "PairedWindows",
    "Protocol",
    "ReportPoint",
    "WindowSuccess",
    "episodes_succeeded",
    "eval_episodes",
    "evaluation_steps",
    "first_at_least",
    "paired_comparison",
    "paired_windows",
    "pooled_comparison",
    "report_points",
    "summarize_point",
    "window_success",
]

#: The metrics column of final-state success (the paper's measure).
SUCCESS = "eval/success"


@dataclass(frozen=True)
class Protocol:
    """The reporting budgets of a task (env steps, ascending) and the window before each: a tenth of the first
    budget unless given (a task whose evaluations lie further apart than that).

    Examples:
        >>> Protocol((500_000, 1_000_000)).window
        50000
        >>> Protocol((27_000,), window=9_000).window
        9000
    """

    budgets: tuple[int, ...]
    window: int | None = None

    def __post_init__(self) -> None:
        budgets = tuple(int(b) for b in self.budgets)
        if not budgets or any(b <= 0 for b in budgets) or list(budgets) != sorted(set(budgets)):
            raise ValueError(
                f"budgets must be positive env-step counts in ascending order, got {self.budgets!r}."
            )
        window = budgets[0] // 10 if self.window is None else int(self.window)
        if window <= 0:
            raise ValueError(f"window must be a positive number of env steps, got {self.window!r}.")
        object.__setattr__(self, "budgets", budgets)
        object.__setattr__(self, "window", window)


@dataclass(frozen=True)
class WindowSuccess:
    """One seed's success over a window: whole episodes, the evaluations they came from and their env steps."""

    successes: int
    episodes: int
    evaluations: int
    first_step: int
    last_step: int

    @property
    def rate(self) -> float:
        return self.successes / self.episodes if self.episodes else math.nan


@dataclass(frozen=True)
class ReportPoint:
    """Where success is reported: ``steps`` (the window's end), ``kind`` ``"budget"``, ``"last common"`` or
    (``recipes/report.py``'s DHRL-against-baseline table) ``"both agents"``."""

    steps: int
    kind: str


@dataclass(frozen=True)
class PairedComparison:
    """Two variants of an agent on the same test episodes: how many each succeeded in, the episodes only one did,
    and the two-sided exact McNemar p-value (a binomial test of ``only_variant`` among the discordant episodes at
    1/2: the chance of so uneven a split if the switch changed nothing).

    Examples:
        >>> comparison = paired_comparison([True, False, False], [True, True, True])
        >>> comparison.as_dict()
        {'episodes': 3, 'reference': 1, 'variant': 3, 'only_variant': 2, 'only_reference': 0, 'p_value': 0.5}
    """

    episodes: int
    reference: int
    variant: int
    only_variant: int
    only_reference: int
    p_value: float

    def as_dict(self) -> dict:
        return {name: getattr(self, name) for name in self.__dataclass_fields__}


def paired_comparison(reference: Sequence[bool], variant: Sequence[bool]) -> PairedComparison:
    """Compares two variants' per-episode final successes on the same test episodes (episode ``i`` of both met the
    same start and goal).

    Examples:
        >>> comparison = paired_comparison([1, 1, 0, 0, 0, 0], [1, 0, 1, 1, 1, 1])
        >>> comparison.reference, comparison.variant, comparison.only_variant, comparison.only_reference
        (2, 5, 4, 1)
        >>> round(comparison.p_value, 3)  # 4 against 1 of 5 discordant episodes: 2 x (5 + 1) / 32
        0.375
    """
    a = np.asarray(reference, dtype=bool).reshape(-1)
    b = np.asarray(variant, dtype=bool).reshape(-1)
    if a.shape != b.shape or a.size == 0:
        raise ValueError(
            f"`reference` and `variant` must hold one success per episode each, the same episodes, got "
            f"{a.size} and {b.size}."
        )
    only_variant, only_reference = int((b & ~a).sum()), int((a & ~b).sum())
    return PairedComparison(
        episodes=int(a.size),
        reference=int(a.sum()),
        variant=int(b.sum()),
        only_variant=only_variant,
        only_reference=only_reference,
        p_value=_mcnemar_p(only_variant, only_reference),
    )


def _mcnemar_p(only_variant: int, only_reference: int) -> float:
    """The two-sided exact McNemar p-value: a binomial test of ``only_variant`` among the discordant episodes at 1/2
    (1.0 without a discordant episode)."""
    from scipy.stats import binomtest

    discordant = only_variant + only_reference
    return float(binomtest(only_variant, discordant, 0.5).pvalue) if discordant else 1.0


def pooled_comparison(comparisons: Sequence[PairedComparison]) -> PairedComparison:
    """Several paired comparisons of one switch (e.g. one per seed, each on its own test episodes) as one: the
    counts summed, and the exact McNemar p-value of the summed discordant episodes (under "the switch changes
    nothing" each discordant episode of every seed is the variant's with probability 1/2, so their sum is a
    binomial at 1/2 whatever each seed's own success rate).

    Examples:
        >>> seeds = [paired_comparison([0, 0, 1, 1], [1, 1, 1, 0]), paired_comparison([0, 0, 0], [1, 1, 0])]
        >>> pooled = pooled_comparison(seeds)
        >>> pooled.episodes, pooled.reference, pooled.variant, pooled.only_variant, pooled.only_reference
        (7, 2, 5, 4, 1)
        >>> round(pooled.p_value, 3)
        0.375
    """
    if not comparisons:
        raise ValueError("pooled_comparison needs at least one comparison.")
    counts = ("episodes", "reference", "variant", "only_variant", "only_reference")
    total = {name: sum(getattr(c, name) for c in comparisons) for name in counts}
    return PairedComparison(**total, p_value=_mcnemar_p(total["only_variant"], total["only_reference"]))


def episodes_succeeded(rate: float, episodes: int) -> int:
    """The whole number of episodes behind a stored success rate (``rate * episodes``, rounded).

    A rate that is not a whole number of episodes (beyond float32 round-off) is refused: it was not a success
    rate over ``episodes`` test episodes.

    Examples:
        >>> episodes_succeeded(0.8999999761581421, 10)  # 9 of 10, as float32 stores it
        9
    """
    count = rate * episodes
    whole = round(count) if math.isfinite(count) else -1
    if whole < 0 or abs(count - whole) > 1e-3 * max(episodes, 1) or whole > episodes:
        raise ValueError(f"success rate {rate!r} is not a whole number of {episodes} test episodes.")
    return int(whole)


def _evaluations(run: RunRecord, metric: str = SUCCESS) -> list[tuple[int, float]]:
    """``(env steps, rate)`` of every evaluation of ``run`` (rows with a finite ``metric``), in step order."""
    points = [(int(r["env_steps"]), r[metric]) for r in run.rows if math.isfinite(r.get(metric, math.nan))]
    return sorted(points)


def evaluation_steps(run: RunRecord) -> list[int]:
    """The env steps of ``run``'s evaluations, in order."""
    return [s for s, _ in _evaluations(run)]


def eval_episodes(run: RunRecord) -> int:
    """Test episodes per evaluation of ``run`` (``schedule.eval_episodes``; 10, the reference's, if absent)."""
    return int(run.config.get("schedule.eval_episodes", 10))


def window_success(run: RunRecord, end: int, window: int) -> WindowSuccess:
    """``run``'s final-state success over its evaluations in ``(end - window, end]``, in whole episodes."""
    n = eval_episodes(run)
    inside = [(s, r) for s, r in _evaluations(run) if end - window < s <= end]
    if not inside:
        raise ValueError(f"{run.path}: no evaluation in ({end - window}, {end}] env steps.")
    return WindowSuccess(
        successes=sum(episodes_succeeded(r, n) for _, r in inside),
        episodes=n * len(inside),
        evaluations=len(inside),
        first_step=inside[0][0],
        last_step=inside[-1][0],
    )


def last_evaluation(run: RunRecord) -> int:
    """The env steps of ``run``'s last evaluation."""
    points = _evaluations(run)
    if not points:
        raise ValueError(f"{run.path}: no evaluation in its metrics.csv.")
    return points[-1][0]


def reached(run: RunRecord, budget: int) -> bool:
    """Whether ``run`` ran to ``budget``: its last evaluation lies within one evaluation interval below it
    (the interval: the median spacing of its evaluations) or beyond it."""
    steps = [s for s, _ in _evaluations(run)]
    spacing = float(np.median(np.diff(steps))) if len(steps) > 1 else 0.0
    return steps[-1] > budget - spacing if steps else False


def report_points(runs: Sequence[RunRecord], protocol: Protocol) -> list[tuple[ReportPoint, list[RunRecord]]]:
    """The points the protocol reports for these seeds, each with the seeds it is reported over.

    Every budget some seed reached, over the seeds that reached it; and, where a seed stopped short of a budget
    (the first or a later one), the last evaluation every seed reached (``"last common"``, over all seeds), unless
    it is the end of a budget's window that every seed reached.
    """
    points = []
    for budget in protocol.budgets:
        members = [r for r in runs if reached(r, budget)]
        if members:
            points.append((ReportPoint(int(budget), "budget"), members))
    common = min(last_evaluation(r) for r in runs)
    by_all = [b for b in protocol.budgets if all(reached(r, b) for r in runs)]
    if common > max(by_all, default=0):  # some seed stopped short of the next budget: where all of them got
        points.append((ReportPoint(common, "last common"), list(runs)))
    return sorted(points, key=lambda item: item[0].steps)


def summarize_point(
    runs: Sequence[RunRecord], point: ReportPoint, protocol: Protocol, *, reps: int = 2000
) -> dict:
    """One reporting point over seeds: per seed (in order) its :class:`WindowSuccess`, and over seeds
    ``mean``, ``std`` (``ddof=1``; 0 for one seed), ``iqm``, ``iqm_ci`` (95% bootstrap)."""
    per_seed = [window_success(r, point.steps, protocol.window) for r in runs]
    rates = np.array([w.rate for w in per_seed])
    return {
        "steps": point.steps,
        "kind": point.kind,
        "seeds": per_seed,
        "mean": float(rates.mean()),
        "std": float(rates.std(ddof=1)) if len(rates) > 1 else 0.0,
        "iqm": iqm(rates),
        "iqm_ci": bootstrap_iqm_ci(rates, reps=reps),
    }


def first_at_least(run: RunRecord, successes: int) -> int | None:
    """The env steps of ``run``'s first evaluation with at least ``successes`` successful test episodes."""
    n = eval_episodes(run)
    return next((s for s, r in _evaluations(run) if episodes_succeeded(r, n) >= successes), None)


@dataclass(frozen=True)
class PairedWindows:
    """Two configurations' runs of the same seeds at one budget: per seed (in the first's order) its window in each,
    and over those seeds the mean rate of each and the mean and sample standard deviation of the differences
    (first minus second; ``ddof=1``, 0 for one seed)."""

    steps: int
    seeds: tuple
    windows: tuple[WindowSuccess, ...]
    other_windows: tuple[WindowSuccess, ...]

    @property
    def differences(self) -> np.ndarray:
        return np.array([a.rate - b.rate for a, b in zip(self.windows, self.other_windows, strict=True)])

    @property
    def mean(self) -> float:
        return float(np.mean([w.rate for w in self.windows]))

    @property
    def other_mean(self) -> float:
        return float(np.mean([w.rate for w in self.other_windows]))

    @property
    def mean_difference(self) -> float:
        return float(self.differences.mean())

    @property
    def std_difference(self) -> float:
        d = self.differences
        return float(d.std(ddof=1)) if d.size > 1 else 0.0


def paired_windows(
    runs: Sequence[RunRecord], others: Sequence[RunRecord], protocol: Protocol
) -> list[PairedWindows]:
    """``runs`` against ``others`` seed by seed (runs paired by their configuration's ``seed``): at each budget of
    ``protocol``, over the seeds whose runs both reached it, each run's success over the same window.

    Budgets no seed's pair reached are left out. A seed that appears twice among ``runs`` or among ``others`` is
    refused: a pairing must be one to one.

    Examples:
        >>> from pathlib import Path
        >>> def run(seed, rates):
        ...     rows = [{"env_steps": float(s), "eval/success": r} for s, r in zip((100, 200), rates)]
        ...     return RunRecord(Path(f"s{seed}"), {"seed": seed}, rows)
        >>> [point] = paired_windows([run(0, (1.0, 1.0))], [run(0, (0.5, 0.0)), run(1, (1.0, 1.0))],
        ...                          Protocol((200,), window=200))
        >>> point.seeds, point.windows[0].successes, point.other_windows[0].successes, point.mean_difference
        ((0,), 20, 5, 0.75)
    """
    for name, group in (("runs", runs), ("others", others)):
        seeds = [repr(r.seed) for r in group]
        repeated = sorted({s for s in seeds if seeds.count(s) > 1})
        if repeated:
            raise ValueError(f"`{name}` holds more than one run of seed {', '.join(repeated)}; pairs must be one to one.")
    by_seed = {repr(r.seed): r for r in others}
    points = []
    for budget in protocol.budgets:
        pairs = [
            (run, by_seed[repr(run.seed)])
            for run in runs
            if repr(run.seed) in by_seed and reached(run, budget) and reached(by_seed[repr(run.seed)], budget)
        ]
        if pairs:
            points.append(
                PairedWindows(
                    steps=int(budget),
                    seeds=tuple(run.seed for run, _ in pairs),
                    windows=tuple(window_success(run, budget, protocol.window) for run, _ in pairs),
                    other_windows=tuple(window_success(other, budget, protocol.window) for _, other in pairs),
                )
            )
    return points
