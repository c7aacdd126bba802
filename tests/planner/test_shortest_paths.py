"""All-pairs shortest paths and path read-out against scipy / networkx, under ties and float rounding:
routes reach their target and cost what is reported.

Property tests over thousands of random graphs (sparse, lattices with straight-line distances, integer and
rounded weights with many ties and zero-weight edges, very large weights, ``inf`` entries, disconnected and
degenerate graphs) against scipy / networkx, the reproductions of stale hop counts and the same on
:class:`LandmarkGraph` / :class:`GraphPlanner`; the capturable read-out (``max_length`` columns)."""

import io
import math

import networkx as nx
import numpy as np
import pytest
import torch
from scipy.sparse.csgraph import csgraph_from_dense, shortest_path
from tensordict import TensorDict

from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph, floyd_warshall, reconstruct_paths
from torchrl_dhrl.planner.shortest_paths import count_hops

INF = math.inf


def random_weights(n, density, seed, zero_fraction=0.0):
    gen = torch.Generator().manual_seed(seed)
    weights = torch.rand(n, n, generator=gen) * 10 + 0.1
    weights[torch.rand(n, n, generator=gen) < zero_fraction] = 0.0
    weights[torch.rand(n, n, generator=gen) > density] = INF
    weights.fill_diagonal_(0.0)
    return weights


def scipy_distances(weights):
    dense = weights.double().numpy().copy()
    # scipy treats 0 as "no edge" in dense input: encode the graph explicitly
    rows, cols = np.nonzero(np.isfinite(dense) & ~np.eye(len(dense), dtype=bool))
    graph = nx.DiGraph()
    graph.add_nodes_from(range(len(dense)))
    graph.add_weighted_edges_from((int(i), int(j), dense[i, j]) for i, j in zip(rows, cols, strict=True))
    matrix = nx.to_scipy_sparse_array(graph, nodelist=range(len(dense)), weight="weight")
    # explicit zeros of a sparse array are kept as edges by csgraph
    return shortest_path(matrix, method="D", directed=True), graph


@pytest.mark.parametrize("n,density,seed", [(50, 0.1, 0), (120, 0.05, 1), (200, 0.03, 2), (500, 0.01, 3)])
def test_distances_match_scipy_and_paths_are_valid(n, density, seed):
    weights = random_weights(n, density, seed)
    sp = floyd_warshall(weights)
    expected, graph = scipy_distances(weights)
    got = sp.distances.double().numpy()
    assert np.array_equal(np.isinf(got), np.isinf(expected))
    finite = np.isfinite(expected)
    np.testing.assert_allclose(got[finite], expected[finite], rtol=1e-5, atol=1e-4)
    # some pairs must be unreachable and some multi-hop for the test to mean something
    assert (~finite).any() and (sp.hop_counts > 2).any()

    # every reachable pair: following next-hop gives a path of edges whose weights sum to the distance
    src, dst = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
    src, dst = src.reshape(-1), dst.reshape(-1)
    paths, lengths = reconstruct_paths(sp.next_hop, sp.hop_counts, src, dst)
    reachable = torch.from_numpy(finite.reshape(-1))
    assert torch.equal(lengths > 0, reachable)
    cols = torch.arange(paths.shape[1])
    valid_hop = (cols[1:].unsqueeze(0) < lengths.unsqueeze(1)) & reachable.unsqueeze(1)
    hop_weights = weights[paths[:, :-1].clamp_min(0), paths[:, 1:].clamp_min(0)]
    assert torch.isfinite(hop_weights[valid_hop]).all()  # consecutive nodes are real edges
    summed = torch.where(valid_hop, hop_weights, torch.zeros(())).sum(-1)
    torch.testing.assert_close(summed[reachable], sp.distances.reshape(-1)[reachable], rtol=1e-5, atol=1e-4)
    rows = torch.arange(n * n)
    last = paths[rows, (lengths - 1).clamp_min(0)]
    assert torch.equal(paths[reachable, 0], src[reachable])
    assert torch.equal(last[reachable], dst[reachable])
    assert (paths[~reachable] == -1).all()
    # spot-check against networkx Dijkstra path weights
    for i, j in [(0, n - 1), (1, n // 2), (n // 3, 2)]:
        if finite[i, j]:
            assert nx.dijkstra_path_length(graph, i, j) == pytest.approx(float(sp.distances[i, j]), rel=1e-5)


def test_zero_weight_edges_and_ties_give_acyclic_paths():
    weights = random_weights(80, 0.08, seed=5, zero_fraction=0.05)
    sp = floyd_warshall(weights)
    expected, _ = scipy_distances(weights)
    finite = np.isfinite(expected)
    np.testing.assert_allclose(sp.distances.double().numpy()[finite], expected[finite], rtol=1e-5, atol=1e-4)
    src, dst = torch.nonzero(torch.from_numpy(finite), as_tuple=True)
    paths, lengths = reconstruct_paths(sp.next_hop, sp.hop_counts, src, dst)
    # a path reaches its target, with no repeated node (no cycle through zero-weight edges)
    for row in range(0, len(src), 97):
        nodes = paths[row, : lengths[row]].tolist()
        assert nodes[-1] == int(dst[row]) and len(set(nodes)) == len(nodes)


def test_small_graph_by_hand():
    w = torch.tensor([[0.0, 1.0, 5.0, INF], [INF, 0.0, 1.0, INF], [INF, INF, 0.0, 1.0], [INF, INF, INF, 0.0]])
    sp = floyd_warshall(w)
    assert sp.distances[0].tolist() == [0.0, 1.0, 2.0, 3.0]
    assert sp.next_hop[0].tolist() == [0, 1, 1, 1]
    assert sp.hop_counts[0].tolist() == [0, 1, 2, 3]
    assert sp.next_hop[3, 0].item() == -1 and math.isinf(sp.distances[3, 0])
    paths, lengths = reconstruct_paths(sp.next_hop, sp.hop_counts, torch.tensor([0, 0]), torch.tensor([3, 0]))
    assert paths.tolist() == [[0, 1, 2, 3], [0, -1, -1, -1]] and lengths.tolist() == [4, 1]
    paths, lengths = reconstruct_paths(sp.next_hop, sp.hop_counts, torch.tensor([0]), torch.tensor([3]), 2)
    assert paths.tolist() == [[0, 1]] and lengths.tolist() == [2]


def test_empty_graph_and_errors():
    sp = floyd_warshall(torch.zeros(0, 0))
    assert sp.distances.shape == (0, 0) and sp.next_hop.shape == (0, 0)
    with pytest.raises(ValueError, match="square"):
        floyd_warshall(torch.zeros(2, 3))
    with pytest.raises(ValueError, match=">= 0"):
        floyd_warshall(torch.tensor([[0.0, -1.0], [1.0, 0.0]]))
    with pytest.raises(ValueError, match="NaN"):
        floyd_warshall(torch.tensor([[0.0, math.nan], [1.0, 0.0]]))
    with pytest.raises(TypeError):
        floyd_warshall(torch.zeros(2, 2, dtype=torch.int64))


KINDS = ("sparse", "integer", "rounded", "lattice", "large", "disconnected")


# ----------------------------------------------------------------------------- graphs
def _mask(weights, density, gen):
    weights[torch.rand(weights.shape, generator=gen) > density] = INF
    return weights


def lattice_weights(gen, n_max=30):
    """Grid points (some removed, shuffled) with Euclidean edge lengths under a cutoff."""
    rows, cols = (int(v) for v in torch.randint(1, 7, (2,), generator=gen))
    points = torch.cartesian_prod(torch.arange(rows), torch.arange(cols)).double()
    removed = int(torch.randint(0, 4, (), generator=gen))
    keep = torch.randperm(points.shape[0], generator=gen)[: max(1, points.shape[0] - removed)]
    points = points[keep][:n_max] / float(torch.empty(()).uniform_(0.03, 1.0, generator=gen))
    spacing = torch.pdist(points).min().item() if points.shape[0] > 1 else 1.0
    dist = torch.cdist(points, points)
    cutoff = spacing * float(torch.empty(()).uniform_(1.01, 3.0, generator=gen))
    return torch.where(dist < cutoff, dist, torch.full_like(dist, INF))


def random_graph(kind, gen):
    n = int(torch.randint(1, 31, (), generator=gen))
    density = float(torch.empty(()).uniform_(0.03, 0.7, generator=gen))
    if kind == "sparse":
        weights = _mask(torch.rand(n, n, generator=gen, dtype=torch.float64) * 10 + 0.01, density, gen)
    elif kind == "integer":  # zeros included: zero-weight edges and cycles, ties everywhere
        weights = _mask(torch.randint(0, 5, (n, n), generator=gen).double(), density, gen)
    elif kind == "rounded":
        weights = (torch.rand(n, n, generator=gen, dtype=torch.float64) * 5).round(decimals=1)
        weights = _mask(weights, density, gen)
    elif kind == "lattice":
        weights = lattice_weights(gen)
    elif kind == "large":  # 1e8-scale edges next to unit edges: the unit edges vanish in float32 sums
        small = torch.randint(0, 4, (n, n), generator=gen).double()
        big = 1e8 * torch.randint(1, 3, (n, n), generator=gen).double() + small
        weights = torch.where(torch.rand(n, n, generator=gen) < 0.3, big, small)
        weights = _mask(weights, density, gen)
    elif kind == "disconnected":  # two components (no edge between them), shuffled
        a, b = random_graph("rounded", gen), random_graph("sparse", gen)
        weights = torch.full((a.shape[0] + b.shape[0],) * 2, INF, dtype=torch.float64)
        weights[: a.shape[0], : a.shape[0]] = a
        weights[a.shape[0] :, a.shape[0] :] = b
        perm = torch.randperm(weights.shape[0], generator=gen)
        weights = weights[perm][:, perm]
    else:
        raise ValueError(kind)
    weights = weights.clone()
    weights.fill_diagonal_(0.0)
    return weights


def reference_distances(weights):
    """scipy's Dijkstra in float64 on the same (possibly float32-rounded) weights; zeros are edges."""
    dense = weights.double().numpy().copy()
    np.fill_diagonal(dense, INF)
    graph = csgraph_from_dense(dense, null_value=INF)
    return shortest_path(graph, method="D", directed=True)


def tolerance(dtype, n, scale):
    """Float rounding of sums of up to ``n`` terms of size up to ``scale``."""
    return 8 * max(n, 1) * torch.finfo(dtype).eps * max(scale, 1.0)


def assert_shortest_paths_are_sound(weights):
    """Every reachable pair: the route starts at the source, ends at the target, follows edges, visits
    no node twice, has ``hop_counts + 1`` nodes and costs the reported distance, which is the true
    shortest distance; unreachable pairs: ``inf``, ``-1``, empty route."""
    n = weights.shape[0]
    sp = floyd_warshall(weights)
    expected = reference_distances(weights)
    got = sp.distances.double().numpy()
    finite = np.isfinite(expected)
    assert np.array_equal(np.isfinite(got), finite)
    scale = float(np.abs(expected[finite]).max()) if finite.any() else 1.0
    tol = tolerance(weights.dtype, n, scale)
    np.testing.assert_allclose(got[finite], expected[finite], rtol=0, atol=tol)
    reachable = torch.from_numpy(finite)
    assert torch.equal(sp.next_hop >= 0, reachable)
    assert torch.equal(sp.next_hop.diagonal(), torch.arange(n)) and (sp.hop_counts.diagonal() == 0).all()
    assert (sp.hop_counts[~reachable] == 0).all()
    assert torch.equal(count_hops(sp.next_hop), sp.hop_counts)

    src, dst = (t.reshape(-1) for t in torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij"))
    paths, lengths = reconstruct_paths(sp.next_hop, sp.hop_counts, src, dst)
    flat_reach = reachable.reshape(-1)
    assert torch.equal(lengths, torch.where(flat_reach, sp.hop_counts.reshape(-1) + 1, 0))
    rows = torch.arange(n * n)
    assert torch.equal(paths[flat_reach, 0], src[flat_reach])
    assert torch.equal(paths[rows, (lengths - 1).clamp_min(0)][flat_reach], dst[flat_reach])
    cols = torch.arange(paths.shape[1])
    valid = cols.unsqueeze(0) < lengths.unsqueeze(1)
    assert (paths[~valid] == -1).all() and (paths[valid] >= 0).all()
    # no node twice on a route (no cycle, no padding with copies of the target)
    visits = torch.zeros(n * n, n, dtype=torch.int64).scatter_add_(1, paths.clamp_min(0), valid.long())
    assert visits.max() <= 1
    # consecutive nodes are edges and the route costs the reported distance
    hop = valid[:, 1:]
    hop_weights = weights.double()[paths[:, :-1].clamp_min(0), paths[:, 1:].clamp_min(0)]
    assert torch.isfinite(hop_weights[hop]).all()
    cost = torch.where(hop, hop_weights, torch.zeros((), dtype=torch.float64)).sum(-1)
    torch.testing.assert_close(
        cost[flat_reach], sp.distances.double().reshape(-1)[flat_reach], rtol=0, atol=tol
    )
    torch.testing.assert_close(
        cost[flat_reach], torch.from_numpy(expected).reshape(-1)[flat_reach], rtol=0, atol=tol
    )
    return sp


# ----------------------------------------------------------------------------- property tests
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("kind", KINDS)
def test_random_graphs_give_sound_routes(kind, dtype):
    gen = torch.Generator().manual_seed(KINDS.index(kind) * 10 + (dtype == torch.float64))
    multi_hop = 0
    for _ in range(300):
        weights = random_graph(kind, gen).to(dtype)
        sp = assert_shortest_paths_are_sound(weights)
        multi_hop += bool((sp.hop_counts > 2).any())
    assert multi_hop > 50  # the graphs exercise real routes


def test_networkx_agrees_on_a_sample_of_tie_heavy_graphs():
    gen = torch.Generator().manual_seed(123)
    for graph_index in range(60):
        weights = random_graph(KINDS[graph_index % len(KINDS)], gen).float()
        sp = floyd_warshall(weights)
        n = weights.shape[0]
        g = nx.DiGraph()
        g.add_nodes_from(range(n))
        rows, cols = torch.nonzero(torch.isfinite(weights) & ~torch.eye(n, dtype=torch.bool), as_tuple=True)
        edges = zip(rows.tolist(), cols.tolist(), strict=True)
        g.add_weighted_edges_from((i, j, float(weights[i, j])) for i, j in edges)
        expected = dict(nx.all_pairs_dijkstra_path_length(g))
        scale = max([1.0] + [v for d in expected.values() for v in d.values()])
        tol = tolerance(torch.float32, n, scale)
        for i in range(n):
            for j in range(n):
                if j in expected[i]:
                    assert abs(float(sp.distances[i, j]) - expected[i][j]) <= tol
                else:
                    assert math.isinf(sp.distances[i, j]) and sp.next_hop[i, j] == -1


@pytest.mark.parametrize(
    "weights",
    [
        [[0.0]],
        [[5.0]],  # the diagonal counts as 0
        [[0.0, 1.0], [INF, 0.0]],
        [[0.0, INF], [INF, 0.0]],
        [[0.0, 0.0], [0.0, 0.0]],  # zero-weight cycle
        [[0.0, 1e8], [1.0, 0.0]],
        [[0.0, 3.0], [2.0, 0.0]],
    ],
)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_degenerate_graphs(weights, dtype):
    weights = torch.tensor(weights, dtype=dtype)
    assert_shortest_paths_are_sound(weights)


# ----------------------------------------------------------------------------- reproductions
def test_equal_length_routes_reproduction():
    # 3 -> 0 -> 1 and 3 -> 0 -> 2 -> 1 both cost 1.8: the first one is kept (2 hops, not 3)
    weights = torch.tensor([[0, 1.2, 0.3, INF], [0, 0, INF, INF], [0.4, 0.9, 0, 0], [0.6, INF, INF, 0]])
    sp = assert_shortest_paths_are_sound(weights)
    paths, lengths = reconstruct_paths(sp.next_hop, sp.hop_counts, torch.tensor([3]), torch.tensor([1]))
    assert sp.hop_counts[3, 1].item() == 2
    assert paths.tolist() == [[3, 0, 1]] and lengths.tolist() == [3]


def test_large_weights_reproduction():
    # 1e8 + 1 + 1 and 1e8 + 3 are both 1e8 in float32: the route 0 -> 3 must still end at 3
    weights = torch.tensor([[0, 1e8, INF, INF], [INF, 0, 1, 3], [INF, INF, 0, 1], [INF, INF, INF, 0]])
    sp = assert_shortest_paths_are_sound(weights)
    paths, lengths = reconstruct_paths(sp.next_hop, sp.hop_counts, torch.tensor([0]), torch.tensor([3]))
    assert paths.tolist() == [[0, 1, 2, 3]] and lengths.tolist() == [4]


def test_count_hops_rejects_cycles_and_bad_tables():
    assert count_hops(torch.zeros(0, 0, dtype=torch.int64)).shape == (0, 0)
    cycle = torch.tensor([[0, 1, 1], [0, 1, 0], [-1, -1, 2]])  # to 2: 0 -> 1 -> 0 -> ... never reaches it
    with pytest.raises(ValueError, match="cycle"):
        count_hops(cycle)
    with pytest.raises(ValueError, match=r"next_hop\[j, j\] = j"):
        count_hops(torch.tensor([[1, 1], [0, 1]]))
    with pytest.raises(ValueError, match="square"):
        count_hops(torch.zeros(2, 3, dtype=torch.int64))


# ----------------------------------------------------------------------------- planning on lattices
SPEED = 0.07  # goal units per step: lattice neighbours 14.3 steps apart, diagonals 20.2, cutoff 30


def lattice_distance(states, goals):
    return (goals - states[..., :2]).norm(dim=-1) / SPEED


def assert_plans_are_sound(graph, states, subgoals, plan):
    """Reachable rows: an edge chain from a connected entry landmark to an exit landmark within the
    cutoff of the subgoal (or the direct edge), no landmark twice, a cost equal to the sum of the
    route's hops and of its budgets, and that cost the shortest one (float64 reference)."""
    num, cutoff = states.shape[0], graph.cutoff
    rows = torch.arange(num)
    start_cost = graph.start_costs(states, lattice_distance)  # [B, K]
    exit_all = lattice_distance(graph.landmark_states.unsqueeze(0), subgoals.unsqueeze(1))  # [B, K]
    straight = lattice_distance(states, subgoals)
    reachable, length = plan.reachable, plan.length
    valid = torch.arange(plan.path.shape[1]).unsqueeze(0) < length.unsqueeze(1)
    assert (plan.path[~valid] == -1).all()
    path = plan.path.clamp_min(0)
    visits = torch.zeros(num, graph.num_landmarks, dtype=torch.int64).scatter_add_(1, path, valid.long())
    assert visits.max() <= 1  # no landmark twice (no padding with copies of the last one)
    via = reachable & (length > 0)
    direct = reachable & (length == 0)
    assert (straight[direct] < cutoff).all()
    first = path[:, 0]
    last = path.gather(1, (length - 1).clamp_min(0).unsqueeze(1)).squeeze(1)
    hop_valid = valid[:, 1:]
    hops = graph.edge_weights[path[:, :-1], path[:, 1:]]
    assert torch.isfinite(start_cost[rows, first][via]).all()
    assert torch.isfinite(hops[hop_valid & via.unsqueeze(1)]).all()
    assert (exit_all[rows, last][via] < cutoff).all()  # the route ends next to the subgoal
    route = start_cost[rows, first] + torch.where(hop_valid, hops, 0.0).sum(-1) + exit_all[rows, last]
    route = torch.where(via, route, straight)
    torch.testing.assert_close(route[reachable], plan.cost[reachable], rtol=1e-5, atol=1e-4)
    columns = torch.arange(plan.budgets.shape[1]).unsqueeze(0)
    budgets = torch.where(columns <= length.unsqueeze(1), plan.budgets, 0.0).sum(-1)
    torch.testing.assert_close(budgets[reachable], plan.cost[reachable], rtol=1e-5, atol=1e-4)
    # the shortest cost over entry, graph (scipy, float64) and exit, or the direct edge
    table = torch.from_numpy(reference_distances(graph.edge_weights))
    exit_cost = torch.where(exit_all < cutoff, exit_all, INF).double()
    best = (start_cost.double().unsqueeze(2) + table + exit_cost.unsqueeze(1)).flatten(1).min(-1).values
    best = torch.minimum(best, torch.where(straight < cutoff, straight, INF).double())
    assert torch.equal(torch.isfinite(best), reachable)
    torch.testing.assert_close(plan.cost[reachable].double(), best[reachable], rtol=1e-5, atol=1e-4)


#: 11 landmarks of a 5 x 5 lattice where the stale hop count cut the route one landmark short
LATTICE = [
    [3.0, 4.0], [4.0, 3.0], [3.0, 0.0], [0.0, 2.0], [0.0, 4.0], [2.0, 4.0],
    [3.0, 1.0], [1.0, 1.0], [1.0, 3.0], [1.0, 2.0], [1.0, 0.0],
]  # fmt: skip
QUERY = ([2.9916915893554688, -0.05607754737138748], [3.9980673789978027, 3.0125889778137207])


def test_lattice_plan_reaches_the_subgoal_reproduction():
    points = torch.tensor(LATTICE)
    graph = LandmarkGraph(cutoff=30.0, max_landmarks=64)
    graph.set_landmarks(points, points.clone(), lattice_distance)
    states, subgoals = torch.tensor([QUERY[0]]), torch.tensor([QUERY[1]])
    plan = graph.plan(states, subgoals, lattice_distance)
    assert plan.reachable.item() and not plan.truncated.item()
    assert_plans_are_sound(graph, states, subgoals, plan)
    # through 10, 7, 9, 8, 5 and then 0 (at one lattice step from the subgoal), not ending at 5
    path = plan.path[0, : plan.length[0]].tolist()
    assert path[-1] == 0 and plan.length.item() == 6


def test_random_lattice_plans_are_sound():
    gen = torch.Generator().manual_seed(1)
    for _ in range(150):
        side = int(torch.randint(3, 6, (), generator=gen))
        points = torch.cartesian_prod(torch.arange(side).float(), torch.arange(side).float())
        num = int(torch.randint(6, points.shape[0] + 1, (), generator=gen))
        points = points[torch.randperm(points.shape[0], generator=gen)[:num]]
        graph = LandmarkGraph(cutoff=30.0, max_landmarks=64)
        graph.set_landmarks(points, points.clone(), lattice_distance)
        pairs = torch.cartesian_prod(torch.arange(num), torch.arange(num))
        states = points[pairs[:, 0]] + torch.randn(pairs.shape[0], 2, generator=gen) * 0.05
        subgoals = points[pairs[:, 1]] + torch.randn(pairs.shape[0], 2, generator=gen) * 0.05
        plan = graph.plan(states, subgoals, lattice_distance)
        assert_plans_are_sound(graph, states, subgoals, plan)


def test_graph_planner_on_a_lattice_plans_the_full_route():
    planner = GraphPlanner(
        LandmarkGraph(cutoff=30.0, max_landmarks=64), lattice_distance, 2, max_path_length=8
    )
    points = torch.tensor(LATTICE)
    planner.graph.set_landmarks(points, points.clone(), lattice_distance)
    start, subgoal = torch.tensor([QUERY[0]]), torch.tensor([QUERY[1]])
    td = TensorDict(
        observation=start,
        achieved_goal=start.clone(),
        subgoal=subgoal,
        new_subgoal=torch.ones(1, 1, dtype=torch.bool),
        batch_size=[1],
    )
    td = planner(td)
    waypoints = planner.planned_path(td, 0)  # landmarks, then the subgoal
    assert torch.equal(waypoints[-1], subgoal[0])
    assert (waypoints[1:] != waypoints[:-1]).any(-1).all()  # no repeated waypoint
    hops = lattice_distance(waypoints[:-1], waypoints[1:])
    assert (hops < planner.cutoff).all()  # every hop is an edge within the cutoff, the last one too
    length = td["planner", "path_length"].item()
    budgets = td["planner", "budgets"][0, : length + 1]
    assert torch.isfinite(budgets).all()
    assert budgets.sum().item() == pytest.approx(planner.plan(start, subgoal).cost.item(), rel=1e-5)


def test_loading_a_checkpoint_recounts_stale_hop_counts():
    points = torch.tensor(LATTICE)
    graph = LandmarkGraph(cutoff=30.0, max_landmarks=64)
    graph.set_landmarks(points, points.clone(), lattice_distance)
    state = graph.state_dict()
    state["hop_counts"] = state["hop_counts"] + (state["next_hop"] >= 0).long()  # a stale checkpoint
    state["hop_counts"].fill_diagonal_(0)
    buffer = io.BytesIO()
    torch.save(state, buffer)
    buffer.seek(0)
    loaded = LandmarkGraph(cutoff=30.0, max_landmarks=64)
    loaded.load_state_dict(torch.load(buffer))
    assert torch.equal(loaded.hop_counts, graph.hop_counts)
    assert torch.equal(loaded.next_hop, graph.next_hop)


def test_reconstruct_paths_capturable_has_max_length_columns():
    gen = torch.Generator().manual_seed(3)
    for _ in range(100):
        n = int(torch.randint(1, 20, (), generator=gen))
        weights = torch.randint(0, 4, (n, n), generator=gen).float()  # zero-weight edges and ties
        weights[torch.rand(n, n, generator=gen) > 0.3] = INF
        weights.fill_diagonal_(0.0)
        table = floyd_warshall(weights)
        sources, targets = torch.randint(0, n, (2, 30), generator=gen)
        for max_length in (1, 3, 25):
            paths, lengths = reconstruct_paths(table.next_hop, table.hop_counts, sources, targets, max_length)
            got, got_lengths = reconstruct_paths(
                table.next_hop, table.hop_counts, sources, targets, max_length, capturable=True
            )
            assert got.shape == (30, max_length)
            assert torch.equal(got_lengths, lengths)
            assert torch.equal(got[:, : paths.shape[1]], paths)
            assert (got[:, paths.shape[1] :] == -1).all()
