"""Diagnostics of a maze run's subgoals and graph against the maze's TRUE geometry.

When a run does not learn, these numbers say whether the high level proposes impossible subgoals
(inside walls, outside the arena: the main criticism of DHRL in the later literature), whether the
graph's edges cut through walls, whether the learned distances rank landmark pairs like the true
obstacle-free path lengths do, and how much of the free space the landmarks cover.

The true geometry is a :class:`MazeGeometry`: the maze's wall boxes, its arena and a fine
occupancy grid (free cells: centre outside every wall box inflated by ``margin``, the agent's
radius), on which :func:`grid_shortest_paths` computes obstacle-free path lengths by vectorised
min-plus relaxation (torch only). :func:`maze_epoch_diagnostics` gathers the ``diag/...`` metrics
the recipe logs after every evaluation, :func:`graph_diagnosis` computes them for a trained agent
(``recipes/diagnose_graph.py`` rebuilds a saved run's).
"""

from __future__ import annotations

import copy
import functools
import math
import time
from collections.abc import Sequence
from typing import NamedTuple

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import Tensor

from torchrl_dhrl.planner import LineOfSightDistance

from .subgoal_landscape import landscape_summary, subgoal_box, subgoal_landscape

__all__ = [
    "GraphDiagnosis",
    "MazeGeometry",
    "feasibility_fractions",
    "furthest_progress",
    "graph_diagnosis",
    "default_coverage_radius",
    "graph_quality",
    "grid_moves",
    "grid_shortest_paths",
    "landmark_budget_sweep",
    "landmark_coverage",
    "maze_epoch_diagnostics",
    "spearman_correlation",
    "start_subgoal",
]

#: The ``diag/...`` metrics :func:`maze_epoch_diagnostics` writes (every one, NaN where undefined).
DIAG_KEYS = (
    "diag/subgoals_in_walls",
    "diag/subgoals_outside",
    "diag/waypoints_in_walls",
    "diag/waypoints_outside",
    "diag/edges_crossing_walls",
    "diag/edges_shortcut",
    "diag/distance_rank_corr",
    "diag/graph_distance_rank_corr",
    "diag/landmark_coverage",
    "diag/landmark_progress",
    "diag/start_subgoal_x",
    "diag/start_subgoal_y",
    "diag/start_subgoal_feasible",
)
#: The keys :func:`maze_epoch_diagnostics` adds with ``high_loss`` (the high level's critic at the first test
#: start, :func:`~torchrl_dhrl.training.landscape_summary` over a grid of the subgoal box).
LANDSCAPE_DIAG_KEYS = (
    "diag/start_q_range",
    "diag/start_best_subgoal_in_wall",
    "diag/start_top_subgoals_in_walls",
    "diag/start_actor_q_gap",
)


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
    ) -> None:
        boxes = torch.as_tensor(boxes, dtype=torch.float32).reshape(-1, 2, 2)
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
        self._segments = LineOfSightDistance(1.0, boxes=self.boxes, margin=self.margin)
        self._walls = LineOfSightDistance(1.0, boxes=self.boxes)

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
        from torchrl_dhrl.envs import get_maze_spec

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
    def distance_fields(self, points: Tensor) -> Tensor:
        """``[N, H, W]`` grid path lengths from the free cells nearest to ``points [N, 2]``."""
        cells = self.nearest_free_cell(points.reshape(-1, 2))
        width = self.shape[1]
        sources = torch.stack([cells // width, cells % width], -1)
        size_x, size_y = self.cell_size.tolist()
        return grid_shortest_paths(
            self.free, sources, resolution=(size_y, size_x), connectivity=self.connectivity
        )

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
        width = self.shape[1]
        size_x, size_y = self.cell_size.tolist()
        fields = grid_shortest_paths(
            self.free,
            torch.stack([cells // width, cells % width], -1),
            resolution=(size_y, size_x),
            connectivity=self.connectivity,
        ).flatten(1)
        grid = fields[inverse, end_cells]
        straight = (ends - starts).norm(dim=-1)
        visible = ~self._segments.crosses_obstacle(starts, ends)
        out = torch.where(visible, straight, torch.maximum(grid, straight))
        return out.reshape(shape)


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
def _maze_geometry(name: str, margin: float, resolution: float | None) -> MazeGeometry:
    return MazeGeometry.from_maze(name, margin=margin, resolution=resolution)


def _fraction(mask: Tensor) -> float:
    return mask.float().mean().item() if mask.numel() else math.nan


def feasibility_fractions(geometry: MazeGeometry, rollout: TensorDictBase, *, margin: float = 0.0) -> dict:
    """The fractions of a rollout's subgoals and waypoints in walls and outside the arena.

    Subgoals: the ``subgoal`` entries of the steps where ``new_subgoal`` is ``True`` (the proposals,
    one per ``c_h`` steps), so each proposal counts once. Waypoints: the ``waypoint`` entry of every
    step, i.e. the fraction of steps spent chasing an infeasible waypoint. ``NaN`` where a rollout has
    none. "In walls" and "outside" are disjoint (see :class:`MazeGeometry`).

    Args:
        geometry (MazeGeometry): the maze.
        rollout (TensorDictBase): a ``[..., T]`` rollout with ``subgoal``, ``new_subgoal`` and ``waypoint``.

    Keyword Args:
        margin (float): wall growth of the "in walls" test (e.g. the agent's radius). Defaults to ``0``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> geometry = MazeGeometry.from_maze("PointMaze")
        >>> points = torch.tensor([[0.0, 0.0], [2.0, 4.0], [12.0, 0.0], [8.0, 4.0]])  # free, wall, out, free
        >>> td = TensorDict(subgoal=points, waypoint=points.flip(0),
        ...                 new_subgoal=torch.tensor([[True], [True], [True], [False]]), batch_size=[4])
        >>> {k: round(v, 3) for k, v in feasibility_fractions(geometry, td).items()}
        {'subgoals_in_walls': 0.333, 'subgoals_outside': 0.333,
         'waypoints_in_walls': 0.25, 'waypoints_outside': 0.25}
    """
    out = {}
    for name, points in (
        ("subgoals", rollout["subgoal"][rollout["new_subgoal"].squeeze(-1).bool()]),
        ("waypoints", rollout["waypoint"].reshape(-1, rollout["waypoint"].shape[-1])),
    ):
        points = points.reshape(-1, points.shape[-1])
        out[f"{name}_in_walls"] = _fraction(geometry.in_walls(points, margin))
        out[f"{name}_outside"] = _fraction(geometry.outside(points))
    return out


def _average_ranks(x: Tensor) -> Tensor:
    """1-based ranks of ``x [n]``, ties sharing their average rank (``inf`` values tie as well)."""
    order = x.argsort()
    _, inverse, counts = torch.unique_consecutive(x[order], return_inverse=True, return_counts=True)
    ends = counts.cumsum(0).double()
    average = ends - (counts.double() - 1) / 2
    ranks = torch.empty(x.shape[0], dtype=torch.float64)
    ranks[order] = average[inverse]
    return ranks


def spearman_correlation(x: Tensor, y: Tensor) -> float:
    """Spearman's rank correlation of two ``[n]`` samples (average ranks for ties; pairs with a NaN dropped).

    ``inf`` values are ranked (as the largest); ``NaN`` when fewer than two pairs remain or a sample is
    constant.

    Examples:
        >>> import torch
        >>> x = torch.tensor([1.0, 2.0, 3.0, 4.0])
        >>> spearman_correlation(x, x ** 3), spearman_correlation(x, -x)
        (1.0, -1.0)
        >>> round(spearman_correlation(x, torch.tensor([1.0, 3.0, 2.0, float("inf")])), 3)
        0.8
    """
    x, y = x.flatten().double().cpu(), y.flatten().double().cpu()
    keep = ~(x.isnan() | y.isnan())
    x, y = x[keep], y[keep]
    if x.numel() < 2:
        return math.nan
    rx, ry = _average_ranks(x), _average_ranks(y)
    rx, ry = rx - rx.mean(), ry - ry.mean()
    norm = (rx.square().sum() * ry.square().sum()).sqrt()
    return (rx @ ry / norm).item() if norm > 0 else math.nan


def furthest_progress(geometry: MazeGeometry, points: Tensor, start: Tensor | None = None) -> float:
    """The largest true path length (:meth:`MazeGeometry.path_length`) from ``start`` to one of ``points [..., 2]``.

    How far into the maze a set of points reaches: the graph's landmarks (``landmark_progress`` of
    :func:`graph_quality`), the states of training episodes (:class:`TrainingEpisodeLog`). ``start`` defaults
    to the origin, every maze's start; points cut off from it are ignored, and ``-inf`` is returned when none
    is left.

    Examples:
        >>> geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
        >>> furthest_progress(geometry, torch.tensor([[4.0, 0.0], [1.0, 0.0]]))  # along the first corridor
        4.0
        >>> furthest_progress(geometry, torch.zeros(0, 2))
        -inf
    """
    origin = torch.zeros(2) if start is None else torch.as_tensor(start, dtype=torch.float32).reshape(2)
    reach = geometry.path_length(origin, points.reshape(-1, 2))
    reach = reach[torch.isfinite(reach)]
    return float(reach.max()) if reach.numel() else -math.inf


def default_coverage_radius(env_name: str) -> float:
    """The ``coverage_radius`` of the recipe's ``diag/landmark_coverage``: half the maze's scale, half a corridor width
    (2 for PointMaze and AntMazeSmall, 4 for the other mazes).

    Examples:
        >>> default_coverage_radius("PointMaze"), default_coverage_radius("AntMaze")
        (2.0, 4.0)
    """
    from torchrl_dhrl.envs import get_maze_spec

    return get_maze_spec(env_name).layout.scale / 2


def landmark_coverage(geometry: MazeGeometry, landmarks: Tensor, radius: float) -> float:
    """The fraction of the free grid cells within ``radius`` of a landmark, in a straight line clear of walls.

    A free cell (of ``geometry``'s occupancy grid) is covered when some landmark goal lies within
    Euclidean distance ``radius`` of its centre and the segment between them crosses no wall box.

    Examples:
        >>> import torch
        >>> geometry = MazeGeometry.from_maze("PointMaze")
        >>> landmark_coverage(geometry, geometry.cell_centers[geometry.free], 0.1)
        1.0
        >>> round(landmark_coverage(geometry, torch.tensor([[0.0, 0.0]]), 2.0), 3)
        0.116
    """
    centers = geometry.cell_centers[geometry.free]  # [F, 2]
    landmarks = landmarks.float().cpu().reshape(-1, 2)
    if landmarks.shape[0] == 0 or centers.shape[0] == 0:
        return 0.0 if centers.shape[0] else math.nan
    cell, mark = (torch.cdist(centers, landmarks) <= radius).nonzero(as_tuple=True)
    clear = ~geometry.crosses_walls(centers[cell], landmarks[mark])
    covered = torch.zeros(centers.shape[0], dtype=torch.bool)
    covered[cell[clear]] = True
    return covered.float().mean().item()


def _source_pairs(num: int, max_sources: int | None) -> tuple[Tensor, Tensor]:
    """Rows ``i < max_sources`` (the first landmarks: FPS order spreads them out) and every other column."""
    sources = torch.arange(min(num, max_sources or num))
    rows, cols = torch.meshgrid(sources, torch.arange(num), indexing="ij")
    keep = rows != cols
    return rows[keep], cols[keep]


def graph_quality(
    geometry: MazeGeometry,
    planner,
    *,
    coverage_radius: float,
    max_sources: int | None = 64,
    shortcut_ratio: float = 1.5,
    start: Tensor | None = None,
    return_pairs: bool = False,
):
    """The planner's graph against the maze: edges through walls, distance ranks, coverage, reach.

    * ``edges_crossing_walls``: the fraction of directed graph edges whose straight segment between the
      two landmark goals crosses a wall box (not inflated). An edge around a wall's corner counts too,
      though the agent can follow it with a small detour;
    * ``edges_shortcut``: the fraction of edges whose true path length is more than ``shortcut_ratio``
      times the straight distance between their landmarks: edges through a wall, which the graph
      believes short and which in fact need a long way round (corner cuts do not count); over the
      edges leaving the first ``max_sources`` landmarks (whose distance fields are computed anyway);
    * ``distance_rank_corr``: Spearman's correlation between the learned landmark-to-landmark distance
      ``landmark_distances[i, j] = d(state_i -> goal_j)`` and the true path length
      (:meth:`MazeGeometry.path_length`) between the goals, over the pairs ``(i, j)``, ``i != j``, with
      ``i`` among the first ``max_sources`` landmarks (all pairs when ``None``);
    * ``graph_distance_rank_corr``: the same with the graph's all-pairs shortest distances (``inf`` for
      disconnected pairs, ranked last);
    * ``landmark_coverage``: :func:`landmark_coverage` with ``coverage_radius``;
    * ``landmark_progress``: how far the graph reaches into the maze, the largest true path length from
      ``start`` to a landmark (goal units; the U of AntMaze is about 37 long from the start to the test goal).

    All ``NaN`` without a graph.

    Args:
        geometry (MazeGeometry): the maze.
        planner (GraphPlanner or LandmarkGraph): its graph (2-D goals).

    Keyword Args:
        coverage_radius (float): the radius of :func:`landmark_coverage`.
        max_sources (int, optional): landmarks whose rows enter the rank correlations (a distance field
            each). Defaults to ``64``.
        shortcut_ratio (float): see ``edges_shortcut``. Defaults to ``1.5``.
        start (Tensor, optional): ``[2]`` where ``landmark_progress`` is measured from. Defaults to the
            origin, every maze's start.
        return_pairs (bool): also return ``(rows, cols, true, learned, graph)`` tensors of those pairs.

    Examples:
        >>> import torch
        >>> from torchrl_dhrl.planner import LandmarkGraph
        >>> geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
        >>> goals = torch.tensor([[0.0, 0.0], [4.0, 0.0], [8.0, 0.0], [8.0, 8.0], [0.0, 8.0]])
        >>> euclid = lambda s, g: (g - s[..., :2]).norm(dim=-1)
        >>> graph = LandmarkGraph(cutoff=8.5).set_landmarks(goals, goals, euclid)  # ignores the wall
        >>> out = graph_quality(geometry, graph, coverage_radius=2.0)
        >>> round(out["edges_crossing_walls"], 2), round(out["distance_rank_corr"], 2)
        (0.29, 0.72)
        >>> round(out["landmark_progress"], 1)  # (0, 8): behind the U's inner wall, the long way round
        19.0
    """
    graph = getattr(planner, "graph", planner)
    nan = {
        "edges_crossing_walls": math.nan,
        "edges_shortcut": math.nan,
        "distance_rank_corr": math.nan,
        "graph_distance_rank_corr": math.nan,
        "landmark_coverage": math.nan,
        "landmark_progress": math.nan,
    }
    if not graph.has_graph:
        return (nan, None) if return_pairs else nan
    goals = graph.landmark_goals.detach().float().cpu()
    edges = graph.edges.cpu()
    crossing = geometry.crosses_walls(goals[edges[:, 0]], goals[edges[:, 1]])
    out = {"edges_crossing_walls": _fraction(crossing)}
    # true path lengths from the first landmarks (one distance field each) to all
    num_sources = min(goals.shape[0], max_sources or goals.shape[0])
    true_matrix = geometry.path_length(goals[:num_sources, None], goals[None])  # [S, K]
    from_source = edges[edges[:, 0] < num_sources]
    straight = (goals[from_source[:, 1]] - goals[from_source[:, 0]]).norm(dim=-1)
    shortcut = true_matrix[from_source[:, 0], from_source[:, 1]] > shortcut_ratio * straight
    out["edges_shortcut"] = _fraction(shortcut)
    rows, cols = _source_pairs(goals.shape[0], max_sources)
    if rows.numel():
        true = true_matrix[rows, cols]
        learned = graph.landmark_distances.detach().float().cpu()[rows, cols]
        shortest = graph.shortest_distances.detach().float().cpu()[rows, cols]
        out["distance_rank_corr"] = spearman_correlation(learned, true)
        out["graph_distance_rank_corr"] = spearman_correlation(shortest, true)
    else:
        true = learned = shortest = torch.zeros(0)
        out["distance_rank_corr"] = out["graph_distance_rank_corr"] = math.nan
    out["landmark_coverage"] = landmark_coverage(geometry, goals, coverage_radius)
    reach = furthest_progress(geometry, goals, start)
    out["landmark_progress"] = reach if math.isfinite(reach) else math.nan
    if return_pairs:
        return out, (rows, cols, true, learned, shortest)
    return out


@torch.no_grad()
def landmark_budget_sweep(
    geometry: MazeGeometry,
    planner,
    replay_buffer,
    budgets: Sequence[tuple[int, int]],
    *,
    draws: int = 3,
    coverage_radius: float,
    start: Tensor | None = None,
    observation_key: str = "observation",
    achieved_goal_key: str = "achieved_goal",
    generator: torch.Generator | None = None,
) -> tuple[list[dict], float]:
    """Does the graph's size limit how far it reaches? Rebuilds with other landmark and candidate budgets.

    For each ``(max_landmarks, candidates)`` of ``budgets`` a copy of ``planner``'s graph is rebuilt
    ``draws`` times from ``candidates`` states drawn uniformly (with replacement, as the recipe's
    :func:`~torchrl_dhrl.training.rebuild_graph` does) from ``replay_buffer``'s storage, with the planner's
    learned distance, and the rebuilt landmarks' ``landmark_progress`` (:func:`furthest_progress`) and
    ``landmark_coverage`` are measured. The same draw index uses the same candidates in every budget with
    the same candidate count. The planner itself is left as it was.

    The second return value is the progress of the whole buffer (every stored achieved goal): when a budget's
    progress is close to it, the graph reaches as far as the data does, and a larger graph cannot help;
    exploration is what limits it.

    Args:
        geometry (MazeGeometry): the maze.
        planner (GraphPlanner): the planner whose graph (settings and distance) is copied.
        replay_buffer (ReplayBuffer): the low-level buffer the recipe builds its graph from.
        budgets (sequence of (int, int)): ``(max_landmarks, candidates)`` pairs.

    Keyword Args:
        draws (int): rebuilds per budget. Defaults to ``3``.
        coverage_radius (float): see :func:`landmark_coverage`.
        start (Tensor, optional): where progress is measured from (default: the origin).
        observation_key, achieved_goal_key (str): the storage's entries. Default to ``"observation"`` and
            ``"achieved_goal"``.
        generator (torch.Generator, optional): the candidates' random draws.

    Returns:
        one row per budget (``max_landmarks``, ``candidates``, ``landmarks`` (mean built), ``progress_mean``,
        ``progress_min``, ``progress_max``, ``coverage_mean``, ``build_s``) and the buffer's progress.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, ReplayBuffer
        >>> from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph
        >>> geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
        >>> xy = torch.stack([torch.linspace(0.0, 8.0, 40), torch.zeros(40)], -1)  # the first corridor
        >>> rb = ReplayBuffer(storage=LazyTensorStorage(40))
        >>> _ = rb.extend(TensorDict(observation=xy, achieved_goal=xy, batch_size=[40]))
        >>> planner = GraphPlanner(LandmarkGraph(cutoff=3.0, early_stop=0.0),
        ...                        lambda s, g: (s[..., :2] - g).norm(dim=-1), goal_dim=2)
        >>> rows, buffer_progress = landmark_budget_sweep(geometry, planner, rb, [(2, 400), (40, 400)],
        ...                                               coverage_radius=2.0, generator=torch.Generator().manual_seed(0))
        >>> [row["landmarks"] for row in rows], rows[1]["progress_min"], buffer_progress
        ([2.0, 40.0], 8.0, 8.0)
        >>> planner.num_landmarks  # the planner's own graph is untouched
        0
    """
    if isinstance(draws, bool) or not isinstance(draws, int) or draws < 1:
        raise ValueError(f"`draws` must be a positive int, got {draws!r}.")
    budgets = [tuple(budget) for budget in budgets]
    for budget in budgets:
        if len(budget) != 2 or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in budget):
            raise ValueError(
                f"`budgets` must hold (max_landmarks, candidates) pairs of positive ints, got {budget!r}."
            )
    storage = replay_buffer.storage
    if len(storage) == 0:
        raise ValueError("`replay_buffer` is empty: there is nothing to build a graph from.")
    data = storage[:].reshape(-1)  # the written entries (every env lane of a multi-dimensional storage)
    goals = data.get(achieved_goal_key)
    states = data.get(observation_key)
    buffer_progress = furthest_progress(geometry, goals.float().cpu()[..., :2], start)
    seeds = torch.randint(0, 2**62, (draws,), generator=generator).tolist()
    rows = []
    for max_landmarks, candidates in budgets:
        graph = copy.deepcopy(planner.graph)
        graph.max_landmarks = max_landmarks
        graph.min_landmarks = min(graph.min_landmarks, max_landmarks)
        progress, coverage, built, seconds = [], [], [], []
        for seed in seeds:
            index = torch.randint(
                0, goals.shape[0], (candidates,), generator=torch.Generator().manual_seed(seed)
            )
            begin = time.perf_counter()
            graph.build(states[index.to(states.device)], goals[index.to(goals.device)], planner.distance)
            seconds.append(time.perf_counter() - begin)
            landmarks = graph.landmark_goals.detach().float().cpu()[..., :2]
            progress.append(furthest_progress(geometry, landmarks, start))
            coverage.append(landmark_coverage(geometry, landmarks, coverage_radius))
            built.append(graph.num_landmarks)
        rows.append(
            {
                "max_landmarks": max_landmarks,
                "candidates": candidates,
                "landmarks": sum(built) / draws,
                "progress_mean": sum(progress) / draws,
                "progress_min": min(progress),
                "progress_max": max(progress),
                "coverage_mean": sum(coverage) / draws,
                "build_s": sum(seconds) / draws,
            }
        )
    return rows, buffer_progress


@torch.no_grad()
def start_subgoal(high_actor: TensorDictModuleBase, observation: Tensor, desired_goal: Tensor) -> Tensor:
    """The subgoal the deterministic high-level actor proposes at ``observation`` for ``desired_goal``.

    ``high_actor`` is the bare network (:class:`~torchrl_dhrl.modules.HighLevelActor`, e.g.
    ``agent.high_policy.actor``): no exploration noise, no ``c_h`` cadence.

    Examples:
        >>> import torch
        >>> from torchrl_dhrl.modules import HighLevelActor
        >>> actor = HighLevelActor(6, 2, [-2.0, -2.0], [10.0, 10.0], num_cells=(8,))
        >>> start_subgoal(actor, torch.zeros(6), torch.tensor([0.0, 8.0])).shape
        torch.Size([2])
    """
    td = TensorDict(
        {
            high_actor.in_keys[0]: observation.reshape(1, -1),
            high_actor.in_keys[1]: desired_goal.reshape(1, -1),
        },
        batch_size=[1],
    )
    return high_actor(td)[high_actor.out_keys[0]][0].detach().float().cpu()


def maze_epoch_diagnostics(
    env_name: str,
    planner,
    rollout: TensorDictBase,
    high_actor: TensorDictModuleBase,
    *,
    margin: float = 0.5,
    coverage_radius: float | None = None,
    max_sources: int | None = 64,
    resolution: float | None = None,
    high_loss=None,
) -> dict:
    """The ``diag/...`` metrics of an evaluation: subgoals and graph against the maze's true geometry.

    Empty for the arm envs (not a maze). Every entry of :data:`DIAG_KEYS` otherwise, with
    ``time/diag_s``, its own cost:

    * ``diag/subgoals_in_walls``, ``diag/subgoals_outside``: fractions of the rollout's subgoal proposals
      strictly inside a wall box, outside the arena (:func:`feasibility_fractions`);
    * ``diag/waypoints_in_walls``, ``diag/waypoints_outside``: the same for the waypoints of all steps;
    * ``diag/edges_crossing_walls``, ``diag/edges_shortcut``, ``diag/distance_rank_corr``,
      ``diag/graph_distance_rank_corr``, ``diag/landmark_coverage``, ``diag/landmark_progress``:
      :func:`graph_quality` (``NaN`` without a graph), the true path lengths on the grid of
      :meth:`MazeGeometry.from_maze` (cells of ``resolution``) around walls inflated by ``margin``;
    * ``diag/start_subgoal_x``, ``diag/start_subgoal_y``, ``diag/start_subgoal_feasible``: the deterministic
      high-level proposal at the start state of the rollout's first episode, for its goal
      (:func:`start_subgoal`), and whether it is feasible (``1.0``/``0.0``).

    Args:
        env_name (str): the environment.
        planner (GraphPlanner): the planner whose graph is evaluated.
        rollout (TensorDictBase): ``[B, T]`` evaluation rollout (``observation``, ``desired_goal``,
            ``subgoal``, ``new_subgoal``, ``waypoint``).
        high_actor (TensorDictModuleBase): the deterministic high-level actor.

    Keyword Args:
        margin (float): wall inflation of the true path lengths (the agent's radius; the recipe passes
            ``planner.oracle_margin``). Defaults to ``0.5``.
        coverage_radius (float, optional): defaults to half the maze scale, half a corridor width (2 for
            PointMaze and AntMazeSmall, 4 for the others): a free cell farther from every landmark lies in
            a stretch of corridor the graph does not reach. A fixed fraction of the maze rather than the
            graph's own resolution (``early_stop`` x oracle speed: 2 for PointMaze, 1 for the ant mazes),
            so that the number compares across runs and configurations.
        max_sources (int, optional): see :func:`graph_quality`. Defaults to ``64``.
        resolution (float, optional): the grid cell size. Defaults to :meth:`MazeGeometry.from_maze`'s.
        high_loss (HighLevelLoss, optional): with it, the high level's critic at the first episode's start
            (:data:`LANDSCAPE_DIAG_KEYS`: :func:`~torchrl_dhrl.training.landscape_summary` of its Q over a
            49 x 49 grid of the subgoal box): ``diag/start_q_range``, ``diag/start_best_subgoal_in_wall``,
            ``diag/start_top_subgoals_in_walls`` (the best 5%) and ``diag/start_actor_q_gap``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_dhrl.modules import HighLevelActor
        >>> from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph
        >>> planner = GraphPlanner(LandmarkGraph(), lambda s, g: (g - s[..., :2]).norm(dim=-1), goal_dim=2)  # no graph
        >>> actor = HighLevelActor(6, 2, [-2.0, -2.0], [10.0, 10.0], num_cells=(8,))
        >>> rollout = TensorDict(observation=torch.zeros(1, 3, 6), desired_goal=torch.zeros(1, 3, 2),
        ...                      subgoal=torch.zeros(1, 3, 2), waypoint=torch.zeros(1, 3, 2),
        ...                      new_subgoal=torch.ones(1, 3, 1, dtype=torch.bool), batch_size=[1, 3])
        >>> out = maze_epoch_diagnostics("PointMaze", planner, rollout, actor)
        >>> out["diag/subgoals_in_walls"], out["diag/distance_rank_corr"]
        (0.0, nan)
        >>> maze_epoch_diagnostics("Reacher3D", planner, rollout, actor)
        {}
    """
    from torchrl_dhrl.envs import MAZE_NAMES

    if env_name not in MAZE_NAMES:
        return {}
    start = time.perf_counter()
    geometry = _maze_geometry(env_name, float(margin), resolution)
    if coverage_radius is None:
        coverage_radius = default_coverage_radius(env_name)
    metrics = {f"diag/{k}": v for k, v in feasibility_fractions(geometry, rollout).items()}
    quality = graph_quality(geometry, planner, coverage_radius=coverage_radius, max_sources=max_sources)
    metrics.update({f"diag/{k}": v for k, v in quality.items()})
    first = rollout.reshape(-1, rollout.shape[-1])[0, 0]
    subgoal = start_subgoal(high_actor, first["observation"], first["desired_goal"])
    metrics["diag/start_subgoal_x"], metrics["diag/start_subgoal_y"] = subgoal[:2].tolist()
    metrics["diag/start_subgoal_feasible"] = float(geometry.feasible(subgoal[:2]).item())
    if high_loss is not None:
        low, high = subgoal_box(high_loss)
        step = max(h - lo for lo, h in zip(low, high, strict=True)) / 48
        land = subgoal_landscape(
            high_loss, high_actor, first["observation"], first["desired_goal"], low, high, step
        )
        summary = landscape_summary(land, geometry.in_walls(land.points()))
        metrics["diag/start_q_range"] = summary["q_range"]
        metrics["diag/start_best_subgoal_in_wall"] = summary["best_in_wall"]
        metrics["diag/start_top_subgoals_in_walls"] = summary["top_in_walls"]
        metrics["diag/start_actor_q_gap"] = summary["actor_q_gap"]
    metrics["time/diag_s"] = time.perf_counter() - start
    return metrics


class GraphDiagnosis(NamedTuple):
    """Outcome of :func:`graph_diagnosis`.

    Attributes:
        metrics (dict): the ``diag/...`` metrics (:func:`maze_epoch_diagnostics`), with ``graph/landmarks``
            and ``graph/edges``.
        pairs (dict): ``rows``, ``cols`` (landmark indices), ``true`` (path length, goal units),
            ``learned`` (``landmark_distances``, steps) and ``graph`` (all-pairs shortest distances, steps)
            of the landmark pairs entering the rank correlations; empty tensors without a graph.
        landmark_goals (Tensor): ``[K, 2]``.
    """

    metrics: dict
    pairs: dict
    landmark_goals: Tensor


def graph_diagnosis(
    agent,
    eval_env,
    env_name: str,
    *,
    oracle_margin: float = 0.5,
    rollout: bool = True,
    max_sources: int | None = 64,
    resolution: float | None = None,
) -> GraphDiagnosis:
    """:func:`maze_epoch_diagnostics` for the graph and the high level of a trained agent.

    With ``rollout`` a deterministic evaluation on the test goals of ``eval_env`` is run (as the recipe does
    after each epoch) for the subgoal and waypoint fractions; without it they are ``NaN`` and the start
    state is the first evaluation env's reset state.

    Args:
        agent (DHRLAgent): the agent, its graph built (or not).
        eval_env (EnvBase): the evaluation env with the agent's primers.
        env_name (str): the maze.

    Keyword Args:
        oracle_margin (float): the agent's radius (walls are inflated by it). Defaults to ``0.5``.
        rollout (bool): run the evaluation episodes. Defaults to ``True``.
        max_sources (int, optional): see :func:`graph_quality`. Defaults to ``64``.
        resolution (float, optional): the grid cell size (default: the recipe's, see
            :meth:`MazeGeometry.from_maze`).

    Raises:
        ValueError: when ``env_name`` is not a maze.

    Examples:
        >>> import torch
        >>> from torchrl_dhrl.training import make_agent, make_environment
        >>> _ = torch.manual_seed(0)
        >>> agent = make_agent(make_environment("PointMaze"), subgoal_low=[-2.0, -2.0], subgoal_high=[10.0, 10.0],
        ...                    subgoal_interval=5, low_num_cells=(8,), high_num_cells=(8,))
        >>> env = make_environment("PointMaze", eval=True, max_episode_steps=10, agent=agent)
        >>> diagnosis = graph_diagnosis(agent, env, "PointMaze", rollout=False)
        >>> diagnosis.metrics["graph/landmarks"], diagnosis.pairs["true"].numel()
        (0, 0)
    """
    from torchrl_dhrl.envs import MAZE_NAMES

    from .evaluation import evaluate

    if env_name not in MAZE_NAMES:
        raise ValueError(f"The graph diagnostics need a maze; this run is on {env_name}.")
    if rollout:
        length = eval_env.base_env.max_episode_steps
        td = evaluate(eval_env, agent.policy, length).rollout
    else:
        td = eval_env.reset().unsqueeze(-1)
        nan = torch.full_like(td["achieved_goal"], math.nan)
        td.set("subgoal", nan).set("waypoint", nan).set("new_subgoal", torch.zeros_like(nan[..., :1]).bool())
    metrics = maze_epoch_diagnostics(
        env_name,
        agent.planner,
        td,
        agent.high_policy.actor,
        margin=oracle_margin,
        max_sources=max_sources,
        resolution=resolution,
    )
    if not rollout:
        for key in ("subgoals", "waypoints"):
            metrics[f"diag/{key}_in_walls"] = metrics[f"diag/{key}_outside"] = math.nan
    graph = agent.planner.graph
    metrics["graph/landmarks"] = graph.num_landmarks
    metrics["graph/edges"] = int(graph.edges.shape[0]) if graph.has_graph else 0
    geometry = _maze_geometry(env_name, float(oracle_margin), resolution)
    _, pairs = graph_quality(geometry, graph, coverage_radius=1.0, max_sources=max_sources, return_pairs=True)
    names = ("rows", "cols", "true", "learned", "graph")
    pairs = (
        dict(zip(names, pairs, strict=True))
        if pairs is not None
        else {name: torch.zeros(0) for name in names}
    )
    return GraphDiagnosis(metrics, pairs, graph.landmark_goals.detach().cpu())
