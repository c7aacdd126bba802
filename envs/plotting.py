"""Matplotlib pictures of the environments (no OpenGL): scene, start, goals, trajectories and graphs.

:func:`plot_maze` draws a maze from above; :func:`plot_arm` draws an arm task as a projection of its 3-D
goal space (top ``x-y``, front ``y-z`` or side ``x-z``) with the arm in its start posture, the boards and
the goal region; :func:`plot_env` dispatches on the environment name. Points (trajectories, landmarks,
edges, paths, goals) are given in goal space: ``[..., 2]`` for the mazes, ``[..., 3]`` for the arms.
"""

from __future__ import annotations

import mujoco
import numpy as np

from .arms import ArmSpec, get_arm_spec
from .goals import BoxGoalSampler, FixedGoalSampler, GaussianGoalSampler
from .gymnasium_goal_env import gymnasium_id
from .mazes import MazeSpec, get_maze_spec
from .registry import get_env_factory, get_env_spec

__all__ = ["plot_maze", "plot_arm", "plot_env", "ARM_VIEWS"]

_WALL_COLOR = "#6b6b80"
_EXTRA_WALL_COLOR = "#40405a"
_BOARD_COLOR = "#8c6239"
_GOAL_COLOR = "#d62728"
#: Executed trajectories, one colour each in turn: dark and unlike the blue graph and the orange plan they
#: are drawn over (the default colour cycle's first blue vanished among the graph's edges).
_TRAJECTORY_COLORS = ("#111111", "#8c2d8c", "#2f6f2f", "#8b5a2b", "#555555")
#: Projections of :func:`plot_arm`: view name -> (horizontal axis, vertical axis) of the goal space.
ARM_VIEWS = {"top": (0, 1), "front": (1, 2), "side": (0, 2)}
_AXIS_LABELS = "xyz"


def _as_numpy(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def _trajectories(trajectory, axes: tuple[int, int]) -> list[np.ndarray]:
    """A ``[T, D]`` array, a ``[B, T, D]`` batch or a list of arrays -> list of ``[T, 2]`` projections."""
    axes = list(axes)
    if isinstance(trajectory, (list, tuple)):
        return [_as_numpy(t)[..., axes] for t in trajectory]
    trajectory = _as_numpy(trajectory)
    if trajectory.ndim == 2:
        return [trajectory[:, axes]]
    if trajectory.ndim == 3:
        return [t[:, axes] for t in trajectory]
    raise ValueError(
        f"trajectory must be [T, D], [B, T, D] or a list of [T, D], got shape {trajectory.shape}."
    )


def _draw_boxes(ax, boxes, axes: tuple[int, int], *, color: str, alpha: float = 1.0, outline: bool = False):
    """Axis-aligned boxes (:class:`~torchrl_dhrl.envs.WallBox`) projected on ``axes`` as filled rectangles
    (``outline`` keeps thin boards visible)."""
    from matplotlib.patches import Rectangle

    i, j = axes
    for box in boxes:
        low = np.asarray(box.center) - np.asarray(box.half_size)
        size = 2 * np.asarray(box.half_size)
        ax.add_patch(
            Rectangle(
                (low[i], low[j]),
                size[i],
                size[j],
                facecolor=color,
                edgecolor=color if outline else "none",
                alpha=alpha,
                zorder=1,
            )
        )


def _draw_overlays(ax, axes: tuple[int, int], *, trajectory, landmarks, edges, path, goal) -> None:
    """Trajectories, graph (landmarks and edges), planned path and goals, projected on ``axes``."""
    from matplotlib.collections import LineCollection

    axes_list = list(axes)
    if edges is not None:
        edges = _as_numpy(edges)
        if edges.ndim == 2 and edges.shape[-1] == 2:
            if landmarks is None:
                raise ValueError("Index edges [E, 2] need `landmarks` to look the node positions up.")
            nodes = _as_numpy(landmarks)[:, axes_list]
            segments = nodes[edges.astype(np.int64)]
        elif edges.ndim == 3 and edges.shape[1] == 2 and edges.shape[2] > max(axes):
            segments = edges[..., axes_list]
        else:
            raise ValueError(
                f"edges must be [E, 2] indices or [E, 2, goal_dim] segments, got shape {edges.shape}."
            )
        ax.add_collection(LineCollection(segments, colors="#7fa7d9", linewidths=0.6, alpha=0.6, zorder=2))
    if landmarks is not None:
        nodes = _as_numpy(landmarks)[:, axes_list]
        ax.scatter(nodes[:, 0], nodes[:, 1], s=8, c="#1f5fbf", zorder=3, label="landmarks")
    if trajectory is not None:
        for k, xy in enumerate(_trajectories(trajectory, axes)):
            color = _TRAJECTORY_COLORS[k % len(_TRAJECTORY_COLORS)]
            label = "trajectory" if k == 0 else None
            ax.plot(xy[:, 0], xy[:, 1], lw=1.3, alpha=0.9, color=color, zorder=5.5, label=label)
            ax.plot(xy[-1, 0], xy[-1, 1], "o", ms=5, color=color, zorder=5.5)  # where it ended
    if path is not None:
        path = _as_numpy(path)[:, axes_list]
        ax.plot(path[:, 0], path[:, 1], "-o", color="#e08000", lw=2.0, ms=4, zorder=5, label="path")
    if goal is not None:
        goal = _as_numpy(goal)
        goals = goal.reshape(-1, goal.shape[-1])[:, axes_list]
        ax.plot(goals[:, 0], goals[:, 1], "X", color="#9467bd", ms=9, zorder=6, label="goal")


def plot_maze(
    maze: str | MazeSpec,
    *,
    trajectory=None,
    landmarks=None,
    edges=None,
    path=None,
    goal=None,
    ax=None,
    show_start: bool = True,
    show_test_goals: bool = True,
    title: str | None = None,
):
    """Draws a maze from above with matplotlib and returns the Axes.

    Args:
        maze (str or MazeSpec): the maze name or spec.

    Keyword Args:
        trajectory (array-like, optional): agent positions ``[T, D]`` (the first two columns are x, y), a
            batch ``[B, T, D]`` or a list of such arrays; each is drawn as a line ending in a dot.
        landmarks (array-like, optional): graph nodes ``[N, 2]`` (x, y).
        edges (array-like, optional): graph edges, either integer ``[E, 2]`` index pairs into ``landmarks``
            or segment coordinates ``[E, 2, 2]``; drawn as thin lines.
        path (array-like, optional): a planned path ``[K, 2]`` (start, waypoints, subgoal), drawn on top.
        goal (array-like, optional): one ``[2]`` or several ``[G, 2]`` goals to mark (e.g. the episode goal).
        ax (matplotlib.axes.Axes, optional): axes to draw on; a new figure is created otherwise.
        show_start (bool): mark the start position (the origin). Defaults to ``True``.
        show_test_goals (bool): mark the fixed test goals with their success radius. Defaults to ``True``.
        title (str, optional): axes title; defaults to the maze name.

    Returns:
        the :class:`matplotlib.axes.Axes` drawn on.

    Examples:
        >>> import matplotlib
        >>> matplotlib.use("Agg")
        >>> import numpy as np
        >>> from torchrl_dhrl.envs import plot_maze
        >>> ax = plot_maze("AntMazeSmall", trajectory=np.array([[0.0, 0.0], [4.0, 0.0], [8.0, 2.0]]),
        ...                landmarks=np.array([[0.0, 0.0], [8.0, 0.0], [8.0, 8.0]]), edges=[[0, 1], [1, 2]])
        >>> [float(v) for v in ax.get_xlim()]
        [-6.0, 14.0]
    """
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    spec = get_maze_spec(maze)
    if ax is None:
        _, ax = plt.subplots(figsize=(5, 5))
    layout = spec.layout
    n_grid_walls = int(layout.walls.sum())
    _draw_boxes(ax, layout.wall_boxes[:n_grid_walls], (0, 1), color=_WALL_COLOR)
    _draw_boxes(ax, layout.wall_boxes[n_grid_walls:], (0, 1), color=_EXTRA_WALL_COLOR)

    _draw_overlays(ax, (0, 1), trajectory=trajectory, landmarks=landmarks, edges=edges, path=path, goal=goal)
    if show_test_goals:
        for k, (gx, gy) in enumerate(spec.test_goals):
            ax.add_patch(
                Circle((gx, gy), spec.success_threshold, facecolor=_GOAL_COLOR, alpha=0.15, zorder=2)
            )
            ax.plot(gx, gy, "*", color=_GOAL_COLOR, ms=12, zorder=6, label="test goal" if k == 0 else None)
    if show_start:
        ax.plot(0.0, 0.0, "s", color="#2ca02c", ms=8, zorder=6, label="start")

    low, high = layout.extent
    ax.set_xlim(float(low[0]), float(high[0]))
    ax.set_ylim(float(low[1]), float(high[1]))
    ax.set_aspect("equal")
    ax.set_title(spec.name if title is None else title)
    return ax


def _start_posture(spec: ArmSpec) -> np.ndarray:
    """World positions ``[K, 3]`` of the arm's joints (body origins) and end effector at the reset posture."""
    model = spec.compile_model()
    data = mujoco.MjData(model)
    data.qpos[:] = spec.agent.init_qpos
    mujoco.mj_kinematics(model, data)
    prefix = f"{spec.agent.model_name}/"
    bodies = [b for b in range(model.nbody) if model.body(b).name.startswith(prefix)]
    points = [data.xpos[b] for b in bodies] + [data.site_xpos[model.site(spec.achieved_goal_site).id]]
    return np.array(points)


def _draw_goal_region(ax, spec: ArmSpec, axes: tuple[int, int]) -> None:
    from matplotlib.patches import Circle, Ellipse, Rectangle

    sampler, (i, j) = spec.test_goal_sampler, axes
    style = {"facecolor": _GOAL_COLOR, "alpha": 0.15, "zorder": 2}
    if isinstance(sampler, BoxGoalSampler):
        low, high = np.asarray(sampler.low), np.asarray(sampler.high)
        ax.add_patch(
            Rectangle((low[i], low[j]), high[i] - low[i], high[j] - low[j], label="test goals", **style)
        )
        centers = ((low + high) / 2)[None]
    elif isinstance(sampler, GaussianGoalSampler):
        mean, std = np.asarray(sampler.mean), np.asarray(sampler.std)
        ax.add_patch(
            Ellipse((mean[i], mean[j]), 4 * std[i], 4 * std[j], label="test goals (2 sigma)", **style)
        )
        centers = mean[None]
    elif isinstance(sampler, FixedGoalSampler):
        centers = np.asarray(sampler.goals, dtype=np.float64)
    else:
        return
    for center in centers:
        ax.add_patch(
            Circle(
                (center[i], center[j]), spec.success_threshold, fill=False, ls="--", ec=_GOAL_COLOR, zorder=2
            )
        )
    ax.plot(centers[:, i], centers[:, j], "*", color=_GOAL_COLOR, ms=12, zorder=6)


def plot_arm(
    arm: str | ArmSpec,
    *,
    trajectory=None,
    landmarks=None,
    edges=None,
    path=None,
    goal=None,
    ax=None,
    view: str = "top",
    show_arm: bool = True,
    show_test_goals: bool = True,
    title: str | None = None,
):
    """Draws an arm task as a 2-D projection of its 3-D goal space and returns the Axes.

    Drawn: the boards (translucent rectangles, their projection), the table (front and side views), the arm in
    its reset posture (grey stick figure through its joints, the end effector as a green square), the test
    goal region (UR3Obstacle: the goal box; Reacher3D: the 2-sigma ellipse of its Gaussian goals) with the
    success radius around its centre (dashed), and the overlays.

    Args:
        arm (str or ArmSpec): the arm task name or spec.

    Keyword Args:
        trajectory (array-like, optional): end-effector positions ``[T, 3]``, a batch ``[B, T, 3]`` or a
            list of such arrays (UR3Obstacle observations work as they are: their first three entries are the
            end effector); each is drawn as a line ending in a dot.
        landmarks (array-like, optional): graph nodes ``[N, 3]``.
        edges (array-like, optional): integer ``[E, 2]`` index pairs into ``landmarks`` or segments
            ``[E, 2, 3]``.
        path (array-like, optional): a planned path ``[K, 3]``.
        goal (array-like, optional): one ``[3]`` or several ``[G, 3]`` goals to mark.
        ax (matplotlib.axes.Axes, optional): axes to draw on; a new figure is created otherwise.
        view (str): ``"top"`` (x-y, from above), ``"front"`` (y-z, looking along -x at the arm) or
            ``"side"`` (x-z, looking along +y). Defaults to ``"top"``.
        show_arm (bool): draw the arm's reset posture. Defaults to ``True``.
        show_test_goals (bool): draw the test goal region. Defaults to ``True``.
        title (str, optional): axes title; defaults to ``"<name> (<view>)"``.

    Returns:
        the :class:`matplotlib.axes.Axes` drawn on.

    Examples:
        >>> import matplotlib
        >>> matplotlib.use("Agg")
        >>> import numpy as np
        >>> from torchrl_dhrl.envs import plot_arm
        >>> ax = plot_arm("UR3Obstacle", view="front", path=np.array([[0.3, -0.2, 0.1], [0.3, 0.0, 0.4],
        ...                                                                 [0.3, 0.2, 0.1]]))
        >>> ax.get_xlabel(), ax.get_ylabel(), ax.get_title()
        ('y', 'z', 'UR3Obstacle (front)')
    """
    import matplotlib.pyplot as plt

    spec = get_arm_spec(arm)
    if view not in ARM_VIEWS:
        raise ValueError(f"view must be one of {', '.join(ARM_VIEWS)}, got {view!r}.")
    axes = ARM_VIEWS[view]
    i, j = axes
    if ax is None:
        _, ax = plt.subplots(figsize=(5, 5))
    _draw_boxes(ax, spec.boards, axes, color=_BOARD_COLOR, alpha=0.45, outline=True)
    if spec.table and j == 2:
        ax.axhline(0.0, color=_WALL_COLOR, lw=2.0, zorder=1)
    if show_test_goals:
        _draw_goal_region(ax, spec, axes)
    if show_arm:
        posture = _start_posture(spec)
        ax.plot(posture[:, i], posture[:, j], "-o", color="0.45", lw=3.0, ms=4, zorder=3, label="arm (start)")
        ax.plot(posture[-1, i], posture[-1, j], "s", color="#2ca02c", ms=8, zorder=6, label="start")
    _draw_overlays(ax, axes, trajectory=trajectory, landmarks=landmarks, edges=edges, path=path, goal=goal)

    low, high = spec.goal_bounds
    ax.set_xlim(float(low[i]), float(high[i]))
    ax.set_ylim(float(low[j]), float(high[j]))
    ax.set_aspect("equal")
    ax.set_xlabel(_AXIS_LABELS[i])
    ax.set_ylabel(_AXIS_LABELS[j])
    ax.set_title(f"{spec.name} ({view})" if title is None else title)
    return ax


def _plot_goal_space(name: str, *, ax=None, title: str | None = None, maze=None, **overlays):
    """The overlays on goal axes 0 and 1 (an environment without a known scene), over the walls, the arena and
    the start of ``maze`` (a :class:`~torchrl_dhrl.envs.geometry.MazeGeometry`) where given."""
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    if ax is None:
        _, ax = plt.subplots(figsize=(5, 5))
    if maze is not None:
        for low, high in maze.boxes.tolist():
            size = (high[0] - low[0], high[1] - low[1])
            ax.add_patch(Rectangle(low, *size, facecolor=_WALL_COLOR, edgecolor="none", zorder=1))
    _draw_overlays(ax, (0, 1), **overlays)
    if maze is not None:
        if maze.start is not None:
            ax.plot(*maze.start.tolist(), "s", color="#2ca02c", ms=8, zorder=6, label="start")
        ax.set_xlim(float(maze.arena_low[0]), float(maze.arena_high[0]))
        ax.set_ylim(float(maze.arena_low[1]), float(maze.arena_high[1]))
        ax.set_aspect("equal")
    else:
        ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(_AXIS_LABELS[0])
    ax.set_ylabel(_AXIS_LABELS[1])
    ax.set_title(name if title is None else title)
    return ax


def plot_env(
    name: str,
    *,
    trajectory=None,
    landmarks=None,
    edges=None,
    path=None,
    goal=None,
    ax=None,
    view: str = "top",
    title: str | None = None,
    maze=None,
):
    """Draws any environment and returns the Axes: :func:`plot_maze` for a maze, :func:`plot_arm` for an arm.

    Points are in the environment's goal space (``[..., 2]`` for the mazes, ``[..., 3]`` for the arms);
    3-D goal spaces are drawn as a projection, from above by default.

    An environment registered with :func:`~torchrl_dhrl.envs.register_env` has no scene to draw: its
    overlays are drawn alone on the first two goal axes.

    Args:
        name (str): any of :data:`~torchrl_dhrl.envs.ENV_NAMES` (or its Gymnasium id), a spec, or the
            name of a registered environment.

    Keyword Args:
        trajectory, landmarks, edges, path, goal, ax: as :func:`plot_maze` / :func:`plot_arm`.
        view (str): the arms' projection, ``"top"``, ``"front"`` or ``"side"`` (see :func:`plot_arm`); the
            mazes are always drawn from above (only ``"top"`` is accepted). Defaults to ``"top"``.
        title (str, optional): axes title (defaults to the environment's name).
        maze (MazeGeometry, optional): for an environment without a known scene, a maze to draw under the
            overlays (its walls, arena and start), e.g. a gymnasium-robotics maze's
            (:meth:`~torchrl_dhrl.envs.GymnasiumGoalEnv.maze_geometry`). Defaults to none.

    Returns:
        the :class:`matplotlib.axes.Axes` drawn on.

    Examples:
        >>> import matplotlib
        >>> matplotlib.use("Agg")
        >>> import numpy as np
        >>> from torchrl_dhrl.envs import plot_env
        >>> plot_env("PointMaze", goal=[0.0, 8.0]).get_title()
        'PointMaze'
        >>> ax = plot_env("Reacher3D", trajectory=np.zeros((5, 3)), landmarks=np.zeros((4, 3)), view="side")
        >>> ax.get_title()
        'Reacher3D (side)'
    """
    overlays = {"trajectory": trajectory, "landmarks": landmarks, "edges": edges, "path": path, "goal": goal}
    if get_env_factory(name) is not None or gymnasium_id(name) is not None:  # goal space only
        return _plot_goal_space(name, ax=ax, title=title, maze=maze, **overlays)
    spec = get_env_spec(name)
    if isinstance(spec, MazeSpec):
        if view != "top":
            raise ValueError(f"Mazes are drawn from above only: view must be 'top', got {view!r}.")
        return plot_maze(spec, ax=ax, title=title, **overlays)
    return plot_arm(spec, ax=ax, view=view, title=title, **overlays)
