"""Re-evaluates a DHRL run's agent: as many deterministic test episodes as asked, on its task's test goals, with
success counted in whole episodes (final state, as the recipe's ``eval/success``); writes ``final_eval.yaml``.

    python recipes/evaluate.py outputs/<date>/<time>                   # the run directory (its checkpoint)
    python recipes/evaluate.py results/antmaze_cpu/seed0/agent --episodes 100 --seed 0   # a saved agent
    python recipes/evaluate.py run/checkpoint --flat --out run/final_eval_flat.yaml     # + the low level alone
    python recipes/evaluate.py run --episodes 50 --variant planner.edge_rule=connected \
        --variant high.critic_candidates=8 high.landmark_candidates=true     # test-time switches, paired

The episodes run in batches of the run's ``schedule.eval_episodes`` envs (the recipe's evaluation env), batch k
seeded with ``seed + k`` (the envs' streams and the global ones): the same seed gives the same episodes. On the
built-in ant mazes the record also counts the episodes that ended with the ant upside down (``ended_upside_down``,
each variant's too).

``--variant KEY=VALUE ...`` (repeatable) re-evaluates the same trained agent with keys no checkpointed state holds
changed (role ``unsaved`` in docs/training.md's key roles: ``planner.edge_rule``, ``high.critic_candidates``, ...;
a ``planner`` key redoes the loaded graph's edges), on the same episodes as the agent as trained: each variant's
successes, the episodes only it or only the agent as trained succeeded in, and the exact McNemar p-value
(:func:`~torchrl_dhrl.recipe.paired_comparison`). Every variant is checked before the first episode runs; the
record then goes to ``variants_eval.yaml`` (the protocol's ``final_eval.yaml`` is left as it is).
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
import yaml
from dhrl_utils import agent_from_checkpoint, build_environment, episode_outcomes, upside_down_test

from torchrl_dhrl.recipe import (
    ConfigError,
    agent_checkpoint_file,
    code_and_machine,
    load_checkpoint,
    paired_comparison,
    write_yaml,
)
from torchrl_dhrl.training import goal_as_waypoint

#: The default record's name, in the run directory.
FINAL_EVAL_NAME = "final_eval.yaml"
#: The default record's name with ``--variant``.
VARIANTS_EVAL_NAME = "variants_eval.yaml"


def parse_changes(items: list[str]) -> dict:
    """``["high.critic_candidates=8", "planner.edge_rule=connected"]`` -> their values (YAML: ``8``, ``true``,
    ``null``, a string)."""
    changes = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--variant takes KEY=VALUE items, got {item!r}.")
        changes[key] = yaml.safe_load(value)
    return changes


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("path", help="a run directory, its saved agent (agent/) or a checkpoint")
    parser.add_argument("--episodes", type=int, default=100, help="at least this many test episodes")
    parser.add_argument("--seed", type=int, default=0, help="batch k of episodes is seeded with seed + k")
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--out",
        help=f"where to write the record (default: <run dir>/{FINAL_EVAL_NAME}, with --variant {VARIANTS_EVAL_NAME})",
    )
    parser.add_argument("--flat", action="store_true", help="also the low level alone chasing the goal")
    parser.add_argument(
        "--variant",
        nargs="+",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="also the agent with these keys changed (role unsaved), on the same episodes; repeatable",
    )
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error("--episodes must be at least 1")
    try:
        variants = [parse_changes(items) for items in args.variant]
    except ValueError as err:
        parser.error(str(err))
    device = torch.device(args.device)
    path = agent_checkpoint_file(args.path)
    cfg, agent = agent_from_checkpoint(path, device)
    # every variant built (and its keys checked) before the first episode
    try:
        variant_agents = [agent_from_checkpoint(path, device, changes) for changes in variants]
    except ConfigError as err:  # a key a trained agent cannot change: one line, as the recipe's errors
        parser.error(f"--variant: {err}")
    counters = load_checkpoint(path, components=("counters",)).get("counters") or {}
    env = build_environment(cfg, device, eval=True, agent=agent)
    batches = math.ceil(args.episodes / env.batch_size.numel())
    episodes = batches * env.batch_size.numel()
    start = time.perf_counter()
    upside_down = upside_down_test(cfg)
    trained, flipped = episode_outcomes(env, agent.policy, batches, args.seed, upside_down)
    successes = int(trained.sum())
    record = {
        "env_name": cfg["env_name"],
        "agent": str(path),
        "env_steps": counters.get("env_steps"),
        "episodes": episodes,
        "successes": successes,
        "success": successes / episodes,
    }
    if flipped is not None:  # the ant mazes: test episodes that ended with the ant on its back
        record["ended_upside_down"] = int(flipped.sum())
    if args.flat:  # the same episodes (the same seeds), the low level alone
        flat = int(episode_outcomes(env, goal_as_waypoint(agent.low_actor), batches, args.seed)[0].sum())
        record |= {"flat_successes": flat, "flat_success": flat / episodes}
    if variants:
        record["variants"] = []
        for changes, (variant_cfg, variant_agent) in zip(variants, variant_agents, strict=True):
            variant_env = build_environment(variant_cfg, device, eval=True, agent=variant_agent)
            outcome, variant_flipped = episode_outcomes(
                variant_env, variant_agent.policy, batches, args.seed, upside_down
            )
            paired = paired_comparison(trained.numpy(), outcome.numpy())
            row = {
                "changes": changes,
                "successes": paired.variant,
                "success": paired.variant / episodes,
                "only_variant": paired.only_variant,
                "only_reference": paired.only_reference,
                "p_value": paired.p_value,
            }
            if variant_flipped is not None:
                row["ended_upside_down"] = int(variant_flipped.sum())
            record["variants"].append(row)
    record |= {
        "seed": args.seed,
        "batch_envs": env.batch_size.numel(),
        "episode_length": env.max_episode_steps,
        "command": shlex.join(["python", "recipes/evaluate.py", *(sys.argv[1:] if argv is None else argv)]),
        **code_and_machine(device),
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "wall_s": round(time.perf_counter() - start, 1),
    }
    out = Path(args.out) if args.out else path.parent / (VARIANTS_EVAL_NAME if variants else FINAL_EVAL_NAME)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_yaml(record, out)
    flat_note = f", flat {record['flat_successes']}/{episodes}" if args.flat else ""
    if flipped is not None:
        flat_note += f", {record['ended_upside_down']} ended upside down"
    print(
        f"{cfg['env_name']} at {record['env_steps']} env steps: {successes}/{episodes} test episodes succeeded "
        f"({record['success']:.1%}, seed {args.seed}){flat_note}; written to {out}"
    )
    for row in record.get("variants", []):
        name = " ".join(f"{key}={value}" for key, value in row["changes"].items())
        print(
            f"  {name}: {row['successes']}/{episodes} ({row['success']:.1%}); only this variant "
            f"{row['only_variant']}, only as trained {row['only_reference']}, McNemar p={row['p_value']:.3g}"
            + (f"; {row['ended_upside_down']} ended upside down" if "ended_upside_down" in row else "")
        )
    return record


if __name__ == "__main__":
    main()
