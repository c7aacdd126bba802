"""The run's success curve and the over-seeds figure read at a glance (issue 53, item 7): the x-axis spans the
runs' own steps whatever the paper's budgets, the paper's points within them are drawn at their steps, those
beyond are named in the legend (not drawn far to the right), and the legend covers no data."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PathCollection
from matplotlib.figure import Figure

from torchrl_dhrl.recipe import aggregate_runs, plot_aggregate, plot_success_curve
from torchrl_dhrl.recipe.aggregate import RunRecord
from torchrl_dhrl.recipe.plots import draw_paper_reference

POINTMAZE = {250_000: 0.969, 500_000: 0.998}  # the paper's Table 2
BOTTLENECK = {500_000: 0.165, 1_000_000: 0.387}


@pytest.fixture
def saved(monkeypatch):
    """The figures the plotting functions save, in order (``Figure.savefig`` recorded, then run)."""
    figures = []
    savefig = Figure.savefig

    def record(fig, *args, **kwargs):
        figures.append(fig)
        return savefig(fig, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", record)
    return figures


def _history(last, every):
    steps = np.arange(every, last + 1, every)
    success = np.clip((steps - 0.6 * last) / (0.3 * last), 0.0, 1.0)
    return [
        {"env_steps": float(s), "eval/success": float(v), "eval/any_success": float(v)}
        for s, v in zip(steps, success, strict=True)
    ]


def _legends(owner, ax):
    """The legends of ``owner`` (the figure or the panel's subfigure) and of ``ax``."""
    return [*owner.legends, *([ax.get_legend()] if ax.get_legend() else [])]


def _legend_texts(legends):
    return " | ".join(t.get_text() for legend in legends for t in legend.get_texts())


def _crosses(ax):
    """The paper's crosses: ``[(step, success), ...]`` of every scatter on ``ax``."""
    scatters = [c for c in ax.collections if isinstance(c, PathCollection)]  # not fill_between's bands
    return [tuple(p) for c in scatters for p in np.asarray(c.get_offsets())]


def _legend_clear_of_data(fig, ax, legends):
    """Every legend's box lies outside the axes (so it can cover no curve), and inside the saved figure."""
    assert legends
    renderer = FigureCanvasAgg(fig).get_renderer()
    fig.draw(renderer)
    axes_box = ax.get_window_extent(renderer)
    for legend in legends:
        box = legend.get_window_extent(renderer)
        assert not box.overlaps(axes_box), (box, axes_box)


@pytest.mark.parametrize(
    "last, every, reference",
    [
        (84_000, 3000, POINTMAZE),  # a quick PointMaze run: both paper points beyond it
        (993_000, 9000, BOTTLENECK),  # a 1M ant run: both within
        (300_000, 10_000, {2_500_000: 0.204, 4_000_000: 0.401}),  # AntMazeComplex's far budgets
        (60_000, 3000, None),
    ],
)
def test_success_curve_axis_spans_the_run(saved, tmp_path, last, every, reference):
    plot_success_curve(_history(last, every), tmp_path / "curve.png", title="t", reference=reference)
    fig = saved[-1]
    (ax,) = fig.axes
    low, high = ax.get_xlim()
    assert last <= high <= 1.1 * last  # the paper's budgets do not stretch the axis
    assert low <= every and low > -0.1 * last
    for step, value in (reference or {}).items():
        figure = f"{100 * value:.1f}%"
        if step <= high:
            assert (step, pytest.approx(value)) in _crosses(ax)  # drawn at its step
        else:
            assert all(x <= high for x, _ in _crosses(ax))
            assert figure in _legend_texts(_legends(fig, ax))  # named, with its budget
            assert f"{step / 1e6:g}M" in _legend_texts(_legends(fig, ax))
    _legend_clear_of_data(fig, ax, _legends(fig, ax))


def test_success_curve_far_paper_point_is_a_reference_line(saved, tmp_path):
    plot_success_curve(_history(84_000, 3000), tmp_path / "curve.png", reference=POINTMAZE)
    fig = saved[-1]
    (ax,) = fig.axes
    texts = _legend_texts(_legends(fig, ax))
    assert "paper: 96.9% at 0.25M" in texts and "paper: 99.8% at 0.5M" in texts
    # a horizontal line at the paper's rate across the axes, not a point at 250k
    levels = [line.get_ydata()[0] for line in ax.get_lines() if line.get_label().startswith("paper: 96.9%")]
    assert levels == [pytest.approx(0.969)]
    assert not _crosses(ax)
    assert (tmp_path / "curve.png").stat().st_size > 1000


def test_success_curve_forks_and_empty_history_still_draw(saved, tmp_path):
    history = _history(120_000, 6000)
    plot_success_curve(history, tmp_path / "curve.png", reference=POINTMAZE, forks=[60_000])
    (ax,) = saved[-1].axes
    assert ax.get_xlim()[1] <= 1.1 * 120_000
    assert "forked" in _legend_texts(_legends(saved[-1], ax))
    plot_success_curve([], tmp_path / "empty.png", reference=POINTMAZE)  # nothing logged yet: no error
    assert Path(tmp_path / "empty.png").is_file()


def _runs(env, lengths, every=9000, seed_offset=0, config=None):
    rng = np.random.default_rng(len(lengths) + seed_offset)
    runs = []
    for seed, last in enumerate(lengths):
        steps = np.arange(every, last + 1, every)
        rows = [{"env_steps": float(s), "eval/success": float(rng.integers(0, 11) / 10)} for s in steps]
        runs.append(
            RunRecord(Path(f"/runs/{env}/{seed}"), {"env_name": env, "seed": seed, **(config or {})}, rows)
        )
    return runs


def test_aggregate_axis_spans_the_runs_and_names_far_paper_points(saved, tmp_path):
    runs = _runs("PointMaze", [81_000, 81_000, 81_000]) + _runs("AntMazeBottleneck", [990_000])
    table = aggregate_runs(runs, reps=50)
    plot_aggregate(
        table, tmp_path / "aggregate.png", reference={"PointMaze": POINTMAZE, "AntMazeBottleneck": BOTTLENECK}
    )
    fig = saved[-1]
    panels = {sub.axes[0].get_title(): sub for sub in fig.subfigs}
    assert set(panels) == {"PointMaze", "AntMazeBottleneck"}  # the far budgets are no longer in the title

    pm = panels["PointMaze"]
    ax = pm.axes[0]
    assert 81_000 <= ax.get_xlim()[1] <= 1.1 * 81_000
    assert not _crosses(ax)
    texts = _legend_texts(_legends(pm, ax))
    assert "96.9% at 0.25M" in texts and "99.8% at 0.5M" in texts
    assert "(n=3): mean ± std" in texts
    assert ax.collections, "three seeds: the band of one standard deviation is drawn"
    _legend_clear_of_data(fig, ax, _legends(pm, ax))

    ant = panels["AntMazeBottleneck"]
    ax = ant.axes[0]
    assert 990_000 <= ax.get_xlim()[1] <= 1.1 * 990_000
    crosses = _crosses(ax)
    for step, value in BOTTLENECK.items():
        assert (step, pytest.approx(value)) in crosses
    assert "(n=1)" in _legend_texts(_legends(ant, ax)) and "IQM" not in _legend_texts(_legends(ant, ax))
    _legend_clear_of_data(fig, ax, _legends(ant, ax))


def test_aggregate_without_reference_or_ylim(saved, tmp_path):
    table = aggregate_runs(_runs("PointMaze", [30_000, 30_000]), reps=20)
    plot_aggregate(table, tmp_path / "aggregate.png", reference=None, ylim=None, metric_label="frontier")
    ax = saved[-1].subfigs[0].axes[0]
    assert 27_000 <= ax.get_xlim()[1] <= 33_000
    assert ax.get_ylabel() == "frontier"


def test_draw_paper_reference_keeps_a_late_run_start():
    """A run whose history starts late (past a fifth of its last step) keeps its own left edge; a paper
    point before it is named, not drawn far to the left."""
    ax = Figure().subplots()
    low, high = draw_paper_reference(ax, {250_000: 0.5}, [800_000, 900_000, 1_000_000])
    assert 750_000 < low < 800_000 and 1_000_000 <= high <= 1_100_000
    assert not _crosses(ax)
    assert any("50.0% at 0.25M, before this run" in line.get_label() for line in ax.get_lines())
