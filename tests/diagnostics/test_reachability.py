"""The part of the landmark graph a plan from a state can use (``graph_reach``), against networkx's reachability
and a direct computation of each number."""

import math

import networkx as nx
import pytest
import torch
from torchrl_dhrl.envs.geometry import MazeGeometry

from tests.diagnostics.test_graph_quality import _candidates
from torchrl_dhrl.diagnostics import graph_reach
from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph


def euclid_steps(states, goals):
    return (goals - states[..., :2]).norm(dim=-1) / 0.2


def _expected(geometry, planner, state, goal):
    """The same four numbers from networkx's reachability and plain loops."""
    graph = planner.graph
    goals = graph.landmark_goals[:, :2]
    num = goals.shape[0]
    # the entry rule as documented: the landmarks within the cutoff, else those within
    # start_fallback_factor x the nearest landmark's distance
    to_landmarks = euclid_steps(state, goals)
    within = [k for k in range(num) if to_landmarks[k] < graph.cutoff]
    nearest = to_landmarks.min().item()
    entries = within or [
        k
        for k in range(num)
        if to_landmarks[k] <= graph.start_fallback_factor * nearest and math.isfinite(nearest)
    ]
    digraph = nx.DiGraph()
    digraph.add_nodes_from(range(num))
    digraph.add_edges_from(graph.edges.tolist())
    reachable = set(entries)
    for k in entries:
        reachable |= nx.descendants(digraph, k)
    out = {"reachable_landmarks": len(reachable) / num}
    origin = torch.zeros(2)
    progress = [geometry.path_length(origin, goals[k]).item() for k in sorted(reachable)]
    progress = [p for p in progress if math.isfinite(p)]
    out["reachable_progress"] = max(progress) if progress else math.nan
    to_goal = [geometry.path_length(goal, goals[k]).item() for k in sorted(reachable)]
    out["goal_to_reachable"] = min(to_goal) if to_goal else math.inf
    across = [
        graph.landmark_distances[i, j].item() for i in reachable for j in range(num) if j not in reachable
    ]
    out["bridge_distance"] = min(across) if across else math.inf
    return out


def test_graph_reach_matches_networkx_on_random_graphs():
    geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
    free = geometry.cell_centers[geometry.free]
    partial = 0
    for seed in range(40):
        generator = torch.Generator().manual_seed(seed)
        num = int(torch.randint(1, 13, (), generator=generator))
        _, goals = _candidates(geometry, num, seed=seed)
        # few distinct values (ties), some pairs far beyond any cutoff; the cutoff sometimes equal to an entry
        distances = torch.randint(1, 8, (num, num), generator=generator).float() * 5.0
        distances[torch.rand(num, num, generator=generator) < 0.3] = 1e6
        cutoff = float(torch.randint(1, 8, (), generator=generator)) * 5.0
        planner = GraphPlanner(LandmarkGraph(cutoff=cutoff, early_stop=0.0), euclid_steps, goal_dim=2)
        planner.graph.set_distance_matrix(goals, goals, distances)
        for _ in range(3):
            state, goal = free[torch.randint(0, free.shape[0], (2,), generator=generator)]
            out = graph_reach(geometry, planner, state, goal)
            expected = _expected(geometry, planner, state, goal)
            assert out.keys() == expected.keys()
            for key, value in expected.items():
                assert out[key] == pytest.approx(value, nan_ok=True), (seed, key)
            partial += 0.0 < out["reachable_landmarks"] < 1.0
    assert partial >= 20  # of the 120 cases: graphs in pieces, not only connected ones


def test_graph_reach_on_a_graph_cut_in_two():
    """Two chains of landmarks, the second (round the U's inner wall to the goal) never entered from the start."""
    geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
    near = torch.tensor([[0.0, 0.0], [2.0, 0.0], [4.0, 0.0], [6.0, 0.0], [8.0, 0.0]])
    far = torch.tensor([[8.0, 6.0], [8.0, 8.0], [6.0, 8.0], [4.0, 8.0]])
    goals = torch.cat([near, far])
    planner = GraphPlanner(LandmarkGraph(cutoff=15.0, early_stop=0.0), euclid_steps, goal_dim=2)
    # 2 apart: 10 steps, an edge; (8, 0) -> (8, 6): 30, none
    planner.graph.set_landmarks(goals, goals, euclid_steps)
    out = graph_reach(geometry, planner, torch.zeros(2), torch.tensor([0.0, 8.0]))
    assert out["reachable_landmarks"] == pytest.approx(5 / 9)
    assert out["reachable_progress"] == pytest.approx(8.0)  # (8, 0) in sight of the start
    assert out["goal_to_reachable"] == pytest.approx(
        geometry.path_length(torch.tensor([0.0, 8.0]), near).min().item()
    )
    assert out["bridge_distance"] == pytest.approx(30.0)  # (8, 0) -> (8, 6)
    # the bridge below the cutoff: one graph, every landmark reachable
    planner.graph.cutoff = 31.0
    planner.graph.set_landmarks(goals, goals, euclid_steps)
    out = graph_reach(geometry, planner, torch.zeros(2), torch.tensor([0.0, 8.0]))
    assert out["reachable_landmarks"] == 1.0 and out["bridge_distance"] == math.inf
    assert out["goal_to_reachable"] == pytest.approx(4.0)  # (4, 8)
    # plans from inside the far chain reach it only (the edges are directed, here both ways)
    planner.graph.cutoff = 15.0
    planner.graph.set_landmarks(goals, goals, euclid_steps)
    out = graph_reach(geometry, planner, torch.tensor([8.0, 7.0]), torch.tensor([0.0, 8.0]))
    assert out["reachable_landmarks"] == pytest.approx(4 / 9)
    assert out["goal_to_reachable"] == pytest.approx(4.0)


def test_graph_reach_without_a_graph_or_a_goal():
    geometry = MazeGeometry.from_maze("PointMaze", margin=0.5)
    planner = GraphPlanner(LandmarkGraph(), euclid_steps, goal_dim=2)
    out = graph_reach(geometry, planner, torch.zeros(2), torch.tensor([0.0, 8.0]))
    assert set(out) == {"reachable_landmarks", "reachable_progress", "goal_to_reachable", "bridge_distance"}
    assert all(math.isnan(v) for v in out.values())
    goals = torch.tensor([[0.0, 0.0], [4.0, 0.0]])
    planner.graph.set_landmarks(goals, goals, euclid_steps)
    out = graph_reach(geometry, planner, torch.zeros(2))
    assert math.isnan(out["goal_to_reachable"]) and out["reachable_landmarks"] == 1.0
    # a state no landmark connects to (its learned distances all infinite): nothing reachable
    nowhere = GraphPlanner(LandmarkGraph(), lambda s, g: torch.full(g.shape[:-1], math.inf), goal_dim=2)
    nowhere.graph.set_distance_matrix(goals, goals, torch.ones(2, 2))
    out = graph_reach(geometry, nowhere, torch.zeros(2), torch.tensor([0.0, 8.0]))
    assert out["reachable_landmarks"] == 0.0 and math.isnan(out["reachable_progress"])
    assert out["goal_to_reachable"] == math.inf and out["bridge_distance"] == math.inf
    with pytest.raises(TypeError, match="GraphPlanner"):
        graph_reach(geometry, planner.graph, torch.zeros(2))
