"""Maze geometry and goal distributions: compiled walls against the grids, samplers against the facts."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from scipy import stats
from torchrl_dhrl.envs import (
    COMPLEX_MAZE,
    MAZE_NAMES,
    U_MAZE,
    BoxGoalSampler,
    FixedGoalSampler,
    FreeCellGoalSampler,
    GoalSimulation,
    MazeLayout,
    WallBox,
    bottleneck_walls,
    compile_maze_model,
    get_maze_spec,
)

DIRECTIONS = {(1, 0): (0, 1), (-1, 0): (0, -1), (0, 1): (1, 0), (0, -1): (-1, 0)}  # (dx, dy) -> (drow, dcol)


def _grid_distance_to_wall(grid, row, col, drow, dcol, scale):
    """Distance from a cell centre to the first wall cell face along a grid axis, walking the raw grid."""
    k = 1
    while grid[row + k * drow][col + k * dcol] != "1":
        k += 1
    return (k - 0.5) * scale


def _ray(model, data, origin, direction):
    geomid = np.zeros(1, dtype=np.int32)
    groups = np.array([1, 0, 0, 0, 0, 0], dtype=np.uint8)  # group 0: walls and agent (goal marker is group 1)
    distance = mujoco.mj_ray(
        model, data, np.asarray(origin, float), np.asarray(direction, float), groups, 1, -1, geomid
    )
    return distance, int(geomid[0])


@pytest.mark.parametrize("name", ["AntMazeSmall", "AntMaze", "AntMazeComplex", "PointMaze"])
def test_raycasts_match_grid(name):
    """From every free cell centre, rays along the 4 axes hit a wall exactly where the grid says."""
    spec = get_maze_spec(name)
    model = compile_maze_model(spec)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    layout = spec.layout
    # Above the agent (at the origin, at most ~1.1 tall) and below the wall tops.
    z = 0.75 * layout.wall_height * layout.scale
    wall_names = set()
    for row, line in enumerate(layout.grid):
        for col, char in enumerate(line):
            if char == "1":
                continue
            x, y = layout.cell_center(row, col)
            for (dx, dy), (drow, dcol) in DIRECTIONS.items():
                distance, geom = _ray(model, data, (x, y, z), (dx, dy, 0.0))
                expected = _grid_distance_to_wall(layout.grid, row, col, drow, dcol, layout.scale)
                assert distance == pytest.approx(expected, abs=1e-6), (row, col, dx, dy)
                wall_names.add(model.geom(geom).name)
    assert all(n.startswith("wall_") for n in wall_names)


@pytest.mark.parametrize("name", MAZE_NAMES)
def test_wall_geoms_cover_grid_walls(name):
    """One box per wall cell, centred on the cell, of the cell's size and half the scale tall."""
    spec = get_maze_spec(name)
    model = compile_maze_model(spec)
    layout = spec.layout
    walls = [g for g in range(model.ngeom) if model.geom(g).name.startswith("wall_")]
    n_grid = sum(line.count("1") for line in layout.grid)
    assert len(walls) == n_grid + len(layout.extra_walls)
    rows, cols = np.nonzero(np.array([[c == "1" for c in line] for line in layout.grid]))
    expected = {
        (
            round(c * layout.scale - layout.origin_offset[0], 6),
            round(r * layout.scale - layout.origin_offset[1], 6),
        )
        for r, c in zip(rows, cols, strict=True)
    }
    centers = {
        (round(float(model.geom_pos[g][0]), 6), round(float(model.geom_pos[g][1]), 6)) for g in walls[:n_grid]
    }
    assert centers == expected
    np.testing.assert_allclose(
        model.geom_size[walls[:n_grid]],
        np.tile([layout.scale / 2, layout.scale / 2, layout.scale / 4], (n_grid, 1)),
    )


def test_layout_coordinates():
    small = MazeLayout(U_MAZE, scale=4.0)
    assert small.start_cell == (1, 1) and small.goal_cell == (3, 1)
    np.testing.assert_allclose(small.cell_center(1, 1), [0.0, 0.0])
    np.testing.assert_allclose(small.cell_center(3, 1), [0.0, 8.0])  # rows map to y
    np.testing.assert_allclose(small.cell_center(1, 3), [8.0, 0.0])  # columns map to x
    low, high = small.bounds
    np.testing.assert_allclose(low, [-2, -2]) and np.testing.assert_allclose(high, [10, 10])
    complex_low, complex_high = MazeLayout(COMPLEX_MAZE, scale=8.0).bounds
    np.testing.assert_allclose(complex_low, [-4, -4]) and np.testing.assert_allclose(complex_high, [52, 52])
    assert small.in_free_cell([[0.0, 0.0], [4.0, 4.0], [8.0, 4.0], [100.0, 0.0]]).tolist() == [
        True,
        False,
        True,
        False,
    ]


@pytest.mark.parametrize("grid", [("111", "1r1", "11"), ("111", "101", "111"), ("111", "1x1", "1r1")])
def test_layout_rejects_bad_grids(grid):
    with pytest.raises(ValueError):
        MazeLayout(grid, scale=1.0)


def test_bottleneck_gap_by_raycast():
    """The bottleneck's thin walls leave a gap of about 1.6 between x = 15.4 and x = 17.0 at y = 8."""
    spec = get_maze_spec("AntMazeBottleneck")
    model = compile_maze_model(spec)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    origin = (16.2, 8.0, 1.5)
    right, right_geom = _ray(model, data, origin, (1.0, 0.0, 0.0))
    left, left_geom = _ray(model, data, origin, (-1.0, 0.0, 0.0))
    assert right + left == pytest.approx(1.6, abs=1e-6)
    assert origin[0] - left == pytest.approx(15.4, abs=1e-6) and origin[0] + right == pytest.approx(
        17.0, abs=1e-6
    )
    # The thin walls are 2 thick (y in [7, 9]) and carry their own friction.
    down, _ = _ray(model, data, (13.5, 5.0, 1.5), (0.0, 1.0, 0.0))
    assert down == pytest.approx(2.0, abs=1e-6)
    for geom in (left_geom, right_geom):
        np.testing.assert_allclose(model.geom_friction[geom], [2.0, 0.1, 0.002])
    assert bottleneck_walls()[0].xy_bounds == (11.6, 15.4, 7.0, 9.0)
    assert WallBox((0.0, 0.0, 0.0), (1.0, 2.0, 3.0)).xy_bounds == (-1.0, 1.0, -2.0, 2.0)


def _push_ant(sim, start_xy, force_xy, steps=150):
    """Places the ant, standing, at ``start_xy`` and pushes its torso with a constant force; returns the torso
    xy path."""
    model, data = sim.model, sim.datas[0]
    mujoco.mj_resetData(model, data)
    # Standing on its four feet (torso at 0.55, ankles folded down), not the reset pose it drops from.
    data.qpos[:] = (0.0, 0.0, 0.55, 1.0, 0.0, 0.0, 0.0) + (0.0, 1.0, 0.0, -1.0, 0.0, -1.0, 0.0, 1.0)
    data.qpos[:2] = start_xy
    torso = model.body("ant/").id
    path = []
    for _ in range(steps):
        data.xfrc_applied[torso, :2] = force_xy
        mujoco.mj_step(model, data, sim.agent.frame_skip)
        path.append(data.qpos[:2].copy())
    return np.array(path)


def test_ant_sized_probe_cannot_pass_walls():
    """Pushing the ant's torso into a block wall and a thin bottleneck wall never gets it through.

    The push, 50 N, is about 5.6 times the ant's weight (0.91 kg): far more than its legs can produce. The
    reference's soft contacts (``solimp (0.8, 0.8, 0.01)`` on the ant, the floor and the walls) let the torso,
    pushed this hard, sink up to about 0.15 into a wall (0.06 into a block, 0.15 into a thin wall whose
    friction 2 pins the legs): the tolerance keeps the torso's centre in front of the face.
    """
    torso_radius = get_maze_spec("AntMaze").agent.torso_radius
    tolerance = 0.2
    push = 50.0
    sim = GoalSimulation("AntMazeSmall")
    path = _push_ant(sim, (7.0, 0.0), (push, 0.0))
    assert path[:, 0].max() <= 10.0 - torso_radius + tolerance  # outer wall face at x = 10
    assert path[-1, 0] > 9.0  # it did reach the wall
    sim = GoalSimulation("AntMazeBottleneck")
    path = _push_ant(sim, (13.5, 4.5), (0.0, push))
    assert path[:, 1].max() <= 7.0 - torso_radius + tolerance  # thin wall face at y = 7
    assert path[-1, 1] > 6.0


# ---------------------------------------------------------------------------------------------- goals
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


def test_in_wall_counts_shared_block_faces_as_inside():
    """The inner wall of the U is two blocks: the face they share is wall, the face on free space is not."""
    from torchrl_dhrl.envs import get_maze_spec

    layout = get_maze_spec("PointMaze").layout
    points = [
        [2.0, 4.0],
        [-2.0, 4.0],
        [4.0, 4.0],
        [6.0, 4.0],
        [5.999, 4.0],
        [6.001, 4.0],
        [2.0, 2.0],
        [0.0, 0.0],
    ]
    assert layout.in_wall(points).tolist() == [True, True, True, False, True, False, False, False]
    # grown by a margin, the free-facing face moves out with it
    assert layout.in_wall([[6.3, 4.0], [6.6, 4.0]], margin=0.5).tolist() == [True, False]
