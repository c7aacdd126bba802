"""The landmark graph against the maze's true geometry: edges through walls, shortcuts, rank correlations
of the learned distances, the furthest landmark along the maze."""

import math

import pytest
import torch
from torchrl_dhrl.envs.geometry import MazeGeometry

from torchrl_dhrl.diagnostics import graph_quality
from torchrl_dhrl.planner import CutoffEdgeRule, GraphPlanner, LandmarkGraph


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
