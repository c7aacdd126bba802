"""Where along the maze each run stops and which part of the agent stops it: one table over a task's seeds.

    python recipes/diagnose_summary.py results/antmazebottleneck_cps/seed0 results/antmazebottleneck_cps/seed1
    python recipes/diagnose_summary.py ~/runs/complex_s{0,1,2,3} --ablations --repeats 5 --out diagnosis.md

Per run (a built-in maze, or a gymnasium-robotics maze with a fixed start cell: its test goals from its test env's
resets, its oracle's walls from the env's map), from its ``metrics.csv`` row at ``--at`` env steps (the last evaluation at or before; by
default the last): the test success of that evaluation; ``G``, the farthest test goal's progress along the maze
(the obstacle-free path length from the start); how far the training episodes got (``F``, ``train/frontier``),
the landmarks (``L``, ``diag/landmark_progress``) and the landmarks a plan from the start can use (``R``,
``diag/reachable_progress``, with their share); the high level's subgoal at the start (in free space or in a
wall, and how far below its critic's best free subgoal in Q). With ``--ablations`` the run's agent (its saved
``agent/`` or checkpoint; the row is then the one at the agent's env steps) is re-evaluated on the same test
episodes as trained, with the goal as subgoal, with the oracle's graph on the same landmarks (and the goal as
subgoal), and without the graph (:func:`~torchrl_dhrl.diagnostics.planning_ablations`), and its graph's reach is
measured as saved, with the shortest learned edge out of the part plans can use (``bridge``).

The last column lists every check that holds (:func:`findings`; docs/diagnostics.md, "Which part stops a run"),
with the figures behind it: a run can be held back by more than one part.
"""

from __future__ import annotations

import argparse
import functools
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
import yaml
from dhrl_utils import (
    add_oracle_options,
    agent_from_checkpoint,
    build_environment,
    oracle_distance,
    oracle_overrides,
    print_table,
    run_maze,
)
from torchrl_dhrl.envs import ENVS, MAZE_NAMES, MazeSpec, get_maze_spec, gymnasium_id
from torchrl_dhrl.envs.geometry import MazeGeometry

from torchrl_dhrl.diagnostics import graph_diagnosis, planning_ablations
from torchrl_dhrl.recipe import agent_checkpoint_file, load_checkpoint
from torchrl_dhrl.recipe.aggregate import read_run

#: How much better (success, absolute) a planning variant must do than the agent as trained to name a part.
MARGIN = 0.1
#: The share of the training steps an ant may spend upside down before the check "flipped ant" holds.
UPSIDE_DOWN = 0.1
#: The planning variants of the table (``planning_ablations``' names).
VARIANTS = (
    "as trained",
    "goal as subgoal",
    "unreachable=subgoal",
    "oracle graph",
    "oracle graph, goal",
    "no graph",
)


def _finite(value) -> bool:
    return value is not None and not (isinstance(value, float) and math.isnan(value))


def findings(
    m: Mapping[str, float],
    *,
    goal: float,
    tolerance: float,
    cutoff: float,
    ablations: Mapping[str, float] | None = None,
    margin: float = MARGIN,
) -> list[str]:
    """Every check that holds for one run, each with its figures (a check whose inputs are missing or ``NaN`` is
    skipped). ``m`` holds the run's ``frontier``, ``landmark_progress``, ``reachable_progress``,
    ``reachable_landmarks``, ``bridge_distance``, ``start_subgoal_feasible``, ``start_best_subgoal_in_wall``,
    ``start_actor_q_gap``, ``upside_down`` and ``ended_upside_down``; ``goal`` is the farthest test goal's progress
    along the maze and ``tolerance`` that of every comparison along the maze (the recipe: the task's success radius,
    the distance at which a goal counts as reached); ``ablations`` the success of the planning variants
    (``"as trained"``, ``"goal as subgoal"``, ``"unreachable=subgoal"``, ``"oracle graph"``, ``"oracle graph, goal"``).

    * exploration: the training episodes' frontier more than ``tolerance`` short of the goal;
    * flipped ant: at least ``UPSIDE_DOWN`` of the training steps (of the last evaluation interval) spent upside
      down, the episodes that end so stopped exploring where the ant fell (``right_flipped_after``);
    * landmarks: no landmark within ``tolerance`` of how far the episodes (or the goal, if nearer) got;
    * graph cut: part of the landmarks unreachable from the start and the reachable ones more than ``tolerance``
      short of the farthest landmark (with the bridge, the shortest learned edge across, against the cutoff);
    * learned distances: the oracle's edges on the same landmarks (either oracle variant) at least ``margin``
      above the agent as trained;
    * high level: its subgoal at the start in a wall (with the Q gap to its critic's best free subgoal), or the
      goal as subgoal at least ``margin`` above the agent as trained;
    * graph fallback: going straight for the subgoals the graph cannot reach (``"unreachable=subgoal"``) at least
      ``margin`` above the agent as trained with the reference's fallback (the reachable landmark nearest to them);
    * high-level critic: its best subgoal at the start in a wall;
    * low level: the oracle's graph with the goal as subgoal below ``margin`` although the landmarks reach the
      goal (within ``tolerance``).

    Examples:
        >>> findings({"frontier": 26.1, "landmark_progress": 25.9}, goal=40.1, tolerance=5.0, cutoff=30.0)
        ['exploration: training episodes reach 26.1 of 40.1']
        >>> findings({"frontier": 36.1, "landmark_progress": 34.6, "reachable_progress": 30.8,
        ...           "reachable_landmarks": 0.957, "bridge_distance": 31.3}, goal=40.1, tolerance=5.0, cutoff=30.0,
        ...          ablations={"as trained": 0.26, "goal as subgoal": 0.28, "oracle graph": 0.66})
        ['graph cut: plans from the start reach 30.8 of 34.6 (96% of the landmarks; bridge 31.3 steps, cutoff 30)', 'learned distances: the oracle graph 66% vs 26% as trained']
    """
    get = lambda key: m.get(key, math.nan)  # noqa: E731
    out = []
    frontier, landmarks, reachable = get("frontier"), get("landmark_progress"), get("reachable_progress")
    if _finite(frontier) and frontier < goal - tolerance:
        out.append(f"exploration: training episodes reach {frontier:.1f} of {goal:.1f}")
    upside_down, ended = get("upside_down"), get("ended_upside_down")
    if _finite(upside_down) and upside_down >= UPSIDE_DOWN:
        episodes = f", {ended:.0%} of the episodes end so" if _finite(ended) else ""
        out.append(f"flipped ant: {upside_down:.0%} of the training steps upside down{episodes} (right_flipped_after)")
    if _finite(landmarks):
        explored = min(frontier, goal) if _finite(frontier) else goal
        if landmarks < explored - tolerance:
            out.append(f"landmarks: none past {landmarks:.1f} (the episodes reach {explored:.1f})")
    share = get("reachable_landmarks")
    if (
        _finite(reachable)
        and _finite(landmarks)
        and _finite(share)
        and share < 1
        and reachable < landmarks - tolerance
    ):
        bridge = get("bridge_distance")
        across = (
            f"; bridge {bridge:.1f} steps, cutoff {cutoff:g}"
            if _finite(bridge) and math.isfinite(bridge)
            else ""
        )
        out.append(
            f"graph cut: plans from the start reach {reachable:.1f} of {landmarks:.1f} ({share:.0%} of the "
            f"landmarks{across})"
        )
    ablations = dict(ablations or {})
    trained = ablations.get("as trained", math.nan)
    oracle = max(
        (ablations[k] for k in ("oracle graph", "oracle graph, goal") if _finite(ablations.get(k))),
        default=math.nan,
    )
    if _finite(trained) and _finite(oracle) and oracle >= trained + margin:
        out.append(f"learned distances: the oracle graph {oracle:.0%} vs {trained:.0%} as trained")
    if get("start_subgoal_feasible") == 0:
        gap = get("start_actor_q_gap")
        why = f" ({gap:.2f} in Q below its critic's best free subgoal)" if _finite(gap) and gap > 0 else ""
        out.append(f"high level: its subgoal at the start lies in a wall{why}")
    to_goal = ablations.get("goal as subgoal", math.nan)
    if _finite(trained) and _finite(to_goal) and to_goal >= trained + margin:
        out.append(f"high level: the goal as subgoal {to_goal:.0%} vs {trained:.0%} as trained")
    straight = ablations.get("unreachable=subgoal", math.nan)
    if _finite(trained) and _finite(straight) and straight >= trained + margin:
        out.append(
            f"graph fallback: straight for the subgoals the graph cannot reach {straight:.0%} vs {trained:.0%} "
            "as trained (planner.unreachable=subgoal)"
        )
    if get("start_best_subgoal_in_wall") == 1:
        out.append("high-level critic: its best subgoal at the start lies in a wall")
    oracle_goal = ablations.get("oracle graph, goal", math.nan)
    if _finite(oracle_goal) and oracle_goal < margin and _finite(landmarks) and landmarks >= goal - tolerance:
        out.append(f"low level: {oracle_goal:.0%} along the oracle graph's route to the goal")
    return out


#: The ``diag/`` and ``train/`` columns :func:`findings` reads, by its names.
COLUMNS = {
    "frontier": "train/frontier",
    "landmark_progress": "diag/landmark_progress",
    "reachable_progress": "diag/reachable_progress",
    "reachable_landmarks": "diag/reachable_landmarks",
    "start_subgoal_feasible": "diag/start_subgoal_feasible",
    "start_best_subgoal_in_wall": "diag/start_best_subgoal_in_wall",
    "start_actor_q_gap": "diag/start_actor_q_gap",
    "upside_down": "train/upside_down",
    "ended_upside_down": "train/ended_upside_down",
}


def row_at(rows: Sequence[Mapping[str, float]], steps: float | None) -> Mapping[str, float]:
    """The last evaluation row at or before ``steps`` (the last row for ``None``)."""
    evaluated = [
        r for r in rows if _finite(r.get("eval/success")) and (steps is None or r["env_steps"] <= steps)
    ]
    if not evaluated:
        raise SystemExit(f"no evaluation at or before {steps} env steps.")
    return evaluated[-1]


def goal_progress(env_name: str, margin: float) -> tuple[float, float]:
    """The farthest test goal's progress along the maze from the start (the origin; walls inflated by ``margin``)
    and the maze's success radius."""
    spec = get_maze_spec(env_name)
    geometry = MazeGeometry.from_maze(env_name, margin=margin)
    goals = torch.tensor(spec.test_goals, dtype=torch.float32)
    progress = geometry.path_length(torch.zeros(1, 2), goals).max().item()
    return progress, float(spec.success_threshold)


def gymnasium_goal_progress(cfg: dict) -> tuple[float, float]:
    """:func:`goal_progress` of a run on a gymnasium-robotics maze (its nested configuration ``cfg``): the farthest
    goal of the recipe's first batch of test episodes (its test env, seeded as the recipe seeds it), from the fixed
    start of its training resets (:func:`run_maze`), and its success radius (``low.reward_threshold``). Raises
    ``SystemExit`` naming the run's env when it has no maze or no fixed start."""
    cpu = torch.device("cpu")
    geometry = run_maze(cfg, build_environment(cfg, cpu))
    if geometry is None or geometry.start is None:
        what = "no maze" if geometry is None else "no fixed start (`gymnasium.reset_options` without one `reset_cell`)"
        raise SystemExit(f"env_name={cfg['env_name']}: {what}; the table measures progress along a maze from its start.")
    goals = build_environment(cfg, cpu, eval=True).reset()["desired_goal"][..., :2]
    return geometry.path_length(geometry.start, goals).max().item(), float(cfg["low"]["reward_threshold"])


def check_run(
    path, *, ablations: bool = False, oracle_margin: float | None = None, oracle_speed: float | None = None
):
    """The run of directory ``path`` (:func:`~torchrl_dhrl.recipe.aggregate.read_run`), checked: a maze (built-in,
    or gymnasium-robotics' with a fixed start) whose geometry its ``planner.oracle_margin`` (or ``oracle_margin``, which
    then replaces it in the record) leaves open, with an agent to re-evaluate for ``ablations``; ``oracle_speed``
    replaces the record's ``planner.oracle_speed`` (the oracle's goal units per step). Raises ``SystemExit`` naming
    the run and what is missing."""
    path = Path(path)
    if not (path / "metrics.csv").is_file():
        raise SystemExit(
            f"{path}: no metrics.csv (a run directory of the recipe, or a results folder's seed)."
        )
    run = read_run(path)
    gymnasium = gymnasium_id(run.env) is not None
    if not isinstance(ENVS.get(run.env), MazeSpec) and not gymnasium:
        raise SystemExit(
            f"{path}: env_name={run.env!r} is not a maze; accepted: {', '.join(MAZE_NAMES)} and gymnasium-robotics "
            "mazes (gymnasium:PointMaze_*, gymnasium:AntMaze_*)."
        )
    if ablations and not agent_checkpoint_file(path).exists():
        raise SystemExit(f"{path}: --ablations needs the run's agent/ or checkpoint/; it has neither.")
    if oracle_margin is not None:
        run.config["planner.oracle_margin"] = oracle_margin
    if oracle_speed is not None:
        run.config["planner.oracle_speed"] = oracle_speed
    try:
        run_goal(run)
    except ValueError as err:  # a margin that closes the maze (ConfigError from run_maze)
        raise SystemExit(
            f"{path}: {err} Give the maze diagnostics' agent radius with --oracle-margin (runs of 0.4.0 and earlier "
            "recorded the ant mazes' 0.5 for every gymnasium-robotics maze; the recipe now derives an 8th of a cell)."
        ) from err
    return run


def run_goal(run) -> tuple[float, float]:
    """The run's :func:`goal_progress` (a built-in maze) or :func:`gymnasium_goal_progress`, walls inflated by its
    record's ``planner.oracle_margin`` (computed once per run and margin: :func:`check_run` and
    :func:`summarize_run` both ask)."""
    return _run_goal(run.path, run.env, float(run.config.get("planner.oracle_margin", 0.5)))


@functools.cache
def _run_goal(path: Path, env_name: str, margin: float) -> tuple[float, float]:
    if gymnasium_id(env_name) is None:
        try:
            return goal_progress(env_name, margin)
        except ValueError as err:
            raise ValueError(f"planner.oracle_margin={margin:g} on env_name={env_name}: {err}") from err
    cfg = yaml.safe_load((path / "config.yaml").read_text())
    cfg["planner"]["oracle_margin"] = margin
    return gymnasium_goal_progress(cfg)


def summarize_run(run, *, at: float | None = None, ablations: bool = False, repeats: int = 5) -> dict:
    """One run's row of the table (a :func:`check_run` record): the figures and :func:`findings`."""
    env_name, path = run.env, run.path
    margin = float(run.config.get("planner.oracle_margin", 0.5))
    goal, tolerance = run_goal(run)
    values, variants, agent_steps = {}, {}, None
    if ablations:
        checkpoint = agent_checkpoint_file(path)
        agent_steps = (load_checkpoint(checkpoint, components=("counters",)).get("counters") or {}).get(
            "env_steps"
        )
        at = agent_steps if agent_steps is not None else at
        cfg, agent = agent_from_checkpoint(checkpoint)
        cfg["planner"]["oracle_margin"] = margin  # the record's, or --oracle-margin
        cfg["planner"]["oracle_speed"] = run.config.get("planner.oracle_speed", cfg["planner"]["oracle_speed"])
        env = build_environment(cfg, torch.device("cpu"), eval=True, agent=agent)
        maze = run_maze(cfg, env) if gymnasium_id(env_name) is not None else env_name
        diagnosis = graph_diagnosis(agent, env, maze, oracle_margin=margin, rollout=False)
        values = {key: diagnosis.metrics.get(column, math.nan) for key, column in COLUMNS.items()}
        values["bridge_distance"] = diagnosis.reach.get("bridge_distance", math.nan)
        rows = planning_ablations(
            agent, env, env.max_episode_steps, repeats=repeats, oracle=oracle_distance(cfg, env)
        )
        variants = {r["variant"]: r["success"] for r in rows if r["variant"] in VARIANTS}
        variants["episodes"] = rows[0]["episodes"]
    row = row_at(run.rows, at)
    for (
        key,
        column,
    ) in COLUMNS.items():  # the frontier always from the metrics; the graph as saved where measured
        if not _finite(values.get(key)):
            values[key] = row.get(column, math.nan)
    cutoff = float(run.config.get("planner.cutoff", math.nan))
    return {
        "run": str(path),
        "env_steps": int(row["env_steps"]),
        "agent_steps": agent_steps,
        "success": row["eval/success"],
        "goal": goal,
        "tolerance": tolerance,
        "cutoff": cutoff,
        **values,
        "ablations": variants,
        "findings": findings(values, goal=goal, tolerance=tolerance, cutoff=cutoff, ablations=variants),
    }


def _fmt(value, spec: str = ".1f") -> str:
    return format(value, spec) if _finite(value) else "-"


def markdown(rows: Sequence[dict]) -> str:
    """The table, one line per run."""
    with_ablations = any(r["ablations"] for r in rows)
    head = [
        "run",
        "env steps",
        "success (last evaluation)",
        "goal G",
        "frontier F",
        "landmarks L",
        "reachable R (share)",
        "start subgoal (Q gap)",
    ]
    if with_ablations:
        head += [f"{name} ({rows[0]['ablations'].get('episodes', '?')} ep.)" for name in VARIANTS]
    head += ["findings"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        feasible = r.get("start_subgoal_feasible")
        start = "-" if not _finite(feasible) else ("free" if feasible == 1 else "in a wall")
        if _finite(r.get("start_actor_q_gap")):
            start += f" ({r['start_actor_q_gap']:.2f})"
        cells = [
            r["run"],
            f"{r['env_steps']:,}",
            f"{r['success']:.0%}",
            _fmt(r["goal"]),
            _fmt(r.get("frontier")),
            _fmt(r.get("landmark_progress")),
            f"{_fmt(r.get('reachable_progress'))} ({_fmt(r.get('reachable_landmarks'), '.0%')})",
            start,
        ]
        if with_ablations:
            cells += [_fmt(r["ablations"].get(name), ".0%") for name in VARIANTS]
        cells += ["; ".join(r["findings"]) or "none of the checks"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "runs", nargs="+", help="run directories (metrics.csv, config.yaml; agent/ for --ablations)"
    )
    parser.add_argument("--at", type=float, default=None, help="env steps: the last evaluation at or before")
    parser.add_argument(
        "--ablations", action="store_true", help="also re-evaluate each run's agent (planning)"
    )
    parser.add_argument("--repeats", type=int, default=5, help="with --ablations: batches of test episodes")
    parser.add_argument("--out", default=None, help="also write the table to this file")
    add_oracle_options(parser)
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    oracle = oracle_overrides(parser, args)
    runs = [check_run(path, ablations=args.ablations, **oracle) for path in args.runs]  # every run before any work
    rows = [summarize_run(run, at=args.at, ablations=args.ablations, repeats=args.repeats) for run in runs]
    print_table(markdown(rows), args.out)
    return rows


if __name__ == "__main__":
    main()
