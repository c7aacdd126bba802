"""Re-evaluates a DHRL run's agent: as many deterministic test episodes as asked, on its task's test goals, with
success counted in whole episodes (final state, as the recipe's ``eval/success``); writes ``final_eval.yaml``.

    python recipes/evaluate.py outputs/<date>/<time>                   # the run directory (its checkpoint)
    python recipes/evaluate.py results/antmaze_cpu/seed0/agent --episodes 100 --seed 0   # a saved agent
    python recipes/evaluate.py run/checkpoint --flat --out run/final_eval_flat.yaml     # + the low level alone

The episodes run in batches of the run's ``schedule.eval_episodes`` envs (the recipe's evaluation env), batch k
seeded with ``seed + k`` (the envs' streams and the global ones): the same seed gives the same episodes.
"""

from __future__ import annotations

import argparse
import datetime
import math
import shlex
import sys
import time
from pathlib import Path

import torch
from dhrl_utils import agent_from_checkpoint, build_environment, seed_everything

from torchrl_dhrl.recipe import agent_checkpoint_file, code_and_machine, load_checkpoint, write_yaml
from torchrl_dhrl.training import evaluate, goal_as_waypoint

#: The default record's name, in the run directory.
FINAL_EVAL_NAME = "final_eval.yaml"


def count_successes(env, policy, batches: int, seed: int) -> int:
    """Final-state successes of ``batches`` batches of deterministic episodes, batch k seeded with ``seed + k``."""
    successes = 0
    for k in range(batches):
        seed_everything(seed + k, env)
        rollout = evaluate(env, policy, env.max_episode_steps).rollout
        success = rollout["next", "is_success"].reshape(*rollout.shape, -1).any(-1)
        successes += int(success[..., -1].sum())
    return successes


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("path", help="a run directory, its saved agent (agent/) or a checkpoint")
    parser.add_argument("--episodes", type=int, default=100, help="at least this many test episodes")
    parser.add_argument("--seed", type=int, default=0, help="batch k of episodes is seeded with seed + k")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", help=f"where to write the record (default: <run dir>/{FINAL_EVAL_NAME})")
    parser.add_argument("--flat", action="store_true", help="also the low level alone chasing the goal")
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error("--episodes must be at least 1")
    device = torch.device(args.device)
    path = agent_checkpoint_file(args.path)
    cfg, agent = agent_from_checkpoint(path, device)
    counters = load_checkpoint(path, components=("counters",)).get("counters") or {}
    env = build_environment(cfg, device, eval=True, agent=agent)
    batches = math.ceil(args.episodes / env.batch_size.numel())
    episodes = batches * env.batch_size.numel()
    start = time.perf_counter()
    successes = count_successes(env, agent.policy, batches, args.seed)
    record = {
        "env_name": cfg["env_name"],
        "agent": str(path),
        "env_steps": counters.get("env_steps"),
        "episodes": episodes,
        "successes": successes,
        "success": successes / episodes,
    }
    if args.flat:  # the same episodes (the same seeds), the low level alone
        flat = count_successes(env, goal_as_waypoint(agent.low_actor), batches, args.seed)
        record |= {"flat_successes": flat, "flat_success": flat / episodes}
    record |= {
        "seed": args.seed,
        "batch_envs": env.batch_size.numel(),
        "episode_length": env.max_episode_steps,
        "command": shlex.join(["python", "recipes/evaluate.py", *(sys.argv[1:] if argv is None else argv)]),
        **code_and_machine(device),
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "wall_s": round(time.perf_counter() - start, 1),
    }
    out = Path(args.out) if args.out else path.parent / FINAL_EVAL_NAME
    out.parent.mkdir(parents=True, exist_ok=True)
    write_yaml(record, out)
    flat_note = f", flat {record['flat_successes']}/{episodes}" if args.flat else ""
    print(
        f"{cfg['env_name']} at {record['env_steps']} env steps: {successes}/{episodes} test episodes succeeded "
        f"({record['success']:.1%}, seed {args.seed}){flat_note}; written to {out}"
    )
    return record


if __name__ == "__main__":
    main()
