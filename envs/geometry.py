"""The true geometry of the environments, for diagnostics and oracles.

A :class:`MazeGeometry` holds a maze's wall boxes, its arena and a fine occupancy grid (free cells: centre
outside every wall box inflated by ``margin``, the agent's radius), on which :func:`grid_shortest_paths`
computes obstacle-free path lengths by vectorised min-plus relaxation (torch only) and
:func:`furthest_progress` how far along them points got; :func:`obstacle_boxes` gives any env's obstacles in
goal space (a maze's wall footprints, the UR3 task's boards).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from torchrl_dhrl.planner import LineOfSightDistance

__all__ = [
    "MazeGeometry",
    "cached_maze_geometry",
    "furthest_progress",
    "grid_moves",
    "grid_shortest_paths",
    "obstacle_boxes",
]


def grid_moves(connectivity: int = 16) -> list[tuple[tuple[int, int], list[tuple[int, int]]]]:
    """The moves of the occupancy-grid graph: ``[((di, dj), [cells that must be free]), ...]``.

    ``connectivity`` 4 (orthogonal steps), 8 (plus diagonals) or 16 (plus knight moves). A move from
    cell ``(i, j)`` to ``(i + di, j + dj)`` needs both cells free and, for the diagonal and knight moves,
    the cells the straight segment between the two centres passes through (offsets from ``(i, j)``):
    ``(di, 0)`` and ``(0, dj)`` for a diagonal (no corner cutting), ``(0, dj / 2)`` and ``(di, dj / 2)``
    for a knight move with ``|dj| = 2`` (``(di / 2, 0)`` and ``(di / 2, dj)`` for ``|di| = 2``). Its cost
    is the distance between the centres. 16-connectivity overestimates a straight free path by at most
    2.8% (8-connectivity: 8.2%).

    Examples:
        >>> [move for move, _ in grid_moves(8)][:4]
        [(-1, 0), (1, 0), (0, -1), (0, 1)]
        >>> dict(grid_moves(16))[(1, 2)]
        [(0, 1), (1, 1)]
    """
    if connectivity not in (4, 8, 16):
        raise ValueError(f"`connectivity` must be 4, 8 or 16, got {connectivity!r}.")
    moves = [((-1, 0), []), ((1, 0), []), ((0, -1), []), ((0, 1), [])]
    if connectivity >= 8:
        moves += [((di, dj), [(di, 0), (0, dj)]) for di in (-1, 1) for dj in (-1, 1)]
    if connectivity == 16:
        for di in (-1, 1):
            for dj in (-2, 2):
                moves.append(((di, dj), [(0, dj // 2), (di, dj // 2)]))
        for di in (-2, 2):
            for dj in (-1, 1):
                moves.append(((di, dj), [(di // 2, 0), (di // 2, dj)]))
    return moves


def _shift(mask: Tensor, di: int, dj: int) -> Tensor:
    """``out[i, j] = mask[i + di, j + dj]`` (``False`` outside the grid)."""
    height, width = mask.shape
    out = torch.zeros_like(mask)
    out[max(0, -di) : height - max(0, di), max(0, -dj) : width - max(0, dj)] = mask[
        max(0, di) : height + min(0, di), max(0, dj) : width + min(0, dj)
    ]
    return out


def grid_shortest_paths(
    free: Tensor,
    sources: Tensor,
    *,
    resolution: float | Sequence[float] = 1.0,
    connectivity: int = 16,
    max_sweeps: int | None = None,
) -> Tensor:
    """Obstacle-free path lengths from source cells to every cell of an occupancy grid.

    Bellman-Ford on the grid graph of :func:`grid_moves`, vectorised over cells and sources: each
    sweep relaxes every move once for every cell of every source's distance field (a shifted copy of
    the fields plus the move's cost, ``+inf`` where the move is not allowed, then an elementwise
    minimum, in place so that a sweep can chain moves). The sweeps stop when nothing changes, at the
    latest after ``max_sweeps`` (default: the number of cells, enough for any grid). Only the sweeps
    are a Python loop (plus the constant 4/8/16 moves within each).

    Args:
        free (Tensor): ``[H, W]`` bool, ``True`` on free cells (rows along y, columns along x).
        sources (Tensor): ``[S, 2]`` int ``(row, column)`` of the source cells.

    Keyword Args:
        resolution (float or (float, float)): the cell size (``(row, column)`` sizes if different).
            Defaults to ``1.0``.
        connectivity (int): 4, 8 or 16 (see :func:`grid_moves`). Defaults to ``16``.
        max_sweeps (int, optional): upper bound on the relaxation sweeps.

    Returns:
        ``[S, H, W]`` float32 path lengths (``inf``: unreachable, or a wall cell; a source on a wall
        cell reaches nothing but itself).

    Examples:
        >>> import torch
        >>> free = torch.ones(3, 5, dtype=torch.bool)
        >>> free[0:2, 2] = False  # a wall with a gap in the bottom row
        >>> d = grid_shortest_paths(free, torch.tensor([[0, 0]]), connectivity=4)
        >>> d[0].tolist()
        [[0.0, 1.0, inf, 7.0, 8.0], [1.0, 2.0, inf, 6.0, 7.0], [2.0, 3.0, 4.0, 5.0, 6.0]]
    """
    if free.ndim != 2 or free.dtype != torch.bool:
        raise ValueError(f"`free` must be a 2-D bool tensor, got {free.dtype} of shape {tuple(free.shape)}.")
    sources = torch.as_tensor(sources, dtype=torch.long, device=free.device).reshape(-1, 2)
    height, width = free.shape
    if sources.numel() and (
        (sources < 0).any() or (sources[:, 0] >= height).any() or (sources[:, 1] >= width).any()
    ):
        raise ValueError(f"`sources` must be (row, column) cells of the {height} x {width} grid.")
    if isinstance(resolution, (int, float)):
        res_i = res_j = float(resolution)
    else:
        res_i, res_j = map(float, resolution)
    # Fields live in a flat [S, (H + 6) * (W + 4)] buffer padded with +inf (two columns, three rows on each
    # side), so that every move reads one contiguous slice: the band of the H grid rows shifted by the move.
    pad, pad_rows = 2, 3
    padded_width = width + 2 * pad
    band = slice(pad_rows * padded_width, (pad_rows + height) * padded_width)
    penalties = []  # (flat offset of the predecessor, [H * (W + 4)] cost of the move into each band cell)
    for (di, dj), through in grid_moves(connectivity):
        allowed = free & _shift(free, -di, -dj)  # the target (i, j) and its predecessor (i - di, j - dj)
        for ti, tj in through:  # intermediate cells, as offsets from the predecessor
            allowed &= _shift(free, ti - di, tj - dj)
        cost = torch.full((height, padded_width), math.inf, dtype=torch.float32, device=free.device)
        cost[:, pad : pad + width] = torch.where(allowed, math.hypot(di * res_i, dj * res_j), math.inf)
        penalties.append((-(di * padded_width + dj), cost.flatten()))
    num = sources.shape[0]
    fields = torch.full(
        (num, (height + 2 * pad_rows) * padded_width), math.inf, dtype=torch.float32, device=free.device
    )
    flat_sources = (sources[:, 0] + pad_rows) * padded_width + sources[:, 1] + pad
    fields[torch.arange(num, device=free.device), flat_sources] = 0.0
    current = fields[:, band]  # a view: updated in place
    candidate, before = torch.empty_like(current), torch.empty_like(current)
    for _ in range(max_sweeps or height * width):
        before.copy_(current)
        for offset, cost in penalties:
            torch.add(fields[:, band.start + offset : band.stop + offset], cost, out=candidate)
            torch.minimum(current, candidate, out=current)
        if torch.equal(before, current):
            break
    return current.reshape(num, height, padded_width)[:, :, pad : pad + width].clone()


class MazeGeometry:
    """The true geometry of a maze in goal space: wall boxes, the arena and an occupancy grid.

    Points are ``(x, y)`` goals. A point is *in a wall* when it lies inside the arena and inside the
    walls (optionally grown by a margin, see :meth:`in_walls`); *outside* when it lies outside the arena
    (the rectangle inside the outer walls, ``MazeLayout.bounds``); *feasible* when neither. True obstacle-free path
    lengths (:meth:`path_length`) are computed on the occupancy grid: cells of size ``resolution``
    tiling the arena, free when their centre is not inside the walls inflated by ``margin`` (the agent's
    radius: its centre cannot come closer to a wall; see :meth:`in_walls`).

    Args:
        boxes (Tensor or sequence): ``[W, 2, 2]`` wall boxes (``boxes[:, 0]`` lower corners,
            ``boxes[:, 1]`` upper corners).
        low (sequence of float): lower corner of the arena.
        high (sequence of float): upper corner of the arena.

    Keyword Args:
        margin (float): wall inflation of the occupancy grid and of :meth:`path_length`. Defaults to
            ``0.0``.
        resolution (float): grid cell size (rounded so that whole cells tile the arena). Defaults to
            ``0.5``.
        connectivity (int): of the grid graph, see :func:`grid_moves`. Defaults to ``16``.
        start (sequence of float, optional): where progress along the maze is measured from
            (:func:`furthest_progress`); ``None`` where episodes start anywhere (progress is then undefined).
            Defaults to the origin, the built-in mazes' start.
        scale (float, optional): the maze's cell size (the width of a corridor), for sizes that follow it
            (:func:`~torchrl_dhrl.diagnostics.default_coverage_radius`). Defaults to ``None``.

    Examples:
        >>> import torch
        >>> geometry = MazeGeometry.from_maze("PointMaze", margin=0.5, resolution=0.25)
        >>> geometry.free.shape, geometry.arena_low.tolist(), geometry.arena_high.tolist()
        (torch.Size([48, 48]), [-2.0, -2.0], [10.0, 10.0])
        >>> points = torch.tensor([[0.0, 0.0], [2.0, 4.0], [12.0, 0.0]])
        >>> geometry.in_walls(points).tolist(), geometry.outside(points).tolist()
        ([False, True, False], [False, False, True])
        >>> # around the U's inner wall: 18.3 exactly for a 0.5-radius agent (16-connected grid, 0.25 cells)
        >>> round(geometry.path_length(torch.tensor([0.0, 0.0]), torch.tensor([0.0, 8.0])).item(), 1)
        19.4
    """

    def __init__(
        self,
        boxes: Tensor | Sequence,
        low: Sequence[float],
        high: Sequence[float],
        *,
        margin: float = 0.0,
        resolution: float = 0.5,
        connectivity: int = 16,
        start: Sequence[float] | None = (0.0, 0.0),
        scale: float | None = None,
    ) -> None:
        boxes = torch.as_tensor(boxes, dtype=torch.float32).reshape(-1, 2, 2)
        #: ``[2]`` where progress is measured from, or ``None``
        self.start = None if start is None else torch.as_tensor(start, dtype=torch.float32).reshape(2)
        #: the maze's cell size, or ``None``
        self.scale = None if scale is None else float(scale)
        if not margin >= 0 or not resolution > 0:
            raise ValueError(f"Need margin >= 0 and resolution > 0, got {margin}, {resolution}.")
        self.boxes = boxes
        self.arena_low = torch.as_tensor(low, dtype=torch.float32).reshape(2)
        self.arena_high = torch.as_tensor(high, dtype=torch.float32).reshape(2)
        if not (self.arena_high > self.arena_low).all():
            raise ValueError(f"The arena needs low < high, got {list(low)}, {list(high)}.")
        self.margin = float(margin)
        self.connectivity = connectivity
        extent = (self.arena_high - self.arena_low).double()
        cells = (extent / resolution).round().clamp_min(1).long()
        self.cell_size = (extent / cells).float()  # (x, y) sizes
        self.shape = (int(cells[1]), int(cells[0]))  # (rows along y, columns along x)
        cols = self.arena_low[0] + (torch.arange(self.shape[1]) + 0.5) * self.cell_size[0]
        rows = self.arena_low[1] + (torch.arange(self.shape[0]) + 0.5) * self.cell_size[1]
        ys, xs = torch.meshgrid(rows, cols, indexing="ij")
        #: ``[H, W, 2]`` ``(x, y)`` of every cell centre
        self.cell_centers = torch.stack([xs, ys], -1)
        #: ``[H, W]`` bool, free cells
        self.free = ~self.in_walls(self.cell_centers, margin=self.margin)
        self._free_index = self.free.flatten().nonzero().squeeze(-1)
        if not self._free_index.numel():
            width = f"; its corridors are {self.scale:g} wide: accepted a margin well below {self.scale / 2:g}" if self.scale else ""
            raise ValueError(
                f"margin={margin:g} leaves no free cell: the walls grown by it cover the whole arena{width}."
            )
        # segment tests of (x, y) points (crosses_obstacle): the goals are the states
        self._segments = LineOfSightDistance(1.0, boxes=self.boxes, margin=self.margin, goal_indices=(0, 1))
        self._walls = LineOfSightDistance(1.0, boxes=self.boxes, goal_indices=(0, 1))

    @classmethod
    def from_maze(
        cls, maze, *, margin: float = 0.0, resolution: float | None = None, connectivity: int = 16
    ) -> MazeGeometry:
        """The geometry of a maze (a name or a :class:`~torchrl_dhrl.envs.MazeSpec`).

        The default ``resolution`` is the largest cell size of at most an eighth of the maze scale that
        puts cell centres on the inflated wall faces (``margin / (j + 1/2)`` for an integer ``j``, when it
        divides the scale), so that the grid's free space is the true one rather than up to half a cell
        narrower: 1/3 for PointMaze and 1 for the ant mazes with the recipe's 0.5 margin; an eighth of the
        scale otherwise.
        """
        from .mazes import get_maze_spec

        layout = get_maze_spec(maze).layout
        if resolution is None:
            resolution = _aligned_resolution(layout.scale, margin)
        boxes = [[[x0, y0], [x1, y1]] for x0, x1, y0, y1 in (wall.xy_bounds for wall in layout.wall_boxes)]
        low, high = layout.bounds
        return cls(
            boxes,
            low.tolist(),
            high.tolist(),
            margin=margin,
            resolution=resolution,
            connectivity=connectivity,
            scale=layout.scale,
        )

    @classmethod
    def from_gymnasium_maze(
        cls,
        maze,
        *,
        start_cell: Sequence[int] | None = None,
        margin: float = 0.0,
        resolution: float | None = None,
        connectivity: int = 16,
    ) -> MazeGeometry:
        """The geometry of a gymnasium-robotics maze (``env.unwrapped.maze`` of ``PointMaze_*`` and ``AntMaze_*``):
        a wall box per wall cell of its ``maze_map`` (cells of ``maze_size_scaling``, centred where its
        ``cell_rowcol_to_xy`` puts them), the arena inside the outer walls, the start at the centre of
        ``start_cell`` (the ``reset_cell`` of fixed-start resets; ``None``: no start). ``resolution`` as
        :meth:`from_maze`.

        Examples:
            >>> from types import SimpleNamespace
            >>> import numpy as np
            >>> cells = [[1, 1, 1, 1], [1, 0, 0, 1], [1, 0, 1, 1], [1, 1, 1, 1]]  # an L of 3 free cells
            >>> maze = SimpleNamespace(maze_map=cells, maze_size_scaling=1.0,
            ...                        cell_rowcol_to_xy=lambda rc: np.array([rc[1] - 1.5, 1.5 - rc[0]]))
            >>> geometry = MazeGeometry.from_gymnasium_maze(maze, start_cell=(2, 1))
            >>> geometry.arena_low.tolist(), geometry.arena_high.tolist(), geometry.start.tolist(), geometry.scale
            ([-1.0, -1.0], [1.0, 1.0], [-0.5, -0.5], 1.0)
            >>> round(furthest_progress(geometry, torch.tensor([[-0.5, 0.5]])), 2)  # one cell up the L
            1.0
        """
        walls = np.asarray(maze.maze_map) == 1
        scale = float(maze.maze_size_scaling)
        rows, cols = walls.shape

        def centre(row: int, col: int) -> np.ndarray:
            return np.asarray(maze.cell_rowcol_to_xy(np.array([row, col])), dtype=np.float64)

        boxes = [[centre(r, c) - scale / 2, centre(r, c) + scale / 2] for r, c in zip(*walls.nonzero(), strict=True)]
        corners = np.stack([centre(1, 1), centre(rows - 2, cols - 2)])  # the cells inside the outer walls
        low, high = corners.min(0) - scale / 2, corners.max(0) + scale / 2
        if resolution is None:
            resolution = _aligned_resolution(scale, margin)
        return cls(
            np.asarray(boxes, dtype=np.float32).reshape(-1, 2, 2),
            low.tolist(),
            high.tolist(),
            margin=margin,
            resolution=resolution,
            connectivity=connectivity,
            start=None if start_cell is None else centre(*start_cell).tolist(),
            scale=scale,
        )

    # ------------------------------------------------------------------ points
    def outside(self, points: Tensor) -> Tensor:
        """``[...]`` bool: outside the arena (``points [..., 2]``)."""
        points = points.float().cpu()
        return ((points < self.arena_low) | (points > self.arena_high)).any(-1)

    def in_walls(self, points: Tensor, margin: float = 0.0, *, closed: bool = False) -> Tensor:
        """``[...]`` bool: inside the arena and inside the walls (the union of the boxes grown by ``margin``).

        A point on the outer boundary of the walls counts as outside them, one on a face shared by two
        adjacent wall blocks (e.g. ``x = 2`` in PointMaze's inner wall) as inside: a point is inside when
        the four points ``1e-4`` away from it diagonally all lie in the closed boxes. With ``closed`` the
        boundary counts as inside too (as for :class:`LineOfSightDistance`, which blocks a segment touching
        a box).
        """
        points = points.float().cpu()
        if self.boxes.shape[0] == 0:
            return torch.zeros(points.shape[:-1], dtype=torch.bool)
        low, high = self.boxes[:, 0] - margin, self.boxes[:, 1] + margin

        def in_closed_boxes(p: Tensor) -> Tensor:
            p = p.unsqueeze(-2)  # [..., 1, 2]
            return ((p >= low) & (p <= high)).all(-1).any(-1)

        if closed:
            inside = in_closed_boxes(points)
        else:
            eps = 1e-4
            inside = torch.ones(points.shape[:-1], dtype=torch.bool)
            for dx, dy in ((eps, eps), (eps, -eps), (-eps, eps), (-eps, -eps)):
                inside &= in_closed_boxes(points + torch.tensor([dx, dy]))
        return inside & ~self.outside(points)

    def feasible(self, points: Tensor, margin: float = 0.0) -> Tensor:
        """``[...]`` bool: neither in a wall (grown by ``margin``) nor outside the arena."""
        return ~self.in_walls(points, margin) & ~self.outside(points)

    def crosses_walls(self, start: Tensor, end: Tensor) -> Tensor:
        """``[n]`` bool: does the segment ``start -> end`` (``[n, 2]``) cross a wall box (not inflated)?"""
        return self._walls.crosses_obstacle(start.float().cpu(), end.float().cpu())

    def nearest_free_cell(self, points: Tensor) -> Tensor:
        """``[...]`` int64 flat index (``row * W + column``) of the free cell whose centre is nearest."""
        points = points.float().cpu()
        centers = self.cell_centers.reshape(-1, 2)[self._free_index]
        flat = points.reshape(-1, 2)
        nearest = torch.cdist(flat, centers).argmin(-1) if flat.shape[0] else flat.new_zeros(0).long()
        return self._free_index[nearest].reshape(points.shape[:-1])

    # ------------------------------------------------------------------ path lengths
    def _fields(self, cells: Tensor) -> Tensor:
        """``[N, H * W]`` grid path lengths from the free cells ``cells [N]`` (flat indices) to every cell."""
        width = self.shape[1]
        size_x, size_y = self.cell_size.tolist()
        return grid_shortest_paths(
            self.free,
            torch.stack([cells // width, cells % width], -1),
            resolution=(size_y, size_x),
            connectivity=self.connectivity,
        ).flatten(1)

    def path_length(self, starts: Tensor, ends: Tensor) -> Tensor:
        """The true obstacle-free path length between ``starts [..., 2]`` and ``ends [..., 2]`` (broadcast).

        The Euclidean distance when the straight segment clears every wall box inflated by ``margin``;
        otherwise the grid path length between the free cells nearest to the two points (at least the
        Euclidean distance); ``inf`` between disconnected parts of the free space. One distance field
        is computed per distinct start cell: ``path_length(a[:, None], b[None])`` gives a matrix.

        Accuracy: 16-connected moves overestimate a long free run by at most 2.8%, snapping to cell
        centres up to a cell's diagonal: around the U's inner wall (0.5 margin) the default grids give
        19.0 for the exact 18.3 (PointMaze, 1/3 cells; 18.8 with 1/9 cells) and 36.7 for 35.0 (AntMaze).
        """
        starts, ends = starts.float().cpu(), ends.float().cpu()
        shape = torch.broadcast_shapes(starts.shape[:-1], ends.shape[:-1])
        # snapped before broadcasting: once per point, not per pair
        start_cells = self.nearest_free_cell(starts).expand(shape).reshape(-1)
        end_cells = self.nearest_free_cell(ends).expand(shape).reshape(-1)
        starts = starts.expand(*shape, 2).reshape(-1, 2)
        ends = ends.expand(*shape, 2).reshape(-1, 2)
        if starts.shape[0] == 0:
            return torch.zeros(shape)
        cells, inverse = torch.unique(start_cells, return_inverse=True)
        grid = self._fields(cells)[inverse, end_cells]
        straight = (ends - starts).norm(dim=-1)
        visible = ~self._segments.crosses_obstacle(starts, ends)
        out = torch.where(visible, straight, torch.maximum(grid, straight))
        return out.reshape(shape)

    def points_along(self, progress: Sequence[float], *, clearance: float = 0.0) -> tuple[Tensor, Tensor]:
        """Points along the maze: for each ``progress`` ``p``, the free cell centre at least ``clearance`` from
        every wall whose path length from the start (:meth:`path_length`) is nearest ``p`` (the first in row-major
        order on a tie). E.g. starts for a reach test along the route (room for the agent's body: ``clearance``).

        Returns:
            ``[K, 2]`` points and ``[K]`` their path lengths from the start.

        Raises:
            ValueError: for a geometry without a start, or a ``clearance`` that leaves no cell connected to it.

        Examples:
            >>> geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
            >>> points, length = geometry.points_along([4.0, 12.0], clearance=1.5)  # along the first corridor, up the U
            >>> [f"({x:.1f}, {y:.1f}) at {d:.1f}" for (x, y), d in zip(points.tolist(), length.tolist())]
            ['(3.8, -0.5) at 3.9', '(7.5, 6.2) at 12.0']
        """
        if self.start is None:
            raise ValueError("This maze geometry has no start (episodes start anywhere): progress is undefined.")
        cells = self.cell_centers[self.free]
        cells = cells[~self.in_walls(cells, margin=clearance)]
        length = self.path_length(self.start, cells)
        connected = torch.isfinite(length)
        if not connected.any():
            raise ValueError(
                f"clearance={clearance:g} leaves no free cell connected to the start {self.start.tolist()}."
            )
        cells, length = cells[connected], length[connected]
        target = torch.as_tensor(list(progress), dtype=length.dtype).reshape(-1, 1)
        index = (length - target).abs().argmin(-1)
        return cells[index], length[index]


def _aligned_resolution(scale: float, margin: float) -> float:
    """See :meth:`MazeGeometry.from_maze`: wall faces lie at multiples of ``scale`` from the corner."""
    if margin > 0:
        first = max(0, math.ceil(8 * margin / scale - 0.5))  # the first cell size <= scale / 8
        for j in range(first, first + 64):
            resolution = margin / (j + 0.5)
            cells = scale / resolution
            if abs(cells - round(cells)) < 1e-6:
                return resolution
    return scale / 8


@functools.lru_cache(maxsize=16)
def cached_maze_geometry(name: str, margin: float, resolution: float | None) -> MazeGeometry:
    """:meth:`MazeGeometry.from_maze`, cached per ``(name, margin, resolution)`` (the geometry is immutable).

    Examples:
        >>> from torchrl_dhrl.envs.geometry import cached_maze_geometry
        >>> cached_maze_geometry("PointMaze", 0.5, None) is cached_maze_geometry("PointMaze", 0.5, None)
        True
    """
    return MazeGeometry.from_maze(name, margin=margin, resolution=resolution)


def furthest_progress(geometry: MazeGeometry, points: Tensor, start: Tensor | None = None) -> float:
    """The largest true path length (:meth:`MazeGeometry.path_length`) from ``start`` to one of ``points [..., 2]``.

    How far into the maze a set of points reaches: the graph's landmarks (``landmark_progress`` of
    :func:`graph_quality`), the states of training episodes (:class:`TrainingEpisodeLog`). ``start`` defaults
    to the geometry's (the origin, every built-in maze's start); points cut off from it are ignored, and
    ``-inf`` is returned when none is left, ``NaN`` when neither gives a start.

    Examples:
        >>> geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
        >>> furthest_progress(geometry, torch.tensor([[4.0, 0.0], [1.0, 0.0]]))  # along the first corridor
        4.0
        >>> furthest_progress(geometry, torch.zeros(0, 2))
        -inf
    """
    start = geometry.start if start is None else start
    if start is None:
        return math.nan
    origin = torch.as_tensor(start, dtype=torch.float32).reshape(2)
    reach = geometry.path_length(origin, points.reshape(-1, 2))
    reach = reach[torch.isfinite(reach)]
    return float(reach.max()) if reach.numel() else -math.inf


def obstacle_boxes(env_name: str) -> torch.Tensor | None:
    """``[W, 2, goal_dim]`` obstacle boxes in goal space (lower and upper corners): the wall footprints of a
    maze, the boards of the UR3 arm task; ``None`` for an env without obstacles (or not of this package).

    Examples:
        >>> obstacle_boxes("PointMaze").shape, obstacle_boxes("Reacher3D")
        (torch.Size([18, 2, 2]), None)
    """
    from .arms import ARM_NAMES, get_arm_spec
    from .mazes import MAZE_NAMES, get_maze_spec

    if env_name in MAZE_NAMES:
        boxes = [wall.xy_bounds for wall in get_maze_spec(env_name).layout.wall_boxes]
        return torch.tensor([[[x0, y0], [x1, y1]] for x0, x1, y0, y1 in boxes], dtype=torch.float32)
    if env_name in ARM_NAMES and get_arm_spec(env_name).boards:
        boards = get_arm_spec(env_name).boards
        centre = torch.tensor([b.center for b in boards], dtype=torch.float32)
        half = torch.tensor([b.half_size for b in boards], dtype=torch.float32)
        return torch.stack([centre - half, centre + half], 1)
    return None
