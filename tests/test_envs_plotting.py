"""Top-down matplotlib maps, the demo entry point, and MuJoCo offscreen rendering (where OpenGL exists)."""

from __future__ import annotations

import os

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402
from matplotlib.colors import to_hex  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402
from torchrl_dhrl.envs import MAZE_NAMES, GymGoalEnv, get_maze_spec, make_env, plot_maze  # noqa: E402
from torchrl_dhrl.envs.demo import main as demo_main  # noqa: E402


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


def test_demo_writes_png(tmp_path, capsys):
    path = demo_main(["--out", str(tmp_path), "--steps", "5", "--num-envs", "2"])
    assert path == tmp_path / "mazes.png" and path.stat().st_size > 10_000
    assert str(path) in capsys.readouterr().out
    image = plt.imread(path)
    assert image.ndim == 3 and image.shape[1] > 2 * image.shape[0]  # five maps side by side


_GL = os.environ.get("MUJOCO_GL", "").lower()


@pytest.mark.skipif(
    _GL not in ("egl", "osmesa", "glfw"),
    reason="offscreen rendering needs MUJOCO_GL=egl or osmesa (an OpenGL backend)",
)
def test_offscreen_rendering():
    env = make_env("AntMazeSmall", num_envs=2, seed=0, eval=True)
    env.reset()
    frame = env.render(1, width=96, height=64)
    assert frame.shape == (64, 96, 3) and frame.dtype == torch.uint8 and frame.float().std() > 1.0
    tracked = env.render(0, width=64, height=64, camera="ant/track")
    assert tracked.shape == (64, 64, 3)
    gym_env = GymGoalEnv("PointMaze", render_mode="rgb_array", width=80, height=80)
    gym_env.reset(seed=0)
    assert gym_env.render().shape == (80, 80, 3)
    gym_env.close()
    env.close()
