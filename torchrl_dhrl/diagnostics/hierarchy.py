"""Does the high level ask for the right subgoals, and does the low level deliver them?

Env-agnostic numbers from an evaluation rollout, logged as ``diag/...`` every epoch for every task (the
maze-only ones, against the true geometry, live in :mod:`~torchrl_dhrl.diagnostics.maze`). They
separate the two ways a hierarchical agent fails: a high level whose subgoals do not lead to the goal,
and a low level that does not reach the subgoals it is given.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey

__all__ = ["HIERARCHY_DIAG_KEYS", "LEARNED_DISTANCE_DIAG_KEYS", "hierarchy_diagnostics", "subgoal_segments"]

#: The keys :func:`hierarchy_diagnostics` returns (prefixed ``diag/`` by the recipe).
HIERARCHY_DIAG_KEYS = (
    "subgoal_goal_distance",
    "subgoal_offset",
    "subgoal_end_distance",
    "subgoal_reached",
    "segment_progress",
    "graph_steps",
)
#: The keys :func:`hierarchy_diagnostics` adds when given the learned distances.
LEARNED_DISTANCE_DIAG_KEYS = ("subgoal_learned_distance", "subgoal_graph_distance", "subgoals_far_from_graph")


def subgoal_segments(new_subgoal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """First and last step (flat row-major indices) of every subgoal segment of a ``[..., T]`` rollout.

    A segment starts at a step whose ``new_subgoal`` flag is set (and at every row's first step, where an
    episode starts) and ends at the step before the next start or at the row's last step. Both outputs
    have one entry per segment, in the same order.

    Examples:
        >>> import torch
        >>> flags = torch.tensor([[True, False, False, True, False], [False, True, True, False, False]])
        >>> subgoal_segments(flags)
        (tensor([0, 3, 5, 6, 7]), tensor([2, 4, 5, 6, 9]))
    """
    flags = new_subgoal.bool()
    if flags.ndim < 1 or flags.shape[-1] == 0:
        raise ValueError(
            f"`new_subgoal` must have a time dimension of size >= 1, got shape {tuple(flags.shape)}."
        )
    flags = flags.reshape(-1, flags.shape[-1]).clone()
    flags[:, 0] = True
    ends = torch.zeros_like(flags)
    ends[:, :-1] = flags[:, 1:]
    ends[:, -1] = True
    return flags.reshape(-1).nonzero().squeeze(-1), ends.reshape(-1).nonzero().squeeze(-1)


def _mean(x: torch.Tensor) -> float:
    return x.float().mean().item() if x.numel() else math.nan


@torch.no_grad()
def hierarchy_diagnostics(
    rollout: TensorDictBase,
    threshold: float,
    *,
    distance: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
    distance_from_graph: Callable[[torch.Tensor], torch.Tensor] | None = None,
    far_threshold: float | None = None,
    observation_key: NestedKey = "observation",
    achieved_goal_key: NestedKey = "achieved_goal",
    desired_goal_key: NestedKey = "desired_goal",
    subgoal_key: NestedKey = "subgoal",
    new_subgoal_key: NestedKey = "new_subgoal",
    waypoint_key: NestedKey = "waypoint",
) -> dict:
    """Per-segment statistics of a ``[..., T]`` rollout's subgoals (one segment per high-level decision).

    For each segment with subgoal ``s``, goal ``g``, achieved goal ``a0`` at its first step and ``a1``
    after its last step (``("next", achieved_goal_key)``), the means over all segments of:

    * ``subgoal_goal_distance``: ``||s - g||``, how far the requested subgoal is from the real goal;
    * ``subgoal_offset``: ``||s - a0||``, how far the high level asks the low level to go;
    * ``subgoal_end_distance``: ``||a1 - s||``, how far from the subgoal the segment ends;
    * ``subgoal_reached``: the fraction of segments with ``||a1 - s|| <= threshold``;
    * ``segment_progress``: ``||a0 - g|| - ||a1 - g||``, the goal distance gained per segment;

    and ``graph_steps``: the fraction of steps whose waypoint is not the subgoal itself (the low level
    follows the graph). ``NaN`` where a rollout has no segment (it always has one per row).

    Given the learned distances (env steps), also what the agent believes about its subgoals, to compare
    with the true offsets above (a learned distance far below ``subgoal_offset / speed`` is a critic that
    extrapolates optimistically to goals it never reached):

    * ``subgoal_learned_distance``: ``distance(state at the segment's start, s)``;
    * ``subgoal_graph_distance``: ``distance_from_graph(s)``, the nearest landmark's distance to ``s``
      (``NaN`` where there is no graph, i.e. where it is infinite);
    * ``subgoals_far_from_graph``: the fraction of subgoals with ``distance_from_graph(s) > far_threshold``:
      those the gradual penalty punishes (the recipe passes ``far_from_graph_factor x cutoff``).

    Args:
        rollout (TensorDictBase): the rollout, e.g. :attr:`EvaluationResult.rollout`.
        threshold (float): the "reached" radius (the recipe passes the sparse-reward threshold).

    Keyword Args:
        distance (callable, optional): ``distance(states, goals)``, e.g. ``GraphPlanner.distance``.
        distance_from_graph (callable, optional): ``distance_from_graph(goals)``, e.g.
            ``GraphPlanner.distance_from_graph``.
        far_threshold (float, optional): the gradual penalty's "far from the graph" distance (needs
            ``distance_from_graph``).
        observation_key, achieved_goal_key, desired_goal_key, subgoal_key, new_subgoal_key, waypoint_key
            (NestedKey): the rollout's entries. Default to the recipe's names.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> T = 4  # one row, two segments of two steps; the agent moves +1 in x per step
        >>> x = torch.arange(T + 1.0)
        >>> ag = torch.stack([x, torch.zeros(T + 1)], -1)
        >>> rollout = TensorDict(
        ...     achieved_goal=ag[:-1], desired_goal=torch.tensor([[4.0, 0.0]]).expand(T, 2),
        ...     subgoal=torch.tensor([[2.0, 0.0], [2.0, 0.0], [5.0, 0.0], [5.0, 0.0]]),
        ...     waypoint=torch.tensor([[1.0, 0.0], [2.0, 0.0], [5.0, 0.0], [5.0, 0.0]]),
        ...     new_subgoal=torch.tensor([[True], [False], [True], [False]]),
        ...     next=TensorDict(achieved_goal=ag[1:], batch_size=[T]), batch_size=[T])
        >>> d = hierarchy_diagnostics(rollout[None], threshold=0.5)
        >>> d["subgoal_goal_distance"], d["subgoal_offset"], d["subgoal_reached"], d["segment_progress"]
        (1.5, 2.5, 0.5, 2.0)
        >>> d["graph_steps"]  # the first step chases a waypoint short of its subgoal
        0.25
        >>> steps = lambda states, goals: (goals - states[..., :2]).norm(dim=-1) / 0.5  # 0.5 goal units per step
        >>> d = hierarchy_diagnostics(rollout.set("observation", ag[:-1])[None], 0.5, distance=steps,
        ...     distance_from_graph=lambda goals: (goals[..., 0] - 4.0).abs(), far_threshold=0.5)
        >>> d["subgoal_learned_distance"], d["subgoal_graph_distance"], d["subgoals_far_from_graph"]
        (5.0, 1.5, 1.0)
    """
    if rollout.ndim < 1:
        raise ValueError("`rollout` must have a time dimension (batch_size [..., T]).")
    for key in (achieved_goal_key, desired_goal_key, subgoal_key, new_subgoal_key, waypoint_key):
        if key not in rollout.keys(include_nested=True):
            raise KeyError(f"hierarchy_diagnostics: the rollout has no {key!r} entry.")
    if ("next", achieved_goal_key) not in rollout.keys(include_nested=True):
        raise KeyError(f"hierarchy_diagnostics: the rollout has no ('next', {achieved_goal_key!r}) entry.")
    flags = rollout[new_subgoal_key]
    flags = flags.reshape(*rollout.shape, -1).any(-1) if flags.ndim > rollout.ndim else flags
    starts, ends = subgoal_segments(flags)

    def flat(key):
        value = rollout[key]
        return value.reshape(-1, value.shape[-1]).float()

    subgoal, goal = flat(subgoal_key)[starts], flat(desired_goal_key)[starts]
    a0, a1 = flat(achieved_goal_key)[starts], flat(("next", achieved_goal_key))[ends]
    end_distance = (a1 - subgoal).norm(dim=-1)
    waypoint, step_subgoal = flat(waypoint_key), flat(subgoal_key)
    out = {
        "subgoal_goal_distance": _mean((subgoal - goal).norm(dim=-1)),
        "subgoal_offset": _mean((subgoal - a0).norm(dim=-1)),
        "subgoal_end_distance": _mean(end_distance),
        "subgoal_reached": _mean(end_distance <= threshold),
        "segment_progress": _mean((a0 - goal).norm(dim=-1) - (a1 - goal).norm(dim=-1)),
        "graph_steps": _mean((waypoint != step_subgoal).any(-1)),
    }
    if distance is not None:
        out["subgoal_learned_distance"] = _mean(distance(flat(observation_key)[starts], subgoal))
    if distance_from_graph is not None:
        from_graph = distance_from_graph(subgoal).float()
        finite = torch.isfinite(from_graph)
        out["subgoal_graph_distance"] = _mean(from_graph[finite]) if bool(finite.all()) else math.nan
        if far_threshold is not None:
            out["subgoals_far_from_graph"] = (
                _mean(from_graph > far_threshold) if bool(finite.all()) else math.nan
            )
    return out
