"""The public swap points of the graph level: the distance protocol, the edge rule and the composed graph."""

import math

import pytest
import torch
from tensordict import TensorDict
from torch import nn

import torchrl_dhrl
from torchrl_dhrl.modules import GoalConditionedCritic, LowLevelActor
from torchrl_dhrl.planner import (
    AutocastDistance,
    CutoffEdgeRule,
    EdgeRule,
    FrontierGoalShifting,
    GoalDistance,
    GraphPlanner,
    LandmarkGraph,
    LineOfSightDistance,
    TemporalDistance,
    distances,
)

#: A 5 x 5 lattice of landmarks, 1 unit apart; states are (x, y, 0) (obs_dim 3).
LATTICE = torch.cartesian_prod(torch.arange(5.0), torch.arange(5.0))
STATES = torch.cat([LATTICE, torch.zeros(25, 1)], -1)


def manhattan(states, goals):
    """A user-written temporal distance: one step per unit along each axis (4-neighbour moves)."""
    return (goals - states[..., :2]).abs().sum(-1)


def query(start, subgoal):
    return TensorDict(
        observation=torch.tensor([[*start, 0.0]]),
        achieved_goal=torch.tensor([start]),
        subgoal=torch.tensor([subgoal]),
        new_subgoal=torch.ones(1, 1, dtype=torch.bool),
        batch_size=[1],
    )


# ------------------------------------------------------------------ distances
def test_the_distances_live_in_the_planner_and_follow_the_protocol():
    assert torchrl_dhrl.GoalDistance is GoalDistance is distances.GoalDistance
    assert torchrl_dhrl.LineOfSightDistance is LineOfSightDistance is distances.LineOfSightDistance
    assert {"TemporalDistance", "AutocastDistance", "EdgeRule", "CutoffEdgeRule"} <= set(torchrl_dhrl.__all__)
    actor = LowLevelActor(3, 2, action_max=1.0, action_dim=2, num_cells=(8,))
    critic = GoalConditionedCritic(3, 2, action_max=1.0, action_dim=2, num_cells=(8,))
    learned, oracle = GoalDistance(actor, critic), LineOfSightDistance(1.0)
    assert isinstance(learned, AutocastDistance) and isinstance(learned, TemporalDistance)
    # the oracle has no network: its with_autocast is the identity, so reduced-precision builds accept it
    assert isinstance(oracle, AutocastDistance) and oracle.with_autocast(torch.bfloat16) is oracle
    assert isinstance(manhattan, TemporalDistance) and not isinstance(manhattan, AutocastDistance)
    assert not isinstance(3.0, TemporalDistance)
    # the shapes of the protocol, for every kind: pairs, all pairs by broadcasting, single points
    for distance in (learned, oracle, manhattan):
        assert distance(STATES[:4], LATTICE[:4]).shape == (4,)
        assert distance(STATES[:4, None], LATTICE[None, :6]).shape == (4, 6)
        assert distance(STATES[0], LATTICE[1]).shape == ()


def test_a_user_written_function_drives_the_planner_and_fgs():
    planner = GraphPlanner(LandmarkGraph(cutoff=1.5, max_landmarks=25, early_stop=0.0), manhattan, goal_dim=2)
    planner.build(STATES, LATTICE.clone())
    assert planner.num_landmarks == 25 and planner.distance is manhattan
    # 4-neighbour edges only (the diagonals cost 2 steps, above the cutoff)
    assert planner.edges.shape[0] == 2 * 2 * 4 * 5 and torch.equal(planner.edge_costs, torch.ones(80))
    td = planner(query([0.0, 0.0], [4.0, 4.0]))
    path = planner.planned_path(td, 0)  # landmarks, then the subgoal
    assert torch.equal(path[-1], torch.tensor([4.0, 4.0])) and path.shape[0] >= 9
    steps = (path[1:] - path[:-1]).abs().sum(-1)
    assert (steps <= 1).all() and path[0].abs().sum() + steps.sum() == 8  # a shortest Manhattan route
    assert planner.plan(STATES[:1], torch.tensor([[4.0, 4.0]])).cost.item() == 8.0
    far = planner.distance_from_graph(torch.tensor([[4.0, 7.0], [2.0, 2.0]]))
    assert far.tolist() == [3.0, 0.0]
    fgs = FrontierGoalShifting(planner, noise=0.0, generator=torch.Generator().manual_seed(0))
    shifted = fgs(TensorDict(observation=STATES[:1], desired_goal=torch.tensor([[2.0, 2.0]]), batch_size=[1]))
    assert shifted["goal_shifted"].item()  # covered by the graph: moved to a landmark of its frontier
    assert manhattan(STATES[:1], shifted["desired_goal"]).item() >= 1.0


def test_a_distance_breaking_the_protocol_is_named():
    planner = GraphPlanner(LandmarkGraph(cutoff=1.5), lambda s, g: (g - s[..., :2]).sum(-1, keepdim=True), 2)
    with pytest.raises(ValueError, match="TemporalDistance"):
        planner.build(STATES, LATTICE.clone())
    with pytest.raises(TypeError, match="callable"):
        GraphPlanner(LandmarkGraph(), "manhattan", 2)


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


# ------------------------------------------------------------------ composition
def test_the_planner_is_composed_of_a_landmark_graph():
    graph = LandmarkGraph(cutoff=1.5, max_landmarks=25, early_stop=0.0)
    planner = GraphPlanner(graph, manhattan, goal_dim=2, reach_radius=0.1, max_path_length=4)
    assert planner.graph is graph and dict(planner.named_children()) == {"graph": graph}
    planner.build(STATES, LATTICE.clone())
    assert graph.num_landmarks == 25 and all(k.startswith("graph.") for k in planner.state_dict())
    assert planner.max_path_length == 4 and planner.reach_radius == 0.1
    with pytest.raises(
        TypeError, match=r"`graph` must be a LandmarkGraph, e\.g\. GraphPlanner\(LandmarkGraph"
    ):
        GraphPlanner(manhattan, LandmarkGraph(), 2)  # distance and graph swapped
    with pytest.raises(TypeError, match="with_autocast"):
        GraphPlanner(LandmarkGraph(build_autocast_dtype=torch.bfloat16), manhattan, 2)
