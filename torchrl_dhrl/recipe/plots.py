"""Pictures of a training run: the graph with a test episode, and the success curve."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure  # no pyplot: no global figure registry, no backend chosen at import
from tensordict import TensorDictBase

from torchrl_dhrl.envs import plot_env
from torchrl_dhrl.envs.geometry import MazeGeometry
from torchrl_dhrl.planner import GraphPlanner

__all__ = [
    "SUCCESS_CURVE_SERIES",
    "draw_paper_reference",
    "graph_path_to_goal",
    "plot_distance_scatter",
    "plot_episode",
    "plot_success_curve",
    "success_curve_series",
]


def graph_path_to_goal(planner: GraphPlanner, state: torch.Tensor, goal: torch.Tensor) -> np.ndarray:
    """The planner's route ``[K, goal_dim]`` from ``state`` (``[obs_dim]``) to ``goal``: landmarks, then goal."""
    if not planner.has_graph:
        return goal.reshape(1, -1).cpu().numpy()
    plan = planner.plan(state.reshape(1, -1), goal.reshape(1, -1).to(state))
    length = int(plan.length[0])
    landmarks = planner.landmark_goals[plan.path[0, :length]].to(goal)
    return torch.cat([landmarks, goal.reshape(1, -1)]).cpu().numpy()


def plot_episode(
    env_name: str,
    planner: GraphPlanner,
    rollout: TensorDictBase,
    path: str | Path,
    *,
    title: str | None = None,
    maze: MazeGeometry | None = None,
) -> Path:
    """Saves a top view with the graph (landmarks, edges), the route the graph plans from the start
    to the test goal and the executed trajectory of the first episode of ``rollout`` (``[B, T]``), over ``maze``
    where the env has no scene of its own (:func:`~torchrl_dhrl.envs.plot_env`)."""
    episode = rollout[0]
    start, goal = episode[0]["observation"], episode[0]["desired_goal"]
    trajectory = torch.cat([episode[0]["achieved_goal"].reshape(1, -1), episode["next", "achieved_goal"]])
    route = np.concatenate(
        [episode[0]["achieved_goal"].reshape(1, -1).cpu().numpy(), graph_path_to_goal(planner, start, goal)]
    )
    has_graph = planner.has_graph
    fig = Figure(figsize=(5, 5))
    ax = fig.subplots()
    plot_env(
        env_name,
        trajectory=trajectory.cpu().numpy(),
        landmarks=planner.landmark_goals.cpu().numpy() if has_graph else None,
        edges=planner.edges.cpu().numpy() if has_graph else None,
        path=route,
        goal=goal.cpu().numpy(),
        ax=ax,
        title=title,
        maze=maze,
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    return path


#: The curves of :func:`plot_success_curve`: ``(metrics key, label, line style)``; the last three only where
#: logged.
SUCCESS_CURVE_SERIES = (
    ("eval/success", "final-state success", "-"),
    ("eval/any_success", "any-time success", "--"),
    ("train/success", "training episodes' success", "-."),
    ("diag/landmark_coverage", "landmark coverage of the free space", ":"),
    ("train/upside_down", "training steps upside down (ant)", (0, (1, 3))),
)


def success_curve_series(history: Sequence[Mapping[str, float]]) -> dict[str, tuple[list, list]]:
    """The curves :func:`plot_success_curve` draws: ``{label: (env steps, values)}``.

    Evaluation success (final state and any time) always; the training episodes' success, the landmark
    coverage of a maze's free space and the fraction of training steps an ant spent upside down (all
    fractions too) where the history has finite values of them (a run before the graph, an arm env or an
    older ``metrics.csv`` has none). Non-finite points are left out of their curve.

    Examples:
        >>> history = [{"env_steps": 9000, "eval/success": 0.0, "eval/any_success": 0.1, "diag/landmark_coverage": float("nan")},
        ...            {"env_steps": 18000, "eval/success": 0.5, "eval/any_success": 0.6, "diag/landmark_coverage": 0.4}]
        >>> series = success_curve_series(history)
        >>> list(series)
        ['final-state success', 'any-time success', 'landmark coverage of the free space']
        >>> series["landmark coverage of the free space"]
        ([18000], [0.4])
    """
    out: dict[str, tuple[list, list]] = {}
    for key, label, _ in SUCCESS_CURVE_SERIES:
        points = [(h["env_steps"], float(h[key])) for h in history if key in h and _finite(h[key])]
        if points or key in ("eval/success", "eval/any_success"):
            out[label] = ([p[0] for p in points], [p[1] for p in points])
    return out


def _finite(value) -> bool:
    try:
        return math.isfinite(float(value))
    except (TypeError, ValueError):
        return False


def plot_success_curve(
    history: Sequence[Mapping[str, float]],
    path: str | Path,
    *,
    title: str | None = None,
    reference: Mapping[float, float] | None = None,
    forks: Sequence[float] = (),
) -> Path:
    """Saves success rate (final state and any time) against env steps, with the training episodes' success and
    the landmark coverage where logged (:func:`success_curve_series`); ``reference`` maps steps to the paper's
    success rates (:func:`draw_paper_reference`: crosses within the run's steps, a labelled horizontal line for
    a budget beyond them, so the x-axis spans the run's own steps); ``forks``, the env steps where the run was
    forked from another's checkpoint (``fork=``), as dotted vertical lines. The legend sits below the axes."""
    fig = Figure(figsize=(6, 5), layout="constrained")
    ax = fig.subplots()
    styles = {label: style for _, label, style in SUCCESS_CURVE_SERIES}
    for label, (steps, values) in success_curve_series(history).items():
        evaluation = label == "final-state success"
        ax.plot(
            steps,
            values,
            ls=styles[label],
            marker="o" if evaluation else None,
            ms=4,
            alpha=1.0 if evaluation else 0.7,
            label=label,
            zorder=3 if evaluation else 2,
        )
    run_steps = [h["env_steps"] for h in history if "env_steps" in h and _finite(h["env_steps"])]
    draw_paper_reference(ax, reference, run_steps)
    for i, step in enumerate(forks):
        ax.axvline(step, color="0.4", ls=":", lw=1.2, label="forked" if i == 0 else None)
    ax.set_xlabel("env steps (warm-up included)")
    ax.set_ylabel("success rate / fraction")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    fig.legend(loc="outside lower center", ncol=2, fontsize="small", frameon=False)
    return _save(fig, ax, path, title)


def _steps_text(step: float, millions: bool = True) -> str:
    """``250000`` -> ``"0.25M"`` (the paper's budgets), or ``"250k"`` with ``millions=False``."""
    if not step:
        return "0"
    return f"{step / 1e6:g}M" if millions else f"{step / 1e3:g}k"


def draw_paper_reference(
    ax,
    reference: Mapping[float, float] | None,
    steps: Sequence[float],
    *,
    margin: float = 0.03,
    label: str = "paper",
) -> tuple[float, float] | None:
    """Draws the paper's success rates (``reference``: env steps -> success) on ``ax`` without stretching its
    x-axis beyond the run's own ``steps``, and sets the x-axis to those steps; returns its limits.

    The x-axis runs from 0 (or the run's first step, where that is past a fifth of its last) to the run's last
    step, with ``margin`` (a fraction of the range) either side. A paper point within the run's steps (or
    up to 5% of the range past the last, the axis then stretched to it) is a black cross at its step; one
    beyond them is a dashed horizontal line at its success rate, marked by a triangle at the right edge,
    with its figure in the legend (``"paper: 96.9% at 0.25M, beyond this run"``). The x ticks read
    ``0.25M``/``90k``. Without ``steps`` the paper's points are crosses and the axis is left alone.

    Examples:
        >>> from matplotlib.figure import Figure
        >>> ax = Figure().subplots()
        >>> _ = ax.plot([9000, 84000], [0.0, 1.0])
        >>> low, high = draw_paper_reference(ax, {250_000: 0.969, 500_000: 0.998}, [9000, 84000])
        >>> high < 90_000
        True
        >>> [line.get_label() for line in ax.get_lines() if line.get_label().startswith("paper")]
        ['paper: 96.9% at 0.25M, beyond this run', 'paper: 99.8% at 0.5M, beyond this run']
    """
    import matplotlib.ticker as mticker  # here: the package's import does not pull matplotlib in

    reference = dict(reference or {})
    steps = [float(s) for s in steps if _finite(s)]
    if not steps:
        if reference:
            texts = ", ".join(f"{100 * v:.1f}% at {_steps_text(s)}" for s, v in sorted(reference.items()))
            ax.scatter(
                list(reference),
                list(reference.values()),
                marker="x",
                color="k",
                zorder=4,
                label=f"{label}: {texts}",
            )
        return None
    first, last = min(steps), max(steps)
    low = 0.0 if first >= 0 and first <= 0.2 * last else first
    span = (last - low) or max(abs(last), 1.0)
    reach = last + 0.05 * span
    near = {s: v for s, v in sorted(reference.items()) if low <= s <= reach}
    far = {s: v for s, v in sorted(reference.items()) if s not in near}
    if near:
        texts = ", ".join(f"{100 * v:.1f}% at {_steps_text(s)}" for s, v in near.items())
        ax.scatter(
            list(near), list(near.values()), marker="x", s=50, color="k", zorder=4, label=f"{label}: {texts}"
        )
    edge = ax.get_yaxis_transform()  # x in axes fraction, y in data
    for i, (step, value) in enumerate(far.items()):
        where = "beyond" if step > last else "before"
        ax.axhline(
            value,
            color="k",
            lw=1.0,
            alpha=0.55,
            ls=("--", ":", "-.")[i % 3],
            zorder=1.5,
            label=f"{label}: {100 * value:.1f}% at {_steps_text(step)}, {where} this run",
        )
        ax.plot(
            [1.0 if step > last else 0.0],
            [value],
            marker=">" if step > last else "<",
            color="k",
            ms=6,
            transform=edge,
            clip_on=False,
            zorder=4,
        )
    limits = (low - margin * span, max([last, *near]) + margin * span)
    ax.set_xlim(*limits)
    millions = limits[1] >= 2e5  # one unit on the whole axis
    ax.xaxis.set_major_formatter(mticker.FuncFormatter(lambda x, _: _steps_text(x, millions)))
    return limits


def plot_distance_scatter(
    true: torch.Tensor,
    learned: torch.Tensor,
    path: str | Path,
    *,
    graph: torch.Tensor | None = None,
    speed: float | None = None,
    title: str | None = None,
) -> Path:
    """Saves the learned landmark-to-landmark distances (steps) against the true obstacle-free path
    lengths (goal units) of the same pairs (see :func:`~torchrl_dhrl.diagnostics.graph_quality`).

    ``learned`` is the graph's direct distance matrix entry, ``graph`` (optional) the all-pairs shortest
    distance through the graph; ``speed`` (goal units per step, e.g. ``planner.oracle_speed``) draws the
    line ``steps = length / speed`` a distance would follow at that nominal speed. Pairs the graph does
    not connect (``inf``) are left out of the ``graph`` series.
    """
    true = torch.as_tensor(true).double().cpu()
    fig = Figure(figsize=(5.5, 4.5))
    ax = fig.subplots()
    learned = torch.as_tensor(learned).double().cpu()
    ax.scatter(true.numpy(), learned.numpy(), s=6, alpha=0.4, label="learned d(i, j)")
    if graph is not None:
        graph = torch.as_tensor(graph).double().cpu()
        finite = torch.isfinite(graph)
        ax.scatter(
            true[finite].numpy(),
            graph[finite].numpy(),
            s=6,
            alpha=0.4,
            marker="x",
            label="shortest path in the graph",
        )
    if speed and true.numel() and torch.isfinite(true).any():
        top = true[torch.isfinite(true)].max().item()
        label = f"length / {speed:g} (nominal speed)"
        ax.plot([0.0, top], [0.0, top / speed], color="k", lw=1, ls="--", label=label)
    ax.set_xlabel("true obstacle-free path length (goal units)")
    ax.set_ylabel("distance (steps)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    return _save(fig, ax, path, title)


def _save(fig, ax, path: str | Path, title: str | None) -> Path:
    """Titles the axes (if ``title``) and writes the figure to ``path`` (parents created)."""
    if title:
        ax.set_title(title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    return path
