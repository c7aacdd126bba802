"""SAC + HER (stable-baselines3) on a Gymnasium goal env, evaluated as the DHRL recipe evaluates: the final-state
success of ``--eval-episodes`` deterministic test episodes every ``--eval-every`` env steps, written to
``<out>/metrics.csv`` (``env_steps``, ``eval/success``, ``eval/any_success``, ``time/wall_s``).

The baseline next to ``env=gymnasium`` runs of the recipe (docs/results.md)::

    python benchmarks/sac_her_baseline.py --env-id PointMaze_UMaze-v3 --steps 60000 --seed 0 \\
        --reset-options '{"reset_cell": [3, 1]}' --out runs/sac_her_umaze_s0

Needs ``pip install stable-baselines3 gymnasium-robotics`` (the ``[baselines]`` extra).
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import numpy as np


def _env(env_id: str, options: dict | None, make_kwargs: dict):
    import gymnasium as gym

    try:
        import gymnasium_robotics

        gym.register_envs(gymnasium_robotics)
    except ImportError:
        pass

    class ResetOptions(gym.Wrapper):
        """Every reset with ``options`` (e.g. the mazes' fixed start cell)."""

        def reset(self, *, seed=None, options=None):
            return self.env.reset(seed=seed, options=options if options is not None else ResetOptions.options)

    ResetOptions.options = {k: np.asarray(v) for k, v in (options or {}).items()} or None
    return ResetOptions(gym.make(env_id, **make_kwargs))


def evaluate(model, env, episodes: int) -> tuple[float, float]:
    """Final-state and any-time success of ``episodes`` deterministic episodes."""
    final, anytime = [], []
    for _ in range(episodes):
        obs, info = env.reset()
        reached, done = False, False
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, _, terminated, truncated, info = env.step(action)
            reached |= bool(info.get("success", info.get("is_success", False)))
            done = terminated or truncated
        final.append(bool(info.get("success", info.get("is_success", False))))
        anytime.append(reached)
    return float(np.mean(final)), float(np.mean(anytime))


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env-id", default="PointMaze_UMaze-v3")
    parser.add_argument("--steps", type=int, default=60_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-every", type=int, default=4_500, help="env steps (the recipe's epoch: 15 x 300)")
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--reset-options", type=json.loads, default=None, help="JSON, e.g. '{\"reset_cell\": [3, 1]}'")
    parser.add_argument("--make-kwargs", type=json.loads, default={})
    parser.add_argument("--learning-starts", type=int, default=1_000)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)

    import torch
    from stable_baselines3 import SAC, HerReplayBuffer
    from stable_baselines3.common.callbacks import BaseCallback

    torch.set_num_threads(1)
    env = _env(args.env_id, args.reset_options, args.make_kwargs)
    eval_env = _env(args.env_id, args.reset_options, args.make_kwargs)
    eval_env.reset(seed=args.seed + 10_000)
    model = SAC(
        "MultiInputPolicy",
        env,
        replay_buffer_class=HerReplayBuffer,
        replay_buffer_kwargs={"n_sampled_goal": 4, "goal_selection_strategy": "future"},
        learning_starts=args.learning_starts,
        seed=args.seed,
        device="cpu",
        verbose=0,
    )
    args.out.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    start = time.perf_counter()

    class Evaluate(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps % args.eval_every == 0:
                success, any_success = evaluate(self.model, eval_env, args.eval_episodes)
                rows.append(
                    {
                        "env_steps": self.num_timesteps,
                        "eval/success": success,
                        "eval/any_success": any_success,
                        "time/wall_s": round(time.perf_counter() - start, 1),
                    }
                )
                with (args.out / "metrics.csv").open("w", newline="") as file:
                    writer = csv.DictWriter(file, fieldnames=list(rows[0]))
                    writer.writeheader()
                    writer.writerows(rows)
                print(rows[-1], flush=True)
            return True

    model.learn(total_timesteps=args.steps, callback=Evaluate())
    (args.out / "config.json").write_text(json.dumps(vars(args) | {"out": str(args.out)}, indent=2))
    return args.out / "metrics.csv"


if __name__ == "__main__":
    main()
