"""The capturable planner: ``LandmarkGraph.plan(capturable=True)`` and ``GraphPlanner(capturable=True)``.

The capturable path plans with static shapes and no host synchronisation (every entry/exit landmark pair, the
fallback of every row, paths of ``max_path_length`` columns; the tracker plans every env and keeps the new plans
where a replan is due), so that the acting policy compiles as one graph (``make_collector(compile_policy=...)``).
Checked here: the plans equal the host-branching planner's field by field over many random graphs and queries
(Euclidean, walls with unreachable subgoals and isolated starts, integer distances full of ties, asymmetric
distances, truncation, no graph, empty batches); the tracker's waypoints and state equal it over random walks with
new subgoals, rebuilds and partial resets; ``torch.compile(fullgraph=True)`` traces it and agrees; the acting
policy has no graph break with it and several without it; the collector's ``compile_policy`` and the recipe's key.
"""

import math

import pytest
import torch
from tensordict import TensorDict
from test_planner import line_of_sight_distance as walled  # U-wall: unreachable subgoals

from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph, floyd_warshall, reconstruct_paths

INF = math.inf


def euclidean(states, goals):
    return (goals - states[..., :2]).norm(dim=-1)


def rounded(states, goals):  # integer distances: ties everywhere
    return euclidean(states, goals).ceil()


def asymmetric(states, goals):
    delta = goals - states[..., :2]
    return delta.norm(dim=-1) + 0.5 * delta[..., 1].clamp_min(0)


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


# ----------------------------------------------------------------------------- tracking
def _planner_pair(distance, max_path_length=4, reach_radius=0.5, fixed_size=False, plan_on_demand=True):
    graph = LandmarkGraph(cutoff=3.0, max_landmarks=64, fixed_size=fixed_size)
    make = lambda capturable: GraphPlanner(  # noqa: E731
        graph,
        distance,
        2,
        reach_radius=reach_radius,
        max_path_length=max_path_length,
        capturable=capturable,
        plan_on_demand=plan_on_demand,
    )
    return graph, make(False), make(True)


def _set_random_landmarks(graph, distance, gen, num):
    points = torch.rand(num, 2, generator=gen) * 12 - 2
    graph.set_landmarks(torch.cat([points, torch.zeros(num, 2)], -1), points, distance)


def _walk(gen, batch, steps):
    """Observations drifting in the maze, subgoals re-drawn where ``new_subgoal``."""
    obs = torch.rand(*batch, 4, generator=gen) * 12 - 2
    subgoal = torch.rand(*batch, 2, generator=gen) * 12 - 2
    for _ in range(steps):
        obs = obs + torch.randn(obs.shape, generator=gen) * 0.4
        new = torch.rand(*batch, 1, generator=gen) < 0.15
        subgoal = torch.where(new, torch.rand(*batch, 2, generator=gen) * 12 - 2, subgoal)
        yield obs.clone(), new, subgoal.clone()


def _step_td(td, obs, new, subgoal):
    td = td.clone()
    td["observation"], td["achieved_goal"] = obs, obs[..., :2].clone()
    td["new_subgoal"], td["subgoal"] = new, subgoal
    return td


def _assert_same_tracking(got, expected, planner, exact=True):
    for key in ("waypoint", *planner._state_keys.values()):
        if exact or not expected[key].is_floating_point():
            assert torch.equal(got[key], expected[key]), key
        else:  # compiled distances: float round-off in the budgets
            torch.testing.assert_close(got[key], expected[key], rtol=1e-5, atol=1e-5, msg=str(key))


@pytest.mark.parametrize("plan_on_demand", [True, False])
@pytest.mark.parametrize("fixed_size", [False, True])
@pytest.mark.parametrize("name", ["walled", "rounded"])
def test_capturable_tracking_equals_tracking_over_random_walks(name, fixed_size, plan_on_demand):
    """Waypoints and every tracking entry, step by step, ``[3, 2]`` envs: new subgoals, timeouts and radius
    advances, truncated paths used up, two rebuilds (other landmark counts) and a partial reset; on the
    graph's own buffers and on a fixed-size graph's padded copies; planning only in the calls where a replan
    is due, or at every call."""
    distance = DISTANCES[name]
    gen = torch.Generator().manual_seed(7)
    graph, planner, capturable = _planner_pair(
        distance, reach_radius=1.0, fixed_size=fixed_size, plan_on_demand=plan_on_demand
    )
    batch = (3, 2)
    td = TensorDict(batch_size=batch)
    mine = theirs = None
    replans = 0
    for step, (obs, new, subgoal) in enumerate(_walk(gen, batch, 80)):
        if step in (0, 30, 55):
            _set_random_landmarks(graph, distance, gen, num=(25, 40, 12)[(0, 30, 55).index(step)])
        if step == 45:  # a partial reset (env mode): only the active envs get a fresh plan
            reset = torch.rand(*batch, 1, generator=gen) < 0.5
            fresh = _step_td(td, obs, new, subgoal).exclude("planner")
            theirs = planner._reset(theirs.set("_reset", reset), fresh.clone())
            mine = capturable._reset(mine.set("_reset", reset), fresh.clone())
            _assert_same_tracking(mine, theirs, planner)
            continue
        theirs = planner(_step_td(td if theirs is None else theirs, obs, new, subgoal))
        mine = capturable(_step_td(td if mine is None else mine, obs, new, subgoal))
        _assert_same_tracking(mine, theirs, planner)
        replans += int((theirs["planner", "index"] == 0).sum())
    assert replans > 0 and bool(theirs["planner", "has_plan"].all())


@pytest.mark.parametrize("plan_on_demand", [True, False])
def test_capturable_planner_queries_the_distance_only_when_a_replan_is_due(plan_on_demand):
    """``plan_on_demand``: the distance is evaluated in exactly the calls where the host-branching planner plans
    (some env due for a replan); without it, at every call. The tracking agrees either way (test above)."""
    calls = {"host": 0, "capturable": 0}

    def counting(who):
        def distance(states, goals):
            calls[who] += 1
            return euclidean(states, goals)

        return distance

    gen = torch.Generator().manual_seed(5)
    graph, planner, capturable = _planner_pair(euclidean, reach_radius=1.0, plan_on_demand=plan_on_demand)
    _set_random_landmarks(graph, euclidean, gen, num=30)
    planner.distance, capturable.distance = counting("host"), counting("capturable")
    mine = theirs = TensorDict(batch_size=(3,))
    planned_calls = idle_calls = 0
    for obs, new, subgoal in _walk(gen, (3,), 40):
        before = dict(calls)
        theirs = planner(_step_td(theirs, obs, new, subgoal))
        mine = capturable(_step_td(mine, obs, new, subgoal))
        host_planned = calls["host"] > before["host"]
        capturable_planned = calls["capturable"] > before["capturable"]
        assert capturable_planned == (host_planned or not plan_on_demand)
        planned_calls += host_planned
        idle_calls += not host_planned
    assert planned_calls > 0 and idle_calls > 0  # both kinds of call happened


@pytest.mark.parametrize("plan_on_demand", [True, False])
def test_compiled_planner_with_the_learned_distance_plans_inside_torch_cond(plan_on_demand):
    """Under ``torch.compile(fullgraph=True)`` with the recipe's learned distance (``GoalDistance.from_loss``:
    the networks evaluated with the loss's parameters): one graph with the planning in a ``torch.cond``
    (``plan_on_demand``) or without any (every call); the same waypoints and tracking state as eager over a
    walk with new subgoals and a rebuild; the distance's networks left as they were. Dynamo's graph is run
    as traced (no inductor: its kernels are covered by the slow tests)."""
    agent, _ = _agent(True)
    planner = agent.planner
    planner.plan_on_demand = plan_on_demand
    networks = [planner.distance.actor, planner.distance.critic]
    before = [dict(net.named_parameters()) for net in networks]
    graphs = []

    def traced_as_is(gm, example_inputs):
        graphs.append(gm)
        return gm.forward

    torch._dynamo.reset()
    compiled = torch.compile(planner, backend=traced_as_is, fullgraph=True)
    obs_dim = planner.distance.observation_dim
    gen = torch.Generator().manual_seed(3)
    eager_td = compiled_td = TensorDict(batch_size=(4,))
    idle = 0
    for step, (obs, new, subgoal) in enumerate(_walk(gen, (4,), 16)):
        if step == 8:
            points = torch.rand(50, obs_dim, generator=gen) * 12 - 2
            planner.build(points, points[:, :2].clone())
        obs = torch.cat([obs, torch.zeros(4, obs_dim - 4)], -1)
        idle += not bool(new.any())
        eager_td = planner(_step_td(eager_td, obs, new, subgoal))
        compiled_td = compiled(_step_td(compiled_td, obs, new, subgoal))
        _assert_same_tracking(compiled_td, eager_td, planner)
    torch._dynamo.reset()  # the frames traced for this backend stay out of later tests' compilations
    assert idle > 0
    conds = [node for gm in graphs for node in gm.graph.nodes if node.target is torch.ops.higher_order.cond]
    assert bool(conds) is plan_on_demand
    assert [dict(net.named_parameters()) for net in networks] == before


@pytest.mark.slow
def test_capturable_planner_compiles_whole_and_agrees():
    """``torch.compile(fullgraph=True)``: no graph break in the planner's call (would raise), the same
    waypoints and state as eager over a walk with a rebuild to another landmark count."""
    torch._dynamo.reset()  # nothing cached from another test's backend
    gen = torch.Generator().manual_seed(11)
    graph, _, capturable = _planner_pair(euclidean)
    compiled = torch.compile(capturable, fullgraph=True)
    batch = (4,)
    eager_td = compiled_td = TensorDict(batch_size=batch)
    for step, (obs, new, subgoal) in enumerate(_walk(gen, batch, 24)):
        if step in (0, 12):
            _set_random_landmarks(graph, euclidean, gen, num=(20, 33)[step // 12])
        eager_td = capturable(_step_td(eager_td, obs, new, subgoal))
        compiled_td = compiled(_step_td(compiled_td, obs, new, subgoal))
        _assert_same_tracking(compiled_td, eager_td, capturable, exact=False)
        compiled_td = eager_td.clone()  # keeps a budget's round-off from flipping a later timeout


@pytest.mark.slow
def test_fixed_size_planner_is_not_recompiled_by_rebuilds():
    """On a ``fixed_size`` graph the compiled planner survives rebuilds to other landmark counts and a clear
    without recompiling (``fail_on_recompile``) and agrees with eager; on a plain graph a rebuild recompiles."""
    for fixed_size in (True, False):
        torch._dynamo.reset()
        gen = torch.Generator().manual_seed(13)
        graph, _, capturable = _planner_pair(euclidean, fixed_size=fixed_size)
        compiled = torch.compile(capturable, fullgraph=True)
        eager_td = compiled_td = TensorDict(batch_size=(4,))
        recompiled = False
        for step, (obs, new, subgoal) in enumerate(_walk(gen, (4,), 16)):
            if step in (0, 5, 9, 13):  # 20 landmarks, then 33, none, 8
                _set_random_landmarks(graph, euclidean, gen, 20 + step) if step != 9 else graph.clear()
            stance = "fail_on_recompile" if step >= 2 else "default"  # two calls: without, then with state
            with torch.compiler.set_stance(stance):
                eager_td = capturable(_step_td(eager_td, obs, new, subgoal))
                try:
                    compiled_td = compiled(_step_td(compiled_td, obs, new, subgoal))
                except RuntimeError as err:
                    assert not fixed_size and "recompil" in str(err).lower(), err
                    recompiled = True
                    break
            _assert_same_tracking(compiled_td, eager_td, capturable, exact=False)
            compiled_td = eager_td.clone()
        assert recompiled is not fixed_size


# ----------------------------------------------------------------------------- acting policy and collector
def _agent(capturable_planner, num_cells=(16,)):
    from torchrl_dhrl.training import make_agent, make_environment

    env = make_environment("PointMaze", num_envs=2, seed=0, max_episode_steps=30)
    agent = make_agent(
        env,
        subgoal_low=[-2.0, -2.0],
        subgoal_high=[10.0, 10.0],
        subgoal_interval=5,
        goal_indices=[0, 1],
        low_num_cells=num_cells,
        high_num_cells=num_cells,
        capturable_planner=capturable_planner,
    )
    points = torch.rand(
        60, env.observation_spec["observation"].shape[-1], generator=torch.Generator().manual_seed(0)
    )
    points = points * 12 - 2
    agent.planner.build(points, points[:, :2])
    return agent, make_environment("PointMaze", num_envs=2, seed=0, max_episode_steps=30, agent=agent)


def test_acting_policy_has_no_graph_break_with_a_capturable_planner():
    counts = {}
    for capturable in (False, True):
        agent, env = _agent(capturable)
        td = env.reset()
        for _ in range(2):  # past the first step (a plan exists; the tracking branch)
            td = env.step(agent.policy(td))["next"]
        torch._dynamo.reset()
        counts[capturable] = torch._dynamo.explain(agent.policy)(td.clone()).graph_break_count
    assert counts[True] == 0
    assert counts[False] > 0  # the host-side replanning branch


def test_make_collector_compile_policy_needs_a_capturable_planner():
    from torchrl_dhrl.training import make_collector

    agent, env = _agent(False)
    with pytest.raises(ValueError, match="`compile_policy` needs a capturable planner"):
        make_collector(env, agent, 30, compile_policy=True)
    make_collector(env, agent, 30).shutdown()  # the default needs nothing


@pytest.mark.slow
def test_compiled_collector_collects_what_the_eager_one_does():
    """The collector's ``compile_policy`` with a capturable planner: the same two batches as an eager
    collector with the host-branching planner (inductor's random ops falling back to eager's)."""
    from torch._inductor import config as inductor_config

    from torchrl_dhrl.training import make_collector

    batches = {}
    for compiled in (False, True):
        torch.manual_seed(0)
        agent, env = _agent(compiled)
        torch.manual_seed(1)
        collector = make_collector(env, agent, 30, compile_policy={"warmup": 1} if compiled else False)
        with inductor_config.patch(fallback_random=True):
            it = iter(collector)
            batches[compiled] = torch.cat([next(it), next(it)])
        collector.shutdown()
    for key in (("next", "observation"), "action", "waypoint", "subgoal", ("planner", "path")):
        expected = batches[False][key]
        if expected.is_floating_point():
            torch.testing.assert_close(batches[True][key], expected, rtol=1e-4, atol=1e-4, msg=str(key))
        else:
            assert torch.equal(batches[True][key], expected), key


def test_compile_policy_key_is_validated_and_reaches_the_planner_and_collector():
    from _recipe import recipe_config
    from dhrl_utils import build_run

    from torchrl_dhrl.training import RESUME_MUTABLE_KEYS, ConfigError, validate_config

    assert "compile_policy" in RESUME_MUTABLE_KEYS  # same plans: a resumed run may switch it
    with pytest.raises(ConfigError, match="`compile_policy` must be true or false, got 'yes'"):
        validate_config(recipe_config("env=PointMaze", "device=cpu", "compile_policy=yes"))
    for value in (False, True):
        cfg = recipe_config("env=PointMaze", "preset=smoke", f"compile_policy={str(value).lower()}")
        validate_config(cfg)
        parts = build_run(cfg, torch.device("cpu"))
        assert parts.agent.planner.capturable is value
        assert parts.collector.compiled_policy is value
        parts.collector.shutdown()


@pytest.mark.slow
def test_recipe_runs_with_a_compiled_policy_and_resumes_without_it(tmp_path, capsys):
    from _recipe import load_recipe, metrics_rows, recipe_config

    recipe = load_recipe()
    overrides = ("env=PointMaze", "preset=smoke", "logger.backend=csv", "plots.every_epochs=0", "device=cpu")
    torch.manual_seed(0)
    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    recipe.train(recipe_config(*overrides, "total_steps=240", "compile_policy=true"), run_dir=tmp_path)
    assert "Acting: the policy compiled in the collector" in capsys.readouterr().out
    # one graph: nothing of the recipe's (e.g. a timing hook on the planner) breaks the compiled policy
    assert not torch._dynamo.utils.counters["graph_break"], dict(torch._dynamo.utils.counters["graph_break"])
    assert all("time/planner_ms_per_call" not in row for row in metrics_rows(tmp_path))
    summary = recipe.train(
        recipe_config(*overrides, "total_steps=480", f"resume={tmp_path}", "compile_policy=false"),
        run_dir=tmp_path,
    )
    printed = capsys.readouterr().out
    assert "Acting: the policy compiled" not in printed and "compile_policy" in printed  # the resume note
    assert summary["env_steps"] == 480 and 0.0 <= summary["eval/success"] <= 1.0
    timed = [row["time/planner_ms_per_call"] != "" for row in metrics_rows(tmp_path)]
    assert timed and timed[-1]  # the eager segment times the planner again
