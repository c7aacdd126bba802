"""Temporal distances: the ``TemporalDistance`` protocol, ``GoalDistance``'s speed options (reduced-precision
autocast, the CPU chunk default, the actor fast path) and the oracle ``LineOfSightDistance``."""

import math

import pytest
import torch
from tensordict import TensorDict

import torchrl_dhrl
from torchrl_dhrl.modules import GoalConditionedCritic, LowLevelActor
from torchrl_dhrl.planner import (
    AutocastDistance,
    FrontierGoalShifting,
    GoalDistance,
    GraphPlanner,
    LandmarkGraph,
    LineOfSightDistance,
    TemporalDistance,
    distances,
)
from torchrl_dhrl.planner.distances import DEFAULT_CPU_CHUNK_SIZE

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
    actor = LowLevelActor(3, 2, action_max=1.0, action_dim=2, num_cells=(8,), goal_indices=(0, 1))
    critic = GoalConditionedCritic(
        3, 2, action_max=1.0, action_dim=2, num_cells=(8,), relative_goal=True, goal_indices=(0, 1)
    )
    learned, oracle = GoalDistance(actor, critic), LineOfSightDistance(1.0, goal_indices=(0, 1))
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


OBS, GOAL, ACT = 9, 2, 4


#: Tolerances of the reduced-precision path against float32 on the network below: the error is about
#: absolute (bfloat16 rounding of the hidden activations, times the output weights), up to 0.28 steps
#: (measured, both twin members; p99 0.16-0.17), so relative to the distance it is small for the
#: pessimistic member (median 0.06%, max 0.7%) and larger for the optimistic one, whose distances reach
#: below 1 step here (median 0.12%, max 11% at a distance of 0.5). float16 is about 8x more accurate.
BF16_MEDIAN_REL, BF16_ABS, BF16_REL = 0.005, 0.3, 0.02


def trained_like(seed=0, width=64):
    """Actor and twin critic whose distances spread over ~[5, 120] steps, like a trained critic.

    Random weights of the default initialisation give distances of about 0.7 for every pair; the
    output layer is rescaled so that the distance depends strongly on the inputs.
    """
    torch.manual_seed(seed)
    actor = LowLevelActor(
        OBS, GOAL, action_max=2.0, action_dim=ACT, num_cells=(width, width), goal_indices=(0, 1)
    )
    critic = GoalConditionedCritic(
        OBS,
        GOAL,
        action_max=2.0,
        action_dim=ACT,
        num_cells=(width, width),
        relative_goal=True,
        goal_indices=(0, 1),
    )
    last = critic.module.ensemble.layers[-1]
    with torch.no_grad():
        last.weight.mul_(60.0)
        last.bias.fill_(40.0)
    return actor, critic


def pairs(num, seed=1):
    gen = torch.Generator().manual_seed(seed)
    return torch.randn(num, OBS, generator=gen) * 3, torch.randn(num, GOAL, generator=gen) * 3


def relative_error(value, reference):
    return (value - reference).abs() / reference.abs().clamp_min(1.0)


@pytest.mark.parametrize("twin", ["optimistic", "pessimistic"])
@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_autocast_is_close_to_float32_and_really_reduced(dtype, twin):
    actor, critic = trained_like()
    states, goals = pairs(4000)
    ref = GoalDistance(actor, critic, twin=twin)(states, goals)
    assert 5.0 < ref.median() < 120.0 and ref.std() > 5.0  # a spread of distances, as trained
    fast = GoalDistance(actor, critic, autocast_dtype=dtype, twin=twin)(states, goals)
    assert fast.dtype == torch.float32 and fast.shape == ref.shape
    assert relative_error(fast, ref).median() < BF16_MEDIAN_REL
    assert ((fast - ref).abs() <= BF16_ABS + BF16_REL * ref).all()
    assert (fast != ref).float().mean() > 0.5  # the networks really ran in reduced precision


def test_bfloat16_output_layer_is_not_rounded():
    # The raw output is the distance (distance parameterisation): were it computed by a bfloat16
    # matmul, (almost) every distance above 20 steps would sit on the bfloat16 grid.
    actor, critic = trained_like()
    states, goals = pairs(2000)
    fast = GoalDistance(actor, critic, autocast_dtype=torch.bfloat16)(states, goals)
    large = fast[fast > 20.0]
    assert large.numel() > 200
    on_grid = (large == large.bfloat16().float()).float().mean()
    assert on_grid < 0.2


def test_default_path_ignores_an_enclosing_autocast():
    actor, critic = trained_like()
    states, goals = pairs(500)
    distance = GoalDistance(actor, critic)
    ref = distance(states, goals)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        inside = distance(states, goals)
    assert torch.equal(inside, ref)


def test_with_autocast_copies_and_shares_the_networks():
    actor, critic = trained_like()
    distance = GoalDistance(actor, critic, max_distance=100.0)
    fast = distance.with_autocast(torch.bfloat16)
    assert fast is not distance and fast.autocast_dtype is torch.bfloat16 and distance.autocast_dtype is None
    assert fast.actor is actor and fast.critic is critic and fast.max_distance == 100.0
    assert fast.with_autocast(None).autocast_dtype is None
    states, goals = pairs(300)
    torch.testing.assert_close(fast(states, goals), distance(states, goals), rtol=BF16_REL, atol=BF16_ABS)
    # it follows training: an in-place update of the shared critic changes both
    with torch.no_grad():
        critic.module.ensemble.layers[-1].bias.add_(5.0)
    torch.testing.assert_close(fast(states, goals), distance(states, goals), rtol=BF16_REL, atol=BF16_ABS)


@pytest.mark.parametrize("bad", [torch.float32, torch.float64, torch.int8, "bfloat16"])
def test_autocast_dtype_is_validated(bad):
    actor, critic = trained_like()
    with pytest.raises(ValueError, match="autocast_dtype"):
        GoalDistance(actor, critic, autocast_dtype=bad)
    with pytest.raises(ValueError, match="autocast_dtype"):
        GoalDistance(actor, critic).with_autocast(bad)


@pytest.mark.parametrize("bad", [0, -3, 2.5, True])
def test_chunk_size_is_validated(bad):
    actor, critic = trained_like()
    with pytest.raises(ValueError, match="chunk_size"):
        GoalDistance(actor, critic, chunk_size=bad)


@pytest.mark.parametrize("dtype", [None, torch.bfloat16])
def test_results_do_not_depend_on_the_chunk_size(dtype):
    actor, critic = trained_like()
    states, goals = pairs(37)
    grid = GoalDistance(actor, critic, autocast_dtype=dtype)(states[:, None], goals[None])  # 1369 pairs
    for chunk in (64, 500, 100_000):
        chunked = GoalDistance(actor, critic, chunk_size=chunk, autocast_dtype=dtype)(
            states[:, None], goals[None]
        )
        # matmul kernels may differ in the last bits between batch sizes
        tol = 1e-5 if dtype is None else 2e-3
        torch.testing.assert_close(chunked, grid, rtol=tol, atol=tol * 10)


def test_default_chunk_on_cpu_and_explicit_chunk():
    actor, critic = trained_like(width=16)
    sizes = []
    handle = actor.module.register_forward_hook(lambda mod, args, out: sizes.append(args[0].shape[0]))
    states, goals = pairs(2 * DEFAULT_CPU_CHUNK_SIZE + 5)
    GoalDistance(actor, critic)(states, goals)
    assert sizes == [DEFAULT_CPU_CHUNK_SIZE, DEFAULT_CPU_CHUNK_SIZE, 5]
    sizes.clear()
    GoalDistance(actor, critic, chunk_size=65536)(states, goals)
    assert sizes == [states.shape[0]]
    handle.remove()


def test_actor_fast_path_equals_the_tensordict_path():
    actor, critic = trained_like()
    states, goals = pairs(700)
    fast = GoalDistance(actor, critic)(states, goals)
    # a hook on the TensorDictModule sends the call through the TensorDict path
    calls = []
    handle = actor.register_forward_pre_hook(lambda mod, args: calls.append(1))
    slow = GoalDistance(actor, critic)(states, goals)
    handle.remove()
    assert calls and torch.equal(fast, slow)


def test_autocast_with_swapped_parameters():
    actor, critic = trained_like(seed=0)
    other_actor, other_critic = trained_like(seed=3)
    states, goals = pairs(400)
    swapped = GoalDistance(
        actor,
        critic,
        actor_params=TensorDict.from_module(other_actor),
        critic_params=TensorDict.from_module(other_critic),
        autocast_dtype=torch.bfloat16,
    )
    expected = GoalDistance(other_actor, other_critic, autocast_dtype=torch.bfloat16)(states, goals)
    torch.testing.assert_close(swapped(states, goals), expected)
    assert not torch.allclose(expected, GoalDistance(actor, critic)(states, goals), rtol=0.05)


def test_autocast_keeps_float64_parameters_in_float64():
    actor, critic = trained_like()
    actor.double()
    critic.double()
    states, goals = pairs(200)
    ref = GoalDistance(actor, critic)(states, goals)
    out = GoalDistance(actor, critic, autocast_dtype=torch.bfloat16)(states, goals)
    assert out.dtype == torch.float64
    torch.testing.assert_close(out, ref)  # autocast leaves float64 alone


@pytest.mark.parametrize("num_cells", [(), (32,)])
def test_autocast_with_shallow_critics(num_cells):
    torch.manual_seed(0)
    actor = LowLevelActor(OBS, GOAL, action_max=2.0, action_dim=ACT, num_cells=(16,), goal_indices=(0, 1))
    critic = GoalConditionedCritic(
        OBS,
        GOAL,
        action_max=2.0,
        action_dim=ACT,
        num_cells=num_cells,
        relative_goal=True,
        goal_indices=(0, 1),
    )
    states, goals = pairs(300)
    ref = GoalDistance(actor, critic)(states, goals)
    fast = GoalDistance(actor, critic, autocast_dtype=torch.bfloat16)(states, goals)
    torch.testing.assert_close(fast, ref, rtol=0.02, atol=0.02)


# ---------------------------------------------------------------- oracle distance
def _blocked_by_sampling(start, end, boxes, n=4001):
    t = torch.linspace(0, 1, n).view(1, n, 1)
    points = start.unsqueeze(1) + t * (end - start).unsqueeze(1)  # [P, n, d]
    inside = (points.unsqueeze(2) >= boxes[:, 0]) & (points.unsqueeze(2) <= boxes[:, 1])  # [P, n, W, d]
    return inside.all(-1).any(-1).any(-1)


def test_line_of_sight_matches_dense_sampling():
    torch.manual_seed(0)
    boxes = torch.tensor([[[1.0, -1.0], [2.0, 3.0]], [[-3.0, 2.0], [0.5, 2.5]], [[4.0, 4.0], [6.0, 4.2]]])
    oracle = LineOfSightDistance(0.5, boxes=boxes, goal_indices=(0, 1))
    start, end = torch.rand(400, 2) * 10 - 4, torch.rand(400, 2) * 10 - 4
    d = oracle(start, end)
    blocked = _blocked_by_sampling(start, end, boxes)
    free = ~blocked
    torch.testing.assert_close(d[free], (end - start)[free].norm(dim=-1) / 0.5)
    # dense sampling can miss a corner clip but never reports a false block
    assert torch.isinf(d[blocked]).all()
    assert torch.isinf(d).float().mean() >= blocked.float().mean()
    assert (torch.isinf(d) & free).float().mean() < 0.01


def test_line_of_sight_axis_parallel_and_broadcast():
    wall = torch.tensor([[[1.0, -5.0], [2.0, 5.0]]])
    oracle = LineOfSightDistance(1.0, boxes=wall, margin=0.5, goal_indices=(0, 1))
    states = torch.tensor([[0.0, 0.0], [0.0, 6.0]])
    goals = torch.tensor([[3.0, 0.0], [3.0, 6.0], [0.0, 3.0]])
    d = oracle(states[:, None], goals[None])
    assert d.shape == (2, 3)
    # (0,0)->(3,0) crosses the wall; (0,6)->(3,6) passes 1 above it but inside the 0.5 margin? no: 6 > 5.5
    assert math.isinf(d[0, 0]) and d[1, 1] == pytest.approx(3.0) and d[0, 2] == pytest.approx(3.0)
    finite = LineOfSightDistance(1.0, boxes=wall, margin=0.5, goal_indices=(0, 1), blocked=1e4)
    assert finite(states[0], goals[0]) == 1e4
    with pytest.raises(ValueError, match="boxes"):
        LineOfSightDistance(1.0, boxes=torch.zeros(2, 2), goal_indices=(0, 1))
    with pytest.raises(ValueError, match="speed"):
        LineOfSightDistance(0.0, goal_indices=(0, 1))


def test_a_blind_landmark_or_state_gets_no_edge_through_the_walls():
    """Landmarks in three rooms with no line of sight between them except inside a room: with the default (blocked
    = inf) the graph's edges stay inside the rooms and a state that sees no landmark plans the subgoal alone; with a
    finite ``blocked`` (0.4.0's 1e4) the nearest-neighbour rule joins the lone landmark to every other through the
    walls and the start fallback joins the blind state to every landmark."""
    from torchrl_dhrl.planner import LandmarkGraph

    walls = torch.tensor([[[1.0, -10.0], [2.0, 10.0]], [[4.0, -10.0], [5.0, 10.0]]])
    points = torch.tensor([[0.0, 0.0], [0.0, 1.0], [3.0, 0.0], [3.0, 1.0], [6.0, 0.0]])  # room 3 holds one landmark
    same_room = torch.tensor([0, 0, 1, 1, 2])
    inside = (same_room[:, None] == same_room[None]) & ~torch.eye(5, dtype=torch.bool)
    blind, subgoal = torch.tensor([[1.5, 0.0]]), torch.tensor([[6.0, 1.0]])  # a state inside a wall: sees nothing
    for blocked in (math.inf, 1e4):
        oracle = LineOfSightDistance(1.0, boxes=walls, goal_indices=(0, 1), blocked=blocked)
        graph = LandmarkGraph(cutoff=5.0, max_landmarks=8)
        graph.set_landmarks(points, points.clone(), oracle)
        plan = graph.plan(blind, subgoal, oracle, 4)
        if math.isinf(blocked):
            assert torch.equal(graph.edge_mask, inside)
            assert plan.length.item() == 0 and not plan.reachable.item()  # the subgoal alone
        else:  # the lone landmark joined to all four it cannot see; the blind state "reaches" it through two walls
            assert graph.edge_mask[4, :4].all() and not graph.edge_mask[4, 4]
            assert plan.reachable.item() and plan.path[0, : plan.length[0]].tolist() == [4]
            assert plan.cost.item() == pytest.approx(1e4 + 1.0)


def test_line_of_sight_builds_the_same_graph_under_reduced_precision_building():
    # the recipe's preset=cpu builds graphs with planner.build_dtype=bfloat16; the oracle has no network, so
    # with_autocast is the identity and the graph is the float32 one, bit for bit
    torch.manual_seed(0)
    boxes = torch.tensor([[[1.0, -1.0], [2.0, 3.0]], [[-3.0, 2.0], [0.5, 2.5]]])
    oracle = LineOfSightDistance(0.5, boxes=boxes, margin=0.2, goal_indices=(0, 1))
    assert oracle.with_autocast(torch.bfloat16) is oracle and oracle.with_autocast(None) is oracle
    candidates = torch.rand(300, 2) * 10 - 4
    graphs = []
    for dtype in (None, torch.bfloat16):
        graph = LandmarkGraph(cutoff=6.0, max_landmarks=40, early_stop=0.0, build_autocast_dtype=dtype)
        GraphPlanner(graph, oracle, goal_dim=2).build(candidates, candidates.clone())
        graphs.append(graph)
    assert graphs[0].num_landmarks == 40
    for key, value in graphs[0].state_dict().items():
        torch.testing.assert_close(graphs[1].state_dict()[key], value, rtol=0, atol=0)
