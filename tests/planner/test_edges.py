"""Edge rules of the landmark graph: the reference ``CutoffEdgeRule`` (cutoff and nearest-neighbour rule)
and a user-made rule in its place."""

import math

import numpy as np
import pytest
import torch
from torch import nn

from tests.planner.test_distances import LATTICE, STATES, manhattan
from torchrl_dhrl.planner import CutoffEdgeRule, EdgeRule, GraphPlanner, LandmarkGraph


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


# ------------------------------------------------------------------ the edge rule
def test_the_default_edge_rule_is_the_reference_rule():
    graph = LandmarkGraph()
    assert isinstance(graph.edge_rule, CutoffEdgeRule) and graph.edge_rule.nn_factor == 1.2
    assert isinstance(graph.edge_rule, EdgeRule)
    assert "edge_rule=CutoffEdgeRule(nn_factor=1.2)" in repr(graph)
    for bad in (0.0, -1.0, math.nan, True, "1.2"):
        with pytest.raises(ValueError, match="nn_factor"):
            CutoffEdgeRule(bad)
    with pytest.raises(TypeError, match="edge_rule"):
        LandmarkGraph(edge_rule=1.2)


class KNearest(nn.Module):
    """A user-made rule (an ``nn.Module``): each landmark's ``k`` nearest landmarks, whatever the cutoff."""

    def __init__(self, k):
        super().__init__()
        self.k = k
        self.calls = []

    def forward(self, distances, cutoff):
        self.calls.append((distances.clone(), cutoff))
        index = distances.topk(self.k, dim=1, largest=False).indices
        distances.fill_(0.0)  # a rule may scribble on its input: it is a copy
        return torch.zeros_like(distances, dtype=torch.bool).scatter_(1, index, True)


def test_a_custom_edge_rule_replaces_the_reference_rule():
    rule = KNearest(k=4)
    graph = LandmarkGraph(cutoff=1.5, edge_rule=rule)
    graph.set_landmarks(STATES, LATTICE.clone(), manhattan)
    ((distances, cutoff),) = rule.calls
    assert cutoff == 1.5 and torch.isinf(distances.diagonal()).all()  # no self loops offered
    assert torch.equal(distances.masked_fill(torch.eye(25, dtype=torch.bool), 0.0), graph.landmark_distances)
    # 4 out-edges each: the border landmarks reach 2 steps away, beyond the cutoff (the reference rule: 80 edges)
    assert graph.edge_mask.sum(dim=1).tolist() == [4] * 25 and graph.edge_costs.max() == 2.0
    assert list(graph.state_dict()) == list(LandmarkGraph().state_dict())  # the rule is not a submodule
    assert "edge_rule" not in dict(graph.named_modules()) and graph.landmark_distances[0, 1] == 1.0
    # the planner plans on the rule's edges: corner to corner, 8 steps
    planner = GraphPlanner(graph, manhattan, goal_dim=2)
    assert planner.graph is graph and planner.cutoff == 1.5
    assert planner.plan(STATES[:1], torch.tensor([[4.0, 4.0]])).cost.item() == 8.0
    # assigning a rule (here a plain function) takes effect at the next build
    graph.edge_rule = lambda d, cutoff: d < cutoff  # the cutoff edges only
    graph.set_landmarks(STATES, LATTICE.clone(), manhattan)
    assert graph.edge_mask.sum().item() == 80 and len(rule.calls) == 1
    graph.edge_rule = lambda d, cutoff: torch.zeros_like(d, dtype=torch.bool)  # no edges at all
    graph.set_landmarks(STATES, LATTICE.clone(), manhattan)
    assert not graph.edge_mask.any() and math.isinf(
        graph.plan(STATES[:1], LATTICE[-1:], manhattan).cost.item()
    )


@pytest.mark.parametrize(
    "rule",
    [lambda d, c: (d < c).float(), lambda d, c: (d < c)[:-1], lambda d, c: None],
    ids=["float", "shape", "none"],
)
def test_an_edge_rule_returning_something_else_is_named(rule):
    graph = LandmarkGraph(cutoff=1.5, edge_rule=rule)
    with pytest.raises(ValueError, match=r"must return a bool tensor of shape \(25, 25\)"):
        graph.set_landmarks(STATES, LATTICE.clone(), manhattan)
