"""Chunked evaluation of a :class:`~torchrl_dhrl.planner.TemporalDistance` (private helpers)."""

from __future__ import annotations

import torch
from torch import Tensor

from .distances import TemporalDistance

#: Default number of (state, goal) pairs per call of the distance function.
DEFAULT_CHUNK_SIZE = 65536

#: Reduced-precision dtypes for graph building (``build_autocast_dtype``).
BUILD_AUTOCAST_DTYPES = (torch.bfloat16, torch.float16)


def check_build_autocast_dtype(dtype: torch.dtype | None) -> torch.dtype | None:
    if dtype is not None and dtype not in BUILD_AUTOCAST_DTYPES:
        raise ValueError(
            f"`build_autocast_dtype` must be None, torch.bfloat16 or torch.float16, got {dtype!r}."
        )
    return dtype


def check_supports_autocast(distance: TemporalDistance, dtype: torch.dtype | None) -> None:
    """Reduced-precision building needs a distance with ``with_autocast(dtype)`` (e.g. ``GoalDistance``)."""
    if dtype is not None and not callable(getattr(distance, "with_autocast", None)):
        raise TypeError(
            f"`build_autocast_dtype={dtype}` needs a distance with a `with_autocast(dtype)` method returning "
            f"its reduced-precision version (e.g. torchrl_dhrl.planner.GoalDistance); got "
            f"{type(distance).__name__}. Use build_autocast_dtype=None for other distances."
        )


def build_distance(distance: TemporalDistance, dtype: torch.dtype | None) -> TemporalDistance:
    """The distance used for graph building: ``distance.with_autocast(dtype)``, or ``distance`` itself."""
    if dtype is None:
        return distance
    check_supports_autocast(distance, dtype)
    return distance.with_autocast(dtype)


def check_chunk_size(chunk_size: int) -> int:
    if not isinstance(chunk_size, int) or isinstance(chunk_size, bool) or chunk_size < 1:
        raise ValueError(f"`chunk_size` must be a positive int, got {chunk_size!r}.")
    return chunk_size


def _call(distance: TemporalDistance, states: Tensor, goals: Tensor, shape: torch.Size) -> Tensor:
    out = distance(states, goals)
    if not isinstance(out, Tensor):
        raise TypeError(f"The distance function must return a Tensor, got {type(out).__name__}.")
    if out.shape != shape:
        raise ValueError(
            "The distance function must return one distance per (state, goal) pair, i.e. a tensor of "
            f"shape {tuple(shape)} for states {tuple(states.shape)} and goals {tuple(goals.shape)}; "
            f"got {tuple(out.shape)}. Contract: distance(states[..., obs_dim], goals[..., goal_dim]) "
            "-> Tensor[...], broadcasting over the leading dims (torchrl_dhrl.planner.TemporalDistance)."
        )
    if not out.is_floating_point():
        raise TypeError(f"The distance function must return a floating tensor, got {out.dtype}.")
    return out


@torch.no_grad()
def paired_distances(distance: TemporalDistance, states: Tensor, goals: Tensor, chunk_size: int) -> Tensor:
    """``out[p] = distance(states[p], goals[p])`` for ``P`` pairs, at most ``chunk_size`` pairs per call."""
    num = states.shape[0]
    if num <= chunk_size:
        return _call(distance, states, goals, states.shape[:1])
    outs = [
        _call(
            distance,
            states[i : i + chunk_size],
            goals[i : i + chunk_size],
            states[i : i + chunk_size].shape[:1],
        )
        for i in range(0, num, chunk_size)
    ]
    return torch.cat(outs)


@torch.no_grad()
def pairwise_distances(distance: TemporalDistance, states: Tensor, goals: Tensor, chunk_size: int) -> Tensor:
    """``out[i, j] = distance(states[i], goals[j])`` as an ``[M, N]`` matrix, built from broadcast calls.

    Rows are processed in blocks so that one call sees at most ``max(chunk_size, N)`` pairs.
    """
    num_states, num_goals = states.shape[0], goals.shape[0]
    if num_states == 0 or num_goals == 0:
        return torch.empty(num_states, num_goals, device=states.device, dtype=states.dtype)
    rows = max(1, chunk_size // num_goals)
    goals_b = goals.unsqueeze(0)
    outs = []
    for i in range(0, num_states, rows):
        block = states[i : i + rows].unsqueeze(1)
        outs.append(_call(distance, block, goals_b, torch.Size((block.shape[0], num_goals))))
    return outs[0] if len(outs) == 1 else torch.cat(outs)
