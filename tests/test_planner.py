"""LandmarkGraph and GraphPlanner behaviour: graph building, queries, waypoint tracking, checkpoints."""

import io
import math

import networkx as nx
import numpy as np
import pytest
import torch
from tensordict import TensorDict

from torchrl_dhrl.planner import CutoffEdgeRule, GraphPlanner, LandmarkGraph

INF = math.inf

# ----------------------------------------------------------------------------- oracles
# U-maze of the reference at scale 4: free space [-2, 10]^2, wall block x < 6, 2 < y < 6.
WALL_LOW, WALL_HIGH = torch.tensor([-2.0, 2.0]), torch.tensor([6.0, 6.0])
SPEED = 0.5  # goal units per env step


def line_of_sight_distance(states, goals):
    """Euclidean distance / speed when the straight segment avoids the wall, ``inf`` otherwise."""
    start = states[..., :2]
    delta = goals - start
    t = torch.linspace(0, 1, 41).unsqueeze(-1)
    points = start.unsqueeze(-2) + t * delta.unsqueeze(-2)
    blocked = ((points > WALL_LOW) & (points < WALL_HIGH)).all(-1).any(-1)
    dist = delta.norm(dim=-1) / SPEED
    return torch.where(blocked, torch.full_like(dist, INF), dist)


def euclidean(states, goals):
    return (goals - states[..., :2]).norm(dim=-1)


def asymmetric(states, goals):
    delta = goals - states[..., :2]
    return delta.norm(dim=-1) + 0.5 * delta[..., 1].clamp_min(0)


def u_maze_candidates(spacing=0.5):
    xs = torch.arange(-2.0, 10.0 + 1e-6, spacing)
    grid = torch.cartesian_prod(xs, xs)
    free = ~((grid > WALL_LOW) & (grid < WALL_HIGH)).all(-1)
    goals = grid[free]
    states = torch.cat([goals, torch.zeros(goals.shape[0], 3)], -1)  # obs_dim 5, goal = obs[:2]
    return states, goals


def line_planner(max_path_length=32, **kwargs):
    """Six landmarks on the x axis at 0, 1, ..., 5, one unit (= one step) apart."""
    planner = GraphPlanner(LandmarkGraph(cutoff=1.5), euclidean, 2, max_path_length=max_path_length, **kwargs)
    points = torch.stack([torch.arange(6.0), torch.zeros(6)], -1)
    planner.graph.set_landmarks(points, points.clone(), euclidean)
    return planner


def step_td(obs, subgoal, new):
    obs = torch.as_tensor(obs, dtype=torch.float32).reshape(-1, 2)
    num = obs.shape[0]
    return TensorDict(
        observation=obs,
        achieved_goal=obs.clone(),
        subgoal=torch.as_tensor(subgoal, dtype=torch.float32).reshape(-1, 2).expand(num, 2),
        new_subgoal=torch.full((num, 1), new, dtype=torch.bool),
        batch_size=[num],
    )


def advance(planner, td, obs, new=False, subgoal=None):
    """The next env step: same tracking state, new observation."""
    td = td.clone()
    obs = torch.as_tensor(obs, dtype=torch.float32).reshape(td["observation"].shape)
    td["observation"], td["achieved_goal"] = obs, obs.clone()
    td["new_subgoal"] = torch.full_like(td["new_subgoal"], new)
    if subgoal is not None:
        td["subgoal"] = torch.as_tensor(subgoal, dtype=torch.float32).expand_as(td["subgoal"]).clone()
    return planner(td)


# ----------------------------------------------------------------------------- graph building
def test_edges_follow_cutoff_and_nearest_neighbour_rule():
    gen = torch.Generator().manual_seed(0)
    num = 60
    matrix = torch.rand(num, num, generator=gen) * 20
    matrix[:15] += 4.0  # landmarks with no neighbour within the cutoff: only the 1.2 x NN rule connects them
    graph = LandmarkGraph(cutoff=3.0, edge_rule=CutoffEdgeRule(nn_factor=1.2))
    pts = torch.rand(num, 2, generator=gen)
    graph.set_distance_matrix(pts, pts.clone(), matrix)
    d = matrix.numpy().copy()
    np.fill_diagonal(d, np.inf)
    nearest = d.min(1, keepdims=True)
    expected = (d < 3.0) | (d < 1.2 * nearest)
    np.fill_diagonal(expected, False)
    assert np.array_equal(graph.edge_mask.numpy(), expected)
    assert (expected & ~(d < 3.0)).sum() >= 15  # the nearest-neighbour rule added edges
    assert graph.edge_mask.any(dim=1).all()  # every node has an outgoing edge
    edges = graph.edges
    torch.testing.assert_close(graph.edge_costs, matrix[edges[:, 0], edges[:, 1]])
    assert graph.version.item() == 1


def test_build_fills_lazy_gaps_with_true_distances():
    states, goals = u_maze_candidates(spacing=1.0)
    graph = LandmarkGraph(cutoff=6.0, max_landmarks=40, early_stop=0.0)
    graph.build(states, goals, line_of_sight_distance)
    expected = line_of_sight_distance(graph.landmark_states.unsqueeze(1), graph.landmark_goals.unsqueeze(0))
    expected.fill_diagonal_(0.0)
    assert graph.num_landmarks == 40
    # the coverage radius is the largest min-distance of a candidate to the landmarks
    to_landmarks = (
        line_of_sight_distance(graph.landmark_states.unsqueeze(1), goals.unsqueeze(0)).min(0).values
    )
    chosen = torch.isin(torch.arange(len(goals)), torch.cdist(graph.landmark_goals, goals).argmin(-1))
    assert graph.coverage_radius.item() == pytest.approx(to_landmarks[~chosen].max().item(), rel=1e-5)
    torch.testing.assert_close(graph.landmark_distances, expected)
    dense = LandmarkGraph(cutoff=6.0, max_landmarks=40, early_stop=0.0, fps_strategy="dense")
    dense.build(states, goals, line_of_sight_distance)
    assert torch.equal(dense.landmark_goals, graph.landmark_goals)


def test_u_maze_path_goes_around_the_wall():
    states, goals = u_maze_candidates()
    graph = LandmarkGraph(cutoff=6.0, max_landmarks=150, early_stop=2.0)
    graph.build(states, goals, line_of_sight_distance)
    start = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0]])
    subgoal = torch.tensor([[0.0, 8.0]])
    assert math.isinf(line_of_sight_distance(start, subgoal).item())  # straight line is blocked
    plan = graph.plan(start, subgoal, line_of_sight_distance)
    assert plan.reachable.item() and not plan.truncated.item()
    waypoints = graph.landmark_goals[plan.path[0, : plan.length[0]]]
    sequence = torch.cat([start[:, :2], waypoints, subgoal])
    hops = line_of_sight_distance(sequence[:-1], sequence[1:])
    assert torch.isfinite(hops).all()  # every hop is collision free
    assert (waypoints[:, 0] > 6.0).any()  # through the right-hand corridor
    # the planned cost is the sum of the hop budgets and close to the geodesic length
    budgets = plan.budgets[0, : plan.length[0] + 1]
    assert budgets.sum().item() == pytest.approx(plan.cost.item(), rel=1e-5)
    geodesic = (2 * math.hypot(6.0, 2.0) + 4.0) / SPEED
    assert geodesic - 1e-3 <= plan.cost.item() <= 1.25 * geodesic


def reference_query(graph, distance, state, subgoal):
    """The reference approach: copy the graph, add start/goal nodes, run Dijkstra (networkx)."""
    g = nx.DiGraph()
    g.add_nodes_from(range(graph.num_landmarks))
    for (i, j), w in zip(graph.edges.tolist(), graph.edge_costs.tolist(), strict=True):
        g.add_edge(i, j, weight=w)
    start_cost = graph.start_costs(state.unsqueeze(0), distance)[0]
    for k in torch.isfinite(start_cost).nonzero().squeeze(-1).tolist():
        g.add_edge("start", k, weight=float(start_cost[k]))
    to_goal = distance(graph.landmark_states, subgoal.expand(graph.num_landmarks, -1))
    for k in (to_goal < graph.cutoff).nonzero().squeeze(-1).tolist():
        g.add_edge(k, "goal", weight=float(to_goal[k]))
    direct = float(distance(state, subgoal))
    if direct < graph.cutoff:
        g.add_edge("start", "goal", weight=direct)
    reachable = nx.descendants(g, "start") - {"goal"} if "start" in g else set()
    if "goal" not in g or not nx.has_path(g, "start", "goal"):
        return INF, reachable
    return nx.dijkstra_path_length(g, "start", "goal"), reachable


@pytest.mark.parametrize("num_landmarks,seed", [(50, 0), (200, 1)])
def test_batched_query_matches_networkx_dijkstra(num_landmarks, seed):
    gen = torch.Generator().manual_seed(seed)
    points = torch.rand(num_landmarks, 2, generator=gen) * 20
    graph = LandmarkGraph(cutoff=3.0)
    graph.set_landmarks(points, points.clone(), asymmetric)
    states = torch.rand(24, 2, generator=gen) * 22 - 1
    subgoals = torch.rand(24, 2, generator=gen) * 30 - 5
    plan = graph.plan(states, subgoals, asymmetric)
    expected = [reference_query(graph, asymmetric, s, g) for s, g in zip(states, subgoals, strict=True)]
    for row, (cost, reachable) in enumerate(expected):
        if math.isinf(cost):
            assert not plan.reachable[row] and math.isinf(plan.cost[row])
            # fallback: the path ends at the reachable landmark nearest to the subgoal
            nodes = torch.tensor(sorted(reachable))
            nearest = nodes[asymmetric(graph.landmark_states[nodes], subgoals[row]).argmin()]
            assert plan.path[row, plan.length[row] - 1].item() == nearest.item()
            continue
        assert plan.reachable[row]
        assert plan.cost[row].item() == pytest.approx(cost, rel=1e-5, abs=1e-4)
        # the stored path is a chain of real edges whose budgets add up to the cost
        n = plan.length[row].item()
        path = plan.path[row, :n]
        if n > 1:
            assert torch.isfinite(graph.edge_weights[path[:-1], path[1:]]).all()
        assert plan.budgets[row, : n + 1].sum().item() == pytest.approx(cost, rel=1e-5, abs=1e-4)
    costs = [cost for cost, _ in expected]
    assert any(math.isinf(c) for c in costs) and any(not math.isinf(c) for c in costs)
    # batching is independent of the other rows
    single = graph.plan(states[5:6], subgoals[5:6], asymmetric)
    assert torch.equal(single.path[0, : single.length[0]], plan.path[5, : plan.length[5]])


def test_unreachable_subgoal_falls_back_to_nearest_reachable_landmark():
    # two islands: {0, 1, 2} reachable from the start, {3, 4} reachable from nowhere
    points = torch.tensor([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [10.0, 0.0], [11.0, 0.0]])
    graph = LandmarkGraph(cutoff=1.5, edge_rule=CutoffEdgeRule(nn_factor=1.0))
    graph.set_landmarks(points, points.clone(), euclidean)
    plan = graph.plan(torch.tensor([[0.0, 0.0]]), torch.tensor([[11.5, 0.0]]), euclidean)
    assert not plan.reachable.item() and math.isinf(plan.cost.item())
    assert plan.path[0, : plan.length[0]].tolist() == [
        0,
        1,
        2,
    ]  # to the reachable landmark nearest the subgoal

    # a start connected to no landmark at all (and no direct edge): the subgoal alone
    def from_nowhere(states, goals):  # landmarks connect among themselves, queries connect to nothing
        d = euclidean(states, goals)
        return torch.where(states[..., 1] > 50, torch.full_like(d, INF), d)

    plan = graph.plan(torch.tensor([[0.0, 99.0]]), torch.tensor([[1.0, 0.0]]), from_nowhere)
    assert plan.length.item() == 0 and not plan.reachable.item()

    # reachable landmarks that are all infinitely far from the subgoal: the subgoal alone as well
    def blind(states, goals):
        d = euclidean(states, goals)
        return torch.where(goals[..., 1] > 50, torch.full_like(d, INF), d)

    plan = graph.plan(torch.tensor([[0.0, 0.0]]), torch.tensor([[1.0, 99.0]]), blind)
    assert plan.length.item() == 0 and not plan.reachable.item()


def test_start_fallback_connects_to_near_landmarks_outside_the_cutoff():
    points = torch.tensor([[3.0, 0.0], [4.0, 0.0], [5.5, 0.0]])
    graph = LandmarkGraph(cutoff=1.5, start_fallback_factor=1.5)
    graph.set_landmarks(points, points.clone(), euclidean)
    costs = graph.start_costs(torch.tensor([[0.0, 0.0]]), euclidean)[0]
    # nearest landmark at 3 -> connected within 4.5: landmarks 0 (3) and 1 (4), not 2 (5.5)
    assert torch.isfinite(costs).tolist() == [True, True, False]
    plan = graph.plan(torch.tensor([[0.0, 0.0]]), torch.tensor([[5.0, 0.0]]), euclidean)
    # two equally short routes: start -> 1 -> subgoal, start -> 0 -> 1 -> subgoal
    assert plan.reachable.item() and plan.path[0, plan.length[0] - 1].item() == 1
    assert plan.cost.item() == pytest.approx(5.0)


def test_direct_edge_wins_when_shorter_and_no_graph_means_subgoal():
    planner = line_planner()
    plan = planner.plan(torch.tensor([[2.0, 0.3]]), torch.tensor([[2.5, 0.3]]))
    assert plan.length.item() == 0 and plan.cost.item() == pytest.approx(0.5)
    empty = GraphPlanner(LandmarkGraph(cutoff=1.5), euclidean, 2)
    assert not empty.has_graph and torch.isinf(empty.distance_from_graph(torch.zeros(3, 2))).all()
    td = empty(step_td([[0.0, 0.0], [1.0, 1.0]], [7.0, 7.0], True))
    assert torch.equal(td["waypoint"], torch.full((2, 2), 7.0))
    assert (td["planner", "path_length"] == 0).all() and td["planner", "has_plan"].all()
    empty.graph.set_landmarks(torch.zeros(0, 2), torch.zeros(0, 2), euclidean)
    assert not empty.has_graph


def test_distance_from_graph_is_min_over_landmarks():
    planner = line_planner()
    goals = torch.tensor([[[2.2, 1.0], [7.0, 0.0]], [[-1.0, 0.0], [3.0, 0.0]]])
    expected = torch.cdist(goals.reshape(-1, 2), planner.landmark_states).min(-1).values.reshape(2, 2)
    torch.testing.assert_close(planner.distance_from_graph(goals), expected)


# ----------------------------------------------------------------------------- tracking
class PairCounter:
    """Wraps a distance and counts the (state, goal) pairs it evaluates."""

    def __init__(self, distance):
        self.distance, self.pairs = distance, 0

    def __call__(self, states, goals):
        out = self.distance(states, goals)
        self.pairs += out.numel()
        return out


@pytest.mark.parametrize("at_most", [0.5, 1.5, 3.0, 6.0])
def test_distance_from_graph_at_most_is_exact_relative_to_the_threshold(at_most):
    gen = torch.Generator().manual_seed(3)
    points = torch.rand(120, 2, generator=gen) * 20
    graph = LandmarkGraph(cutoff=3.0)
    graph.set_landmarks(points, points.clone(), asymmetric)
    goals = torch.rand(500, 2, generator=gen) * 40 - 10
    full = graph.distance_from_graph(goals, asymmetric)
    counter = PairCounter(asymmetric)
    fast = graph.distance_from_graph(goals, counter, at_most=at_most, candidates=8)
    for compare in (torch.lt, torch.le, torch.gt, torch.ge):
        assert torch.equal(compare(fast, at_most), compare(full, at_most))
    assert (fast >= full - 1e-6).all()  # settled goals get an upper bound of the minimum
    above = full >= at_most
    torch.testing.assert_close(fast[above], full[above], rtol=0, atol=0)  # the others get it exactly
    assert above.any() and (~above).any()
    unsettled = int(above.sum())  # evaluated from every landmark after the candidate pass
    assert counter.pairs == 500 * 8 + unsettled * 120
    # goals next to landmarks (the common case: subgoals in explored space) settle in the candidate pass
    near = points[torch.randint(0, 120, (500,), generator=gen)] + 0.1 * torch.randn(500, 2, generator=gen)
    counter.pairs = 0
    fast = graph.distance_from_graph(near, counter, at_most=at_most, candidates=8)
    assert counter.pairs == 500 * 8 and (fast < at_most).all()


def test_distance_from_graph_at_most_when_the_nearest_landmarks_are_behind_a_wall():
    # landmarks below the wall of the U-maze, right under goals above it: blocked (inf); the only
    # finite distances come from landmarks in the right-hand corridor, far away in goal space
    below = torch.stack([torch.linspace(-1.5, 5.5, 8), torch.full((8,), 1.5)], -1)
    corridor = torch.tensor([[8.0, 4.0], [8.0, 7.0]])
    points = torch.cat([below, corridor])
    graph = LandmarkGraph(cutoff=30.0)
    states = torch.cat([points, torch.zeros(len(points), 3)], -1)
    graph.set_landmarks(states, points.clone(), line_of_sight_distance)
    goals = torch.tensor([[2.0, 6.5], [4.0, 6.5], [1.0, 1.0]])
    full = graph.distance_from_graph(goals, line_of_sight_distance)
    fast = graph.distance_from_graph(goals, line_of_sight_distance, at_most=20.0, candidates=2)
    assert torch.isfinite(full[:2]).all()  # reachable from the corridor landmark only
    assert torch.equal(fast < 20.0, full < 20.0) and torch.equal(fast[:2], full[:2])
    with pytest.raises(ValueError, match="candidates"):
        graph.distance_from_graph(goals, line_of_sight_distance, at_most=1.0, candidates=0)


def test_tracking_advances_by_radius_and_by_timeout_then_chases_subgoal():
    planner = line_planner(reach_radius=0.5)
    td = planner(step_td([0.0, 0.0], [5.0, 0.0], True))
    # landmarks 0..4 then the subgoal (which lies on landmark 5: an equally short route)
    assert td["planner", "path"][0, :6].tolist() == [0, 1, 2, 3, 4, -1]
    assert td["planner", "path_length"].item() == 5
    assert td["planner", "budgets"][0, :7].tolist() == pytest.approx([0, 1, 1, 1, 1, 1, INF])
    assert td["waypoint"][0].tolist() == [0.0, 0.0] and td["planner", "index"].item() == 0
    td = advance(planner, td, [0.0, 0.0])  # landmark 0 reached
    assert td["waypoint"][0].tolist() == [1.0, 0.0] and td["planner", "steps"].item() == 0
    td = advance(planner, td, [0.6, 0.0])  # within 0.5 of landmark 1
    assert td["waypoint"][0].tolist() == [2.0, 0.0]
    td = advance(planner, td, [0.6, 0.0])  # 1 step on landmark 2, budget 1: keep going
    assert td["waypoint"][0].tolist() == [2.0, 0.0] and td["planner", "steps"].item() == 1
    td = advance(planner, td, [0.6, 0.0])  # 2 steps > budget 1: time out, next waypoint
    assert td["waypoint"][0].tolist() == [3.0, 0.0] and td["planner", "index"].item() == 3
    for x in (3.0, 4.0):
        td = advance(planner, td, [x, 0.0])
    assert td["planner", "index"].item() == 5 and td["waypoint"][0].tolist() == [5.0, 0.0]
    for _ in range(3):  # after the path: the subgoal, forever
        td = advance(planner, td, [9.0, 9.0])
        assert td["planner", "index"].item() == 5 and td["waypoint"][0].tolist() == [5.0, 0.0]
    assert td["planner", "steps"].item() == 3


def test_replan_on_new_subgoal_only():
    planner = line_planner()
    td = planner(step_td([0.0, 0.0], [5.0, 0.0], True))
    td = advance(planner, td, [0.0, 0.0])
    td = advance(planner, td, [2.0, 0.0], subgoal=[0.0, 0.0])  # subgoal changed, no new_subgoal flag
    assert td["planner", "path"][0, :5].tolist() == [0, 1, 2, 3, 4]
    td = advance(planner, td, [2.0, 0.0], new=True, subgoal=[0.0, 0.0])
    expected = planner.plan(torch.tensor([[2.0, 0.0]]), torch.tensor([[0.0, 0.0]]))
    assert td["planner", "path"][0].tolist() == expected.path[0].tolist()
    assert td["planner", "path"][0, 0].item() in (1, 2) and td["planner", "index"].item() == 0
    assert td["planner", "budgets"][0, : td["planner", "path_length"].item() + 1].sum().item() == 2.0


def test_graph_rebuild_triggers_replan_and_truncated_paths_replan_when_used_up():
    planner = line_planner(max_path_length=2)
    td = planner(step_td([0.0, 0.0], [5.0, 0.0], True))
    assert td["planner", "path"][0].tolist() == [0, 1] and td["planner", "truncated"].item()
    assert td["planner", "budgets"][0, 2].item() == INF  # no final hop stored for a cut path
    td = advance(planner, td, [0.0, 0.0])
    td = advance(planner, td, [1.0, 0.0])  # stored part used up: replan from x = 1
    expected = planner.plan(torch.tensor([[1.0, 0.0]]), torch.tensor([[5.0, 0.0]]))
    assert td["planner", "path"][0].tolist() == expected.path[0].tolist()
    assert td["planner", "index"].item() == 0 and td["planner", "graph_version"].item() == 1
    # a rebuild changes landmark indices: the stale plan is dropped at the next step
    shifted = torch.stack([torch.arange(6.0) + 0.25, torch.zeros(6)], -1).flip(0)
    planner.graph.set_landmarks(shifted, shifted.clone(), euclidean)
    td = advance(planner, td, [1.0, 0.0])
    assert td["planner", "graph_version"].item() == 2 and td["planner", "index"].item() == 0
    assert torch.equal(td["waypoint"][0], shifted[td["planner", "path"][0, 0]])


def test_batch_of_envs_with_different_subgoals_and_leading_dims():
    planner = line_planner()
    obs = torch.tensor([[[0.0, 0.0], [5.0, 0.0], [2.0, 0.0]], [[3.0, 0.0], [0.0, 0.0], [1.0, 0.0]]])
    subgoals = torch.tensor([[[5.0, 0.0], [0.0, 0.0], [2.0, 0.0]], [[0.0, 0.0], [3.0, 0.0], [9.0, 9.0]]])
    td = TensorDict(
        observation=obs,
        achieved_goal=obs.clone(),
        subgoal=subgoals,
        new_subgoal=torch.ones(2, 3, 1, dtype=torch.bool),
        batch_size=[2, 3],
    )
    td = planner(td)
    for i in range(2):
        for j in range(3):
            single = planner(step_td(obs[i, j], subgoals[i, j], True))
            assert torch.equal(td["planner", "path"][i, j], single["planner", "path"][0])
            assert torch.equal(td["waypoint"][i, j], single["waypoint"][0])
    waypoints, mask = planner.planned_waypoints(td)
    assert waypoints.shape == (2, 3, 33, 2) and mask.shape == (2, 3, 33)
    path = planner.planned_path(td, (0, 0))
    assert path[:, 0].tolist() == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]  # landmarks 0..4, then the subgoal
    assert planner.planned_path(td, (1, 2))[-1].tolist() == [9.0, 9.0]


# ----------------------------------------------------------------------------- checkpoints
def test_state_dict_round_trip_with_a_different_landmark_count():
    states, goals = u_maze_candidates(spacing=1.0)
    source = GraphPlanner(
        LandmarkGraph(cutoff=6.0, max_landmarks=60, early_stop=2.0), line_of_sight_distance, 2
    )
    source.build(states, goals)
    other = GraphPlanner(
        LandmarkGraph(cutoff=6.0, max_landmarks=60, early_stop=2.0), line_of_sight_distance, 2
    )
    other.build(states[:30], goals[:30])
    assert other.num_landmarks != source.num_landmarks
    buffer = io.BytesIO()
    torch.save(source.state_dict(), buffer)
    buffer.seek(0)
    other.load_state_dict(torch.load(buffer))
    fresh = GraphPlanner(LandmarkGraph(cutoff=6.0), line_of_sight_distance, 2)
    fresh.load_state_dict(source.state_dict())
    for target in (other, fresh):
        for name, value in source.state_dict().items():
            assert torch.equal(target.state_dict()[name], value), name
        td = step_td([[0.0, 0.0], [8.0, 8.0]], [[0.0, 8.0], [0.0, 0.0]], True)
        td = td.set("observation", torch.cat([td["observation"], torch.zeros(2, 3)], -1))
        assert torch.equal(target(td.clone())["planner", "path"], source(td.clone())["planner", "path"])
    # the distance function (e.g. the learner's critics) is not part of the planner's state
    assert all(name.startswith("graph.") for name in source.state_dict()) and not list(source.parameters())


def test_input_validation():
    with pytest.raises(ValueError, match="goal_dim"):
        GraphPlanner(LandmarkGraph(), euclidean, 0)
    with pytest.raises(TypeError, match="callable"):
        GraphPlanner(LandmarkGraph(), 3.0, 2)
    with pytest.raises(ValueError, match="cutoff"):
        LandmarkGraph(cutoff=-1.0)
    with pytest.raises(ValueError, match="start_fallback_factor"):
        LandmarkGraph(start_fallback_factor=0.5)
    planner = line_planner()
    with pytest.raises(KeyError, match="subgoal"):
        planner(step_td([0.0, 0.0], [5.0, 0.0], True).exclude("subgoal"))
    with pytest.raises(ValueError, match="goal_dim"):
        td = step_td([0.0, 0.0], [5.0, 0.0], True)
        planner(td.set("subgoal", torch.zeros(1, 3)))
    with pytest.raises(ValueError, match="features"):
        planner.plan(torch.zeros(1, 4), torch.zeros(1, 2))
    with pytest.raises(ValueError, match="candidate_goals"):
        planner.build(torch.zeros(5, 2), torch.zeros(5, 3))
