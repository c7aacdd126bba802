"""Goal distributions of the mazes: samplers against the facts (free cells, uniformity, the reference's
rejection rules and test goals)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats
from torchrl_dhrl.envs import (
    COMPLEX_MAZE,
    MAZE_NAMES,
    BoxGoalSampler,
    FixedGoalSampler,
    FreeCellGoalSampler,
    MazeLayout,
    get_maze_spec,
)

N_GOALS = 20000


@pytest.mark.parametrize("name", MAZE_NAMES)
def test_train_goals_in_free_cells_and_uniform(name):
    """Train goals never fall in wall blocks, and they are uniform over the free cells (chi-square + KS)."""
    spec = get_maze_spec(name)
    layout = spec.layout
    goals = spec.train_goals.sample(np.random.default_rng(2024), N_GOALS)
    assert goals.shape == (N_GOALS, 2) and goals.dtype == np.float64
    assert layout.in_free_cell(goals).all()
    assert spec.train_goals.contains(goals).all()
    low, high = spec.goal_bounds
    assert (goals >= low).all() and (goals <= high).all()
    # Every free cell is covered, equally often.
    cells = layout.cell_index(goals)
    free = np.argwhere(~layout.walls)
    counts = np.array([np.sum((cells[:, 0] == r) & (cells[:, 1] == c)) for r, c in free])
    assert stats.chisquare(counts).pvalue > 1e-3
    # Within the cells, the offsets are uniform over the cell.
    offsets = (goals - layout.cell_center(cells[:, 0], cells[:, 1])) / layout.scale + 0.5
    for axis in range(2):
        assert stats.kstest(offsets[:, axis], "uniform").pvalue > 1e-3


def test_bottleneck_train_goals_include_thin_walls():
    """As the reference: the bottleneck's thin walls are not excluded from the train goals."""
    spec = get_maze_spec("AntMazeBottleneck")
    goals = spec.train_goals.sample(np.random.default_rng(1), N_GOALS)
    thin = np.zeros(len(goals), dtype=bool)
    for wall in spec.layout.extra_walls:
        x0, x1, y0, y1 = wall.xy_bounds
        thin |= (goals[:, 0] > x0) & (goals[:, 0] < x1) & (goals[:, 1] > y0) & (goals[:, 1] < y1)
    area_fraction = (3.8 * 2 + 3.0 * 2) / (24 * 24 - 8 * 16)
    assert thin.mean() == pytest.approx(area_fraction, abs=0.006)
    assert spec.layout.in_wall(goals).mean() == pytest.approx(area_fraction, abs=0.006)


def test_u_maze_rejection_rule_matches_reference():
    """AntMaze train goals: uniform in [-4, 20]^2 rejecting x < 12 and 4 < y < 12 (and nothing else)."""
    sampler = get_maze_spec("AntMaze").train_goals
    assert sampler == BoxGoalSampler((-4.0, -4.0), (20.0, 20.0), excluded=((-np.inf, 12.0, 4.0, 12.0),))
    small = get_maze_spec("AntMazeSmall").train_goals
    assert small == BoxGoalSampler((-2.0, -2.0), (10.0, 10.0), excluded=((-np.inf, 6.0, 2.0, 6.0),))
    assert get_maze_spec("PointMaze").train_goals == small
    assert sampler.acceptance == pytest.approx(1 - 16 * 8 / 24**2)


def test_test_goals_are_the_references():
    assert get_maze_spec("PointMaze").test_goals == ((0.0, 8.0),)
    assert get_maze_spec("AntMazeSmall").test_goals == ((0.0, 8.0),)
    assert get_maze_spec("AntMaze").test_goals == ((0.0, 16.0),)
    assert get_maze_spec("AntMazeBottleneck").test_goals == ((0.0, 16.0),)
    assert get_maze_spec("AntMazeComplex").test_goals == (
        (40.0, 8.0),
        (16.0, 48.0),
        (40.0, 48.0),
        (16.0, 32.0),
    )
    facts = {
        "PointMaze": (600, 2.5),
        "AntMazeSmall": (600, 2.5),
        "AntMaze": (600, 5.0),
        "AntMazeBottleneck": (600, 5.0),
        "AntMazeComplex": (2000, 5.0),
    }
    for name, (length, threshold) in facts.items():
        spec = get_maze_spec(name)
        assert (spec.episode_length, spec.success_threshold, spec.reward_threshold) == (
            length,
            threshold,
            0.5,
        )
        assert spec.layout.in_free_cell(np.array(spec.test_goals)).all()


def test_complex_test_goals_drawn_uniformly():
    sampler = get_maze_spec("AntMazeComplex").test_goal_sampler
    goals = sampler.sample(np.random.default_rng(0), 4000)
    unique, counts = np.unique(goals, axis=0, return_counts=True)
    assert {tuple(g) for g in unique.tolist()} == set(get_maze_spec("AntMazeComplex").test_goals)
    assert stats.chisquare(counts).pvalue > 1e-3
    assert sampler.contains(goals).all() and not sampler.contains([[40.0, 8.5]]).any()


def test_samplers_are_deterministic_and_exact_count():
    for sampler in (get_maze_spec("AntMaze").train_goals, get_maze_spec("AntMazeComplex").train_goals):
        a = sampler.sample(np.random.default_rng(3), 37)
        b = sampler.sample(np.random.default_rng(3), 37)
        assert a.shape == (37, 2)
        np.testing.assert_array_equal(a, b)
    layout = MazeLayout(COMPLEX_MAZE, scale=8.0)
    assert FreeCellGoalSampler(layout, (-4.0, -4.0), (52.0, 52.0)).sample(
        np.random.default_rng(0), 0
    ).shape == (0, 2)
    with pytest.raises(ValueError):
        FixedGoalSampler(())
