"""Env-step throughput of the DHRL environments (mazes and arms): TorchRL API against raw MuJoCo.

For each environment, prints env steps per second (summed over the batch) of

* ``raw``: ``mujoco.mj_step(model, data, nstep=frame_skip)`` on one MjData of the same model with random
  controls written straight into ``MjData`` (the physics floor);
* ``torchrl N=1`` and ``torchrl N=16``: :class:`~torchrl_dhrl.envs.GoalEnv` with ``num_envs`` 1 and 16,
  random actions, ``env.step`` + ``step_mdp`` with automatic resets (``step_and_maybe_reset``);

and the cost per env step relative to raw physics (``ratio`` = TorchRL time / raw time per env step).
The target is a ratio of at most 2 at ``num_envs=16`` for the ant mazes. With ``--step-threads 2 4``, the 16
envs are also stepped by that many threads (``make_env(..., step_threads=k)``; MuJoCo integrates without the
GIL), and the speed-up over one thread is printed.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/bench_envs.py [--steps 2000] [--envs AntMaze Reacher3D UR3Obstacle]
    OMP_NUM_THREADS=1 python benchmarks/bench_envs.py --envs AntMaze --step-threads 2
"""

from __future__ import annotations

import argparse
import time

import mujoco
import numpy as np
import torch
from torchrl_dhrl.envs import ENV_NAMES, get_env_spec, make_env


def raw_steps_per_second(name: str, steps: int, seed: int = 0) -> float:
    """Env steps/s of bare ``mj_step(nstep=frame_skip)`` with random controls on one MjData."""
    spec = get_env_spec(name)
    agent = spec.agent
    model = spec.compile_model()
    data = mujoco.MjData(model)
    data.qpos[:] = agent.init_qpos
    rng = np.random.default_rng(seed)
    actions = rng.uniform(agent.action_low, agent.action_high, size=(steps, agent.action_dim))
    controls = agent.command(actions, np.zeros((steps, model.nq)))
    field = getattr(data, agent.control_field)
    start = time.perf_counter()
    for t in range(steps):
        field[:] = controls[t]
        mujoco.mj_step(model, data, agent.frame_skip)
    return steps / (time.perf_counter() - start)


def torchrl_steps_per_second(
    name: str, num_envs: int, steps: int, seed: int = 0, step_threads: int = 1
) -> float:
    """Env steps/s (summed over the batch) of ``GoalEnv`` stepped with ``step_and_maybe_reset``."""
    env = make_env(name, num_envs=num_envs, seed=seed, step_threads=step_threads)
    torch.manual_seed(seed)
    batched_steps = max(1, steps // num_envs)
    actions = env.action_spec.rand((batched_steps,))
    td = env.reset()
    for t in range(min(10, batched_steps)):  # warm-up
        td.set("action", actions[t])
        _, td = env.step_and_maybe_reset(td)
    start = time.perf_counter()
    for t in range(batched_steps):
        td.set("action", actions[t])
        _, td = env.step_and_maybe_reset(td)
    elapsed = time.perf_counter() - start
    env.close()
    return batched_steps * num_envs / elapsed


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--steps", type=int, default=2000, help="env steps per measurement")
    parser.add_argument(
        "--envs", "--mazes", dest="envs", nargs="+", default=list(ENV_NAMES), choices=list(ENV_NAMES)
    )
    parser.add_argument(
        "--step-threads",
        type=int,
        nargs="*",
        default=[],
        help="also step the 16 envs with these thread counts",
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    threaded = "".join(f" {f'N=16 {k}thr':>11} {'x1thr':>6}" for k in args.step_threads)
    header = (
        f"{'env':<18} {'raw':>9} {'N=1':>9} {'ratio':>6} {'N=16':>9} {'ratio':>6}{threaded}   (env steps/s)"
    )
    print(header)
    print("-" * len(header))
    for name in args.envs:
        raw = raw_steps_per_second(name, args.steps)
        single = torchrl_steps_per_second(name, 1, args.steps // 2)
        batched = torchrl_steps_per_second(name, 16, args.steps)
        line = f"{name:<18} {raw:>9.0f} {single:>9.0f} {raw / single:>6.2f} {batched:>9.0f} {raw / batched:>6.2f}"
        for k in args.step_threads:
            rate = torchrl_steps_per_second(name, 16, args.steps, step_threads=k)
            line += f" {rate:>11.0f} {rate / batched:>6.2f}"
        print(line)


if __name__ == "__main__":
    main()
