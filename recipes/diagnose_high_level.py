"""Where does a DHRL run's high level want its subgoal? Its critic's Q over the subgoal box at a test start.

    python recipes/diagnose_high_level.py outputs/<date>/<time>                  # the run directory
    python recipes/diagnose_high_level.py run/checkpoint --resolution 0.25 --plot landscape.png

Prints, at the first test episode's start state and goal: the actor's subgoal and its Q, the grid subgoal of
highest Q (over the whole box and over the free space of a maze), the goal itself as a subgoal, the share of the
best-valued subgoals that lie inside walls, and how many of the test starts get an actor subgoal inside a wall;
with ``--along``, the same at every new subgoal of a failed and of a successful test episode.
A critic whose best subgoals lie in walls misleads the actor; an actor far below its critic's best free subgoal
does not follow its critic. 2-D goal spaces only (the mazes).
"""

from __future__ import annotations

import argparse

import torch
from dhrl_utils import agent_from_checkpoint, build_environment, run_maze
from tensordict import TensorDict

from torchrl_dhrl.diagnostics import landscape_summary, subgoal_box, subgoal_landscape, subgoal_values
from torchrl_dhrl.recipe import agent_checkpoint_file, load_checkpoint
from torchrl_dhrl.training import evaluate


def _in_walls(geometry, points):
    """``geometry.in_walls(points)`` (``[..., 2]`` -> ``[...]``); nothing is in a wall without a maze."""
    if geometry is None:
        return torch.zeros(points.shape[:-1], dtype=torch.bool)
    return geometry.in_walls(points)


def _fmt(point) -> str:
    return "(" + ", ".join(f"{float(v):6.2f}" for v in point) + ")"


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", help="a checkpoint or the run directory holding it")
    parser.add_argument(
        "--resolution", type=float, default=0.5, help="grid spacing of the subgoals (goal units)"
    )
    parser.add_argument(
        "--top", type=float, default=0.05, help="share of the best-valued grid subgoals examined"
    )
    parser.add_argument(
        "--plot", default=None, help="write the Q map with the walls and the subgoals here (PNG)"
    )
    parser.add_argument(
        "--along",
        action="store_true",
        help="also at every new subgoal of a failed and of a successful test episode (deterministic rollout)",
    )
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    if not 0 < args.top <= 1:
        parser.error(f"--top must be in (0, 1], got {args.top}")
    device = torch.device(args.device)
    path = agent_checkpoint_file(args.checkpoint)  # the run's checkpoint, else its saved agent
    cfg, agent = agent_from_checkpoint(path, device)
    steps = load_checkpoint(path, components=("counters",))["counters"]["env_steps"]
    env = build_environment(cfg, device, eval=True, agent=agent)
    start = env.reset()
    observations, goals = (
        start["observation"].reshape(-1, start["observation"].shape[-1]),
        start["desired_goal"],
    )
    goals = goals.reshape(-1, goals.shape[-1])
    low, high = subgoal_box(agent.high_loss)
    land = subgoal_landscape(
        agent.high_loss, agent.high_policy.actor, observations[0], goals[0], low, high, args.resolution
    )
    geometry = run_maze({**cfg, "planner": {**cfg["planner"], "oracle_margin": 0.0}}, env)  # the walls themselves
    points = land.points()
    walls = _in_walls(geometry, points)
    summary = landscape_summary(land, walls, args.top)
    goal_q = float(subgoal_values(agent.high_loss, observations[0], goals[0], goals[0].reshape(1, -1))[0, 0])
    best, best_q = land.best()
    best_free, best_free_q = land.best(~walls) if bool((~walls).any()) else (best, best_q)
    actor = agent.high_policy.actor  # the deterministic subgoal of every test start
    with torch.no_grad():
        batch = TensorDict(
            {actor.in_keys[0]: observations, actor.in_keys[1]: goals}, batch_size=[goals.shape[0]]
        )
        actor_all = actor(batch)[actor.out_keys[0]].float().cpu()
    report = {
        **summary,
        "env_steps": steps,
        "start": observations[0][:2].cpu(),
        "goal": goals[0].cpu(),
        "actor_subgoal": land.actor_subgoal,
        "actor_q": float(land.actor_q),
        "actor_in_wall": bool(_in_walls(geometry, land.actor_subgoal)),
        "best_subgoal": best,
        "best_q": float(best_q),
        "best_free_subgoal": best_free,
        "best_free_q": float(best_free_q),
        "goal_q": goal_q,
        "actor_in_walls_over_starts": float(_in_walls(geometry, actor_all).float().mean()),
        "starts": observations.shape[0],
    }
    print(
        f"{cfg['env_name']} at {steps} env steps: the high level at the test start {_fmt(report['start'])} for "
        f"the goal {_fmt(report['goal'])}; Q of the critic's first member over a {args.resolution:g} grid"
    )
    wall = {True: "in a wall", False: "free"}
    print(
        f"  actor's subgoal      {_fmt(land.actor_subgoal)}  Q {report['actor_q']:8.3f}  {wall[report['actor_in_wall']]}"
    )
    print(
        f"  best grid subgoal    {_fmt(best)}  Q {report['best_q']:8.3f}  {wall[bool(report['best_in_wall'])]}"
    )
    print(f"  best free subgoal    {_fmt(best_free)}  Q {report['best_free_q']:8.3f}")
    print(f"  the goal as subgoal  {_fmt(report['goal'])}  Q {report['goal_q']:8.3f}")
    print(
        f"  the best {args.top:.0%} of the grid: {report['top_in_walls']:.0%} in walls "
        f"(walls: {report['walls_share']:.0%} of the box); Q ranges over {report['q_range']:.3f}, the actor "
        f"{report['actor_q_gap']:.3f} below the best free subgoal"
    )
    print(
        f"  actor's subgoals at the {report['starts']} test starts: {report['actor_in_walls_over_starts']:.0%} in walls"
    )
    if args.plot:
        _plot(args.plot, land, geometry, report, cfg["env_name"])
        print(f"  picture: {args.plot}")
    if args.along:
        report["along"] = _along(agent, env, geometry, low, high, args)
    return report


def _along(agent, env, geometry, low, high, args) -> list[dict]:
    """The landscape at every new subgoal of a failed and of a successful test episode (if any)."""
    result = evaluate(env, agent.policy, env.max_episode_steps)
    rollout = result.rollout.reshape(-1, result.rollout.shape[-1])
    success = rollout["next", "is_success"].reshape(*rollout.shape, -1).any(-1)[:, -1]
    picked = [(int(i), "failed") for i in (~success).nonzero()[:1, 0]]
    picked += [(int(i), "succeeded") for i in success.nonzero()[:1, 0]]
    rows = []
    for episode, outcome in picked:
        print(f"  along test episode {episode} ({outcome}); at each new subgoal:")
        print(
            f"  {'step':>5} {'position':>16} {'actor subgoal':>16} {'wall':>5} {'Q gap':>7} "
            f"{'best free subgoal':>18} {'top in walls':>12}"
        )
        steps = rollout[episode]["new_subgoal"].reshape(-1).nonzero()[:, 0].tolist()
        for step in steps:
            td = rollout[episode, step]
            land = subgoal_landscape(
                agent.high_loss,
                agent.high_policy.actor,
                td["observation"],
                td["desired_goal"],
                low,
                high,
                args.resolution,
            )
            walls = _in_walls(geometry, land.points())
            summary = landscape_summary(land, walls, args.top)
            best_free, _ = land.best(~walls) if bool((~walls).any()) else land.best()
            in_wall = bool(_in_walls(geometry, land.actor_subgoal))
            rows.append({"episode": episode, "step": step, "in_wall": in_wall, **summary})
            print(
                f"  {step:>5} {_fmt(td['achieved_goal'])} {_fmt(land.actor_subgoal)} {'yes' if in_wall else 'no':>5} "
                f"{summary['actor_q_gap']:7.3f} {_fmt(best_free):>18} {summary['top_in_walls']:12.0%}"
            )
    return rows


def _plot(path, land, geometry, report, env_name) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    fig, ax = plt.subplots(figsize=(6.4, 5.6))
    extent = [float(land.xs[0]), float(land.xs[-1]), float(land.ys[0]), float(land.ys[-1])]
    image = ax.imshow(land.q.numpy(), origin="lower", extent=extent, cmap="viridis", aspect="equal")
    fig.colorbar(image, ax=ax, label="Q (critic's first member)")
    if geometry is not None:
        for box in geometry.boxes:
            (x0, y0), (x1, y1) = box.tolist()
            ax.add_patch(
                Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, hatch="//", edgecolor="white", lw=0.8)
            )
    markers = (
        ("start", report["start"], "o", "white"),
        ("goal", report["goal"], "*", "gold"),
        ("actor's subgoal", report["actor_subgoal"], "X", "red"),
        ("best subgoal", report["best_subgoal"], "^", "orange"),
        ("best free subgoal", report["best_free_subgoal"], "s", "cyan"),
    )
    for label, point, marker, color in markers:
        ax.scatter(
            [float(point[0])],
            [float(point[1])],
            marker=marker,
            s=90,
            c=color,
            edgecolors="black",
            label=label,
        )
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.legend(loc="upper right", fontsize=7, framealpha=0.8)
    ax.set_title(f"{env_name} at {report['env_steps']} env steps: high-level Q over subgoals")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
