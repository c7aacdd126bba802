"""Can the low level of a DHRL run reach nearby goals on its own (no high level, no graph)?

When a run does not learn, this separates "the low level cannot move yet" from "the graph or the
high level is wrong": the low-level actor of a checkpoint chases fixed goals at a few radii around
the start, in straight-line-reachable directions, with exploration off.

    python recipes/diagnose_low_level.py outputs/<date>/<time>            # the run directory
    python recipes/diagnose_low_level.py run/checkpoint --radii 1 2 4 --steps 120
    # can it pass AntMazeBottleneck's gap? From below it, ten tries per goal, one row per goal
    python recipes/diagnose_low_level.py run --start 16 4.5 --radii 3 6 --directions 4 --repeats 10 --per-offset
    # from points 10, 20, ... units of path along the maze from its start: where does the low level stop walking?
    python recipes/diagnose_low_level.py run --progress 10 20 30 40 60 80 100 --radii 1.5 3 --directions 8
    # a gymnasium-robotics maze's run: from its test start cell, or from the cell holding (x, y)
    python recipes/diagnose_low_level.py pml_run --oracle-speed 0.0523 --oracle-margin 0.125 --start 3 1
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

import torch
from dhrl_utils import add_oracle_options, agent_from_checkpoint, gymnasium_kwargs, oracle_overrides, run_maze
from torchrl_dhrl.envs import make_env

from torchrl_dhrl.diagnostics import reach_test

#: ``--progress`` starts lie this many agent radii (``planner.oracle_margin``) clear of the walls: room for its body
CLEARANCE_RADII = 3.0


def reach_test_from_checkpoint(
    path,
    *,
    radii: Sequence[float] | None = None,
    num_directions: int = 16,
    max_steps: int | None = None,
    device: str | torch.device = "cpu",
    seed: int = 0,
    start: Sequence[float] | None = None,
    repeats: int = 1,
    per_offset: bool = False,
    planner_overrides: dict | None = None,
    progress: Sequence[float] | None = None,
) -> list[dict]:
    """:func:`~torchrl_dhrl.diagnostics.reach_test` for the low-level actor of a recipe checkpoint.

    Defaults follow the run's config: radii ``(0.25, 0.5, 1, 1.5) x cutoff x oracle_speed`` (the goal-space
    span of a graph edge, at the env's nominal speed), ``max_steps = 3 x cutoff``, the planner's
    ``reach_radius`` and ``oracle_margin``, the run's ``angle_features``; a ``gymnasium:<id>`` run's env with its
    ``gymnasium`` options, reset as its test episodes (as its training episodes where the tests start anywhere).
    ``start``, ``repeats`` and ``per_offset`` as in :func:`~torchrl_dhrl.diagnostics.reach_test`;
    ``planner_overrides`` replace the run's ``planner`` values (``oracle_margin``, ``oracle_speed``). ``progress``
    (mazes with a start): one test from each point along the maze that far from the start
    (:meth:`~torchrl_dhrl.envs.geometry.MazeGeometry.points_along`, at least ``CLEARANCE_RADII`` agent radii from
    the walls; progress past the maze's farthest point tests that point once), its rows with the point's
    ``"progress"`` and ``"start"`` (a gymnasium-robotics maze's test starts at the centre of the cell holding the
    point).

    Args:
        path (str or Path): a checkpoint or the run directory holding it.
    """
    cfg, agent = agent_from_checkpoint(path, device)
    planner = {**cfg["planner"], **(planner_overrides or {})}
    env_kwargs = gymnasium_kwargs(cfg, eval=True)
    if env_kwargs is not None and env_kwargs["reset_options"] is None:  # tests start anywhere: the training start
        env_kwargs["reset_options"] = cfg["gymnasium"]["reset_options"]
    if radii is None:
        span = planner["cutoff"] * planner["oracle_speed"]
        radii = [f * span for f in (0.25, 0.5, 1.0, 1.5)]

    def test_from(point: Sequence[float] | None) -> list[dict]:
        return reach_test(
            agent.low_actor,
            cfg["env_name"],
            radii=radii,
            max_steps=int(max_steps or 3 * planner["cutoff"]),
            reach_radius=planner["reach_radius"],
            num_directions=num_directions,
            oracle_margin=planner["oracle_margin"],
            angle_features=cfg.get("angle_features"),
            device=device,
            seed=seed,
            start=point,
            repeats=repeats,
            per_offset=per_offset,
            env_kwargs=env_kwargs,
        )

    if progress is None:
        return test_from(start)
    if start is not None:
        raise ValueError("Give a start or progress along the maze, not both.")
    env = None if env_kwargs is None else make_env(cfg["env_name"], env_kwargs=env_kwargs)
    geometry = run_maze({**cfg, "planner": planner}, env)
    if geometry is None:
        raise ValueError(f"Progress along the maze needs a maze; {cfg['env_name']} has none.")
    points, lengths = geometry.points_along(progress, clearance=CLEARANCE_RADII * planner["oracle_margin"])
    rows, seen = [], set()
    for point, length in zip(points.tolist(), lengths.tolist(), strict=True):
        if tuple(point) in seen:  # progress past the maze's farthest point: that point, once
            continue
        seen.add(tuple(point))
        rows += [{"progress": length, "start": point, **row} for row in test_from(point)]
    return rows


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", help="a checkpoint or the run directory holding it")
    parser.add_argument("--radii", type=float, nargs="+", default=None, help="goal distances (goal units)")
    parser.add_argument("--directions", type=int, default=16, help="directions per radius")
    parser.add_argument("--steps", type=int, default=None, help="steps per goal (default 3 x cutoff)")
    parser.add_argument(
        "--start",
        type=float,
        nargs="+",
        default=None,
        help="start here instead of the task's start (mazes: x y; a gymnasium-robotics maze: the cell holding it)",
    )
    parser.add_argument(
        "--progress",
        type=float,
        nargs="+",
        default=None,
        help="test from points this far along the maze from its start (path length, goal units), one block each",
    )
    parser.add_argument(
        "--repeats", type=int, default=1, help="tries per goal, each with its own reset noise"
    )
    parser.add_argument("--per-offset", action="store_true", help="one row per goal instead of per radius")
    add_oracle_options(parser)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    overrides = oracle_overrides(parser, args)
    try:
        rows = reach_test_from_checkpoint(
            args.checkpoint,
            radii=args.radii,
            num_directions=args.directions,
            max_steps=args.steps,
            device=args.device,
            start=args.start,
            repeats=args.repeats,
            per_offset=args.per_offset,
            planner_overrides=overrides,
            progress=args.progress,
        )
    except ValueError as err:  # the run, the start, the progress or the radii refused: one line
        parser.error(str(err))
    where = f"{'progress':>8} {'start':>14} " if args.progress else ""
    offset = "offset".rjust(16) + " " if args.per_offset else ""
    print(
        f"{where}{offset}{'radius':>8} {'goals':>6} {'reached':>8} {'median steps':>13} {'min dist':>9} "
        f"{'final dist':>11}"
    )
    for row in rows:
        where = ""
        if args.progress:
            where = f"{row['progress']:8.1f} {'(' + ', '.join(f'{v:.1f}' for v in row['start']) + ')':>14} "
        offset = f"{'(' + ', '.join(f'{v:.2f}' for v in row['offset']) + ')':>16} " if args.per_offset else ""
        print(
            f"{where}{offset}{row['radius']:8.2f} {row['goals']:6d} {row['reach_rate']:8.0%} "
            f"{row['median_steps']:13.1f} {row['mean_min_distance']:9.2f} {row['mean_final_distance']:11.2f}"
        )
    return rows


if __name__ == "__main__":
    main()
