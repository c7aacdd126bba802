"""Top-down matplotlib pictures of the mazes (no OpenGL): walls, start, goals, trajectories and graphs."""

from __future__ import annotations

import numpy as np

from .mazes import MazeSpec, get_maze_spec

__all__ = ["plot_maze"]

_WALL_COLOR = "#6b6b80"
_EXTRA_WALL_COLOR = "#40405a"


def _as_numpy(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def _trajectories(trajectory) -> list[np.ndarray]:
    """A ``[T, >=2]`` array, a ``[B, T, >=2]`` batch or a list of arrays -> list of ``[T, 2]`` xy arrays."""
    if isinstance(trajectory, (list, tuple)):
        return [_as_numpy(t)[..., :2] for t in trajectory]
    trajectory = _as_numpy(trajectory)
    if trajectory.ndim == 2:
        return [trajectory[:, :2]]
    if trajectory.ndim == 3:
        return [t[:, :2] for t in trajectory]
    raise ValueError(
        f"trajectory must be [T, D], [B, T, D] or a list of [T, D], got shape {trajectory.shape}."
    )


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
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Circle, Rectangle

    spec = get_maze_spec(maze)
    if ax is None:
        _, ax = plt.subplots(figsize=(5, 5))
    layout = spec.layout
    n_grid_walls = int(layout.walls.sum())
    for k, box in enumerate(layout.wall_boxes):
        x0, x1, y0, y1 = box.xy_bounds
        color = _WALL_COLOR if k < n_grid_walls else _EXTRA_WALL_COLOR
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, facecolor=color, edgecolor="none", zorder=1))

    if edges is not None:
        edges = _as_numpy(edges)
        if edges.ndim == 2 and edges.shape[-1] == 2:
            if landmarks is None:
                raise ValueError("Index edges [E, 2] need `landmarks` to look the node positions up.")
            nodes = _as_numpy(landmarks)[:, :2]
            segments = nodes[edges.astype(np.int64)]
        elif edges.ndim == 3 and edges.shape[1:] == (2, 2):
            segments = edges
        else:
            raise ValueError(f"edges must be [E, 2] indices or [E, 2, 2] segments, got shape {edges.shape}.")
        ax.add_collection(LineCollection(segments, colors="#7fa7d9", linewidths=0.6, alpha=0.6, zorder=2))
    if landmarks is not None:
        nodes = _as_numpy(landmarks)
        ax.scatter(nodes[:, 0], nodes[:, 1], s=8, c="#1f5fbf", zorder=3, label="landmarks")
    if trajectory is not None:
        for k, xy in enumerate(_trajectories(trajectory)):
            (line,) = ax.plot(
                xy[:, 0], xy[:, 1], lw=1.0, alpha=0.8, zorder=4, label="trajectory" if k == 0 else None
            )
            ax.plot(xy[-1, 0], xy[-1, 1], "o", ms=3, color=line.get_color(), zorder=4)
    if path is not None:
        path = _as_numpy(path)[:, :2]
        ax.plot(path[:, 0], path[:, 1], "-o", color="#e08000", lw=2.0, ms=4, zorder=5, label="path")
    if show_test_goals:
        for k, (gx, gy) in enumerate(spec.test_goals):
            ax.add_patch(Circle((gx, gy), spec.success_threshold, facecolor="#d62728", alpha=0.15, zorder=2))
            ax.plot(gx, gy, "*", color="#d62728", ms=12, zorder=6, label="test goal" if k == 0 else None)
    if goal is not None:
        goals = _as_numpy(goal).reshape(-1, 2)
        ax.plot(goals[:, 0], goals[:, 1], "X", color="#9467bd", ms=9, zorder=6, label="goal")
    if show_start:
        ax.plot(0.0, 0.0, "s", color="#2ca02c", ms=8, zorder=6, label="start")

    low, high = layout.extent
    ax.set_xlim(float(low[0]), float(high[0]))
    ax.set_ylim(float(low[1]), float(high[1]))
    ax.set_aspect("equal")
    ax.set_title(spec.name if title is None else title)
    return ax
