"""Demo: roll a random policy through every environment (TorchRL API) and draw them.

Usage::

    python -m torchrl_dhrl.envs.demo [--out DIR] [--num-envs N] [--steps T] [--seed S]

Two pictures in ``DIR`` (default ``outputs/mazes/``): ``mazes.png`` shows each maze's walls, start, test
goal(s) with their success radius, and the random trajectories; ``arms.png`` shows Reacher3D and
UR3Obstacle from above and from the front (arm, boards, test goal region, random end-effector paths).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from .arms import ARM_NAMES
from .mazes import MAZE_NAMES
from .plotting import plot_env, plot_maze
from .torchrl_env import make_env


def random_trajectories(name: str, *, num_envs: int, steps: int | None, seed: int) -> torch.Tensor:
    """Achieved goals ``[num_envs, T + 1, goal_dim]`` of one random-policy episode per env."""
    env = make_env(name, num_envs=num_envs, seed=seed)
    torch.manual_seed(seed)
    steps = env.max_episode_steps if steps is None else steps
    rollout = env.rollout(steps, break_when_any_done=False)
    env.close()
    return torch.cat([rollout["achieved_goal"][:, :1], rollout["next", "achieved_goal"]], dim=1)


def main(argv: list[str] | None = None) -> Path:
    """Writes ``mazes.png`` and ``arms.png`` and returns the path of ``mazes.png``."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=Path("outputs/mazes"), help="output folder")
    parser.add_argument("--num-envs", type=int, default=4, help="random episodes per maze (one batched env)")
    parser.add_argument("--steps", type=int, default=None, help="steps per episode (default: episode length)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    start = time.perf_counter()
    fig, axes = plt.subplots(1, len(MAZE_NAMES), figsize=(4 * len(MAZE_NAMES), 4.3))
    for ax, name in zip(axes, MAZE_NAMES, strict=True):
        xy = random_trajectories(name, num_envs=args.num_envs, steps=args.steps, seed=args.seed)
        plot_maze(name, trajectory=xy, ax=ax, title=f"{name} ({xy.shape[1] - 1} random steps)")
    axes[0].legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "mazes.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(len(ARM_NAMES), 2, figsize=(8, 4.4 * len(ARM_NAMES)))
    for row, name in zip(axes, ARM_NAMES, strict=True):
        xyz = random_trajectories(name, num_envs=args.num_envs, steps=args.steps, seed=args.seed)
        for ax, view in zip(row, ("top", "front"), strict=True):
            plot_env(name, trajectory=xyz, ax=ax, view=view)
    axes[0, 0].legend(loc="lower left", fontsize=7)
    fig.tight_layout()
    arms_path = args.out / "arms.png"
    fig.savefig(arms_path, dpi=110)
    plt.close(fig)
    print(f"Wrote {path} and {arms_path} ({time.perf_counter() - start:.1f} s)")
    return path


if __name__ == "__main__":
    main()
