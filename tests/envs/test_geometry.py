"""The maze's true geometry (``MazeGeometry``, ``grid_shortest_paths``): grid path lengths checked against
scipy's Dijkstra and analytic cases."""

import functools
import math

import numpy as np
import pytest
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from torchrl_dhrl.envs.geometry import MazeGeometry, grid_shortest_paths

# -------------------------------------------------------------------------------------------------- helpers


@functools.cache
def _segment_cells(di: int, dj: int) -> frozenset:
    """Cells (offsets) that the segment between two cell centres touches, by dense sampling: a sample on
    a cell boundary touches the cells on both sides (independent of ``grid_moves``'s table)."""
    cells = set()
    for t in np.linspace(0.0, 1.0, 4001):
        i, j = t * di, t * dj
        rows = {math.floor(i + 0.5), math.ceil(i - 0.5)}
        cols = {math.floor(j + 0.5), math.ceil(j - 0.5)}
        cells |= {(r, c) for r in rows for c in cols}
    return frozenset(cells)


def _scipy_grid_distances(free: np.ndarray, sources, res_i: float, res_j: float, connectivity: int):
    """The same grid graph built cell by cell, solved by scipy's Dijkstra."""
    steps = [(0, 1), (1, 0), (0, -1), (-1, 0)]
    if connectivity >= 8:
        steps += [(1, 1), (1, -1), (-1, 1), (-1, -1)]
    if connectivity == 16:
        steps += [(a, b) for a in (1, -1) for b in (2, -2)] + [(a, b) for a in (2, -2) for b in (1, -1)]
    height, width = free.shape
    rows, cols, costs = [], [], []
    for i in range(height):
        for j in range(width):
            if not free[i, j]:
                continue
            for di, dj in steps:
                touched = {(i + a, j + b) for a, b in _segment_cells(di, dj)}
                if all(0 <= a < height and 0 <= b < width and free[a, b] for a, b in touched):
                    rows.append(i * width + j)
                    cols.append((i + di) * width + j + dj)
                    costs.append(math.hypot(di * res_i, dj * res_j))
    graph = coo_matrix((costs, (rows, cols)), shape=(free.size, free.size)).tocsr()
    indices = [i * width + j for i, j in sources]
    return dijkstra(graph, directed=True, indices=indices).reshape(len(indices), height, width)


def _visible_by_sampling(geometry: MazeGeometry, start, end, margin: float) -> bool:
    """No point of 2001 along the segment lies in a box grown by ``margin`` (closed)."""
    t = torch.linspace(0, 1, 2001)[:, None]
    points = start + t * (end - start)
    low, high = geometry.boxes[:, 0] - margin, geometry.boxes[:, 1] + margin
    inside = ((points[:, None] >= low) & (points[:, None] <= high)).all(-1).any(-1)
    return not bool(inside.any())


# ----------------------------------------------------------------------------------------------- grid paths


@pytest.mark.parametrize("maze", ["PointMaze", "AntMaze"])
@pytest.mark.parametrize("connectivity", [8, 16])
def test_grid_paths_match_scipy_dijkstra(maze, connectivity):
    geometry = MazeGeometry.from_maze(maze, margin=0.5, connectivity=connectivity)
    free = geometry.free
    assert 0.3 < free.float().mean() < 0.9  # walls and free space both present
    generator = torch.Generator().manual_seed(0)
    cells = geometry.free.flatten().nonzero().squeeze(-1)
    picks = cells[torch.randperm(cells.numel(), generator=generator)[:6]]
    width = free.shape[1]
    sources = torch.stack([picks // width, picks % width], -1)
    size_x, size_y = geometry.cell_size.tolist()
    ours = grid_shortest_paths(free, sources, resolution=(size_y, size_x), connectivity=connectivity)
    expected = _scipy_grid_distances(free.numpy(), sources.tolist(), size_y, size_x, connectivity)
    assert np.isinf(expected[:, ~free.numpy()]).all()
    np.testing.assert_allclose(ours.numpy(), expected, rtol=1e-5, atol=1e-4)
    assert np.isfinite(expected[:, free.numpy()]).all()  # the free space is connected


@pytest.mark.parametrize("maze", ["PointMaze", "AntMaze"])
def test_path_length_of_random_point_pairs_against_scipy(maze):
    """Random free points: the Euclidean distance when the segment clears the inflated walls, else the
    scipy grid distance between the nearest free cells (never below the Euclidean distance)."""
    margin = 0.5
    geometry = MazeGeometry.from_maze(maze, margin=margin)
    generator = torch.Generator().manual_seed(1)
    low, high = geometry.arena_low, geometry.arena_high
    points = low + torch.rand(400, 2, generator=generator) * (high - low)
    points = points[~geometry.in_walls(points, margin, closed=True)][:40]
    starts, ends = points[:20], points[20:40]
    ours = geometry.path_length(starts, ends)
    centers = geometry.cell_centers.reshape(-1, 2).numpy()
    free_flat = geometry.free.flatten().numpy()

    def nearest(p):
        d = np.linalg.norm(centers - p.numpy(), axis=-1)
        d[~free_flat] = np.inf
        return int(d.argmin())

    width = geometry.shape[1]
    start_cells = [divmod(nearest(p), width) for p in starts]
    size_x, size_y = geometry.cell_size.tolist()
    fields = _scipy_grid_distances(geometry.free.numpy(), start_cells, size_y, size_x, 16)
    checked = blocked = 0
    for k, (s, e) in enumerate(zip(starts, ends, strict=True)):
        visible = _visible_by_sampling(geometry, s, e, margin - 1e-3)
        if visible != _visible_by_sampling(geometry, s, e, margin + 1e-3):
            continue  # grazes an inflated corner: either answer is right
        straight = (e - s).norm().item()
        grid = fields[k].reshape(-1)[nearest(e)]
        expected = straight if visible else max(grid, straight)
        assert ours[k].item() == pytest.approx(expected, rel=1e-5)
        checked += 1
        blocked += not visible
    assert checked >= 15 and blocked >= 3
    # a matrix by broadcasting: the same numbers
    matrix = geometry.path_length(starts[:, None], ends[None])
    torch.testing.assert_close(matrix.diagonal(), ours)


def test_path_length_analytic_cases():
    # a straight line in a free corridor: the Euclidean distance exactly
    point = MazeGeometry.from_maze("PointMaze", margin=0.5)
    assert point.path_length(torch.tensor([-1.0, 0.0]), torch.tensor([5.0, 0.0])).item() == pytest.approx(6.0)
    # ... and on the grid alone (a source cell to a cell of its row)
    free = torch.ones(4, 9, dtype=torch.bool)
    line = grid_shortest_paths(free, torch.tensor([[1, 0]]), resolution=0.5)[0, 1]
    torch.testing.assert_close(line, torch.arange(9) * 0.5)
    # the U: (0, 0) -> (0, 8) around the inner wall, over its corners inflated by the margin
    for margin in (0.0, 0.5):
        corner_x, low, high = 6 + margin, 2 - margin, 6 + margin
        exact = math.hypot(corner_x, low) + high - low + math.hypot(corner_x, 8 - high)
        fine = MazeGeometry.from_maze("PointMaze", margin=margin, resolution=0.1)
        length = fine.path_length(torch.tensor([0.0, 0.0]), torch.tensor([0.0, 8.0])).item()
        assert exact * 0.99 <= length <= exact * 1.04, (margin, length, exact)
    # the recipe's grid (default resolution, 1/3 here: cell centres on the inflated faces)
    coarse = MazeGeometry.from_maze("PointMaze", margin=0.5)
    assert coarse.cell_size.tolist() == pytest.approx([1 / 3, 1 / 3])
    length = coarse.path_length(torch.tensor([0.0, 0.0]), torch.tensor([0.0, 8.0])).item()
    assert 18.34 <= length <= 18.34 * 1.06
    # AntMaze (scale 8): (0, 0) -> (0, 16), 12.5 / 3.5 / 12.5 corners for a 0.5 margin
    ant = MazeGeometry.from_maze("AntMaze", margin=0.5)
    exact = 2 * math.hypot(12.5, 3.5) + 9.0
    length = ant.path_length(torch.tensor([0.0, 0.0]), torch.tensor([0.0, 16.0])).item()
    assert exact * 0.99 <= length <= exact * 1.06, (length, exact)
    # symmetric, and zero from a point to itself
    a, b = torch.tensor([0.0, 0.0]), torch.tensor([0.0, 8.0])
    assert point.path_length(b, a).item() == pytest.approx(point.path_length(a, b).item(), rel=0.03)
    assert point.path_length(a, a).item() == 0.0


def test_grid_paths_refuse_bad_input():
    with pytest.raises(ValueError, match="bool"):
        grid_shortest_paths(torch.ones(3, 3), torch.tensor([[0, 0]]))
    with pytest.raises(ValueError, match="cells of the 3 x 3 grid"):
        grid_shortest_paths(torch.ones(3, 3, dtype=torch.bool), torch.tensor([[3, 0]]))
    with pytest.raises(ValueError, match="connectivity"):
        grid_shortest_paths(torch.ones(3, 3, dtype=torch.bool), torch.tensor([[0, 0]]), connectivity=6)
    # a wall across the grid: the other side is unreachable
    free = torch.ones(3, 3, dtype=torch.bool)
    free[:, 1] = False
    d = grid_shortest_paths(free, torch.tensor([[0, 0]]))[0]
    assert torch.isinf(d[:, 1:]).all() and torch.isfinite(d[:, 0]).all()


def test_a_margin_that_leaves_no_free_cell_is_refused():
    """Walls grown by half a corridor or more close the maze: refused at construction, naming the margin and the
    corridor's width where the maze has one; just below, the corridors' centre lines stay free."""
    with pytest.raises(ValueError, match=r"^margin=2 leaves no free cell.*corridors are 4 wide"):
        MazeGeometry.from_maze("PointMaze", margin=2.0)
    narrow = MazeGeometry.from_maze("PointMaze", margin=1.9)
    free_centres = narrow.cell_centers[narrow.free]
    assert len(free_centres) and not narrow.in_walls(free_centres, margin=1.9).any()
    boxes = torch.tensor([[[0.0, 0.0], [1.0, 1.0]]])  # one wall box filling the arena
    with pytest.raises(ValueError, match=r"^margin=0 leaves no free cell: the walls grown by it cover the whole arena\.$"):
        MazeGeometry(boxes, [0.0, 0.0], [1.0, 1.0], margin=0.0, resolution=0.25)


def test_points_along_a_corridor_are_the_cells_nearest_each_progress():
    """A straight corridor [0, 10] x [0, 2] between two walls (y < 0, y > 2), start (0.25, 1), 0.5 cells: the path
    length to a cell centre (x, y) is the straight distance; with 0.6 clearance only the centre rows y = 0.75, 1.25
    remain, and the nearest to progress p is the first (row-major: y = 0.75) of the cells whose distance is nearest."""
    boxes = torch.tensor([[[0.0, -1.0], [10.0, 0.0]], [[0.0, 2.0], [10.0, 3.0]]])
    geometry = MazeGeometry(boxes, [0.0, 0.0], [10.0, 2.0], resolution=0.5, start=(0.25, 1.0))
    progress = [0.0, 2.3, 5.0, 7.6, 50.0]
    points, length = geometry.points_along(progress, clearance=0.6)
    assert not geometry.in_walls(points, margin=0.6).any()
    # independent: every candidate's straight distance, the nearest to each target by brute force
    xs, ys = torch.meshgrid(torch.arange(0.25, 10, 0.5), torch.tensor([0.75, 1.25]), indexing="xy")
    candidates = torch.stack([xs, ys], -1).reshape(-1, 2)
    distance = (candidates - torch.tensor([0.25, 1.0])).norm(dim=-1)
    for p, point, d in zip(progress, points, length, strict=True):
        best = (distance - p).abs().min()
        assert abs(d.item() - p) == pytest.approx(best.item(), abs=1e-5)
        assert d.item() == pytest.approx((point - torch.tensor([0.25, 1.0])).norm().item(), abs=1e-5)
    assert points[-1, 0].item() == 9.75  # past the end: the farthest cell
    # ties broken towards the first cell in row-major order: (0.25, 0.75) and (0.25, 1.25) both lie 0.25 away
    assert points[0].tolist() == [0.25, 0.75]
    with pytest.raises(ValueError, match="clearance=1.1 leaves no free cell connected to the start"):
        geometry.points_along([1.0], clearance=1.1)
    with pytest.raises(ValueError, match="no start"):
        MazeGeometry(boxes, [0.0, 0.0], [10.0, 2.0], resolution=0.5, start=None).points_along([1.0])


def test_points_along_the_u_maze_follow_its_route():
    """PointMaze's U: progress along the route past its turn lands in the corridor the route is in (analytic: the
    bottom corridor up to x = 8 (8 units), then up the right one, then back along the top), never across the wall."""
    geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
    points, length = geometry.points_along([2.0, 6.0, 12.0, 18.0], clearance=1.0)
    bottom, right, top = points[:2], points[2], points[3]
    assert (bottom[:, 1].abs() <= 1.0).all() and (bottom[:, 0] - torch.tensor([2.0, 6.0])).abs().max() <= 0.5
    assert right[0] >= 6.0 and 2.0 <= right[1] <= 8.0
    assert top[1] >= 6.0 and top[0] <= 2.0
    torch.testing.assert_close(length, torch.tensor([2.0, 6.0, 12.0, 18.0]), atol=0.35, rtol=0.0)
