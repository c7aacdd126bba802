"""LandmarkGraph: graph building (FPS landmarks, lazy gaps, the build speed options: reuse of the FPS
distances, the FPS proxy and reduced-precision building), queries against networkx's Dijkstra, fallbacks,
distances from the graph, and the capturable plans (``LandmarkGraph.plan(capturable=True)``, static shapes
and no host synchronisation) equal to the host-branching plans field by field over many random graphs and
queries (Euclidean, walls with unreachable subgoals and isolated starts, integer distances full of ties,
asymmetric distances, truncation, no graph, empty batches)."""

import math

import networkx as nx
import pytest
import torch

from torchrl_dhrl.modules import GoalConditionedCritic, LowLevelActor
from torchrl_dhrl.planner import (
    CutoffEdgeRule,
    GoalDistance,
    GraphPlanner,
    LandmarkGraph,
    farthest_point_sampling,
    reconstruct_paths,
)

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


def test_unreachable_subgoal_rule_subgoal_goes_straight_for_it():
    points = torch.tensor([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [10.0, 0.0], [11.0, 0.0]])
    graph = LandmarkGraph(cutoff=1.5, edge_rule=CutoffEdgeRule(nn_factor=1.0), unreachable="subgoal")
    graph.set_landmarks(points, points.clone(), euclidean)
    states, subgoals = torch.tensor([[0.0, 0.0], [0.0, 0.0]]), torch.tensor([[11.5, 0.0], [2.0, 0.0]])
    plan = graph.plan(states, subgoals, euclidean, 8)
    # the unreachable subgoal: no landmark, its one hop the state's own distance to it; the reachable one planned
    assert plan.reachable.tolist() == [False, True] and plan.length.tolist() == [0, 2]
    assert plan.path[0].tolist() == [-1] * 8 and plan.budgets[0, 0].item() == pytest.approx(11.5)
    assert math.isinf(plan.cost[0].item()) and plan.path[1, :2].tolist() == [0, 1]
    # an attribute read at every query: back to the reference's fallback, the same graph
    graph.unreachable = "nearest_landmark"
    assert graph.plan(states, subgoals, euclidean, 8).path[0, :3].tolist() == [0, 1, 2]
    with pytest.raises(ValueError, match=r"`unreachable` must be one of \('nearest_landmark', 'subgoal'\), got 'x'"):
        graph.unreachable = "x"
    with pytest.raises(ValueError, match="unreachable"):
        LandmarkGraph(unreachable="nearest")
    assert "unreachable='nearest_landmark'" in repr(graph)


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


# ----------------------------------------------------------------------------- distances from the graph
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


def candidates(num=700, seed=0, obs_dim=5):
    gen = torch.Generator().manual_seed(seed)
    goals = torch.rand(num, 2, generator=gen) * 20
    states = torch.cat([goals, torch.randn(num, obs_dim - 2, generator=gen) * 0.1], -1)
    return states, goals


class Counting:
    """A distance that counts its pairs; ``with_autocast`` copies count separately, by dtype."""

    def __init__(self, fn, log=None, dtype=None):
        self.fn, self.dtype = fn, dtype
        self.log = log if log is not None else {}

    def __call__(self, states, goals):
        out = self.fn(states, goals)
        self.log[self.dtype] = self.log.get(self.dtype, 0) + out.numel()
        self.log.setdefault("autocast", set()).add((self.dtype, torch.is_autocast_enabled("cpu")))
        return out

    def with_autocast(self, dtype):
        return Counting(self.fn, self.log, dtype)


@pytest.mark.parametrize("proxy", ["goal", None])
def test_build_reuses_fps_distances_and_equals_recomputing(proxy):
    states, goals = candidates()
    counting = Counting(asymmetric)
    graph = LandmarkGraph(cutoff=4.0, max_landmarks=60, early_stop=0.0, fps_proxy=proxy)
    graph.build(states, goals, counting)
    fps_pairs = Counting(asymmetric)
    farthest_point_sampling(states, goals, fps_pairs, 60, early_stop=0.0, min_count=6, proxy=proxy)
    # after FPS only the pairs from later to earlier landmarks are evaluated, the diagonal is not
    assert counting.log[None] == fps_pairs.log[None] + 60 * 59 // 2
    recomputed = LandmarkGraph(cutoff=4.0).set_landmarks(
        graph.landmark_states, graph.landmark_goals, asymmetric
    )
    assert torch.equal(graph.landmark_distances, recomputed.landmark_distances)
    assert torch.equal(graph.edge_weights, recomputed.edge_weights)
    assert torch.equal(graph.shortest_distances, recomputed.shortest_distances)
    assert torch.equal(graph.next_hop, recomputed.next_hop)


def test_fps_options_change_the_cost_not_the_graph():
    states, goals = candidates(seed=1)
    graphs, pairs = {}, {}
    for name, options in {
        "default": {},
        "no_proxy": {"fps_proxy": None, "fps_lazy_batch": 256},
        "callable": {"fps_proxy": lambda a, b: (b - a).abs().sum(-1), "fps_lazy_batch": 7},
        "dense": {"fps_strategy": "dense"},
    }.items():
        counting = Counting(asymmetric)
        graphs[name] = LandmarkGraph(cutoff=4.0, max_landmarks=80, early_stop=0.0, **options)
        graphs[name].build(states, goals, counting)
        pairs[name] = counting.log[None]
    for name in ("no_proxy", "callable", "dense"):
        assert torch.equal(graphs[name].landmark_goals, graphs["default"].landmark_goals)
        assert torch.equal(graphs[name].shortest_distances, graphs["default"].shortest_distances)
    assert pairs["default"] < 0.5 * pairs["no_proxy"] < pairs["dense"]


def test_options_are_validated():
    with pytest.raises(ValueError, match="fps_proxy|proxy"):
        LandmarkGraph(fps_proxy="euclidean")
    for bad in (0, True, 1.5):
        with pytest.raises(ValueError, match="fps_lazy_batch"):
            LandmarkGraph(fps_lazy_batch=bad)
    for bad in (torch.float32, torch.float64, "bfloat16"):
        with pytest.raises(ValueError, match="build_autocast_dtype"):
            LandmarkGraph(build_autocast_dtype=bad)
        with pytest.raises(ValueError, match="build_autocast_dtype"):
            GraphPlanner(LandmarkGraph(build_autocast_dtype=bad), Counting(asymmetric), 2)
    # a distance without `with_autocast`: a clear error at construction, and at build time
    with pytest.raises(TypeError, match="with_autocast"):
        GraphPlanner(LandmarkGraph(build_autocast_dtype=torch.bfloat16), asymmetric, 2)
    states, goals = candidates(50)
    graph = LandmarkGraph(max_landmarks=10, build_autocast_dtype=torch.bfloat16)
    with pytest.raises(TypeError, match="with_autocast"):
        graph.build(states, goals, asymmetric)
    with pytest.raises(TypeError, match="with_autocast"):
        graph.set_landmarks(states[:5], goals[:5], asymmetric)


def test_reduced_precision_is_used_for_building_only():
    states, goals = candidates(300, seed=2)
    counting = Counting(asymmetric)
    graph = LandmarkGraph(cutoff=4.0, max_landmarks=30, early_stop=0.0, build_autocast_dtype=torch.bfloat16)
    planner = GraphPlanner(graph, counting, 2)
    planner.build(states, goals)
    assert counting.log.get(None, 0) == 0 and counting.log[torch.bfloat16] > 0
    built = dict(counting.log)
    planner.plan(states[:4], goals[-4:])
    planner.distance_from_graph(goals[:3])
    assert counting.log[torch.bfloat16] == built[torch.bfloat16] and counting.log[None] > 0
    planner.graph.set_landmarks(states[:8], goals[:8], counting)
    assert counting.log[torch.bfloat16] == built[torch.bfloat16] + 64
    # the build runs under autocast (one cast of the weights per build), the queries do not
    assert counting.log["autocast"] == {(torch.bfloat16, True), (None, False)}


def _trained_like_distance(obs_dim=5):
    torch.manual_seed(0)
    actor = LowLevelActor(obs_dim, 2, action_max=1.0, action_dim=2, num_cells=(64, 64), goal_indices=(0, 1))
    critic = GoalConditionedCritic(
        obs_dim, 2, action_max=1.0, action_dim=2, num_cells=(64, 64), relative_goal=True, goal_indices=(0, 1)
    )
    # regress the critic onto 3 x the Euclidean distance for a few steps: distances of a trained scale
    net = critic.module
    optim = torch.optim.Adam(net.parameters(), lr=3e-3)
    gen = torch.Generator().manual_seed(0)
    for _ in range(150):
        states, _ = candidates(256, seed=int(torch.randint(0, 10**6, (1,), generator=gen)))
        goals = torch.rand(256, 2, generator=gen) * 20
        with torch.no_grad():
            action = actor.module(states, goals)
        raw = net.ensemble(net.features(states, goals, action)).squeeze(-1)
        target = 3 * (goals - states[:, :2]).norm(dim=-1)
        loss = torch.nn.functional.smooth_l1_loss(torch.nn.functional.softplus(raw), target.expand_as(raw))
        optim.zero_grad()
        loss.backward()
        optim.step()
    return GoalDistance(actor, critic)


@pytest.mark.parametrize("twin", ["optimistic", "pessimistic"])
def test_goal_distance_graph_in_bfloat16_is_close_to_float32(twin):
    distance = _trained_like_distance()
    distance.twin = twin
    states, goals = candidates(800, seed=3)
    options = {"cutoff": 15.0, "max_landmarks": 60, "early_stop": 0.0}
    ref = GraphPlanner(LandmarkGraph(**options), distance, 2).build(states, goals)
    fast_graph = LandmarkGraph(build_autocast_dtype=torch.bfloat16, **options)
    fast = GraphPlanner(fast_graph, distance, 2).build(states, goals)
    # FPS may part ways at a near-tie, but the coverage agrees. With the pessimistic member of this network
    # the two runs share most landmarks too; with the optimistic one they part at the 3rd landmark (measured:
    # a near-tie), after which only 44 of 60 coincide while the coverage radius stays within 1%.
    shared = len(
        {tuple(g) for g in ref.landmark_goals.tolist()} & {tuple(g) for g in fast.landmark_goals.tolist()}
    )
    assert shared >= (0.8 if twin == "pessimistic" else 0.5) * ref.num_landmarks
    assert fast.graph.coverage_radius.item() == pytest.approx(ref.graph.coverage_radius.item(), rel=0.1)
    # on the same landmarks, the bfloat16 matrix is within 2% of the float32 one
    same = LandmarkGraph(cutoff=15.0, build_autocast_dtype=torch.bfloat16)
    same.set_landmarks(ref.landmark_states, ref.landmark_goals, distance)
    off_diag = ~torch.eye(ref.num_landmarks, dtype=torch.bool)
    ref_matrix = ref.graph.landmark_distances[off_diag]
    rel = (same.landmark_distances[off_diag] - ref_matrix).abs() / ref_matrix.clamp_min(1.0)
    assert rel.max() < 0.02 and rel.median() < 0.005
    assert (same.landmark_distances[off_diag] != ref_matrix).any()
    # plans on the bfloat16-built graph cost about the same (measured: median 0.04%); an edge whose
    # length sits at the cutoff may flip, which changes a few routes by more
    # (compared on the graphs FPS built when they share most landmarks, and on the same landmarks always)
    plans = [
        (ref.graph.plan(states[:64], goals[-64:], distance), same.plan(states[:64], goals[-64:], distance))
    ]
    if twin == "pessimistic":
        plans.append((ref.plan(states[:64], goals[-64:]), fast.plan(states[:64], goals[-64:])))
    for plan_ref, plan_fast in plans:
        both = torch.isfinite(plan_ref.cost) & torch.isfinite(plan_fast.cost)
        assert both.float().mean() > 0.9
        rel_cost = (plan_fast.cost[both] - plan_ref.cost[both]).abs() / plan_ref.cost[both].clamp_min(1.0)
        assert rel_cost.median() < 0.005 and (rel_cost < 0.01).float().mean() > 0.8


walled = line_of_sight_distance  # U-wall: unreachable subgoals


def rounded(states, goals):  # integer distances: ties everywhere
    return euclidean(states, goals).ceil()


DISTANCES = {"euclidean": euclidean, "rounded": rounded, "asymmetric": asymmetric, "walled": walled}


def random_graph(distance, gen, lattice=False, fixed_size=False):
    """A graph of 1-40 landmarks in [-2, 10]^2 (lattice points: many equal routes) with a random cutoff."""
    if lattice:
        side = int(torch.randint(2, 7, (), generator=gen))
        points = torch.cartesian_prod(torch.arange(side).float(), torch.arange(side).float()) * 2 - 2
        points = points[
            torch.randperm(points.shape[0], generator=gen)[
                : int(torch.randint(1, side * side + 1, (), generator=gen))
            ]
        ]
    else:
        num = int(torch.randint(1, 41, (), generator=gen))
        points = torch.rand(num, 2, generator=gen) * 12 - 2
    cutoff = float(torch.empty(()).uniform_(1.5, 6.0, generator=gen))
    graph = LandmarkGraph(cutoff=cutoff, max_landmarks=64, fixed_size=fixed_size)
    states = torch.cat([points, torch.zeros(points.shape[0], 2)], -1)  # obs_dim 4, goal = obs[:2]
    graph.set_landmarks(states, points.clone(), distance)
    return graph


def random_queries(num, gen):
    """States and subgoals in and around the maze (some far outside: start fallback, unreachable subgoals)."""
    states = torch.cat([torch.rand(num, 2, generator=gen) * 20 - 6, torch.randn(num, 2, generator=gen)], -1)
    subgoals = torch.rand(num, 2, generator=gen) * 20 - 6
    return states, subgoals


def assert_same_plan(got, expected):
    for field in ("path", "length", "budgets", "truncated", "cost", "reachable"):
        a, b = getattr(got, field), getattr(expected, field)
        assert a.shape == b.shape and a.dtype == b.dtype, field
        assert torch.equal(a, b), field


@pytest.mark.parametrize("name", sorted(DISTANCES))
def test_unreachable_rule_changes_only_the_unreachable_rows(name):
    """Over random graphs and queries (ties, islands, walls, capturable or not): with ``unreachable="subgoal"``
    every reachable row's plan is the reference's, and every unreachable row is the subgoal alone (no landmark,
    its budget the state's own distance to the subgoal)."""
    distance = DISTANCES[name]
    gen = torch.Generator().manual_seed(200 + len(name))
    changed = 0
    for trial in range(30):
        graph = random_graph(distance, gen, lattice=trial % 2 == 1)
        states, subgoals = random_queries(int(torch.randint(1, 24, (), generator=gen)), gen)
        for capturable in (False, True):
            graph.unreachable = "nearest_landmark"
            reference = graph.plan(states, subgoals, distance, 5, capturable=capturable)
            graph.unreachable = "subgoal"
            plan = graph.plan(states, subgoals, distance, 5, capturable=capturable)
            same = reference.reachable
            assert torch.equal(plan.reachable, same) and torch.equal(plan.cost, reference.cost)
            for field in ("path", "length", "budgets", "truncated"):
                assert torch.equal(getattr(plan, field)[same], getattr(reference, field)[same]), field
            unreachable = ~same
            assert (plan.length[unreachable] == 0).all() and (plan.path[unreachable] == -1).all()
            assert not plan.truncated[unreachable].any()
            torch.testing.assert_close(
                plan.budgets[unreachable, 0], distance(states[unreachable], subgoals[unreachable]), rtol=0, atol=0
            )
            assert torch.isinf(plan.budgets[unreachable, 1:]).all()
            changed += int((unreachable & (reference.length > 0)).sum())
    assert changed > 0  # some rows took the reference's fallback landmark


@pytest.mark.parametrize("name", sorted(DISTANCES))
def test_capturable_plans_equal_the_plans_on_random_graphs(name):
    distance = DISTANCES[name]
    gen = torch.Generator().manual_seed(len(name))
    kinds = {"fallback": 0, "graph": 0, "truncated": 0}
    for trial in range(60):
        graph = random_graph(distance, gen, lattice=trial % 2 == 1)
        states, subgoals = random_queries(int(torch.randint(1, 24, (), generator=gen)), gen)
        for max_path_length in (1, 2, 5, 32):
            plan = graph.plan(states, subgoals, distance, max_path_length)
            captured = graph.plan(states, subgoals, distance, max_path_length, capturable=True)
            assert_same_plan(captured, plan)
            kinds["graph"] += int((plan.reachable & (plan.length > 0)).sum())
            kinds["fallback"] += int((~plan.reachable & (plan.length > 0)).sum())
            kinds["truncated"] += int(plan.truncated.sum())
    assert all(count > 0 for count in kinds.values()), kinds  # every branch was exercised


@pytest.mark.parametrize("name", sorted(DISTANCES))
def test_fixed_size_capturable_plans_equal_the_plans_on_random_graphs(name):
    """A ``fixed_size`` graph plans on its padded copies (64 rows, 1-40 landmarks; also exactly full, and
    cleared): the same plans as the graph's own buffers planned on by the host-branching path."""
    distance = DISTANCES[name]
    gen = torch.Generator().manual_seed(100 + len(name))
    for trial in range(40):
        graph = random_graph(distance, gen, lattice=trial % 2 == 1, fixed_size=True)
        if trial % 10 == 9:  # exactly max_landmarks landmarks: no padding row
            graph.max_landmarks = graph.num_landmarks
            graph.set_landmarks(graph.landmark_states, graph.landmark_goals, distance)
        states, subgoals = random_queries(int(torch.randint(1, 24, (), generator=gen)), gen)
        assert graph.planning_tensors(capturable=True).valid.shape == (graph.max_landmarks,)
        for max_path_length in (1, 3, 32):
            assert_same_plan(
                graph.plan(states, subgoals, distance, max_path_length, capturable=True),
                graph.plan(states, subgoals, distance, max_path_length),
            )
        if trial % 4 == 0:  # cleared: every row padding, the plans of no graph
            graph.clear()
            assert graph.planning_tensors(capturable=True) is not None and graph.planning_tensors() is None
            assert_same_plan(
                graph.plan(states, subgoals, distance, 3, capturable=True),
                graph.plan(states, subgoals, distance, 3),
            )


def test_fixed_size_storage_is_updated_in_place_and_not_checkpointed():
    """Rebuilds with other landmark counts and ``clear()`` write into the same tensors (what a CUDA graph
    captured after the first build reads); the padding is inert; ``state_dict`` is that of a plain graph and
    a load refreshes the copies; too many landmarks and a non-bool flag are refused."""
    gen = torch.Generator().manual_seed(0)
    graph = LandmarkGraph(cutoff=3.0, max_landmarks=30, fixed_size=True)
    assert graph.planning_tensors(capturable=True) is None  # nothing to copy before the first build
    _set_random_landmarks(graph, euclidean, gen, 10)
    first = graph.planning_tensors(capturable=True)
    pointers = [t.data_ptr() for t in first]
    for num in (30, 4, 0, 17):
        if num:
            _set_random_landmarks(graph, euclidean, gen, num)
        else:
            graph.clear()
        tensors = graph.planning_tensors(capturable=True)
        assert [t.data_ptr() for t in tensors] == pointers
        assert int(tensors.version) == int(graph.version)
        assert tensors.valid.tolist() == [True] * num + [False] * (30 - num)
        if num:
            own = graph.planning_tensors()
            for field in ("states", "goals"):
                assert torch.equal(getattr(tensors, field)[:num], getattr(own, field)), field
            for field in ("distances", "shortest", "next_hop", "hop_counts"):
                assert torch.equal(getattr(tensors, field)[:num, :num], getattr(own, field)), field
            pad = tensors.shortest[num:]
            assert torch.isinf(pad[:, :num]).all() and (tensors.next_hop[num:, :num] == -1).all()
    state = graph.state_dict()
    assert not any("fixed" in key for key in state)
    assert state.keys() == LandmarkGraph().state_dict().keys()
    fresh = LandmarkGraph(cutoff=3.0, max_landmarks=30, fixed_size=True)
    fresh.load_state_dict(state)
    states, subgoals = random_queries(12, gen)
    assert_same_plan(
        fresh.plan(states, subgoals, euclidean, 4, capturable=True),
        graph.plan(states, subgoals, euclidean, 4),
    )
    with pytest.raises(ValueError, match="at most max_landmarks=30 landmarks, got 31"):
        _set_random_landmarks(graph, euclidean, gen, 31)
    with pytest.raises(TypeError, match="`fixed_size` must be a bool, got 1"):
        LandmarkGraph(fixed_size=1)


@pytest.mark.parametrize("name", sorted(DISTANCES))
def test_reserved_graph_plans_like_no_graph_and_its_builds_keep_the_storage(name):
    """``reserve`` before the first build: capturable plans on the all-padding copies equal the plans of a graph
    without landmarks (random queries, three path widths); every later build, clear and load writes into the
    storage reserved (what a policy captured before the first build reads)."""
    distance = DISTANCES[name]
    gen = torch.Generator().manual_seed(300 + len(name))
    graph = LandmarkGraph(cutoff=3.0, max_landmarks=30, fixed_size=True)
    assert graph.reserve(4, 2) is graph and graph.num_landmarks == 0 and graph.planning_tensors() is None
    tensors = graph.planning_tensors(capturable=True)
    assert tensors.valid.tolist() == [False] * 30 and int(tensors.version) == int(graph.version) == 0
    assert tensors.states.shape == (30, 4) and tensors.goals.shape == (30, 2)
    empty = LandmarkGraph(cutoff=3.0, max_landmarks=30)
    for _ in range(10):
        states, subgoals = random_queries(int(torch.randint(1, 24, (), generator=gen)), gen)
        for max_path_length in (1, 3, 32):
            expected = empty.plan(states, subgoals, distance, max_path_length)
            assert_same_plan(
                graph.plan(states, subgoals, distance, max_path_length, capturable=True), expected
            )
            assert_same_plan(graph.plan(states, subgoals, distance, max_path_length), expected)
    pointers = [t.data_ptr() for t in tensors]
    for num in (12, 0, 30, 5):
        _set_random_landmarks(graph, distance, gen, num) if num else graph.clear()
        now = graph.planning_tensors(capturable=True)
        assert [t.data_ptr() for t in now] == pointers and now.valid.tolist() == [True] * num + [False] * (
            30 - num
        )
        assert int(now.version) == int(graph.version)
    assert graph.reserve(4, 2) is graph and graph.num_landmarks == 5  # landmarks kept
    fresh = LandmarkGraph(cutoff=3.0, max_landmarks=30, fixed_size=True).reserve(4, 2)
    reserved = [t.data_ptr() for t in fresh.planning_tensors(capturable=True)]
    fresh.load_state_dict(graph.state_dict())  # a resumed run: the checkpoint's graph in the reserved storage
    assert [t.data_ptr() for t in fresh.planning_tensors(capturable=True)] == reserved
    states, subgoals = random_queries(16, gen)
    assert_same_plan(
        fresh.plan(states, subgoals, distance, 4, capturable=True), graph.plan(states, subgoals, distance, 4)
    )


@pytest.mark.parametrize("name", sorted(DISTANCES))
def test_capturable_distance_from_graph_is_the_exact_minimum(name):
    """``distance_from_graph(capturable=True)`` on a fixed-size graph (reserved, then 1-40 landmarks): the exact
    minimum of the eager query, the same answers as the ``at_most`` query at its threshold, ``inf`` without
    landmarks; a graph without fixed-size tensors is refused."""
    distance = DISTANCES[name]
    gen = torch.Generator().manual_seed(500 + len(name))
    graph = LandmarkGraph(cutoff=3.0, max_landmarks=48, fixed_size=True).reserve(4, 2)
    goals = torch.rand(2, 7, 2, generator=gen) * 20 - 6
    assert torch.isinf(graph.distance_from_graph(goals, distance, capturable=True)).all()
    assert graph.distance_from_graph(goals, distance, capturable=True).shape == (2, 7)
    for _ in range(12):
        _set_random_landmarks(graph, distance, gen, int(torch.randint(1, 41, (), generator=gen)))
        goals = torch.rand(int(torch.randint(1, 60, (), generator=gen)), 2, generator=gen) * 20 - 6
        exact = graph.distance_from_graph(goals, distance)
        captured = graph.distance_from_graph(goals, distance, capturable=True)
        assert torch.equal(captured, exact)
        for threshold in (0.5, 2.0, 6.0):
            bounded = graph.distance_from_graph(goals, distance, at_most=threshold, candidates=4)
            assert torch.equal(captured > threshold, bounded > threshold)
    with pytest.raises(RuntimeError, match="needs a fixed_size graph whose planning tensors exist"):
        LandmarkGraph().distance_from_graph(goals, distance, capturable=True)
    with pytest.raises(ValueError, match="`goals` have 3 features but the landmark goals have 2"):
        graph.distance_from_graph(torch.zeros(4, 3), distance, capturable=True)


def test_reserve_refusals_and_reallocation():
    with pytest.raises(ValueError, match="fixed_size=True; this graph has fixed_size=False"):
        LandmarkGraph().reserve(4, 2)
    for dims, name in (((0, 2), "obs_dim"), ((4, 2.0), "goal_dim"), ((True, 2), "obs_dim")):
        with pytest.raises(ValueError, match=f"`{name}` must be a positive int"):
            LandmarkGraph(fixed_size=True).reserve(*dims)
    graph = LandmarkGraph(cutoff=3.0, max_landmarks=20, fixed_size=True)
    _set_random_landmarks(graph, euclidean, torch.Generator().manual_seed(0), 8)
    with pytest.raises(ValueError, match=r"reserve\(3, 2\): the graph already holds landmarks with 4 state"):
        graph.reserve(3, 2)
    # reserved for other features or another dtype than the builds write: the build reallocates (documented)
    other = LandmarkGraph(cutoff=3.0, max_landmarks=20, fixed_size=True).reserve(4, 2, dtype=torch.float64)
    assert other.planning_tensors(capturable=True).states.dtype == torch.float64
    before = other.planning_tensors(capturable=True).states.data_ptr()
    _set_random_landmarks(other, euclidean, torch.Generator().manual_seed(0), 8)
    after = other.planning_tensors(capturable=True).states
    assert after.dtype == torch.float32 and after.data_ptr() != before


def test_capturable_plans_without_a_graph_and_for_no_query():
    graph = LandmarkGraph(cutoff=3.0)
    states, subgoals = random_queries(5, torch.Generator().manual_seed(0))
    assert_same_plan(
        graph.plan(states, subgoals, euclidean, 4, capturable=True),
        graph.plan(states, subgoals, euclidean, 4),
    )
    graph = random_graph(euclidean, torch.Generator().manual_seed(1))
    empty = graph.plan(states[:0], subgoals[:0], euclidean, 4, capturable=True)
    assert_same_plan(empty, graph.plan(states[:0], subgoals[:0], euclidean, 4))
    assert empty.path.shape == (0, 4)


def test_capturable_needs_a_max_path_length():
    graph = random_graph(euclidean, torch.Generator().manual_seed(0))
    states, subgoals = random_queries(2, torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="`capturable=True` needs `max_path_length`"):
        graph.plan(states, subgoals, euclidean, capturable=True)
    sources = torch.zeros(2, dtype=torch.int64)
    with pytest.raises(ValueError, match="`capturable=True` needs `max_length`"):
        reconstruct_paths(graph.next_hop, graph.hop_counts, sources, sources, capturable=True)
    with pytest.raises(TypeError, match="`capturable` must be a bool, got 1"):
        GraphPlanner(graph, euclidean, 2, capturable=1)
    with pytest.raises(TypeError, match="`plan_on_demand` must be a bool, got 'yes'"):
        GraphPlanner(graph, euclidean, 2, capturable=True, plan_on_demand="yes")


def _set_random_landmarks(graph, distance, gen, num):
    points = torch.rand(num, 2, generator=gen) * 12 - 2
    graph.set_landmarks(torch.cat([points, torch.zeros(num, 2)], -1), points, distance)
