"""Does a DHRL run's graph help? Its agent evaluated as trained, with other waypoint radii or graph cutoffs,
with the oracle's edges, without the graph, and the low level alone, on the same test goals (paired).

    python recipes/diagnose_planning.py outputs/<date>/<time>             # the run directory
    python recipes/diagnose_planning.py run/checkpoint --reach-radii 0.25 0.5 --repeats 5
    python recipes/diagnose_planning.py run/checkpoint --oracle     # + the graph with the oracle distance
    python recipes/diagnose_planning.py run/checkpoint --cutoffs 35 40   # + the learned graph at other cutoffs
"""

from __future__ import annotations

import argparse

import torch
from dhrl_utils import (
    add_oracle_options,
    agent_from_checkpoint,
    build_environment,
    oracle_distance,
    oracle_overrides,
)

from torchrl_dhrl.diagnostics import planning_ablations
from torchrl_dhrl.recipe.schema import ConfigError


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", help="a checkpoint or the run directory holding it")
    parser.add_argument("--reach-radii", type=float, nargs="*", default=[], help="waypoint radii to try")
    parser.add_argument(
        "--cutoffs",
        type=float,
        nargs="*",
        default=[],
        help="graph cutoffs to try (steps; the same landmarks and learned distances, edges redone)",
    )
    parser.add_argument("--repeats", type=int, default=5, help="batches of the run's evaluation episodes")
    parser.add_argument(
        "--oracle",
        action="store_true",
        help="add the variants with the graph rebuilt on the same landmarks with the oracle distance "
        "(planner.distance=oracle's line of sight; mazes and UR3Obstacle)",
    )
    add_oracle_options(parser)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    overrides = oracle_overrides(parser, args)
    device = torch.device(args.device)
    cfg, agent = agent_from_checkpoint(args.checkpoint, device)
    cfg["planner"].update(overrides)
    env = build_environment(cfg, device, eval=True, agent=agent)
    try:
        oracle = oracle_distance(cfg, env) if args.oracle else None
    except ConfigError as err:  # a recorded margin that closes the maze
        parser.error(f"{err} Give the agent's radius with --oracle-margin.")
    rows = planning_ablations(
        agent,
        env,
        env.max_episode_steps,
        reach_radii=args.reach_radii,
        cutoffs=args.cutoffs,
        repeats=args.repeats,
        oracle=oracle,
    )
    print(
        f"{cfg['env_name']}: {agent.planner.num_landmarks} landmarks, reach_radius {agent.planner.reach_radius:g}, "
        f"cutoff {agent.planner.cutoff:g}"
    )
    print(f"{'variant':>20} {'episodes':>9} {'success':>8} {'any-time':>9} {'final dist':>11}")
    for row in rows:
        print(
            f"{row['variant']:>20} {row['episodes']:9d} {row['success']:8.0%} {row['any_success']:9.0%} "
            f"{row['final_distance']:11.3f}"
        )
    return rows


if __name__ == "__main__":
    main()
