"""Benchmark of the graph level: batched planner queries, graph rebuilds and all-pairs shortest paths.

Prints, in one run and side by side:

1. a planner query for a batch of envs (default 16 envs, 500 landmarks, oracle distance) against the
   reference-style approach (networkx graph copy + Dijkstra, one query at a time), plus the per-step
   tracking cost;
2. a full graph rebuild (FPS over 6000 candidates to 500 landmarks, the 500 x 500 distance matrix and
   all-pairs shortest paths) with a distance of realistic cost: a 3x256 ReLU actor and twin critic
   (obs_dim 29, goal_dim 2) evaluated for every pair, whose *values* are a geometric distance so
   that FPS behaves as with a trained critic; the previous build (lazy FPS without proxy, 256
   candidates per round) against the current one (goal proxy, 64 per round);
3. the same rebuild with the library's own distance, ``GoalDistance(LowLevelActor,
   GoalConditionedCritic)`` (3x256, twin critic in one stacked-weight ensemble), first trained for a
   few hundred steps to regress the geometric distance (a "trained-like" network): the previous
   build and distance settings (no proxy, 65536 pairs per forward) against the current defaults in
   float32 and with ``build_autocast_dtype=torch.bfloat16``, interleaved; then the accuracy of the
   bfloat16 path (distance errors, landmark overlap, edges and path costs);
4. the all-pairs step alone: ours (torch Floyd-Warshall with next-hop table) against scipy's
   Floyd-Warshall (with predecessors);
5. the gradual penalty's graph query of one high-level update (paper sizes: 300 landmarks, the 20% of a
   1024 batch that are subgoal tests, the 3x256 distance model): the full minimum over landmarks
   against ``distance_from_graph(at_most=3 x cutoff)`` (16 candidates first), with the far/near
   decisions compared, and the capture-safe form (``capturable=True``: every subgoal of the batch against
   all ``max_landmarks`` rows of a fixed-size graph, what the high level's captured sampling evaluates).

Run ``python benchmarks/bench_planner.py`` (``--quick`` for a smoke run, ``--dense`` to also time
dense FPS instead of extrapolating it, ``--rebuild-repeats`` for more interleaved rebuilds).
Timings on a shared machine are noisy: compare the ratios of rows measured in the same run.
"""

from __future__ import annotations

import argparse
import statistics
import time

import networkx as nx
import numpy as np
import torch
from scipy.sparse.csgraph import floyd_warshall as scipy_floyd_warshall
from tensordict import TensorDict
from torch import nn

from torchrl_dhrl.modules import GoalConditionedCritic, LowLevelActor
from torchrl_dhrl.planner import (
    GoalDistance,
    GraphPlanner,
    LandmarkGraph,
    farthest_point_sampling,
    floyd_warshall,
)
from torchrl_dhrl.planner.distances import DEFAULT_CPU_CHUNK_SIZE

#: The previous build settings: lazy FPS without proxy, 256 candidates per round (same evaluations
#: as the previous implementation, pair for pair).
OLD_GRAPH = {"fps_proxy": None, "fps_lazy_batch": 256}
#: The previous GoalDistance chunk (pairs per forward pass).
OLD_CHUNK = 65536

SPEED = 0.1  # goal units per env step: landmarks ~1 unit apart are ~10 steps apart
CUTOFF = 30.0


def oracle_distance(states, goals):
    return (goals - states[..., :2]).norm(dim=-1) / SPEED


def mlp(in_dim, out_dim, width=256, depth=3):
    layers, dim = [], in_dim
    for _ in range(depth):
        layers += [nn.Linear(dim, width), nn.ReLU()]
        dim = width
    return nn.Sequential(*layers, nn.Linear(dim, out_dim))


class MLPDistance(nn.Module):
    """Learned-distance cost model: actor pi(s, g) then twin critics Q(s, g, a), min over the twin.

    Every pair pays the full network cost; the returned value is the geometric distance plus a
    negligible network term, so farthest point sampling selects realistic landmark sets.
    """

    def __init__(self, obs_dim=29, goal_dim=2, action_dim=8):
        super().__init__()
        self.actor = mlp(obs_dim + goal_dim, action_dim)
        self.q1 = mlp(obs_dim + goal_dim + action_dim, 1)
        self.q2 = mlp(obs_dim + goal_dim + action_dim, 1)
        self.pairs = 0

    @torch.no_grad()
    def forward(self, states, goals):
        shape = torch.broadcast_shapes(states.shape[:-1], goals.shape[:-1])
        s = states.expand(*shape, states.shape[-1]).reshape(-1, states.shape[-1])
        g = goals.expand(*shape, goals.shape[-1]).reshape(-1, goals.shape[-1])
        self.pairs += s.shape[0]
        x = torch.cat([s, g - s[:, :2]], -1)
        a = self.actor(x).tanh()
        y = torch.cat([x, a.to(x.dtype)], -1)
        q = torch.minimum(self.q1(y), self.q2(y)).squeeze(-1).float()
        d = (g - s[:, :2]).norm(dim=-1) / SPEED
        return (d + 1e-6 * torch.nn.functional.softplus(-q)).reshape(shape)


class Counting:
    """Counts the pairs a distance evaluates, also through its ``with_autocast`` copies."""

    def __init__(self, distance, counter=None):
        self.distance = distance
        self.counter = counter if counter is not None else {"pairs": 0}

    def __call__(self, states, goals):
        out = self.distance(states, goals)
        self.counter["pairs"] += out.numel()
        return out

    def with_autocast(self, dtype):
        return Counting(self.distance.with_autocast(dtype), self.counter)

    @property
    def pairs(self):
        return self.counter["pairs"]

    def reset(self):
        self.counter["pairs"] = 0


def timed(fn, repeats):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def points(num, side, obs_dim, gen):
    goals = torch.rand(num, 2, generator=gen) * side
    states = torch.cat([goals, torch.randn(num, obs_dim - 2, generator=gen) * 0.1], -1)
    return states, goals


def reference_query(graph_nx, landmark_states, landmark_goals, state, subgoal):
    """Reference style: copy the graph, add start and goal, loop over landmarks in Python, Dijkstra."""
    g = graph_nx.copy()
    to_landmarks = oracle_distance(state.unsqueeze(0), landmark_goals).tolist()
    from_landmarks = oracle_distance(landmark_states, subgoal.unsqueeze(0)).tolist()
    for k, d in enumerate(to_landmarks):
        if d < CUTOFF:
            g.add_edge("start", k, weight=d)
    for k, d in enumerate(from_landmarks):
        if d < CUTOFF:
            g.add_edge(k, "goal", weight=d)
    direct = float(oracle_distance(state, subgoal))
    if direct < CUTOFF:
        g.add_edge("start", "goal", weight=direct)
    try:
        return nx.dijkstra_path(g, "start", "goal")
    except (nx.NetworkXNoPath, nx.NodeNotFound):
        return ["goal"]


def bench_query(args, gen):
    print(f"\n== 1. planner query: {args.envs} envs, {args.landmarks} landmarks, oracle distance ==")
    side = (args.landmarks**0.5) * 1.0  # ~1 unit (10 steps) between neighbouring landmarks
    states, goals = points(args.landmarks, side, 29, gen)
    planner = GraphPlanner(LandmarkGraph(cutoff=CUTOFF), oracle_distance, 2, max_path_length=32)
    planner.graph.set_landmarks(states, goals, oracle_distance)
    degree = planner.edges.shape[0] / args.landmarks
    q_states, q_goals = points(args.envs, side, 29, gen)
    q_subgoals = torch.rand(args.envs, 2, generator=gen) * side

    ours = timed(lambda: planner.plan(q_states, q_subgoals), args.repeats)
    td = TensorDict(
        observation=q_states,
        achieved_goal=q_goals,
        subgoal=q_subgoals,
        new_subgoal=torch.ones(args.envs, 1, dtype=torch.bool),
        batch_size=[args.envs],
    )
    replan_step = timed(lambda: planner(td.clone()), args.repeats)
    tracked = planner(td.clone())
    tracked["new_subgoal"].zero_()
    track_step = timed(lambda: planner(tracked.clone()), args.repeats)

    graph_nx = nx.DiGraph()
    graph_nx.add_nodes_from(range(args.landmarks))
    graph_nx.add_weighted_edges_from(
        (i, j, w) for (i, j), w in zip(planner.edges.tolist(), planner.edge_costs.tolist(), strict=True)
    )
    single = timed(
        lambda: reference_query(graph_nx, states, goals, q_states[0], q_subgoals[0]),
        max(3, args.repeats // 10),
    )
    batch_ref = single * args.envs
    print(f"graph: {args.landmarks} nodes, {degree:.1f} edges per node, cutoff {CUTOFF} steps")
    print(f"{'':40s}{'time':>12s}{'vs ours':>10s}")
    print(f"{'ours: plan(), batch of ' + str(args.envs):40s}{ours * 1e3:10.3f}ms{1.0:10.1f}x")
    print(f"{'ours: planner(td), all envs replan':40s}{replan_step * 1e3:10.3f}ms{replan_step / ours:10.1f}x")
    print(f"{'ours: planner(td), tracking only':40s}{track_step * 1e3:10.3f}ms{track_step / ours:10.1f}x")
    print(f"{'reference style: one query':40s}{single * 1e3:10.3f}ms{single / ours:10.1f}x")
    print(
        f"{'reference style: batch of ' + str(args.envs):40s}"
        f"{batch_ref * 1e3:10.3f}ms{batch_ref / ours:10.1f}x"
    )


def bench_rebuild(args, gen):
    print(
        f"\n== 2. graph rebuild: FPS {args.candidates} -> {args.landmarks} + distances + all-pairs, "
        "3x256 MLP actor + twin critic (cost model, geometric values) =="
    )
    side = (args.landmarks**0.5) * 1.0
    cand_states, cand_goals = points(args.candidates, side, 29, gen)
    distance = Counting(MLPDistance())
    per_pair = timed(lambda: distance(cand_states, cand_goals), 3) / args.candidates

    rows = {name: ([], [], [], [], None, None) for name in ("old", "new")}
    for _ in range(args.rebuild_repeats):  # interleaved, so that load changes hit both rows alike
        for name, options in (("old", OLD_GRAPH), ("new", {})):
            distance.reset()
            start = time.perf_counter()
            fps = farthest_point_sampling(
                cand_states,
                cand_goals,
                distance,
                args.landmarks,
                early_stop=0.0,
                proxy=options.get("fps_proxy", "goal"),
                lazy_batch=options.get("fps_lazy_batch", 64),
            )
            fps_time, fps_pairs = time.perf_counter() - start, distance.pairs
            graph = LandmarkGraph(cutoff=CUTOFF, max_landmarks=args.landmarks, early_stop=0.0, **options)
            distance.reset()
            start = time.perf_counter()
            graph.build(cand_states, cand_goals, distance)
            build_time = time.perf_counter() - start
            row = rows[name]
            row[0].append(fps_pairs)
            row[1].append(fps_time)
            row[2].append(distance.pairs)
            row[3].append(build_time)
            rows[name] = (*row[:4], fps, graph)
    rows = {
        name: (row[0][0], statistics.median(row[1]), row[2][0], statistics.median(row[3]), row[4], row[5])
        for name, row in rows.items()
    }
    dense_pairs = args.landmarks * args.candidates
    if args.dense:
        distance.reset()
        start = time.perf_counter()
        farthest_point_sampling(
            cand_states, cand_goals, distance, args.landmarks, early_stop=0.0, strategy="dense"
        )
        dense_time = time.perf_counter() - start
        dense_label = "measured"
    else:
        dense_time = dense_pairs * per_pair
        dense_label = "extrapolated"
    print(f"network cost: {per_pair * 1e6:.2f} us per pair (batch {args.candidates})")
    print(
        f"{'median of ' + str(args.rebuild_repeats) + ' interleaved runs':52s}{'pairs':>10s}{'time':>9s}{'vs old':>8s}"
    )
    print(f"{'FPS, dense (' + dense_label + ')':52s}{dense_pairs:10d}{dense_time:8.2f}s")
    for label, index in (("FPS only", 0), ("full build", 2)):
        old_time = rows["old"][index + 1]
        for name, text in (
            ("old", "old (no proxy, 256/round)"),
            ("new", "new (goal proxy, 64/round)"),
        ):
            pairs, elapsed = rows[name][index], rows[name][index + 1]
            print(f"{label + ', ' + text:52s}{pairs:10d}{elapsed:8.2f}s{old_time / elapsed:7.1f}x")
    print("full build = lazy FPS + the missing landmark pairs + all-pairs shortest paths")
    print("same landmarks (exact greedy selection) with both: True")
    graph = rows["new"][5]
    assert torch.equal(graph.landmark_goals, cand_goals[rows["new"][4].indices])
    return graph


def trained_like_distance(args, side, gen):
    """A GoalDistance of the library's modules, its critic regressed onto the geometric distance."""
    torch.manual_seed(1)
    actor = LowLevelActor(29, 2, action_max=30.0, action_dim=8, goal_indices=(0, 1))
    critic = GoalConditionedCritic(
        29, 2, action_max=30.0, action_dim=8, relative_goal=True, goal_indices=(0, 1)
    )
    net = critic.module
    optim = torch.optim.Adam(net.parameters(), lr=1e-3)

    def sample(num):
        start, _ = points(num, side, 29, gen)
        far = torch.rand(num, 2, generator=gen) * side
        near = start[:, :2] + torch.randn(num, 2, generator=gen) * 2.0
        goals = torch.where(torch.rand(num, 1, generator=gen) < 0.5, near, far)
        return start, goals

    for _ in range(args.train_steps):
        states, goals = sample(256)
        with torch.no_grad():
            action = actor.module(states, goals)
        raw = net.ensemble(net.features(states, goals, action)).squeeze(-1)
        target = (goals - states[:, :2]).norm(dim=-1) / SPEED
        loss = torch.nn.functional.smooth_l1_loss(
            torch.nn.functional.softplus(raw) / 10, target.expand_as(raw) / 10
        )
        optim.zero_grad()
        loss.backward()
        optim.step()
    return actor, critic, sample


def error_stats(value, reference):
    abs_err = (value - reference).abs()
    rel_err = abs_err / reference.abs().clamp_min(1.0)
    quantiles = torch.tensor([0.5, 0.99])
    return abs_err.quantile(quantiles).tolist() + [abs_err.max().item()], rel_err.quantile(
        quantiles
    ).tolist() + [rel_err.max().item()]


def bench_goal_distance(args, gen):
    print(
        f"\n== 3. graph rebuild with the library's GoalDistance (LowLevelActor + GoalConditionedCritic, "
        f"3x256, trained-like), FPS {args.candidates} -> {args.landmarks} =="
    )
    side = (args.landmarks**0.5) * 1.0
    start = time.perf_counter()
    actor, critic, sample = trained_like_distance(args, side, gen)
    cand_states, cand_goals = points(args.candidates, side, 29, gen)
    test_states, test_goals = sample(20000)
    fp32 = GoalDistance(actor, critic)
    fit = (fp32(test_states, test_goals) - (test_goals - test_states[:, :2]).norm(dim=-1) / SPEED).abs()
    print(
        f"trained-like critic: {args.train_steps} regression steps in {time.perf_counter() - start:.1f}s, "
        f"median |distance - geometric| {fit.median():.2f} steps"
    )

    # per-pair cost of one forward pass over 32768 pairs
    states_b, goals_b = test_states[:16384].repeat(2, 1), test_goals[:16384].repeat(2, 1)
    variants = {
        f"float32, {OLD_CHUNK} pairs per forward (old default)": GoalDistance(
            actor, critic, chunk_size=OLD_CHUNK
        ),
        f"float32, {DEFAULT_CPU_CHUNK_SIZE} pairs per forward (new CPU default)": fp32,
        f"bfloat16 autocast, {DEFAULT_CPU_CHUNK_SIZE} pairs per forward": fp32.with_autocast(torch.bfloat16),
    }
    costs = {name: [] for name in variants}
    for _ in range(3):  # interleaved
        for name, dist in variants.items():
            costs[name].append(timed(lambda dist=dist: dist(states_b, goals_b), 1) / states_b.shape[0])
    base = statistics.median(costs[next(iter(costs))])
    print(f"{'network cost, batch of 32768 pairs':52s}{'us/pair':>10s}{'vs old':>8s}")
    for name, values in costs.items():
        cost = statistics.median(values)
        print(f"{name:52s}{cost * 1e6:10.2f}{base / cost:7.1f}x")

    configs = {
        "old: no proxy, 256/round, 65536/forward, fp32": (
            OLD_GRAPH,
            GoalDistance(actor, critic, chunk_size=OLD_CHUNK),
        ),
        "new defaults, float32": ({}, fp32),
        "new, build_autocast_dtype=bfloat16": ({"build_autocast_dtype": torch.bfloat16}, fp32),
    }
    times = {name: [] for name in configs}
    cpu_times = {name: [] for name in configs}
    graphs, pairs = {}, {}
    for _ in range(args.rebuild_repeats):  # interleaved, so that load changes hit every row alike
        for name, (options, dist) in configs.items():
            counting = Counting(dist)
            graph = LandmarkGraph(cutoff=CUTOFF, max_landmarks=args.landmarks, early_stop=0.0, **options)
            start, start_cpu = time.perf_counter(), time.process_time()
            graph.build(cand_states, cand_goals, counting)
            times[name].append(time.perf_counter() - start)
            cpu_times[name].append(time.process_time() - start_cpu)
            graphs[name], pairs[name] = graph, counting.pairs
    old_name, fp32_name, bf16_name = configs
    old_time, old_cpu = statistics.median(times[old_name]), statistics.median(cpu_times[old_name])
    print(
        f"{'full rebuild (median of ' + str(args.rebuild_repeats) + ')':52s}{'pairs':>10s}{'time':>9s}"
        f"{'vs old':>8s}{'CPU time':>10s}{'vs old':>8s}"
    )
    for name in configs:
        elapsed, cpu = statistics.median(times[name]), statistics.median(cpu_times[name])
        print(
            f"{name:52s}{pairs[name]:10d}{elapsed:8.2f}s{old_time / elapsed:7.1f}x"
            f"{cpu:9.2f}s{old_cpu / cpu:7.1f}x"
        )
    print(
        "(CPU time: all threads of this process, steadier than the wall-clock time on a machine shared "
        "with other jobs; with --threads 1 on an idle machine the two are equal)"
    )
    old_ids = {tuple(x) for x in graphs[old_name].landmark_goals.tolist()}
    new_ids = {tuple(x) for x in graphs[fp32_name].landmark_goals.tolist()}
    shared = len(old_ids & new_ids)
    if shared == len(old_ids):
        diff = (graphs[old_name].landmark_distances - graphs[fp32_name].landmark_distances).abs().max().item()
        detail = f"max |distance matrix difference| {diff:.2g} steps"
    else:
        detail = "FPS met a near-tie"
    print(
        f"old vs new float32 build: {shared} of {len(old_ids)} landmarks shared, {detail} (the same greedy "
        "selection; a pair evaluated in a batch of another size may differ in the last float bits)"
    )

    print("accuracy of the bfloat16 path against float32:")
    bf16 = fp32.with_autocast(torch.bfloat16)
    abs_err, rel_err = error_stats(bf16(test_states, test_goals), fp32(test_states, test_goals))
    print(
        "  distance, 20000 random pairs: |error| median/p99/max "
        + "/".join(f"{x:.3f}" for x in abs_err)
        + " steps, relative "
        + "/".join(f"{x * 100:.2f}" for x in rel_err)
        + " %"
    )
    ref_graph, fast_graph = graphs[fp32_name], graphs[bf16_name]
    ref_ids = {tuple(x) for x in ref_graph.landmark_goals.tolist()}
    fast_ids = {tuple(x) for x in fast_graph.landmark_goals.tolist()}
    print(
        f"  FPS landmarks shared by the float32 and bfloat16 builds: {len(ref_ids & fast_ids)} of "
        f"{len(ref_ids)}; coverage radius {ref_graph.coverage_radius.item():.2f} vs "
        f"{fast_graph.coverage_radius.item():.2f} steps"
    )
    # the same landmarks, distance matrix in bfloat16: edges and all-pairs path costs
    same_lm = LandmarkGraph(cutoff=CUTOFF, max_landmarks=args.landmarks, build_autocast_dtype=torch.bfloat16)
    same_lm.set_landmarks(ref_graph.landmark_states, ref_graph.landmark_goals, fp32)
    edges_ref, edges_fast = ref_graph.edge_mask, same_lm.edge_mask
    agree = (edges_ref == edges_fast).float().mean().item()
    print(
        f"  same landmarks, bfloat16 matrix: {int(edges_ref.sum())} vs {int(edges_fast.sum())} edges, "
        f"{int((edges_ref != edges_fast).sum())} pairs differ ({agree * 100:.3f}% agree)"
    )
    finite = torch.isfinite(ref_graph.shortest_distances) & torch.isfinite(same_lm.shortest_distances)
    off_diag = ~torch.eye(ref_graph.num_landmarks, dtype=torch.bool)
    _, rel_paths = error_stats(
        same_lm.shortest_distances[finite & off_diag], ref_graph.shortest_distances[finite & off_diag]
    )
    print(
        "  same landmarks, all-pairs path costs: relative error median/p99/max "
        + "/".join(f"{x * 100:.2f}" for x in rel_paths)
        + " %"
    )
    q_states, _ = points(512, side, 29, gen)
    q_goals = torch.rand(512, 2, generator=gen) * side
    cost_ref = ref_graph.plan(q_states, q_goals, fp32).cost
    cost_fast = fast_graph.plan(q_states, q_goals, fp32).cost
    ok = torch.isfinite(cost_ref) & torch.isfinite(cost_fast)
    _, rel_plan = error_stats(cost_fast[ok], cost_ref[ok])
    print(
        "  512 plans (float32 queries) on the bfloat16-built vs float32-built graph: cost difference "
        "median/p99/max "
        + "/".join(f"{x * 100:.2f}" for x in rel_plan)
        + f" % ({int(ok.sum())} reachable in both)"
    )


def bench_apsp(args, graph):
    print(f"\n== 4. all-pairs shortest paths on the rebuilt graph ({graph.num_landmarks} nodes) ==")
    weights = graph.edge_weights
    ours = timed(lambda: floyd_warshall(weights), max(3, args.repeats // 10))
    dense = weights.double().numpy().copy()
    dense[~np.isfinite(dense)] = 0.0  # scipy dense input: 0 means "no edge" (weights here are > 0)
    scipy_time = timed(
        lambda: scipy_floyd_warshall(dense, directed=True, return_predecessors=True),
        max(3, args.repeats // 10),
    )
    ref = scipy_floyd_warshall(dense, directed=True)
    got = floyd_warshall(weights).distances.double().numpy()
    assert np.allclose(np.where(np.isfinite(ref), ref, -1), np.where(np.isfinite(got), got, -1), rtol=1e-4)
    print(f"{'':44s}{'time':>10s}{'vs scipy':>10s}")
    print(f"{'ours (torch, next-hop + hop counts)':44s}{ours * 1e3:8.1f}ms{ours / scipy_time:10.2f}x")
    print(f"{'scipy floyd_warshall (predecessors)':44s}{scipy_time * 1e3:8.1f}ms{1.0:10.2f}x")


def bench_penalty_query(args, gen):
    side = 200.0  # goal units: FPS spreads 300 landmarks about 12 units (120 steps) apart
    states, goals = points(args.candidates, side, 29, gen)
    distance = MLPDistance()
    graph = LandmarkGraph(cutoff=CUTOFF, max_landmarks=args.penalty_landmarks, early_stop=0.0)
    graph.build(states, goals, distance)
    k = graph.num_landmarks
    # tested subgoals: most near explored space (landmark + noise), some anywhere (possibly far)
    num = args.penalty_subgoals
    near = (
        graph.landmark_goals[torch.randint(0, k, (num,), generator=gen)]
        + torch.randn(num, 2, generator=gen) * 3
    )
    anywhere = torch.rand(num, 2, generator=gen) * side * 1.2 - side * 0.1
    subgoals = torch.where(torch.rand(num, 1, generator=gen) < 0.8, near, anywhere)
    threshold = 3 * CUTOFF
    counting = Counting(distance)
    full = graph.distance_from_graph(subgoals, counting)
    full_pairs = counting.pairs
    counting.reset()
    fast = graph.distance_from_graph(subgoals, counting, at_most=threshold)
    fast_pairs = counting.pairs
    same = torch.equal(full > threshold, fast > threshold)
    t_full = timed(lambda: graph.distance_from_graph(subgoals, distance), max(1, args.repeats // 10))
    t_fast = timed(
        lambda: graph.distance_from_graph(subgoals, distance, at_most=threshold), max(1, args.repeats // 10)
    )
    print(
        f"\n5. gradual-penalty query: {num} tested subgoals x {k} landmarks, far = beyond {threshold:.0f} steps "
        f"({int((full > threshold).sum())} far)"
    )
    print(f"   full minimum        {t_full * 1e3:9.1f} ms  {full_pairs:>8} pairs")
    print(
        f"   at_most (16 first)  {t_fast * 1e3:9.1f} ms  {fast_pairs:>8} pairs   x{t_full / t_fast:.1f} faster, same far/near decisions: {same}"
    )
    # the capture-safe form (the high level's sampling inside its CUDA graphs): every subgoal of the batch, not only
    # the tested ones, against all max_landmarks rows of a fixed-size graph, static shapes
    fixed = LandmarkGraph(cutoff=CUTOFF, max_landmarks=args.penalty_landmarks, fixed_size=True)
    fixed.set_landmarks(graph.landmark_states, graph.landmark_goals, distance)
    batch = torch.cat([subgoals] * round(1 / 0.2))  # the whole batch whose 20% are the tested subgoals
    counting.reset()
    exact = fixed.distance_from_graph(batch, counting, capturable=True)
    captured_pairs = counting.pairs
    same = torch.equal(exact[:num] > threshold, fast > threshold)
    t_captured = timed(
        lambda: fixed.distance_from_graph(batch, distance, capturable=True), max(1, args.repeats // 10)
    )
    print(
        f"   capturable, batch {batch.shape[0]:>4} {t_captured * 1e3:9.1f} ms  {captured_pairs:>8} pairs   "
        f"x{t_full / t_captured:.2f} the full minimum's speed, same far/near decisions: {same}"
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", type=int, default=16)
    parser.add_argument("--landmarks", type=int, default=500)
    parser.add_argument("--candidates", type=int, default=6000)
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--rebuild-repeats", type=int, default=3, help="interleaved rebuilds (sections 2, 3)")
    parser.add_argument("--train-steps", type=int, default=300, help="regression steps of the critic")
    parser.add_argument("--sections", default="12345", help="sections to run, e.g. 3 or 234")
    parser.add_argument("--penalty-landmarks", type=int, default=300, help="section 5 (paper: 300)")
    parser.add_argument("--penalty-subgoals", type=int, default=205, help="section 5 (0.2 x batch 1024)")
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    parser.add_argument("--dense", action="store_true", help="also time dense FPS (slow on CPU)")
    parser.add_argument("--quick", action="store_true", help="small sizes, for a smoke run")
    args = parser.parse_args()
    if args.quick:
        args.landmarks, args.candidates, args.repeats = 100, 1000, 5
        args.rebuild_repeats, args.train_steps = 1, 50
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(0)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, device cpu")
    if "1" in args.sections:
        bench_query(args, gen)
    graph = bench_rebuild(args, gen) if "2" in args.sections or "4" in args.sections else None
    if "3" in args.sections:
        bench_goal_distance(args, gen)
    if "4" in args.sections:
        bench_apsp(args, graph)
    if "5" in args.sections:
        bench_penalty_query(args, gen)


if __name__ == "__main__":
    main()
