"""How far do a maze run's training episodes get, goal by goal? Is exploration what holds the run back?

Reads the high-level replay buffer of a checkpoint (one record per ``c_h``-step segment of every stored training
episode) and prints, for the most recent episodes, how far along the maze (obstacle-free path length from the
start) each goal was and how far the agent got, next to the furthest point the stored episodes ever reached
(the frontier), then a summary: how many goals lay beyond the frontier and how far those episodes got, how
many episodes reached the frontier.

    python recipes/diagnose_exploration.py outputs/<date>/<time>          # the run directory
    python recipes/diagnose_exploration.py run/checkpoint --episodes 120 --rows 0

``--box NAME X0 X1 Y0 Y1`` (repeatable) reads the low-level buffer instead, every stored step, and counts per group of
``--per`` training episodes (oldest first) those whose agent entered each box, e.g. AntMazeBottleneck's gap and the
corridor past it::

    python recipes/diagnose_exploration.py <run> --rows 0 --box gap 15.4 17 7 9 --box past 12 20 9 16 --per 100

``--upside-down`` (the ant mazes, built-in and gymnasium-robotics' ``AntMaze_*``) reads the low-level buffer too and
prints, per group of ``--per`` training episodes, the share of their steps the ant spent upside down and how many
ended so: a run logged before ``train/upside_down`` existed, or where a flipped ant may be what stops exploring::

    python recipes/diagnose_exploration.py <run> --rows 0 --upside-down --per 20

``--oracle-margin`` replaces the run's recorded ``planner.oracle_margin`` (the agent's radius, by which the walls grow
in the path lengths), e.g. for a gymnasium-robotics maze trained by 0.4.0 or earlier, which recorded the
configuration's value.
"""

from __future__ import annotations

import argparse

import torch
from dhrl_utils import (
    add_oracle_options,
    agent_from_checkpoint,
    build_environment,
    build_replay_buffers,
    oracle_overrides,
    run_maze,
    upside_down_test,
)
from tensordict import TensorDictBase
from torch import Tensor

from torchrl_dhrl.diagnostics import (
    EpisodeProgress,
    episode_progress,
    episodes_in_boxes,
    upside_down_by_episode,
)
from torchrl_dhrl.recipe import ConfigError, load_checkpoint


def stored_records(path, buffer: str, oracle: dict | None = None) -> tuple[dict, TensorDictBase]:
    """The configuration of a maze run's checkpoint (``oracle``'s ``planner`` keys in place of its recorded ones) and
    every record of its ``"low_rb"`` or ``"high_rb"`` buffer."""
    cfg, agent = agent_from_checkpoint(path)
    cfg["planner"].update(oracle or {})
    if run_maze(cfg, build_environment(cfg, torch.device("cpu"))) is None:
        raise ValueError(f"diagnose_exploration needs a maze run; {path} is a {cfg['env_name']} run.")
    low_rb, high_rb = build_replay_buffers(cfg, agent, torch.device("cpu"))
    rb = {"low_rb": low_rb, "high_rb": high_rb}[buffer]  # a KeyError names any other buffer
    rb.load_state_dict(load_checkpoint(path, components=(buffer,))[buffer])
    return cfg, rb.storage[: len(rb.storage)]


def exploration_from_checkpoint(
    path, *, episodes: int = 60, near: float = 0.9, oracle: dict | None = None
) -> tuple[EpisodeProgress, dict]:
    """:func:`~torchrl_dhrl.diagnostics.episode_progress` of a recipe checkpoint's last ``episodes`` training episodes.

    Returns the progress and a summary: ``explored``, ``goals_beyond`` (goals past the frontier),
    ``beyond_mean_progress`` (how far those episodes got), ``reached_frontier`` (episodes that got to ``near``
    times the frontier's progress or further), ``episodes``.
    """
    cfg, records = stored_records(path, "high_rb", oracle)
    first = records["segment_index"].reshape(-1) == 0
    start = records["achieved_goal"][first].float().mean(0)  # where the episodes start
    geometry = run_maze(cfg, build_environment(cfg, torch.device("cpu")))  # walls grown by planner.oracle_margin
    out = episode_progress(geometry, records, start, last=episodes)
    beyond = out.goal_progress > out.explored
    summary = {
        "episodes": len(out.episode_ids),
        "explored": out.explored,
        "goals_beyond": int(beyond.sum()),
        "beyond_mean_progress": float(out.max_progress[beyond].mean()) if beyond.any() else float("nan"),
        "reached_frontier": int((out.max_progress >= near * out.explored).sum()),
    }
    return out, summary


def boxes_from_checkpoint(path, boxes, oracle: dict | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`~torchrl_dhrl.diagnostics.episodes_in_boxes` over every step of a checkpoint's low-level buffer.

    The position is the stored ``achieved_goal`` (x, y in the mazes), the episode the collector's ``traj_ids``.
    """
    _, steps = stored_records(path, "low_rb", oracle)
    return episodes_in_boxes(steps["achieved_goal"][..., :2], steps["collector", "traj_ids"], boxes)


def upside_down_from_checkpoint(path, oracle: dict | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`~torchrl_dhrl.diagnostics.upside_down_by_episode` over every step of an ant maze run's low-level buffer
    (the ant's :meth:`~torchrl_dhrl.envs.AntAgent.is_upside_down` after each step; episodes from ``traj_ids``)."""
    cfg, steps = stored_records(path, "low_rb", oracle)
    upside_down = upside_down_test(cfg)
    if upside_down is None:
        raise ValueError(f"--upside-down needs an ant maze run; {path} is a {cfg['env_name']} run.")
    flipped = torch.as_tensor(upside_down(steps["next", "observation"]))
    count = steps.get("step_count", None)
    return upside_down_by_episode(flipped, steps["collector", "traj_ids"], None if count is None else count.reshape(-1))


def print_upside_down(ids: Tensor, share: Tensor, ended: Tensor, per: int) -> None:
    """Per group of ``per`` episodes (oldest first): the share of their steps upside down, how many ended so."""
    print(f"{'episodes':>12} {'steps upside down':>18} {'ended upside down':>18}")
    for start in range(0, len(ids), per):
        group, last = share[start : start + per], ended[start : start + per]
        label = f"{start}-{start + len(group) - 1}"
        print(f"{label:>12} {float(group.mean()):>18.1%} {int(last.sum()):>9} of {len(group):<6}")
    print(f"{'all':>12} {float(share.mean()):>18.1%} {int(ended.sum()):>9} of {len(ids):<6}")


def print_box_counts(names: list[str], ids: torch.Tensor, inside: torch.Tensor, per: int) -> None:
    """Per group of ``per`` episodes (oldest first): how many entered each box."""
    print(f"{'episodes':>12} " + " ".join(f"{name:>12}" for name in names))
    for start in range(0, len(ids), per):
        group = inside[start : start + per]
        label = f"{start}-{start + len(group) - 1}"
        print(f"{label:>12} " + " ".join(f"{int(c):>5} of {len(group):<4}" for c in group.sum(0).tolist()))
    print(f"{'all':>12} " + " ".join(f"{int(c):>5} of {len(ids):<4}" for c in inside.sum(0).tolist()))


def main(argv: list[str] | None = None) -> tuple[EpisodeProgress, dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", help="a checkpoint or the run directory holding it")
    parser.add_argument("--episodes", type=int, default=60, help="the most recent training episodes to read")
    parser.add_argument("--rows", type=int, default=25, help="episodes to print one by one (the latest)")
    parser.add_argument(
        "--near",
        type=float,
        default=0.9,
        help="'reached the frontier': this fraction of its progress or further",
    )
    parser.add_argument(
        "--box",
        nargs=5,
        action="append",
        metavar=("NAME", "X0", "X1", "Y0", "Y1"),
        help="count the training episodes whose agent entered this box (repeatable; reads the low-level buffer)",
    )
    parser.add_argument(
        "--upside-down",
        action="store_true",
        help="ant mazes: the share of the training steps upside down per --per episodes (reads the low-level buffer)",
    )
    parser.add_argument("--per", type=int, default=100, help="with --box or --upside-down: episodes per row")
    add_oracle_options(parser)
    args = parser.parse_args(argv)
    oracle = oracle_overrides(parser, args)
    bounds = None
    if args.box:
        try:
            bounds = torch.tensor([[float(v) for v in box[1:]] for box in args.box])
        except ValueError as err:
            parser.error(f"--box NAME X0 X1 Y0 Y1: the bounds must be numbers ({err})")
    if args.per < 1:
        parser.error(f"--per must be >= 1, got {args.per}")
    try:
        return _report(args, oracle, bounds)
    except ConfigError as err:  # a recorded margin that closes the maze
        parser.error(f"{err} Give the agent's radius with --oracle-margin.")


def _report(args, oracle: dict, bounds: torch.Tensor | None) -> tuple[EpisodeProgress, dict]:
    if args.upside_down:
        try:
            print_upside_down(*upside_down_from_checkpoint(args.checkpoint, oracle), args.per)
        except ValueError as err:
            raise SystemExit(f"diagnose_exploration.py: error: {err}") from err
    if bounds is not None:
        ids, inside = boxes_from_checkpoint(args.checkpoint, bounds, oracle)
        print_box_counts([box[0] for box in args.box], ids, inside, args.per)
    out, summary = exploration_from_checkpoint(args.checkpoint, episodes=args.episodes, near=args.near, oracle=oracle)
    if args.rows > 0:
        print(f"{'episode':>8} {'goal':>16} {'goal progress':>14} {'max progress':>13} {'end progress':>13}")
        for k in range(max(len(out.episode_ids) - args.rows, 0), len(out.episode_ids)):
            goal = ", ".join(f"{v:.1f}" for v in out.goals[k].tolist())
            print(
                f"{int(out.episode_ids[k]):8d} {'(' + goal + ')':>16} {float(out.goal_progress[k]):14.1f} "
                f"{float(out.max_progress[k]):13.1f} {float(out.end_progress[k]):13.1f}"
            )
    print(
        f"{summary['episodes']} episodes; the stored episodes reached progress {summary['explored']:.1f} at most "
        f"(path length from the start). {summary['goals_beyond']} goals lay beyond it; those episodes got to "
        f"{summary['beyond_mean_progress']:.1f} on average. {summary['reached_frontier']} episodes reached "
        f"{args.near:.0%} of the frontier's progress or further."
    )
    return out, summary


if __name__ == "__main__":
    main()
