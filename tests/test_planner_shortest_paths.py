"""All-pairs shortest paths and path read-out against scipy / networkx."""

import math

import networkx as nx
import numpy as np
import pytest
import torch
from scipy.sparse.csgraph import shortest_path

from torchrl_dhrl.planner import floyd_warshall, reconstruct_paths

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
