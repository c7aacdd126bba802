"""Benchmark of the graph level: batched planner queries, graph rebuilds and all-pairs shortest paths.

Prints, in one run and side by side:

1. a planner query for a batch of envs (default 16 envs, 500 landmarks, oracle distance) against the
   reference-style approach (networkx graph copy + Dijkstra, one query at a time), plus the per-step
   tracking cost;
2. a full graph rebuild (FPS over 6000 candidates to 500 landmarks, the 500 x 500 distance matrix and
   all-pairs shortest paths) with a distance of realistic cost: a 3x256 ReLU actor and twin critic
   (obs_dim 29, goal_dim 2) evaluated for every pair, whose *values* are a geometric distance so
   that FPS behaves as with a trained critic;
3. the all-pairs step alone: ours (torch Floyd-Warshall with next-hop table) against scipy's
   Floyd-Warshall (with predecessors).

Run ``OMP_NUM_THREADS=1 python benchmarks/bench_planner.py`` (``--quick`` for a smoke run,
``--dense`` to also time dense FPS instead of extrapolating it).
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

from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph, farthest_point_sampling, floyd_warshall

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
        y = torch.cat([x, a], -1)
        q = torch.minimum(self.q1(y), self.q2(y)).squeeze(-1)
        d = (g - s[:, :2]).norm(dim=-1) / SPEED
        return (d + 1e-6 * torch.nn.functional.softplus(-q)).reshape(shape)


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
    planner = GraphPlanner(oracle_distance, 2, cutoff=CUTOFF, max_path_length=32)
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
        "3x256 MLP actor + twin critic =="
    )
    side = (args.landmarks**0.5) * 1.0
    cand_states, cand_goals = points(args.candidates, side, 29, gen)
    distance = MLPDistance()
    per_pair = timed(lambda: distance(cand_states, cand_goals), 3) / args.candidates
    distance.pairs = 0

    start = time.perf_counter()
    fps = farthest_point_sampling(cand_states, cand_goals, distance, args.landmarks, early_stop=0.0)
    fps_time = time.perf_counter() - start
    fps_pairs = distance.pairs
    graph = LandmarkGraph(cutoff=CUTOFF, max_landmarks=args.landmarks, early_stop=0.0)
    distance.pairs = 0
    start = time.perf_counter()
    graph.build(cand_states, cand_goals, distance)
    build_time = time.perf_counter() - start
    dense_pairs = args.landmarks * args.candidates
    if args.dense:
        distance.pairs = 0
        start = time.perf_counter()
        farthest_point_sampling(
            cand_states, cand_goals, distance, args.landmarks, early_stop=0.0, strategy="dense"
        )
        dense_time = time.perf_counter() - start
        dense_label = "measured"
    else:
        dense_time = dense_pairs * per_pair
        dense_label = "extrapolated from the per-pair cost"
    matrix_pairs = args.landmarks**2
    print(f"network cost: {per_pair * 1e6:.2f} us per pair (batch {args.candidates})")
    print(f"{'':44s}{'pairs':>12s}{'time':>10s}")
    print(f"{'FPS, lazy (default)':44s}{fps_pairs:12d}{fps_time:9.2f}s")
    print(f"{'FPS, dense (' + dense_label + ')':44s}{dense_pairs:12d}{dense_time:9.2f}s")
    print(f"{'full build (lazy FPS + missing pairs + APSP)':44s}{distance.pairs:12d}{build_time:9.2f}s")
    print(f"{'separate K x K matrix (not needed)':44s}{matrix_pairs:12d}{matrix_pairs * per_pair:9.2f}s")
    print(
        f"lazy / dense pair ratio {fps_pairs / dense_pairs:.2f}; "
        f"rebuild target 2 s would need <= {2.0 / dense_pairs * 1e6:.2f} us per pair with dense FPS"
    )
    assert torch.equal(graph.landmark_goals, cand_goals[fps.indices])
    return graph


def bench_apsp(args, graph):
    print(f"\n== 3. all-pairs shortest paths on the rebuilt graph ({graph.num_landmarks} nodes) ==")
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


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", type=int, default=16)
    parser.add_argument("--landmarks", type=int, default=500)
    parser.add_argument("--candidates", type=int, default=6000)
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--dense", action="store_true", help="also time dense FPS (slow on CPU)")
    parser.add_argument("--quick", action="store_true", help="small sizes, for a smoke run")
    args = parser.parse_args()
    if args.quick:
        args.landmarks, args.candidates, args.repeats = 100, 1000, 5
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(0)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, device cpu")
    bench_query(args, gen)
    graph = bench_rebuild(args, gen)
    bench_apsp(args, graph)


if __name__ == "__main__":
    main()
