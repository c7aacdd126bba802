"""Are a DHRL maze run's subgoals and graph consistent with the maze's true geometry?

Loads a checkpoint, rebuilds its agent (graph included), runs one deterministic evaluation on the test
goals and prints the ``diag/...`` numbers the recipe logs every epoch (subgoals and waypoints in walls or
outside the arena, graph edges through walls, rank correlation of the learned distances with the true
obstacle-free path lengths, landmark coverage, the part of the graph a plan from the test start can use, the
high level's subgoal at the start), a table of learned vs true distances for a few landmark pairs, and saves
their scatter plot (``distance_scatter.png`` in the run directory unless ``--plot`` says otherwise). With
``--budgets`` it also rebuilds the graph from the checkpoint's low-level buffer with other landmark and
candidate counts and prints how far each reaches into the maze, next to how far the buffer itself reaches
(:func:`~torchrl_dhrl.diagnostics.landmark_budget_sweep`): does a larger graph help, or is exploration what
limits it?

    python recipes/diagnose_graph.py outputs/<date>/<time>            # the run directory
    python recipes/diagnose_graph.py run/checkpoint --no-rollout --pairs 12 --plot /tmp/scatter.png
    python recipes/diagnose_graph.py run --no-rollout --budgets 200:3000 300:6000 --draws 3
    python recipes/diagnose_graph.py run --oracle-margin 0.125 --oracle-speed 0.0523   # the maze's agent radius and speed

``--oracle-margin`` and ``--oracle-speed`` replace the run's recorded ``planner.oracle_margin`` and
``planner.oracle_speed`` (the true geometry's agent radius and the true distances' goal units per step), e.g. for a
gymnasium-robotics maze trained by 0.4.0 or earlier, which recorded the configuration's values.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch
from dhrl_utils import (
    add_oracle_options,
    agent_from_checkpoint,
    build_environment,
    build_replay_buffers,
    oracle_overrides,
    run_maze,
)

from torchrl_dhrl.diagnostics import (
    GraphDiagnosis,
    default_coverage_radius,
    graph_diagnosis,
    landmark_budget_sweep,
)
from torchrl_dhrl.recipe import ConfigError, checkpoint_file, load_checkpoint, plot_distance_scatter


def graph_diagnosis_from_checkpoint(
    path,
    *,
    rollout: bool = True,
    max_sources: int | None = 64,
    resolution: float | None = None,
    device: str | torch.device = "cpu",
    oracle: dict | None = None,
) -> tuple[GraphDiagnosis, dict]:
    """:func:`~torchrl_dhrl.diagnostics.graph_diagnosis` of a recipe checkpoint's agent (rebuilt from its
    configuration, graph included) on its evaluation envs; returns the diagnosis and the configuration.

    ``oracle``: ``planner`` keys (``oracle_margin``, ``oracle_speed``) in place of the run's recorded ones.

    Raises:
        ValueError: when the run's env is not a maze.
    """
    cfg, agent = agent_from_checkpoint(path, device)
    cfg["planner"].update(oracle or {})
    env = build_environment(cfg, torch.device(device), eval=True, agent=agent)
    maze = run_maze(cfg, env)  # a built-in maze's geometry, or a gymnasium-robotics maze's from its map
    if maze is None:
        raise ValueError(f"diagnose_graph needs a maze run; {path} is a {cfg['env_name']} run.")
    diagnosis = graph_diagnosis(
        agent,
        env,
        maze,
        oracle_margin=cfg["planner"]["oracle_margin"],
        rollout=rollout,
        max_sources=max_sources,
        resolution=resolution,
    )
    return diagnosis, cfg


def budget_table(
    path,
    budgets,
    *,
    draws: int = 3,
    seed: int = 0,
    device: str | torch.device = "cpu",
    oracle: dict | None = None,
):
    """:func:`~torchrl_dhrl.diagnostics.landmark_budget_sweep` of a recipe checkpoint: its agent's learned
    distance and its low-level buffer, the progress measured from the maze's start (walls grown by the run's
    ``planner.oracle_margin``, or ``oracle``'s); returns the rows and the buffer's progress."""
    cfg, agent = agent_from_checkpoint(path, device)
    cfg["planner"].update(oracle or {})
    low_rb, _ = build_replay_buffers(cfg, agent, torch.device(device))
    low_rb.load_state_dict(load_checkpoint(path, map_location=device, components=("low_rb",))["low_rb"])
    geometry = run_maze(cfg, build_environment(cfg, torch.device("cpu")))
    return landmark_budget_sweep(
        geometry,
        agent.planner,
        low_rb,
        budgets,
        draws=draws,
        coverage_radius=default_coverage_radius(geometry),
        generator=torch.Generator().manual_seed(seed),
    )


def _budget(text: str) -> tuple[int, int]:
    try:
        landmarks, candidates = (int(v) for v in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"a budget is LANDMARKS:CANDIDATES, e.g. 300:6000; got {text!r}"
        ) from None
    return landmarks, candidates


def pair_table(diagnosis, count: int) -> list[dict]:
    """``count`` landmark pairs spread over the range of true path lengths (evenly spaced quantiles)."""
    pairs = diagnosis.pairs
    true = pairs["true"]
    if true.numel() == 0 or count < 1:
        return []
    order = true.argsort()
    picks = order[torch.linspace(0, true.numel() - 1, min(count, true.numel())).round().long()]
    goals = diagnosis.landmark_goals
    rows = []
    for k in picks.unique_consecutive().tolist():
        i, j = int(pairs["rows"][k]), int(pairs["cols"][k])
        rows.append(
            {
                "i": i,
                "j": j,
                "goal_i": goals[i].tolist(),
                "goal_j": goals[j].tolist(),
                "true": true[k].item(),
                "learned": pairs["learned"][k].item(),
                "graph": pairs["graph"][k].item(),
            }
        )
    return rows


def main(argv: list[str] | None = None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", help="a checkpoint or the run directory holding it")
    parser.add_argument("--pairs", type=int, default=8, help="landmark pairs in the table")
    parser.add_argument("--sources", type=int, default=64, help="landmarks whose pairs are compared")
    parser.add_argument(
        "--no-rollout", action="store_true", help="skip the evaluation (subgoal fractions NaN)"
    )
    parser.add_argument("--plot", default=None, help="scatter plot (default: <run dir>/distance_scatter.png)")
    parser.add_argument(
        "--resolution",
        type=float,
        default=None,
        help="grid cell size of the true paths (default: the recipe's)",
    )
    parser.add_argument(
        "--budgets",
        nargs="+",
        type=_budget,
        default=None,
        metavar="LANDMARKS:CANDIDATES",
        help="also rebuild the graph from the buffer with these landmark and candidate counts",
    )
    parser.add_argument("--draws", type=int, default=3, help="rebuilds per budget (--budgets)")
    add_oracle_options(parser)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    oracle = oracle_overrides(parser, args)
    try:
        diagnosis, cfg = graph_diagnosis_from_checkpoint(
            args.checkpoint,
            rollout=not args.no_rollout,
            max_sources=args.sources,
            resolution=args.resolution,
            device=args.device,
            oracle=oracle,
        )
    except ConfigError as err:  # a recorded margin that closes the maze
        parser.error(f"{err} Give the agent's radius with --oracle-margin.")
    speed = cfg["planner"]["oracle_speed"]
    metrics = diagnosis.metrics
    print(f"{cfg['env_name']}: {metrics['graph/landmarks']} landmarks, {metrics['graph/edges']} edges")
    for key, value in diagnosis.metrics.items():
        if key.startswith("diag/"):
            print(f"  {key:34s} {value:8.3f}")
    reach = diagnosis.reach
    if math.isfinite(reach["reachable_landmarks"]):
        start, goal = ("({:.1f}, {:.1f})".format(*reach[k].tolist()) for k in ("start", "goal"))
        count = round(reach["reachable_landmarks"] * metrics["graph/landmarks"])
        bridge = (
            "every landmark is reachable"
            if math.isinf(reach["bridge_distance"])
            else f"the smallest learned distance from a reachable landmark to an unreachable one: "
            f"{reach['bridge_distance']:.1f} steps (the cutoff: {cfg['planner']['cutoff']:g})"
        )
        print(
            f"\nPlans from the first test start {start} to its goal {goal}: {count} of {metrics['graph/landmarks']} "
            f"landmarks reachable, the furthest {reach['reachable_progress']:.1f} along the maze (of every landmark: "
            f"{metrics['diag/landmark_progress']:.1f}), the nearest to the goal {reach['goal_to_reachable']:.1f} "
            f"from it; {bridge}"
        )
    rows = pair_table(diagnosis, args.pairs)
    if rows:
        print(f"\nlearned vs true distances (true steps = length / oracle_speed {speed:g}):")
        print(
            f"{'i':>4} {'j':>4} {'goal i':>15} {'goal j':>15} {'true len':>9} {'true steps':>10} "
            f"{'learned':>8} {'graph':>8}"
        )
        for row in rows:
            gi = "({:.1f}, {:.1f})".format(*row["goal_i"][:2])
            gj = "({:.1f}, {:.1f})".format(*row["goal_j"][:2])
            true_steps = row["true"] / speed if math.isfinite(row["true"]) else math.inf
            print(
                f"{row['i']:4d} {row['j']:4d} {gi:>15} {gj:>15} {row['true']:9.2f} {true_steps:10.1f} "
                f"{row['learned']:8.1f} {row['graph']:8.1f}"
            )
    if diagnosis.pairs["true"].numel():
        plot = Path(args.plot or checkpoint_file(args.checkpoint).parent / "distance_scatter.png")
        plot_distance_scatter(
            diagnosis.pairs["true"],
            diagnosis.pairs["learned"],
            plot,
            graph=diagnosis.pairs["graph"],
            speed=speed,
            title=f"{cfg['env_name']}: learned vs true landmark distances",
        )
        print(f"\nScatter plot: {plot}")
    else:
        print("\nNo graph in this checkpoint: no distances to compare.")
    budgets = None
    if args.budgets:
        budgets, buffer_progress = budget_table(
            args.checkpoint, args.budgets, draws=args.draws, device=args.device, oracle=oracle
        )
        print(
            f"\nGraphs rebuilt from the buffer ({args.draws} draws each): how far the landmarks reach along the maze "
            f"from the start (path length; the buffer's furthest state: {buffer_progress:.2f})"
        )
        print(
            f"{'landmarks':>9} {'candidates':>10} {'built':>6} {'progress':>8} {'min':>6} {'max':>6} {'coverage':>8}"
        )
        for row in budgets:
            print(
                f"{row['max_landmarks']:9d} {row['candidates']:10d} {row['landmarks']:6.0f} {row['progress_mean']:8.2f} "
                f"{row['progress_min']:6.2f} {row['progress_max']:6.2f} {row['coverage_mean']:8.3f}"
            )
        budgets = (budgets, buffer_progress)
    return diagnosis, rows, budgets


if __name__ == "__main__":
    main()
