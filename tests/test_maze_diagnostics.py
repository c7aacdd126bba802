"""Subgoals and graph against the maze's true geometry: grid path lengths (checked against scipy's
Dijkstra and analytic cases), feasibility, edges through walls, rank correlations, coverage, the
recipe's ``diag/`` columns and ``recipes/diagnose_graph.py``."""

import csv
import functools
import importlib.util
import math

import numpy as np
import pytest
import torch
from _recipe import RECIPES, load_recipe, recipe_config
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.stats import spearmanr
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer

from torchrl_dhrl.modules import HighLevelActor
from torchrl_dhrl.planner import CutoffEdgeRule, GraphPlanner, LandmarkGraph
from torchrl_dhrl.training import (
    MazeGeometry,
    feasibility_fractions,
    graph_quality,
    grid_shortest_paths,
    landmark_budget_sweep,
    landmark_coverage,
    maze_epoch_diagnostics,
    spearman_correlation,
    start_subgoal,
)
from torchrl_dhrl.training.maze_diagnostics import DIAG_KEYS
from torchrl_dhrl.training.plots import success_curve_series

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


# ---------------------------------------------------------------------------------------------- feasibility


def test_feasibility_fractions_of_hand_made_subgoals():
    geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
    wall = [[4.0, 4.0], [2.0, 4.0], [0.0, 3.0]]  # inner wall, incl. a face shared by two blocks
    outside = [[12.0, 0.0], [-3.0, 5.0]]  # beyond the arena [-2, 10]^2 (the second also in an outer wall)
    free = [[0.0, 0.0], [8.0, 4.0], [0.0, 8.0], [0.0, 1.7]]  # the last 0.3 from the inner wall
    points = torch.tensor(wall + outside + free)
    assert geometry.in_walls(points).tolist() == [True] * 3 + [False] * 6
    assert geometry.outside(points).tolist() == [False] * 3 + [True] * 2 + [False] * 4
    assert geometry.feasible(points).tolist() == [False] * 5 + [True] * 4
    assert geometry.in_walls(points, margin=0.5).tolist() == [True] * 3 + [False] * 5 + [True]
    # a [2, 9] rollout: proposals at the first 3 steps of env 0 and 2 steps of env 1
    new = torch.zeros(2, 9, 1, dtype=torch.bool)
    new[0, :3] = True  # 3 wall points
    new[1, [3, 5]] = True  # an outside point and a free one
    td = TensorDict(
        subgoal=points.expand(2, 9, 2),
        waypoint=torch.stack([points, points.flip(0)]),
        new_subgoal=new,
        batch_size=[2, 9],
    )
    out = feasibility_fractions(geometry, td)
    assert out["subgoals_in_walls"] == pytest.approx(3 / 5)
    assert out["subgoals_outside"] == pytest.approx(1 / 5)
    assert out["waypoints_in_walls"] == pytest.approx(6 / 18)
    assert out["waypoints_outside"] == pytest.approx(4 / 18)
    strict = feasibility_fractions(geometry, td, margin=0.5)
    assert strict["waypoints_in_walls"] == pytest.approx(8 / 18)
    # no proposal at all: NaN, not 0
    none = feasibility_fractions(geometry, td.set("new_subgoal", torch.zeros_like(new)))
    assert math.isnan(none["subgoals_in_walls"]) and math.isnan(none["subgoals_outside"])


def test_start_subgoal_is_the_deterministic_actor_output():
    torch.manual_seed(0)
    actor = HighLevelActor(6, 2, [-2.0, -2.0], [10.0, 10.0], num_cells=(16,))
    observation, goal = torch.randn(6), torch.tensor([0.0, 8.0])
    subgoal = start_subgoal(actor, observation, goal)
    td = TensorDict(observation=observation[None], desired_goal=goal[None], batch_size=[1])
    torch.testing.assert_close(subgoal, actor(td)["subgoal"][0])
    assert ((subgoal >= -2) & (subgoal <= 10)).all()


# -------------------------------------------------------------------------------------------- graph quality


def test_edges_crossing_walls_on_a_hand_made_graph():
    geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
    goals = torch.tensor([[0.0, 0.0], [0.0, 8.0], [8.0, 0.0]])
    graph = LandmarkGraph(cutoff=100.0).set_distance_matrix(goals, goals, torch.ones(3, 3))
    assert graph.edges.shape[0] == 6
    out = graph_quality(geometry, graph, coverage_radius=2.0)
    # (0,0) <-> (0,8) through the inner wall, (8,0) <-> (0,8) across its corner (4, 4); (0,0) <-> (8,0) free
    assert out["edges_crossing_walls"] == pytest.approx(4 / 6)
    # (0,0) <-> (0,8): about 19 around the wall for 8 straight, a shortcut; (8,0) <-> (0,8): about 14 for
    # 11.3 straight, a corner cut
    assert out["edges_shortcut"] == pytest.approx(2 / 6)
    keep = torch.tensor([[0.0, 1e9, 1.0], [1e9, 0.0, 1e9], [1.0, 1e9, 0.0]])  # only the free pair
    graph = LandmarkGraph(cutoff=100.0, edge_rule=CutoffEdgeRule(nn_factor=1.0)).set_distance_matrix(
        goals, goals, keep
    )
    assert graph_quality(geometry, graph, coverage_radius=2.0)["edges_crossing_walls"] == 0.0
    empty = graph_quality(geometry, LandmarkGraph(), coverage_radius=2.0)
    assert all(math.isnan(v) for v in empty.values())


def _candidates(geometry, count, seed=0):
    generator = torch.Generator().manual_seed(seed)
    centers = geometry.cell_centers[geometry.free]
    goals = centers[torch.randperm(centers.shape[0], generator=generator)[:count]]
    return torch.cat([goals, torch.zeros(count, 4)], -1), goals


def test_rank_correlation_one_for_the_true_distance_lower_without_walls():
    geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
    states, goals = _candidates(geometry, 150)

    def true_steps(s, g):
        return geometry.path_length(s[..., :2], g) / 0.2

    def straight_steps(s, g):
        return (g - s[..., :2]).norm(dim=-1) / 0.2

    true_planner = GraphPlanner(
        LandmarkGraph(cutoff=30.0, max_landmarks=40, early_stop=0.0), true_steps, goal_dim=2
    )
    true_planner.build(states, goals)
    out = graph_quality(geometry, true_planner, coverage_radius=2.0)
    assert out["distance_rank_corr"] == pytest.approx(1.0, abs=1e-6)
    assert out["graph_distance_rank_corr"] > 0.95
    # edges cut the walls' corners only: short detours, no shortcut through a wall
    assert 0.0 < out["edges_crossing_walls"] < 0.15 and out["edges_shortcut"] == 0.0
    straight = GraphPlanner(
        LandmarkGraph(cutoff=30.0, max_landmarks=40, early_stop=0.0), straight_steps, goal_dim=2
    )
    straight.build(states, goals)
    out = graph_quality(geometry, straight, coverage_radius=2.0)
    assert out["distance_rank_corr"] < 0.95  # 0.91: the pairs across the inner wall
    assert out["edges_shortcut"] > 0.02  # 6-unit edges across the 4-unit inner wall
    # fewer source rows: the same kind of number from a subset of the pairs
    few, pairs = graph_quality(geometry, true_planner, coverage_radius=2.0, max_sources=5, return_pairs=True)
    assert pairs[0].unique().tolist() == [0, 1, 2, 3, 4] and few["distance_rank_corr"] == pytest.approx(1.0)


def test_spearman_matches_scipy_with_ties_and_inf():
    generator = torch.Generator().manual_seed(0)
    x = torch.randint(0, 6, (200,), generator=generator).float()
    y = x + torch.randint(0, 4, (200,), generator=generator).float()
    y[::17] = math.inf
    assert spearman_correlation(x, y) == pytest.approx(spearmanr(x.numpy(), y.numpy()).statistic, abs=1e-10)
    x[3] = math.nan
    keep = ~x.isnan()
    assert spearman_correlation(x, y) == pytest.approx(spearmanr(x[keep], y[keep]).statistic, abs=1e-10)
    assert math.isnan(spearman_correlation(torch.ones(5), torch.arange(5.0)))
    assert math.isnan(spearman_correlation(torch.ones(1), torch.ones(1)))


def test_landmark_progress_is_the_furthest_landmark_along_the_maze():
    geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
    corridor = torch.tensor([[0.5, 0.0], [3.0, 1.0], [7.0, -0.5]])  # in sight of the start: Euclidean
    graph = LandmarkGraph(cutoff=100.0).set_distance_matrix(corridor, corridor, torch.ones(3, 3))
    assert graph_quality(geometry, graph, coverage_radius=2.0)["landmark_progress"] == pytest.approx(
        corridor.norm(dim=-1).max().item()
    )
    behind = torch.cat([corridor, torch.tensor([[0.0, 8.0]])])  # around the inner wall: 18.3 exactly
    graph = LandmarkGraph(cutoff=100.0).set_distance_matrix(behind, behind, torch.ones(4, 4))
    assert 18.3 <= graph_quality(geometry, graph, coverage_radius=2.0)["landmark_progress"] <= 18.3 * 1.05
    far = graph_quality(geometry, graph, coverage_radius=2.0, start=torch.tensor([0.0, 8.0]))
    assert 18.3 <= far["landmark_progress"] <= 18.3 * 1.05  # from the goal end, the start is as far


def test_landmark_coverage():
    geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
    every_cell = geometry.cell_centers[geometry.free]
    assert landmark_coverage(geometry, every_cell, 0.01) == 1.0
    one = landmark_coverage(geometry, torch.tensor([[0.0, 0.0]]), 2.0)
    assert 0.0 < one < 0.2
    assert landmark_coverage(geometry, torch.zeros(0, 2), 2.0) == 0.0
    # the inner wall blocks: a landmark under it does not cover the top corridor within 8 units
    below = torch.tensor([[0.0, 1.0]])
    centers = geometry.cell_centers[geometry.free]
    within = ((centers - below).norm(dim=-1) <= 8.0).float().mean().item()
    near = centers[(centers - below).norm(dim=-1) <= 8.0]
    visible = [_visible_by_sampling(geometry, below[0], c, 0.0) for c in near]
    expected = sum(visible) / centers.shape[0]
    assert landmark_coverage(geometry, below, 8.0) == pytest.approx(expected, abs=2 / centers.shape[0])
    assert expected < within - 0.1


def _maze_points(geometry: MazeGeometry, count: int, generator: torch.Generator) -> torch.Tensor:
    """``count`` random free grid-cell centres of ``geometry`` reachable from the start."""
    centers = geometry.cell_centers[geometry.free]
    centers = centers[torch.isfinite(geometry.path_length(torch.zeros(2), centers))]
    return centers[torch.randint(0, centers.shape[0], (count,), generator=generator)]


@pytest.mark.parametrize("lanes", [1, 3])
def test_landmark_budget_sweep_against_direct_progress(lanes):
    """Over random buffers of maze points: a graph reaches at most as far as its buffer, a budget holding every
    point reaches exactly as far, more landmarks from the same candidates never reach less far (FPS is
    greedy), the rows match a direct computation from the rebuilt landmarks, and the planner is untouched."""
    geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
    generator = torch.Generator().manual_seed(0)
    distance = lambda s, g: (s[..., :2] - g).norm(dim=-1)  # noqa: E731
    for trial in range(6):
        count = int(torch.randint(4, 40, (1,), generator=generator)) * lanes
        points = _maze_points(geometry, count, generator)
        if trial == 0:
            points[:] = points[:1]  # every state the same: a single landmark, progress of that point
        storage = LazyTensorStorage(4 * count, ndim=2 if lanes > 1 else 1)  # max_size: elements, not rows
        rb = ReplayBuffer(storage=storage)
        data = TensorDict(
            observation=torch.cat([points, torch.randn(count, 2)], -1),
            achieved_goal=points,
            batch_size=[count],
        )
        rb.extend(data.reshape(count // lanes, lanes) if lanes > 1 else data)
        planner = GraphPlanner(LandmarkGraph(cutoff=3.0, early_stop=0.0), distance, goal_dim=2)
        planner.build(data["observation"][:2], points[:2])
        before = {k: v.clone() for k, v in planner.state_dict().items()}
        budgets = [(1, 60 * count), (3, 60 * count), (count, 60 * count), (3, 5)]
        rows, buffer_progress = landmark_budget_sweep(
            geometry, planner, rb, budgets, draws=2, coverage_radius=2.0, generator=generator
        )
        expected = max(geometry.path_length(torch.zeros(2), points).tolist())
        assert buffer_progress == pytest.approx(expected)
        assert [(r["max_landmarks"], r["candidates"]) for r in rows] == budgets
        for row in rows:
            assert (
                row["progress_min"] <= row["progress_mean"] <= row["progress_max"] <= buffer_progress + 1e-5
            )
            assert 0.0 < row["coverage_mean"] <= 1.0 and 1 <= row["landmarks"] <= row["max_landmarks"]
        # 60 draws per point: every point among the candidates, and as many landmarks as points
        assert rows[2]["progress_min"] == pytest.approx(buffer_progress)
        assert rows[0]["progress_mean"] <= rows[1]["progress_mean"] + 1e-6 <= rows[2]["progress_mean"] + 2e-6
        if trial == 0:
            assert rows[0]["progress_max"] == pytest.approx(expected)
        after = planner.state_dict()
        assert before.keys() == after.keys() and all(torch.equal(before[k], after[k]) for k in before)
        # the coverage of a row is the coverage of the landmarks a direct rebuild with the same draw gives
        seeds = torch.Generator().manual_seed(trial)
        one, _ = landmark_budget_sweep(
            geometry, planner, rb, [(count, 60 * count)], draws=1, coverage_radius=2.0, generator=seeds
        )
        assert one[0]["coverage_mean"] == pytest.approx(landmark_coverage(geometry, points, 2.0))


def test_landmark_budget_sweep_refuses_bad_input():
    geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
    planner = GraphPlanner(LandmarkGraph(cutoff=3.0), lambda s, g: (s - g).norm(dim=-1), goal_dim=2)
    empty = ReplayBuffer(storage=LazyTensorStorage(10))
    with pytest.raises(ValueError, match="empty"):
        landmark_budget_sweep(geometry, planner, empty, [(10, 10)], coverage_radius=2.0)
    rb = ReplayBuffer(storage=LazyTensorStorage(10))
    rb.extend(TensorDict(observation=torch.zeros(4, 2), achieved_goal=torch.zeros(4, 2), batch_size=[4]))
    for budgets in ([(0, 10)], [(10,)], [(10, 2.5)], [(True, 10)]):
        with pytest.raises(ValueError, match="budgets"):
            landmark_budget_sweep(geometry, planner, rb, budgets, coverage_radius=2.0)
    with pytest.raises(ValueError, match="draws"):
        landmark_budget_sweep(geometry, planner, rb, [(10, 10)], draws=0, coverage_radius=2.0)


# ------------------------------------------------------------------------------------------ recipe and tool


def test_maze_epoch_diagnostics_keys_and_arms():
    planner = GraphPlanner(
        LandmarkGraph(cutoff=5.0, early_stop=0.0), lambda s, g: (g - s[..., :2]).norm(dim=-1), goal_dim=2
    )
    geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
    states, goals = _candidates(geometry, 60)
    planner.build(states, goals)
    actor = HighLevelActor(6, 2, [-2.0, -2.0], [10.0, 10.0], num_cells=(8,))
    rollout = TensorDict(
        observation=states[:4, None].expand(4, 5, 6),
        desired_goal=torch.tensor([0.0, 8.0]).expand(4, 5, 2),
        subgoal=goals[:4, None].expand(4, 5, 2),
        waypoint=goals[:4, None].expand(4, 5, 2),
        new_subgoal=torch.ones(4, 5, 1, dtype=torch.bool),
        batch_size=[4, 5],
    )
    out = maze_epoch_diagnostics("PointMaze", planner, rollout, actor)
    assert set(out) == {*DIAG_KEYS, "time/diag_s"}
    assert all(math.isfinite(out[k]) for k in DIAG_KEYS)
    assert out["diag/subgoals_in_walls"] == 0.0 and out["diag/landmark_coverage"] > 0.5
    expected = start_subgoal(actor, states[0], torch.tensor([0.0, 8.0]))
    assert [out["diag/start_subgoal_x"], out["diag/start_subgoal_y"]] == pytest.approx(expected.tolist())
    assert maze_epoch_diagnostics("UR3Obstacle", planner, rollout, actor) == {}


def test_recipe_logs_diag_columns_and_the_tool_reads_the_checkpoint(tmp_path, capsys):
    run = tmp_path / "run"
    load_recipe().train(
        recipe_config("env=PointMaze", "preset=smoke", "logger.backend=none", "plots.every_epochs=0"),
        run_dir=run,
    )
    with (run / "metrics.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert set(DIAG_KEYS) <= set(rows[0])
    graph_keys = (
        "diag/edges_crossing_walls",
        "diag/edges_shortcut",
        "diag/distance_rank_corr",
        "diag/graph_distance_rank_corr",
        "diag/landmark_coverage",
        "diag/landmark_progress",
    )
    for row in rows:
        has_graph = int(row["graph/landmarks"]) > 0
        for key in DIAG_KEYS:
            value = float(row[key])
            if key in graph_keys and not has_graph:
                assert math.isnan(value), key
            else:
                assert math.isfinite(value), (key, row["epoch"])
        assert 0.0 <= float(row["diag/subgoals_in_walls"]) <= 1.0
        assert float(row["diag/start_subgoal_feasible"]) in (0.0, 1.0)
        assert -2.0 <= float(row["diag/start_subgoal_x"]) <= 10.0  # the subgoal box
    assert not math.isfinite(float(rows[0]["diag/landmark_coverage"]))  # warm-up epoch: no graph
    assert all(int(r["graph/landmarks"]) > 0 for r in rows[1:])
    # the success curve draws the coverage (from the first graph on) and the training episodes' success
    series = success_curve_series([{**r, "env_steps": int(r["env_steps"])} for r in rows])
    coverage = series["landmark coverage of the free space"]
    assert coverage == (
        [int(r["env_steps"]) for r in rows[1:]],
        [float(r["diag/landmark_coverage"]) for r in rows[1:]],
    )
    assert series["training episodes' success"][1] == [float(r["train/success"]) for r in rows]

    spec = importlib.util.spec_from_file_location("diagnose_graph", RECIPES / "diagnose_graph.py")
    cli = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cli)
    plot = tmp_path / "scatter.png"
    diagnosis, table, budgets = cli.main([str(run), "--pairs", "4", "--plot", str(plot)])
    assert budgets is None
    out = capsys.readouterr().out
    assert "diag/edges_crossing_walls" in out and "learned vs true distances" in out
    assert plot.stat().st_size > 1000
    assert 1 <= len(table) <= 4 and all(row["true"] >= 0 for row in table)
    assert diagnosis.metrics["graph/landmarks"] == int(rows[-1]["graph/landmarks"])
    assert math.isfinite(diagnosis.metrics["diag/distance_rank_corr"])
    assert 0.0 <= diagnosis.metrics["diag/waypoints_in_walls"] <= 1.0
    pairs = diagnosis.pairs
    assert pairs["true"].shape == pairs["learned"].shape == pairs["graph"].shape and pairs["true"].numel() > 0
    # without the evaluation rollout: the subgoal fractions are NaN, the graph numbers the same
    quick, _, (budgets, buffer_progress) = cli.main(
        [
            str(run / "checkpoint"),
            "--no-rollout",
            "--pairs",
            "0",
            "--plot",
            str(plot),
            "--budgets",
            "4:50",
            "100:1000",
        ]
    )
    assert math.isnan(quick.metrics["diag/subgoals_in_walls"])
    assert quick.metrics["diag/distance_rank_corr"] == diagnosis.metrics["diag/distance_rank_corr"]
    # the graph rebuilt from the run's buffer: never past the buffer's furthest state; the run's own graph kept
    assert "the buffer's furthest state" in capsys.readouterr().out
    assert [(row["max_landmarks"], row["candidates"]) for row in budgets] == [(4, 50), (100, 1000)]
    assert 0.0 < budgets[0]["progress_mean"] <= budgets[1]["progress_max"] <= buffer_progress + 1e-5
    assert quick.metrics["graph/landmarks"] == diagnosis.metrics["graph/landmarks"]
    with pytest.raises(SystemExit):
        cli.main([str(run), "--no-rollout", "--budgets", "300-6000"])
