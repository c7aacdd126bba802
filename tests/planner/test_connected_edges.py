"""``ConnectedEdgeRule``: a base rule's edges plus the shortest edges that keep the landmark graph strongly connected
where the cutoff cuts it (issue 57), checked against SciPy's graph routines on random graphs with ties, several
components and isolated landmarks; in ``LandmarkGraph`` builds and plans; and the recipe's ``planner.edge_rule``."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components, shortest_path

from torchrl_dhrl.planner import (
    ConnectedEdgeRule,
    CutoffEdgeRule,
    EdgeRule,
    GraphPlanner,
    LandmarkGraph,
    make_edge_rule,
)
from torchrl_dhrl.planner.edges import EDGE_RULES, reachability

INF = math.inf


def euclid(states, goals):
    return (goals - states[..., :2]).norm(dim=-1)


# ------------------------------------------------------------------ independent computations (SciPy, NumPy)
def closure(edges: np.ndarray) -> np.ndarray:
    """Reflexive transitive closure of a bool adjacency matrix, by SciPy's unweighted shortest paths."""
    return np.isfinite(shortest_path(csr_matrix(edges.astype(np.int8)), unweighted=True))


def strong_labels(edges: np.ndarray) -> tuple[int, np.ndarray]:
    return connected_components(csr_matrix(edges.astype(np.int8)), directed=True, connection="strong")


def finite_edges(d: np.ndarray) -> np.ndarray:
    out = np.isfinite(d)
    np.fill_diagonal(out, False)
    return out


def random_case(seed: int):
    """Distances with many ties (small integers), clusters cut apart by the cutoff, ``inf`` entries and isolated
    landmarks; the base edges from the reference rule or a random subset of the finite pairs."""
    rng = np.random.default_rng(seed)
    num = int(rng.integers(2, 36))
    clusters = rng.integers(0, int(rng.integers(1, 6)), num)
    same = clusters[:, None] == clusters[None, :]
    d = np.where(same, rng.integers(1, 5, (num, num)), rng.integers(5, 14, (num, num))).astype(np.float64)
    d[rng.random((num, num)) < rng.choice([0.0, 0.2, 0.6])] = INF
    isolated = np.flatnonzero(rng.random(num) < 0.1)
    d[isolated, :] = INF
    d[:, isolated] = INF
    np.fill_diagonal(d, INF)
    distances = torch.tensor(d, dtype=torch.float32)
    if rng.random() < 0.7:
        nn_factor = [None, 1.2][int(rng.integers(2))]
        base = CutoffEdgeRule(nn_factor=nn_factor)(distances, float(rng.integers(1, 6)))
    else:
        base = torch.tensor(finite_edges(d) & (rng.random((num, num)) < 0.1))
    return d, distances, base, isolated


SEEDS = range(60)


# ------------------------------------------------------------------ properties over random graphs
@pytest.mark.parametrize("seed", SEEDS)
def test_keeps_the_base_edges_and_reaches_what_the_finite_distances_reach(seed):
    d, distances, base, isolated = random_case(seed)
    keep, added = ConnectedEdgeRule.connect(distances, base)
    base_np, keep_np = base.numpy(), keep.numpy()
    assert keep.dtype == torch.bool and keep.shape == base.shape
    assert (keep_np | ~base_np).all()  # every base edge is kept
    # the result is the base plus the added pairs, which are finite, off-diagonal, new and distinct
    pairs = added.numpy()
    expected = base_np.copy()
    expected[pairs[:, 0], pairs[:, 1]] = True
    assert np.array_equal(keep_np, expected)
    assert np.isfinite(d[pairs[:, 0], pairs[:, 1]]).all() and (pairs[:, 0] != pairs[:, 1]).all()
    assert not base_np[pairs[:, 0], pairs[:, 1]].any() and len({tuple(p) for p in pairs}) == len(pairs)
    # landmark i reaches landmark j exactly when the base and the finite distances lead from i to j
    target = closure(base_np | finite_edges(d))
    assert np.array_equal(closure(keep_np), target)
    # so strongly connected whenever the finite-distance graph is (checked on its own terms)
    if strong_labels(finite_edges(d))[0] == 1:
        assert strong_labels(keep_np)[0] == 1
    # landmarks with only infinite distances stay isolated (the base edges are finite ones here)
    assert not keep_np[isolated].any() and not keep_np[:, isolated].any()
    # the rule gives the same, deterministically; and a connected result gets nothing more
    rule = ConnectedEdgeRule(base=lambda distances, cutoff: base.clone())
    assert torch.equal(rule(distances, 3.0), keep) and torch.equal(rule(distances, 3.0), keep)
    again, more = ConnectedEdgeRule.connect(distances, keep)
    assert torch.equal(again, keep) and more.shape == (0, 2)


@pytest.mark.parametrize("seed", SEEDS)
def test_each_added_edge_is_the_shortest_that_adds_reachability_lowest_pair_on_ties(seed):
    """Replays the added edges in order and finds each by brute force over the graph built so far: the shortest
    finite pair whose target its source cannot reach (lexicographically lowest ``(distance, i, j)``), which is also
    the shortest (lowest) pair from the strongly connected component of ``i`` to that of ``j``."""
    d, distances, base, _ = random_case(seed)
    _, added = ConnectedEdgeRule.connect(distances, base)
    current = base.numpy().copy()
    for i, j in added.tolist():
        reach = closure(current)
        open_pairs = finite_edges(d) & ~reach
        assert open_pairs.any()
        best = min((d[a, b], a, b) for a, b in zip(*np.nonzero(open_pairs), strict=True))
        assert (best[1], best[2]) == (i, j), (best, (i, j))
        _, labels = strong_labels(current)
        between = [
            (d[a, b], a, b)
            for a in np.flatnonzero(labels == labels[i])
            for b in np.flatnonzero(labels == labels[j])
        ]
        assert labels[i] != labels[j] and min(between) == (d[i, j], i, j)
        current[i, j] = True
    # and then nothing is left to connect
    assert not (finite_edges(d) & ~closure(current)).any()


@pytest.mark.parametrize("seed", SEEDS)
def test_added_edges_are_as_short_as_possible_at_every_length(seed):
    """Order-free minimality of the returned mask: for every length ``t``, the base edges and the added edges of
    length ``<= t`` reach exactly what the base edges and *all* finite edges of length ``<= t`` reach (the minimax
    property of Kruskal's tree), so no added edge could be replaced by shorter ones."""
    d, distances, base, _ = random_case(seed)
    keep = ConnectedEdgeRule(base=lambda distances, cutoff: base.clone())(distances, 3.0).numpy()
    base_np = base.numpy()
    added = keep & ~base_np
    for t in np.unique(d[np.isfinite(d)]):
        short = np.isfinite(d) & (d <= t)
        assert np.array_equal(
            closure(base_np | (added & short)), closure(base_np | (finite_edges(d) & short))
        ), t


def test_with_distinct_lengths_every_added_edge_is_needed():
    """With no ties, removing any added edge loses reachability at its own length (it is irredundant)."""
    for seed in range(20):
        rng = np.random.default_rng(100 + seed)
        num = 25
        clusters = rng.integers(0, 4, num)
        d = rng.random((num, num)) * 4 + np.where(clusters[:, None] == clusters[None, :], 0.0, 5.0)
        np.fill_diagonal(d, INF)
        distances = torch.tensor(d)
        base = CutoffEdgeRule(nn_factor=None)(distances, 2.0)
        keep, added = ConnectedEdgeRule.connect(distances, base)
        assert len(added) >= 3  # four clusters cut apart: at least one edge into and out of each in a cycle
        for i, j in added.tolist():
            short = keep.numpy() & (d <= d[i, j])
            short[i, j] = False
            assert not closure(base.numpy() | short)[i, j]


# ------------------------------------------------------------------ hand-made cases
def test_an_already_connected_base_graph_gets_nothing():
    gen = torch.Generator().manual_seed(0)
    for num in (2, 5, 40):
        distances = torch.rand(num, num, generator=gen) * 20
        distances.fill_diagonal_(INF)
        base = CutoffEdgeRule()(distances, 15.0)
        assert strong_labels(base.numpy())[0] == 1
        keep, added = ConnectedEdgeRule.connect(distances, base)
        assert torch.equal(keep, base) and added.shape == (0, 2)
        assert torch.equal(ConnectedEdgeRule()(distances, 15.0), base)
    # a single landmark and no landmark: nothing to connect
    for num in (0, 1):
        distances = torch.full((num, num), INF)
        keep, added = ConnectedEdgeRule.connect(distances, torch.zeros(num, num, dtype=torch.bool))
        assert keep.shape == (num, num) and not keep.any() and added.shape == (0, 2)


def test_ties_take_the_lowest_pair_and_isolated_landmarks_stay_isolated():
    # {0, 1} and {2, 3} cut apart; every pair across is 20 steps, landmark 4 has only infinite distances
    d = torch.full((5, 5), 20.0)
    d[0, 1] = d[1, 0] = d[2, 3] = d[3, 2] = 1.0
    d[4, :] = d[:, 4] = INF
    d.fill_diagonal_(INF)
    rule = ConnectedEdgeRule(base=CutoffEdgeRule(nn_factor=None))
    keep, added = rule.connect(d, CutoffEdgeRule(nn_factor=None)(d, 5.0))
    assert added.tolist() == [[0, 2], [2, 0]]  # the lowest (i, j) among the tied pairs, each way
    assert not keep[4].any() and not keep[:, 4].any()
    assert torch.equal(rule(d, 5.0), keep)
    # one way only: 1 -> 2 is finite, nothing leads back, so the rule adds 1 -> 2 and stops
    d = torch.tensor([[INF, 1.0, INF], [1.0, INF, 30.0], [INF, INF, INF]])
    keep, added = ConnectedEdgeRule.connect(d, d < 5.0)
    assert added.tolist() == [[1, 2]] and keep.int().tolist() == [[0, 1, 0], [1, 0, 1], [0, 0, 0]]


def test_the_rule_is_an_edge_rule_and_checks_its_base():
    rule = ConnectedEdgeRule()
    assert isinstance(rule, EdgeRule)
    assert repr(rule) == "ConnectedEdgeRule(base=CutoffEdgeRule(nn_factor=1.2))"
    with pytest.raises(TypeError, match="base"):
        ConnectedEdgeRule(base=1.2)
    bad = ConnectedEdgeRule(base=lambda distances, cutoff: (distances < cutoff).float())
    with pytest.raises(ValueError, match="must return a bool tensor"):
        bad(torch.ones(3, 3), 2.0)
    # the base rule gets a copy it may write into: the caller's distances are untouched
    distances = torch.tensor([[INF, 1.0], [9.0, INF]])
    ConnectedEdgeRule(base=lambda x, cutoff: x.fill_(0.0) < -1)(distances, 5.0)
    assert distances[1, 0] == 9.0


def test_reachability_against_scipy():
    gen = torch.Generator().manual_seed(3)
    for num, p in ((1, 0.5), (7, 0.1), (50, 0.03), (120, 0.01)):
        edges = torch.rand(num, num, generator=gen) < p
        assert np.array_equal(reachability(edges).numpy(), closure(edges.numpy()))
    chain = torch.zeros(64, 64, dtype=torch.bool)
    chain[torch.arange(63), torch.arange(1, 64)] = True  # 63 hops: log2 squarings
    assert torch.equal(reachability(chain), torch.ones(64, 64, dtype=torch.bool).triu())


# ------------------------------------------------------------------ inside LandmarkGraph
CHAIN = torch.tensor([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.5, 0.0], [4.5, 0.0]])


@pytest.mark.parametrize("edge_rule", [CutoffEdgeRule(), ConnectedEdgeRule()], ids=repr)
def test_a_chain_cut_by_the_cutoff_is_planned_through_with_the_connected_rule(edge_rule):
    """Landmarks 1 apart but 1.5 across the middle, cutoff 1.2: the reference rule's edges stop at the gap (the
    nearest-neighbour rule does not bridge it: 1.5 > 1.2 x 1), so the far end cannot be planned to; the connected
    rule adds 2 -> 3 and 3 -> 2 (1.5 steps each) and the plan runs along the whole chain."""
    graph = LandmarkGraph(cutoff=1.2, edge_rule=edge_rule).set_landmarks(CHAIN, CHAIN.clone(), euclid)
    plan = graph.plan(torch.tensor([[0.0, 0.0]]), torch.tensor([[4.5, 0.0]]), euclid)
    back = graph.plan(torch.tensor([[4.5, 0.0]]), torch.tensor([[0.0, 0.0]]), euclid)
    across = {(2, 3), (3, 2)}
    if isinstance(edge_rule, CutoffEdgeRule):
        assert not plan.reachable.item() and not back.reachable.item()
        assert across.isdisjoint(map(tuple, graph.edges.tolist()))
        assert math.isinf(graph.shortest_distances[0, 4].item())
    else:
        assert plan.reachable.item() and back.reachable.item()
        assert across <= set(map(tuple, graph.edges.tolist()))
        # along the chain and across the gap (entry and exit landmarks: those within the cutoff of state and subgoal)
        forth, back_path = plan.path[0, : plan.length[0]].tolist(), back.path[0, : back.length[0]].tolist()
        assert forth == sorted(forth) and {2, 3} <= set(forth)
        assert back_path == sorted(back_path, reverse=True) and {2, 3} <= set(back_path)
        assert plan.cost.item() == pytest.approx(4.5) and back.cost.item() == pytest.approx(4.5)
        assert graph.shortest_distances.isfinite().all()


def test_builds_and_plans_with_the_connected_rule():
    """FPS builds on candidates along two segments 2 apart: the reference graph is cut in two, the connected one
    plans from one end to the other, through the GraphPlanner too."""
    xs = torch.cat([torch.linspace(0.0, 2.0, 21), torch.linspace(4.0, 6.0, 21)])
    candidates = torch.stack([xs, torch.zeros_like(xs)], -1)
    start, goal = torch.tensor([[0.0, 0.0]]), torch.tensor([[6.0, 0.0]])
    results = {}
    for name in EDGE_RULES:
        graph = LandmarkGraph(cutoff=1.2, max_landmarks=20, early_stop=0.6, edge_rule=make_edge_rule(name))
        graph.build(candidates, candidates.clone(), euclid)
        assert graph.num_landmarks >= 6
        results[name] = graph.plan(start, goal, euclid)
        n_labels = strong_labels(graph.edge_mask.numpy())[0]
        assert n_labels == (1 if name == "connected" else 2), name
    assert not results["cutoff"].reachable.item()
    assert results["connected"].reachable.item() and results["connected"].cost.item() == pytest.approx(6.0)
    planner = GraphPlanner(
        LandmarkGraph(cutoff=1.2, max_landmarks=20, early_stop=0.6, edge_rule=ConnectedEdgeRule()),
        euclid,
        goal_dim=2,
    )
    planner.build(candidates, candidates.clone())
    assert planner.graph.plan(start, goal, euclid).reachable.item()


# ------------------------------------------------------------------ the recipe's switch
def test_the_recipe_switch_reaches_the_graph_and_defaults_to_the_reference_rule():
    from _recipe import recipe_config
    from dhrl_utils import build_agent

    from torchrl_dhrl.recipe import validate_config

    small = ("env=PointMaze", "preset=smoke", "device=cpu")
    cfg = recipe_config(*small)
    assert cfg["planner"]["edge_rule"] == "cutoff" and tuple(EDGE_RULES) == ("cutoff", "connected")
    rule = build_agent(cfg, torch.device("cpu")).planner.graph.edge_rule
    assert type(rule) is CutoffEdgeRule and rule.nn_factor == 1.2  # LandmarkGraph's own default
    cfg = recipe_config(*small, "planner.edge_rule=connected")
    validate_config(cfg)
    graph = build_agent(cfg, torch.device("cpu")).planner.graph
    assert type(graph.edge_rule) is ConnectedEdgeRule and type(graph.edge_rule.base) is CutoffEdgeRule
    assert graph.edge_rule.base.nn_factor == 1.2 and graph.cutoff == cfg["planner"]["cutoff"]
    # a configuration saved before the key existed builds the reference rule
    del cfg["planner"]["edge_rule"]
    assert type(build_agent(cfg, torch.device("cpu")).planner.graph.edge_rule) is CutoffEdgeRule


def test_a_bad_edge_rule_stops_the_recipe_before_anything_is_built(tmp_path):
    from _recipe import load_recipe, recipe_config

    from torchrl_dhrl.recipe import ConfigError, validate_config

    cfg = recipe_config("env=PointMaze", "preset=smoke", "device=cpu", "planner.edge_rule=nearest")
    message = "`planner.edge_rule` must be one of ('cutoff', 'connected'), got 'nearest'."
    with pytest.raises(ConfigError) as info:
        validate_config(cfg)
    assert str(info.value) == message
    with pytest.raises(ConfigError) as info:
        load_recipe().train(cfg, run_dir=tmp_path / "run")
    assert str(info.value) == message and not (tmp_path / "run").exists()
