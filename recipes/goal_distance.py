"""Success against the goal's distance on a gymnasium-robotics maze: every agent tested from one start cell to each
other free cell of its maze, the same number of deterministic test episodes per goal cell, success counted in
whole episodes (final state, as the recipe's ``eval/success``). The distance of a goal cell is the number of cells
on the shortest path to it through free cells (4-connected).

    python recipes/goal_distance.py results/pointmaze_large_dhrl_vs_sac/{dhrl,sac}_s{0,1,2} --start 1 1 \\
        --episodes 10 --out results/pointmaze_large_dhrl_vs_sac/goal_distance
    python recipes/goal_distance.py --from-csv results/pointmaze_large_dhrl_vs_sac/goal_distance.csv \\
        --out results/pointmaze_large_dhrl_vs_sac/goal_distance          # the table and figure again, no episode

An agent is a DHRL run directory, its saved agent (``agent/``) or a checkpoint of an ``env=gymnasium`` run
(``recipes/evaluate.py``'s episodes: batches of the run's ``schedule.eval_episodes`` envs, batch k seeded with
``--seed`` + k), or the output folder of ``benchmarks/sac_her_baseline.py`` (its ``model.zip``; episode i reset
with seed ``--seed`` + i, as its ``final_eval.yaml``). Every agent must be on the same env id and maze.

Writes ``<out>.csv`` (a row per agent and goal cell: ``agent``, ``kind``, ``goal_row``, ``goal_col``,
``distance``, ``episodes``, ``successes``, with the start cell), ``<out>.md`` (success per band of distances, per
agent and per kind over its agents, with the command, code and machine), ``<out>.png`` (success against distance, a
thin line per agent and a thick one per kind) and ``<out>_cells.png`` (the maze from above, each goal cell
coloured by its success, a panel per kind).
"""

from __future__ import annotations

import argparse
import copy
import csv
import datetime
import importlib.util
import math
import shlex
import sys
import time
from collections import deque
from collections.abc import Sequence
from pathlib import Path

import matplotlib
import numpy as np
import torch
from dhrl_utils import agent_from_checkpoint, build_environment, episode_outcomes, print_table
from matplotlib.figure import Figure
from torchrl_dhrl.envs import gymnasium_id

from torchrl_dhrl.recipe import agent_checkpoint_file, code_and_machine

#: The SAC + HER baseline script, whose env and episodes a SAC + HER agent is tested with.
SAC_SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "sac_her_baseline.py"
#: The agent kinds, as the table and figure name them.
DHRL, SAC_HER = "DHRL", "SAC + HER"
CSV_FIELDS = ("agent", "kind", "start_row", "start_col", "goal_row", "goal_col", "distance", "episodes", "successes")


def free_cell(value) -> bool:
    """Whether a cell of a gymnasium-robotics maze map is free (``1`` is a wall; ``0``, ``"r"``, ``"g"``, ``"c"``
    are free)."""
    return not (isinstance(value, (int, np.integer)) and value == 1)


def maze_distances(maze_map: Sequence[Sequence], start: tuple[int, int]) -> dict[tuple[int, int], int]:
    """Shortest-path distance in cells from ``start`` to every free cell it connects to (breadth-first over the
    free cells, 4-connected); the cells it cannot reach are left out.

    Examples:
        >>> maze_distances([[1, 1, 1, 1], [1, 0, 0, 1], [1, 1, 0, 1], [1, 1, 1, 1]], (1, 1))
        {(1, 1): 0, (1, 2): 1, (2, 2): 2}
    """
    rows, cols = len(maze_map), len(maze_map[0])
    if not (0 <= start[0] < rows and 0 <= start[1] < cols) or not free_cell(maze_map[start[0]][start[1]]):
        raise ValueError(f"--start {start[0]} {start[1]} is not a free cell of the {rows} x {cols} maze map.")
    distance = {start: 0}
    queue = deque([start])
    while queue:
        row, col = queue.popleft()
        for cell in ((row - 1, col), (row + 1, col), (row, col - 1), (row, col + 1)):
            if (
                cell not in distance
                and 0 <= cell[0] < rows
                and 0 <= cell[1] < cols
                and free_cell(maze_map[cell[0]][cell[1]])
            ):
                distance[cell] = distance[(row, col)] + 1
                queue.append(cell)
    return distance


def distance_bands(max_distance: int, width: int) -> list[tuple[int, int]]:
    """``[(1, width), (width + 1, 2 * width), ...]`` up to ``max_distance`` (the last band ends there)."""
    return [(low, min(low + width - 1, max_distance)) for low in range(1, max_distance + 1, width)]


def pooled_success(rows: list[dict]) -> float:
    """The success of ``rows``' episodes pooled (successes over episodes; ``NaN`` without an episode)."""
    episodes = sum(int(r["episodes"]) for r in rows)
    return sum(int(r["successes"]) for r in rows) / episodes if episodes else math.nan


def band_table(rows: list[dict], width: int) -> str:
    """The markdown table of success per distance band: a column per agent (its episodes pooled over the band's
    goal cells) and per kind (the mean over its agents, ± their standard deviation)."""
    agents = list(dict.fromkeys(row["agent"] for row in rows))
    kinds = list(dict.fromkeys(row["kind"] for row in rows))
    kind_of = {row["agent"]: row["kind"] for row in rows}
    bands = distance_bands(max(int(row["distance"]) for row in rows), width)

    names = [Path(agent).name if Path(agent).name not in ("agent", "checkpoint") else agent for agent in agents]
    header = ["goal distance (cells)", "goal cells", *[f"{kind}, mean ± std" for kind in kinds], *names]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for band in bands:
        inside = [r for r in rows if band[0] <= int(r["distance"]) <= band[1]]
        cells = {(r["goal_row"], r["goal_col"]) for r in inside}
        per_agent = {agent: pooled_success([r for r in inside if r["agent"] == agent]) for agent in agents}
        summaries = []
        for kind in kinds:
            values = np.array([per_agent[a] for a in agents if kind_of[a] == kind])
            spread = f" ± {100 * values.std(ddof=1):.1f}" if len(values) > 1 else ""  # no spread over one agent
            summaries.append(f"{100 * values.mean():.1f}%{spread}")
        label = f"{band[0]}" if band[0] == band[1] else f"{band[0]}-{band[1]}"
        lines.append(
            "| " + " | ".join([label, str(len(cells)), *summaries, *(f"{100 * per_agent[a]:.0f}%" for a in agents)])
            + " |"
        )
    return "\n".join(lines) + "\n"


def plot_goal_distance(rows: list[dict], path: str | Path, title: str) -> Path:
    """Success against the goal's distance: a thin line per agent, a thick one per kind (the mean over its
    agents at each distance)."""
    fig = Figure(figsize=(7, 4.2))
    ax = fig.add_subplot()
    colours = {}
    for agent in dict.fromkeys(row["agent"] for row in rows):
        mine = [r for r in rows if r["agent"] == agent]
        kind = mine[0]["kind"]
        colour = colours.setdefault(kind, f"C{len(colours)}")
        x, y = per_distance(mine)
        ax.plot(x, y, color=colour, linewidth=0.8, alpha=0.45)
    for kind, colour in colours.items():
        agents = list(dict.fromkeys(r["agent"] for r in rows if r["kind"] == kind))
        curves = [per_distance([r for r in rows if r["agent"] == agent]) for agent in agents]
        x = curves[0][0]
        ax.plot(x, np.mean([c[1] for c in curves], axis=0), color=colour, linewidth=2.4,
                label=f"{kind} ({len(agents)} agent{'s' if len(agents) > 1 else ''})")
    ax.set_xlabel("goal distance from the start (cells along the maze)")
    ax.set_ylabel("test success")
    ax.set_ylim(-0.03, 1.03)
    ax.grid(alpha=0.3)
    ax.legend(loc="best")
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return Path(path)


def cell_success(rows: list[dict], kind: str) -> np.ndarray:
    """The maze's cells (``[rows, cols]``, the map's outer walls included) holding each goal cell's success for the
    agents of ``kind``, their episodes pooled; ``NaN`` where no goal was tested (walls, the start)."""
    grid = np.full((max(int(r["goal_row"]) for r in rows) + 2, max(int(r["goal_col"]) for r in rows) + 2), np.nan)
    mine = [r for r in rows if r["kind"] == kind]
    for cell in {(int(r["goal_row"]), int(r["goal_col"])) for r in mine}:
        grid[cell] = pooled_success([r for r in mine if (int(r["goal_row"]), int(r["goal_col"])) == cell])
    return grid


def plot_cells(rows: list[dict], path: str | Path, title: str) -> Path:
    """The maze seen from above, a panel per kind: each goal cell coloured and labelled with its success (the
    kind's agents pooled), the start marked ``S``, cells without a goal grey."""
    kinds = list(dict.fromkeys(row["kind"] for row in rows))
    start = (int(rows[0]["start_row"]), int(rows[0]["start_col"]))
    grids = [cell_success(rows, kind) for kind in kinds]
    height, width = grids[0].shape
    fig = Figure(figsize=(0.36 * width * len(kinds) + 1.6, 0.36 * height + 0.9), layout="constrained")
    axes = fig.subplots(1, len(kinds), squeeze=False)[0]
    cmap = matplotlib.colormaps["viridis"].with_extremes(bad="0.55")
    for ax, kind, grid in zip(axes, kinds, grids, strict=True):
        image = ax.imshow(grid, cmap=cmap, vmin=0.0, vmax=1.0)
        for (row, col), value in np.ndenumerate(grid):
            if not np.isnan(value):
                ax.text(col, row, f"{100 * value:.0f}", ha="center", va="center", fontsize=7,
                        color="black" if value > 0.5 else "white")
        ax.text(start[1], start[0], "S", ha="center", va="center", fontsize=9, fontweight="bold", color="white")
        agents = len({r["agent"] for r in rows if r["kind"] == kind})
        ax.set_title(f"{kind} ({agents} agent{'s' if agents > 1 else ''})", fontsize=10)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.colorbar(image, ax=list(axes), shrink=0.8, label="test success (%)", format=lambda v, _: f"{100 * v:.0f}")
    fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    return Path(path)


def per_distance(rows: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """One agent's success at each distance (its episodes pooled over the goal cells at that distance)."""
    distances = sorted({int(r["distance"]) for r in rows})
    success = [pooled_success([r for r in rows if int(r["distance"]) == d]) for d in distances]
    return np.array(distances), np.array(success)


def _sac_module():
    spec = importlib.util.spec_from_file_location("sac_her_baseline", SAC_SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class SacAgent:
    """A SAC + HER model of ``benchmarks/sac_her_baseline.py`` (its output folder), tested on one goal cell at a
    time."""

    kind = SAC_HER

    def __init__(self, folder: Path):
        import json

        from stable_baselines3 import SAC

        self.baseline = _sac_module()
        self.config = json.loads((folder / "config.json").read_text())
        self.env_id, self.make_kwargs = self.config["env_id"], self.config.get("make_kwargs") or {}
        self.right_flipped_after = self.config.get("right_flipped_after")  # its training and test episodes'
        env = self.baseline._env(
            self.env_id, self.config.get("reset_options"), self.make_kwargs, self.right_flipped_after
        )
        self.model = SAC.load(folder / "model.zip", env=env, device="cpu")  # HER's buffer class wants the env

    def successes(self, start, goal, episodes: int, seed: int) -> tuple[int, int]:
        """Successes and episodes from ``start`` to ``goal`` (episode i reset with seed ``seed`` + i)."""
        options = {"reset_cell": list(start), "goal_cell": list(goal)}
        env = self.baseline._env(self.env_id, options, self.make_kwargs, self.right_flipped_after)
        final, _ = self.baseline.episode_successes(self.model, env, episodes, [seed + i for i in range(episodes)])
        env.close()
        return int(sum(final)), episodes


class DhrlAgent:
    """A DHRL agent of an ``env=gymnasium`` run, tested on one goal cell at a time (its test envs reset with the
    start and goal cells in place of ``gymnasium.eval_reset_options``)."""

    kind = DHRL

    def __init__(self, path: Path, device: torch.device):
        self.device = device
        self.cfg, self.agent = agent_from_checkpoint(agent_checkpoint_file(path), device)
        self.env_id = gymnasium_id(self.cfg["env_name"])
        if self.env_id is None:
            raise SystemExit(
                f"{path}: env_name={self.cfg['env_name']} is not a gymnasium-robotics maze; goal_distance.py tests "
                "env=gymnasium runs (env_name=gymnasium:PointMaze_*/AntMaze_*) and SAC + HER baselines."
            )
        self.make_kwargs = dict(self.cfg["gymnasium"].get("make_kwargs") or {})
        self.right_flipped_after = self.cfg.get("right_flipped_after")  # built into its test envs by the recipe

    def successes(self, start, goal, episodes: int, seed: int) -> tuple[int, int]:
        """Successes and episodes from ``start`` to ``goal``: at least ``episodes``, in whole batches of the run's
        test envs (batch k seeded with ``seed`` + k)."""
        cfg = copy.deepcopy(self.cfg)
        cfg["gymnasium"]["eval_reset_options"] = {"reset_cell": list(start), "goal_cell": list(goal)}
        env = build_environment(cfg, self.device, eval=True, agent=self.agent)
        batches = math.ceil(episodes / env.batch_size.numel())
        outcome, _ = episode_outcomes(env, self.agent.policy, batches, seed)
        env.close()
        return int(outcome.sum()), outcome.numel()


def load_agent(path: str | Path, device: torch.device):
    """A :class:`SacAgent` where ``path`` holds a ``model.zip`` and ``config.json``, else a :class:`DhrlAgent`."""
    path = Path(path)
    if (path / "model.zip").is_file() and (path / "config.json").is_file():
        return SacAgent(path)
    return DhrlAgent(path, device)


def maze_map_of(env_id: str, make_kwargs: dict) -> list[list]:
    """The maze map of a gymnasium-robotics maze env (``SystemExit`` for an env without one)."""
    import gymnasium as gym
    import gymnasium_robotics

    gym.register_envs(gymnasium_robotics)
    env = gym.make(env_id, **make_kwargs)
    maze = getattr(env.unwrapped, "maze", None)
    env.close()
    if maze is None:
        raise SystemExit(f"{env_id} has no maze map (env.unwrapped.maze); goal_distance.py tests maze envs.")
    return [list(row) for row in maze.maze_map]


def read_rows(path: str | Path) -> list[dict]:
    with Path(path).open() as file:
        return list(csv.DictReader(file))


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("agents", nargs="*", help="DHRL runs or agents, SAC + HER output folders")
    parser.add_argument("--start", type=int, nargs=2, metavar=("ROW", "COL"), help="the start cell")
    parser.add_argument("--episodes", type=int, default=10, help="test episodes per goal cell (DHRL: whole batches)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--band", type=int, default=3, help="width of the table's distance bands, in cells")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--from-csv", help="redraw the table and figure from this CSV, testing no agent")
    parser.add_argument("--out", required=True, help="the prefix of <out>.csv, <out>.md and <out>.png")
    args = parser.parse_args(argv)
    command = shlex.join(["python", "recipes/goal_distance.py", *(sys.argv[1:] if argv is None else argv)])
    if args.band < 1:
        parser.error("--band must be at least 1")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if args.from_csv:
        if args.agents:
            parser.error("--from-csv tests no agent: give either agents or --from-csv")
        rows = read_rows(args.from_csv)
        header = f"Redrawn from {args.from_csv} by `{command}`.\n\n"
        where = Path(args.from_csv).stem
    else:
        if not args.agents or args.start is None:
            parser.error("give the agents and --start ROW COL (or --from-csv)")
        if args.episodes < 1:
            parser.error("--episodes must be at least 1")
        device = torch.device(args.device)
        agents = [load_agent(path, device) for path in args.agents]  # every agent loaded before the first episode
        envs = {(a.env_id, repr(sorted(a.make_kwargs.items())), a.right_flipped_after) for a in agents}
        if len(envs) > 1:
            parser.error(
                "the agents are on different envs, maze maps or right_flipped_after (env id, make_kwargs, "
                f"right_flipped_after): {sorted(envs, key=repr)}"
            )
        env_id = agents[0].env_id
        distances = maze_distances(maze_map_of(env_id, agents[0].make_kwargs), tuple(args.start))
        goals = sorted((cell for cell in distances if distances[cell] > 0), key=lambda c: (distances[c], c))
        start_time = time.perf_counter()
        rows = []
        for path, agent in zip(args.agents, agents, strict=True):
            for goal in goals:
                successes, episodes = agent.successes(args.start, goal, args.episodes, args.seed)
                rows.append({
                    "agent": str(path),
                    "kind": agent.kind,
                    "start_row": args.start[0],
                    "start_col": args.start[1],
                    "goal_row": goal[0],
                    "goal_col": goal[1],
                    "distance": distances[goal],
                    "episodes": episodes,
                    "successes": successes,
                })
            mine = [r for r in rows if r["agent"] == str(path)]
            print(f"{path}: {sum(r['successes'] for r in mine)}/{sum(r['episodes'] for r in mine)} test episodes "
                  f"over {len(goals)} goal cells", flush=True)
        with out.with_suffix(".csv").open("w", newline="") as file:
            writer = csv.DictWriter(file, fieldnames=CSV_FIELDS)
            writer.writeheader()
            writer.writerows(rows)
        record = code_and_machine(device)
        righted = agents[0].right_flipped_after
        righted = "" if righted is None else f" (a flipped ant righted after {righted} steps upside down)"
        header = (
            f"`{command}`\n\n{env_id}{righted}, start cell ({args.start[0]}, {args.start[1]}), {len(goals)} goal cells, "
            f"{args.episodes} deterministic test episodes per goal cell and agent (seed {args.seed}); code "
            f"{record['code']['commit'][:7]}{' (modified)' if record['code']['modified'] else ''}, "
            f"{record['machine']['cpu']}, {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d}, "
            f"{round(time.perf_counter() - start_time)} s.\n\n"
        )
        where = env_id
    print_table(header + band_table(rows, args.band), out.with_suffix(".md"))
    where += f" from cell ({rows[0]['start_row']}, {rows[0]['start_col']})"
    plot_goal_distance(rows, out.with_suffix(".png"), f"{where}: success against the goal's distance")
    plot_cells(rows, out.parent / f"{out.name}_cells.png", f"{where}: success per goal cell")
    return rows


if __name__ == "__main__":
    main()
