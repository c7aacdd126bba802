"""The compiled maze models: walls against the grids (raycasts, wall geoms, the bottleneck's gap, an
ant-sized probe)."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from torchrl_dhrl.envs import (
    MAZE_NAMES,
    GoalSimulation,
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
