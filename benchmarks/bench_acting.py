"""Cost of acting: the DHRL policy (high level + planner + low level) per call, eager and compiled.

Times one call of the acting policy ``TensorDictSequential(high_policy, planner, low_policy)`` on a batch of
``num_envs`` envs, inside a real rollout (the env steps between calls are not timed), for:

- ``eager``: the default planner, which plans only the envs that need a new plan, behind a host-side branch
  (``nonzero`` / ``.item()``; a host synchronisation per call on a GPU);
- ``eager capturable``: ``GraphPlanner(capturable=True)``: every env planned with static shapes in the calls
  where some env is due for a replan (``plan_on_demand``, a Python branch eagerly), the new plans kept where a
  replan is due (the same plans);
- ``compiled capturable``: the same policy under ``torch.compile(fullgraph=True)`` (one graph, no break; the
  planning inside a ``torch.cond``), what the recipe's ``compile_policy=true`` runs in the collector; its compile
  time is printed apart;
- ``... every call``: the capturable planner with ``plan_on_demand=False``: every env planned at every call
  (static control flow, the variant for a policy captured whole in a CUDA graph);
- ``captured (cudagraph_policy)`` (CUDA only): the capturable policy captured whole as one CUDA graph with
  :class:`tensordict.nn.CudaGraphModule`, what the recipe's ``cudagraph_policy=true`` runs in the collector
  (inputs copied in, one replay, outputs copied out; the planner plans every env in a replay); the warm-up and
  capture time is printed apart.

The graph is built once from random states of the maze's box with the agent's (untrained) learned distance,
so its landmarks and the distance network have the recipe's sizes (``--landmarks``, ``--hidden``).
Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_acting.py`` (``--device cuda`` on a GPU machine,
``--envs 1 8 64``). Figures are means in milliseconds per call and per env step (the default planner's cost
sits in the one call in ``c_h`` that replans), ratios to ``eager`` in the same run; a shared machine is noisy.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from tensordict.nn import CudaGraphModule
from torchrl.envs.utils import step_mdp

from torchrl_dhrl.factory import make_agent, make_environment


def build(args, num_envs, capturable, plan_on_demand=True):
    torch.manual_seed(0)
    device = torch.device(args.device)
    spec_env = make_environment(args.env, num_envs=num_envs, seed=0, max_episode_steps=args.steps)
    cells = {"num_cells": (args.hidden,) * args.depth}
    agent = make_agent(
        spec_env,
        device,
        goal_indices=[0, 1],
        high_policy={"subgoal_low": [-2.0, -2.0], "subgoal_high": [10.0, 10.0], "interval": args.c_h, **cells},
        high_critic=cells,
        low_actor=cells,
        low_critic=cells,
        graph={"max_landmarks": args.landmarks, "early_stop": 0.0},
        capturable_planner=capturable,
    )
    obs_dim = spec_env.observation_spec["observation"].shape[-1]
    gen = torch.Generator().manual_seed(1)
    states = (torch.rand(args.candidates, obs_dim, generator=gen) * 12 - 2).to(device)
    agent.planner.build(states, states[:, :2].clone())
    agent.planner.plan_on_demand = plan_on_demand
    env = make_environment(
        args.env, device, num_envs=num_envs, seed=0, max_episode_steps=args.steps, agent=agent
    )
    return agent, env


def time_policy(policy, env, steps, synchronize):
    """Mean seconds per policy call over a rollout of ``steps`` env steps (the env steps not timed).

    The mean, not the median: the default planner's cost sits in the one call in ``c_h`` that replans."""
    times = []
    with torch.no_grad():
        td = env.reset()
        for _ in range(steps):
            synchronize()
            start = time.perf_counter()
            td = policy(td)
            synchronize()
            times.append(time.perf_counter() - start)
            td = step_mdp(env.step(td))
    return statistics.fmean(times)


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--env", default="PointMaze")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--envs", type=int, nargs="+", default=[1, 8])
    parser.add_argument("--hidden", type=int, default=256)
    parser.add_argument("--depth", type=int, default=2, help="hidden layers (quick preset 2, paper 3)")
    parser.add_argument("--landmarks", type=int, default=300, help="max_landmarks (the paper's AntMaze: 300)")
    parser.add_argument("--candidates", type=int, default=2000)
    parser.add_argument("--c-h", type=int, default=10, help="env steps per subgoal (c_h)")
    parser.add_argument("--steps", type=int, default=200, help="timed calls per variant")
    parser.add_argument("--threads", type=int, default=None)
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    cuda = torch.device(args.device).type == "cuda"
    synchronize = torch.cuda.synchronize if cuda else (lambda: None)
    print(
        f"{args.env}, device {args.device}, {torch.get_num_threads()} threads, nets {args.depth}x{args.hidden}, "
        f"<= {args.landmarks} landmarks, c_h {args.c_h}, {args.steps} calls per variant (means)"
    )
    header = (
        f"{'envs':>5} {'variant':<34} {'ms/call':>9} {'ms/env step':>12} {'x eager':>8} {'compile s':>10}"
    )
    print(header)
    for num_envs in args.envs:
        base = None
        for name, capturable, compiled, on_demand in (
            ("eager", False, False, True),
            ("eager capturable", True, False, True),
            ("compiled capturable", True, True, True),
            ("eager capturable, every call", True, False, False),
            ("compiled capturable, every call", True, True, False),
            *([("captured (cudagraph_policy)", True, "cudagraph", True)] if cuda else []),
        ):
            agent, env = build(args, num_envs, capturable, on_demand)
            policy, compile_s = agent.policy, float("nan")
            if compiled == "cudagraph":
                policy = CudaGraphModule(agent.policy, warmup=2, device=torch.device(args.device))
                start = time.perf_counter()
                time_policy(policy, env, 4, synchronize)  # two eager warm-up calls, the capture, a replay
                compile_s = time.perf_counter() - start
            elif compiled:
                torch._dynamo.reset()
                policy = torch.compile(agent.policy, fullgraph=True)
                start = time.perf_counter()
                time_policy(policy, env, 3, synchronize)  # compiles (and settles the first recompile)
                compile_s = time.perf_counter() - start
            seconds = time_policy(policy, env, args.steps, synchronize)
            base = seconds if base is None else base
            row = (
                f"{num_envs:>5} {name:<34} {seconds * 1e3:>9.3f} {seconds * 1e3 / num_envs:>12.3f} "
                f"{base / seconds:>7.2f}x {compile_s:>10.1f}"
            )
            print(row, f"({agent.planner.num_landmarks} landmarks)" if name == "eager" else "", flush=True)


if __name__ == "__main__":
    main()
