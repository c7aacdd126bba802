"""Top-down matplotlib maps of the mazes; plot_env / plot_arm: projections of the arm scenes, overlays in
3-D goal space, the mazes through plot_env."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402
from matplotlib.colors import to_hex  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402
from torchrl_dhrl.envs import (  # noqa: E402
    ENV_NAMES,
    MAZE_NAMES,
    get_arm_spec,
    get_maze_spec,
    plot_arm,
    plot_env,
    plot_maze,
)


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


@pytest.mark.parametrize("name", MAZE_NAMES)
def test_plot_walls_and_limits(name):
    spec = get_maze_spec(name)
    ax = plot_maze(name)
    rectangles = [p for p in ax.patches if isinstance(p, Rectangle)]
    assert len(rectangles) == len(spec.layout.wall_boxes)
    drawn = sorted(
        (round(r.get_x(), 6), round(r.get_y(), 6), round(r.get_width(), 6), round(r.get_height(), 6))
        for r in rectangles
    )
    expected = sorted(
        (round(x0, 6), round(y0, 6), round(x1 - x0, 6), round(y1 - y0, 6))
        for x0, x1, y0, y1 in (b.xy_bounds for b in spec.layout.wall_boxes)
    )
    assert drawn == expected
    low, high = spec.layout.extent
    assert ax.get_xlim() == (low[0], high[0]) and ax.get_ylim() == (low[1], high[1])
    assert ax.get_title() == name


def test_plot_graph_path_and_trajectories():
    landmarks = torch.tensor([[0.0, 0.0], [8.0, 0.0], [8.0, 8.0], [0.0, 8.0]])
    edges = np.array([[0, 1], [1, 2], [2, 3]])
    trajectories = np.random.default_rng(0).normal(size=(3, 20, 29))
    fig, ax = plt.subplots()
    returned = plot_maze(
        "AntMazeSmall",
        landmarks=landmarks,
        edges=edges,
        path=landmarks[[0, 1, 2]],
        trajectory=trajectories,
        goal=[8.0, 8.0],
        ax=ax,
    )
    assert returned is ax
    collections = [c for c in ax.collections if isinstance(c, LineCollection)]
    assert len(collections) == 1
    np.testing.assert_allclose(np.array(collections[0].get_segments()), landmarks.numpy()[edges])
    trajectory_lines = [line for line in ax.lines if len(line.get_xdata()) == 20]
    assert len(trajectory_lines) == 3
    np.testing.assert_allclose(trajectory_lines[0].get_xydata(), trajectories[0, :, :2])
    # Readable over the graph: drawn above the planned path, each in its own colour, none the edges' blue
    # nor the path's orange.
    path_line = next(line for line in ax.lines if line.get_label() == "path")
    colors = [to_hex(line.get_color()) for line in trajectory_lines]
    assert all(line.get_zorder() > path_line.get_zorder() for line in trajectory_lines)
    assert len(set(colors)) == 3
    assert not {to_hex(path_line.get_color()), to_hex(collections[0].get_colors()[0])} & set(colors)
    # Segment edges [E, 2, 2] are accepted as they are.
    segments = landmarks.numpy()[edges]
    ax2 = plot_maze("AntMazeSmall", edges=segments)
    np.testing.assert_allclose(np.array(ax2.collections[0].get_segments()), segments)


def test_plot_errors():
    with pytest.raises(ValueError, match="landmarks"):
        plot_maze("AntMaze", edges=[[0, 1]])
    with pytest.raises(ValueError, match="edges"):
        plot_maze("AntMaze", edges=np.zeros((2, 3)), landmarks=np.zeros((3, 2)))
    with pytest.raises(ValueError, match="trajectory"):
        plot_maze("AntMaze", trajectory=np.zeros(3))
    with pytest.raises(ValueError, match="Valid names"):
        plot_maze("Maze")


@pytest.mark.parametrize("name", ENV_NAMES)
def test_plot_env_every_name(name):
    ax = plot_env(name)
    assert ax.get_title().startswith(name)
    assert ax.get_xlim()[0] < ax.get_xlim()[1]


def test_plot_env_on_a_maze_is_plot_maze():
    landmarks = np.array([[0.0, 0.0], [8.0, 0.0], [8.0, 8.0]])
    a = plot_env("AntMazeSmall", landmarks=landmarks, edges=[[0, 1], [1, 2]], path=landmarks, goal=[0, 8])
    b = plot_maze("AntMazeSmall", landmarks=landmarks, edges=[[0, 1], [1, 2]], path=landmarks, goal=[0, 8])
    assert len(a.patches) == len(b.patches) and len(a.lines) == len(b.lines)
    np.testing.assert_allclose(a.collections[0].get_segments(), b.collections[0].get_segments())
    with pytest.raises(ValueError, match="from above only"):
        plot_env("AntMaze", view="front")


@pytest.mark.parametrize("view, axes", [("top", (0, 1)), ("front", (1, 2)), ("side", (0, 2))])
def test_boards_are_projected(view, axes):
    spec = get_arm_spec("UR3Obstacle")
    ax = plot_arm("UR3Obstacle", view=view, show_test_goals=False)
    drawn = sorted(
        (round(r.get_x(), 6), round(r.get_y(), 6), round(r.get_width(), 6), round(r.get_height(), 6))
        for r in ax.patches
        if isinstance(r, Rectangle)
    )
    i, j = axes
    expected = sorted(
        (
            round(b.center[i] - b.half_size[i], 6),
            round(b.center[j] - b.half_size[j], 6),
            round(2 * b.half_size[i], 6),
            round(2 * b.half_size[j], 6),
        )
        for b in spec.boards
    )
    assert drawn == expected
    low, high = spec.goal_bounds
    assert ax.get_xlim() == (low[i], high[i]) and ax.get_ylim() == (low[j], high[j])
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("xyz"[i], "xyz"[j])


def test_overlays_in_goal_space():
    landmarks = torch.tensor([[0.3, -0.2, 0.1], [0.3, 0.0, 0.4], [0.4, 0.2, 0.1]])
    edges = np.array([[0, 1], [1, 2]])
    trajectories = np.random.default_rng(0).normal(size=(2, 20, 3))
    ax = plot_env(
        "UR3Obstacle", landmarks=landmarks, edges=edges, trajectory=trajectories, path=landmarks, view="front"
    )
    (collection,) = [c for c in ax.collections if isinstance(c, LineCollection)]
    np.testing.assert_allclose(np.array(collection.get_segments()), landmarks.numpy()[edges][..., [1, 2]])
    lines = [line for line in ax.lines if len(line.get_xdata()) == 20]
    assert len(lines) == 2
    np.testing.assert_allclose(lines[0].get_xydata(), trajectories[0][:, [1, 2]])
    path_line = [line for line in ax.lines if len(line.get_xdata()) == 3]
    np.testing.assert_allclose(path_line[0].get_xydata(), landmarks.numpy()[:, [1, 2]])
    # The Gaussian goal region of Reacher3D: an ellipse of 2 sigma around the mean.
    ax = plot_arm("Reacher3D", view="top")
    (ellipse,) = [p for p in ax.patches if type(p).__name__ == "Ellipse"]
    assert ellipse.center == (0.0, 0.25) and ellipse.width == pytest.approx(0.4)


def test_plot_arm_errors():
    with pytest.raises(ValueError, match="view must be one of top, front, side"):
        plot_arm("Reacher3D", view="below")
    with pytest.raises(ValueError, match="landmarks"):
        plot_env("Reacher3D", edges=[[0, 1]])
    with pytest.raises(ValueError, match="edges"):
        plot_env("UR3Obstacle", edges=np.zeros((2, 2, 1)), view="front")
    with pytest.raises(ValueError, match="Valid names"):
        plot_arm("AntMaze")


def test_a_maze_geometry_is_drawn_under_a_goal_space_plot():
    """An env without a scene of its own (a Gymnasium id) drawn over a maze's geometry: one wall-coloured rectangle per
    wall box at its corners, the arena as the limits, the start marked."""
    from torchrl_dhrl.envs.geometry import MazeGeometry

    boxes = torch.tensor([[[0.0, 0.0], [1.0, 2.0]], [[2.0, 1.0], [3.0, 3.0]]])
    maze = MazeGeometry(boxes, [-1.0, -1.0], [4.0, 3.0], start=(-0.5, -0.5), scale=1.0)
    ax = plot_env("gymnasium:PointMaze_UMaze-v3", maze=maze, trajectory=np.zeros((3, 2)))
    walls = [p for p in ax.patches if isinstance(p, Rectangle)]
    assert sorted((r.get_x(), r.get_y(), r.get_width(), r.get_height()) for r in walls) == [(0, 0, 1, 2), (2, 1, 1, 2)]
    assert ax.get_xlim() == (-1.0, 4.0) and ax.get_ylim() == (-1.0, 3.0)
    assert "start" in ax.get_legend_handles_labels()[1]
    bare = plot_env("gymnasium:PointMaze_UMaze-v3", trajectory=np.zeros((3, 2)))
    assert not [p for p in bare.patches if isinstance(p, Rectangle)]
    plt.close("all")
