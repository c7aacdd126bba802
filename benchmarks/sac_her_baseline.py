"""SAC + HER (stable-baselines3) on a Gymnasium goal env, evaluated as the DHRL recipe evaluates: the final-state
success of ``--eval-episodes`` deterministic test episodes every ``--eval-every`` env steps, written to
``<out>/metrics.csv`` (``env_steps``, ``eval/success``, ``eval/any_success``, ``time/wall_s``).

The baseline next to ``env=gymnasium`` runs of the recipe (docs/results.md)::

    python benchmarks/sac_her_baseline.py --env-id PointMaze_UMaze-v3 --steps 60000 --seed 0 \\
        --reset-options '{"reset_cell": [3, 1]}' --out runs/sac_her_umaze_s0

``--eval-reset-options`` gives the test episodes their own reset options (the recipe's
``gymnasium.eval_reset_options``, e.g. a fixed far goal cell: ``'{"reset_cell": [1, 1], "goal_cell": [7, 10]}'``);
by default they are the training ones. At the end the final model (``<out>/model.zip``) is re-evaluated over
``--final-episodes`` deterministic test episodes, episode ``i`` reset with seed ``--final-seed + i``, and
``<out>/final_eval.yaml`` records them as ``recipes/evaluate.py`` records a DHRL agent's (``episodes``,
``successes``, ``success``, the code, versions and machine); ``--evaluate-only`` does that again for a finished run,
or for one stopped short: ``<out>/model.zip`` is also written with each checkpoint (the model of the last one).
``--right-flipped-after K`` (gymnasium-robotics' ant mazes) puts a flipped ant back on its feet after ``K`` steps
upside down in training and test episodes alike, as the recipe's ``right_flipped_after=K``
(:class:`~torchrl_dhrl.envs.RightFlippedAnt`). ``<out>/provenance.yaml`` holds one entry per start (command, code, versions, machine).

Long runs: the model and its HER buffer are checkpointed every ``--checkpoint-every`` evaluations, at the end and
on SIGTERM or Ctrl-C (at the next episode's end, then exit 130), to ``<out>/checkpoint/`` (staged, then renamed into
place; a save killed between the renames is recovered at the next start);
``--resume`` continues from it (and may raise ``--steps``). Training runs in chunks of one episode, so every
checkpoint falls between episodes and the buffer holds whole episodes; a resumed run is the same algorithm but not
bit for bit the uninterrupted one (the random streams are not restored).

Needs ``pip install stable-baselines3 gymnasium-robotics`` (the ``[baselines]`` extra).
"""

from __future__ import annotations

import argparse
import datetime
import json
import shlex
import shutil
import signal
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from torchrl_dhrl.recipe import code_and_machine, write_csv, write_yaml

CHECKPOINT = "checkpoint"


def _env(env_id: str, options: dict | None, make_kwargs: dict, right_flipped_after: int | None = None):
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
    env = ResetOptions(gym.make(env_id, **make_kwargs))
    if right_flipped_after is not None:  # the recipe's right_flipped_after, the same righting
        from torchrl_dhrl.envs import RightFlippedAnt

        env = RightFlippedAnt(env, right_flipped_after)
    return env


def episode_successes(model, env, episodes: int, seeds=None) -> tuple[list[bool], list[bool]]:
    """Final-state and any-time success of ``episodes`` deterministic episodes (episode ``i`` reset with
    ``seeds[i]`` when given, else continuing the env's stream)."""
    final, anytime = [], []
    for i in range(episodes):
        obs, info = env.reset(seed=None if seeds is None else int(seeds[i]))
        reached, done = False, False
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, _, terminated, truncated, info = env.step(action)
            reached |= bool(info.get("success", info.get("is_success", False)))
            done = terminated or truncated
        final.append(bool(info.get("success", info.get("is_success", False))))
        anytime.append(reached)
    return final, anytime


def _machine() -> dict:
    """The code, package versions and machine (as the recipe's provenance), with stable-baselines3's version."""
    from importlib.metadata import PackageNotFoundError, version

    record = code_and_machine("cpu")
    for package in ("stable-baselines3", "gymnasium", "gymnasium-robotics"):
        try:
            record["versions"][package] = version(package)
        except PackageNotFoundError:
            record["versions"][package] = None
    return record


def save_checkpoint(model, rows: list[dict], wall_s: float, out: Path) -> None:
    """The model, its replay buffer, the metrics so far and the training's wall clock, to ``out/checkpoint`` (a
    staged copy renamed); then the model alone to ``out/model.zip`` (written, then renamed), the saved agent of a
    run stopped short, as the recipe saves ``agent/`` with each checkpoint."""
    stage, final, old = out / f".{CHECKPOINT}.stage", out / CHECKPOINT, out / f".{CHECKPOINT}.old"
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir(parents=True)
    model.save(stage / "model.zip")
    model.save_replay_buffer(stage / "replay_buffer.pkl")
    state = {"env_steps": int(model.num_timesteps), "wall_s": wall_s, "rows": rows}
    (stage / "state.json").write_text(json.dumps(state))
    if final.exists():
        final.rename(old)
    stage.rename(final)
    shutil.rmtree(old, ignore_errors=True)
    shutil.copyfile(final / "model.zip", out / ".model.zip")
    (out / ".model.zip").replace(out / "model.zip")


def recover_checkpoint(out: Path) -> None:
    """A save killed between its two renames leaves no ``checkpoint``: the staged one goes into place when it is
    complete (its ``state.json``, written last, is there), else the previous one comes back; leftovers go."""
    stage, final, old = out / f".{CHECKPOINT}.stage", out / CHECKPOINT, out / f".{CHECKPOINT}.old"
    if not final.exists():
        if (stage / "state.json").is_file():
            stage.rename(final)
        elif old.exists():
            old.rename(final)
    shutil.rmtree(stage, ignore_errors=True)
    shutil.rmtree(old, ignore_errors=True)


def final_evaluation(model, args, command: str, env_steps: int) -> dict:
    """``--final-episodes`` test episodes of the model, written to ``<out>/final_eval.yaml``."""
    env = _env(args.env_id, args.eval_reset_options, args.make_kwargs, args.right_flipped_after)
    start = time.perf_counter()
    seeds = [args.final_seed + i for i in range(args.final_episodes)]
    final, anytime = episode_successes(model, env, args.final_episodes, seeds)
    record = {
        "env_name": f"gymnasium:{args.env_id}",
        "agent": str(args.out / "model.zip"),
        "env_steps": env_steps,
        "episodes": args.final_episodes,
        "successes": int(sum(final)),
        "success": sum(final) / args.final_episodes,
        "any_successes": int(sum(anytime)),
        "seed": args.final_seed,
        "episode_length": env.spec.max_episode_steps,
        "reset_options": args.eval_reset_options,
        "right_flipped_after": args.right_flipped_after,
        "command": command,
        **_machine(),
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "wall_s": round(time.perf_counter() - start, 1),
    }
    write_yaml(record, args.out / "final_eval.yaml")
    print(
        f"final model at {env_steps} env steps: {record['successes']}/{record['episodes']} test episodes succeeded",
        flush=True,
    )
    return record


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env-id", default="PointMaze_UMaze-v3")
    parser.add_argument("--steps", type=int, default=60_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-every", type=int, default=4_500, help="env steps (the recipe's epoch: 15 x 300)")
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--reset-options", type=json.loads, default=None, help="JSON, e.g. '{\"reset_cell\": [3, 1]}'")
    parser.add_argument(
        "--eval-reset-options", type=json.loads, default=None, help="JSON, the test episodes' (default: the training's)"
    )
    parser.add_argument("--make-kwargs", type=json.loads, default={})
    parser.add_argument(
        "--right-flipped-after",
        type=int,
        default=None,
        help="ant mazes: right a flipped ant after this many steps upside down, training and test episodes alike "
        "(the recipe's right_flipped_after; default: never, as the env)",
    )
    parser.add_argument("--learning-starts", type=int, default=1_000)
    parser.add_argument("--final-episodes", type=int, default=100, help="test episodes of the final model")
    parser.add_argument("--final-seed", type=int, default=0, help="final test episode i is reset with this + i")
    parser.add_argument("--checkpoint-every", type=int, default=5, help="evaluations between checkpoints")
    parser.add_argument("--resume", action="store_true", help="continue from <out>/checkpoint")
    parser.add_argument("--evaluate-only", action="store_true", help="only the final evaluation of <out>/model.zip")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if args.eval_reset_options is None:
        args.eval_reset_options = args.reset_options
    command = shlex.join(["python", "benchmarks/sac_her_baseline.py", *(sys.argv[1:] if argv is None else argv)])

    import torch
    from stable_baselines3 import SAC, HerReplayBuffer

    torch.set_num_threads(1)
    if args.right_flipped_after is not None:  # refused before anything is built where there is no ant to right
        try:
            _env(args.env_id, args.reset_options, args.make_kwargs, args.right_flipped_after).close()
        except ValueError as err:
            parser.error(f"--right-flipped-after: {err}")
    if args.evaluate_only:
        env = _env(args.env_id, args.reset_options, args.make_kwargs, args.right_flipped_after)  # HER's buffer class wants it to load
        model = SAC.load(args.out / "model.zip", env=env, device="cpu")
        final_evaluation(model, args, command, int(model.num_timesteps))  # the model's own count: no checkpoint needed
        return args.out / "final_eval.yaml"
    env = _env(args.env_id, args.reset_options, args.make_kwargs, args.right_flipped_after)
    episode = env.spec.max_episode_steps
    if not episode or args.eval_every % episode or args.steps % episode:
        parser.error(
            f"--eval-every ({args.eval_every}) and --steps ({args.steps}) must be multiples of {args.env_id}'s episode "
            f"length ({episode}): training runs whole episodes between evaluations and checkpoints."
        )
    if args.learning_starts < episode:
        parser.error(
            f"--learning-starts ({args.learning_starts}) must be at least {args.env_id}'s episode length ({episode}): "
            "HER samples only from finished episodes."
        )
    checkpoint = args.out / CHECKPOINT
    recover_checkpoint(args.out)
    if args.resume and not (checkpoint / "state.json").is_file():
        parser.error(f"--resume: no checkpoint in {checkpoint}.")
    if not args.resume and checkpoint.exists():
        parser.error(f"{args.out} already holds a checkpoint; continue it with --resume, or give another --out.")
    args.out.mkdir(parents=True, exist_ok=True)
    eval_env = _env(args.env_id, args.eval_reset_options, args.make_kwargs, args.right_flipped_after)
    eval_env.reset(seed=args.seed + 10_000)
    if args.resume:
        model = SAC.load(checkpoint / "model.zip", env=env, device="cpu")
        model.load_replay_buffer(checkpoint / "replay_buffer.pkl")
        state = json.loads((checkpoint / "state.json").read_text())
        rows, wall_before = state["rows"], state.get("wall_s", 0.0)
    else:
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
        rows, wall_before = [], 0.0
    provenance = args.out / "provenance.yaml"
    starts = yaml.safe_load(provenance.read_text()) if provenance.is_file() else []
    starts.append(
        {
            "started": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "env_steps": int(model.num_timesteps),
            "command": command,
            **_machine(),
            "threads": 1,
        }
    )
    write_yaml(starts, provenance)
    (args.out / "config.json").write_text(json.dumps(vars(args) | {"out": str(args.out)}, indent=2, default=str))

    stop = []
    handlers = {s: signal.signal(s, lambda *_: stop.append(True)) for s in (signal.SIGTERM, signal.SIGINT)}
    start, evaluations = time.perf_counter(), 0
    wall = lambda: round(wall_before + time.perf_counter() - start, 1)  # noqa: E731 - over every start
    try:
        while model.num_timesteps < args.steps and not stop:
            model.learn(total_timesteps=episode, reset_num_timesteps=False)
            if model.num_timesteps % args.eval_every == 0:
                final, anytime = episode_successes(model, eval_env, args.eval_episodes)
                rows.append(
                    {
                        "env_steps": int(model.num_timesteps),
                        "eval/success": float(np.mean(final)),
                        "eval/any_success": float(np.mean(anytime)),
                        "time/wall_s": wall(),
                    }
                )
                write_csv(rows, list(rows[0]), args.out / "metrics.csv")
                print(rows[-1], flush=True)
                evaluations += 1
                if evaluations % args.checkpoint_every == 0:
                    save_checkpoint(model, rows, wall(), args.out)
        save_checkpoint(model, rows, wall(), args.out)
    finally:
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    if stop:
        print(f"Interrupted at {model.num_timesteps} env steps: checkpoint written; continue with --resume.")
        raise SystemExit(130)
    final_evaluation(model, args, command, int(model.num_timesteps))
    return args.out / "metrics.csv"


if __name__ == "__main__":
    main()
