"""Goal distributions: vectorised rejection samplers and fixed test goals, in any goal dimension.

Every sampler draws ``n`` goals at once from a :class:`numpy.random.Generator` (``sample(rng, n)``, a float64
``[n, goal_dim]`` array) and can say whether a point lies in its support (``contains(points)``). Rejection
samplers draw candidates in numpy batches sized from their acceptance rate, so one call costs a handful of
vectorised draws, not one Python iteration per goal.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .layouts import MazeLayout

__all__ = ["GoalSampler", "BoxGoalSampler", "FreeCellGoalSampler", "FixedGoalSampler", "GaussianGoalSampler"]

# Safety factor on the number of candidates drawn per rejection round (given the acceptance rate).
_OVERSAMPLING = 1.25
# A rejection sampler gives up after this many rounds (only reachable with a near-empty support).
_MAX_ROUNDS = 1000


def _rejection_sample(
    rng: np.random.Generator,
    n: int,
    draw: Callable[[np.random.Generator, int], np.ndarray],
    accept: Callable[[np.ndarray], np.ndarray],
    acceptance: float,
) -> np.ndarray:
    """Draws ``n`` points from ``draw(rng, m) -> [m, D]`` kept by ``accept`` (vectorised rounds)."""
    out = None
    filled = 0
    for _ in range(_MAX_ROUNDS):
        if out is not None and filled == n:
            return out
        remaining = n - filled
        candidates = draw(rng, int(np.ceil(remaining / acceptance * _OVERSAMPLING)) + 4)
        if out is None:
            out = np.empty((n, candidates.shape[-1]), dtype=np.float64)
        kept = candidates[accept(candidates)][:remaining]
        out[filled : filled + len(kept)] = kept
        filled += len(kept)
    if filled < n:
        raise RuntimeError("Rejection sampling failed: the goal region is (nearly) empty.")
    return out


def _in_box(points: np.ndarray, low, high) -> np.ndarray:
    """Whether each point of ``points [..., D]`` lies in the closed box ``[low, high]``."""
    return ((points >= np.asarray(low)) & (points <= np.asarray(high))).all(axis=-1)


def _uniform(low, high) -> Callable[[np.random.Generator, int], np.ndarray]:
    low, high = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
    return lambda rng, m: rng.uniform(low, high, size=(m, low.shape[0]))


class GoalSampler:
    """Base class of goal samplers: ``sample(rng, n) -> [n, D]`` and ``contains(points) -> bool [...]``."""

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        raise NotImplementedError

    def contains(self, points) -> np.ndarray:
        raise NotImplementedError


@dataclass(frozen=True)
class BoxGoalSampler(GoalSampler):
    """Uniform goals in a box, minus open boxes.

    Args:
        low (tuple of float): lower corner of the box, ``(x_min, y_min[, z_min])`` (any dimension).
        high (tuple of float): upper corner of the box.
        excluded (tuple of tuples): open boxes to reject, ``(x_min, x_max, y_min, y_max[, z_min, z_max])``
            (bounds interleaved per axis; a box with fewer axes than the goal space leaves the remaining
            axes unbounded); use ``-inf`` / ``inf`` for unbounded sides. All have the same number of axes.
            Defaults to none.

    Examples:
        >>> import numpy as np
        >>> from torchrl_dhrl.envs import BoxGoalSampler
        >>> sampler = BoxGoalSampler((-2.0, -2.0), (10.0, 10.0), excluded=((-np.inf, 6.0, 2.0, 6.0),))
        >>> goals = sampler.sample(np.random.default_rng(0), 1000)
        >>> goals.shape, bool(sampler.contains(goals).all())
        ((1000, 2), True)
        >>> bool(((goals[:, 0] < 6) & (goals[:, 1] > 2) & (goals[:, 1] < 6)).any())
        False
        >>> BoxGoalSampler((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)).sample(np.random.default_rng(0), 4).shape
        (4, 3)
    """

    low: tuple[float, ...]
    high: tuple[float, ...]
    excluded: tuple[tuple[float, ...], ...] = ()

    def _in_excluded(self, points: np.ndarray) -> np.ndarray:
        if not self.excluded:
            return np.zeros(points.shape[:-1], dtype=bool)
        boxes = np.asarray(self.excluded, dtype=np.float64)  # [R, 2 * k]
        k = boxes.shape[1] // 2
        p = points[..., None, :k]
        inside = (p > boxes[:, 0::2]) & (p < boxes[:, 1::2])
        return inside.all(axis=-1).any(axis=-1)

    @cached_property
    def acceptance(self) -> float:
        """Fraction of the box kept (excluded boxes assumed disjoint)."""
        low, high = np.asarray(self.low), np.asarray(self.high)
        removed = 0.0
        for box in self.excluded:
            k = len(box) // 2
            overlap = np.minimum(box[1::2], high[:k]) - np.maximum(box[0::2], low[:k])
            removed += float(np.prod(np.maximum(overlap, 0.0)) / np.prod(high[:k] - low[:k]))
        return float(max(1.0 - removed, 1e-3))

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        return _rejection_sample(
            rng, n, _uniform(self.low, self.high), lambda p: ~self._in_excluded(p), self.acceptance
        )

    def contains(self, points) -> np.ndarray:
        points = np.asarray(points, dtype=np.float64)
        return _in_box(points, self.low, self.high) & ~self._in_excluded(points)


@dataclass(frozen=True)
class FreeCellGoalSampler(GoalSampler):
    """Uniform goals in a box, rejected until they fall in a free cell of a maze grid.

    Args:
        layout (MazeLayout): the maze whose free cells are the support.
        low (tuple of float): ``(x_min, y_min)`` of the sampling box.
        high (tuple of float): ``(x_max, y_max)`` of the sampling box.

    Examples:
        >>> import numpy as np
        >>> from torchrl_dhrl.envs import COMPLEX_MAZE, FreeCellGoalSampler, MazeLayout
        >>> layout = MazeLayout(COMPLEX_MAZE, scale=8.0)
        >>> sampler = FreeCellGoalSampler(layout, (-4.0, -4.0), (52.0, 52.0))
        >>> goals = sampler.sample(np.random.default_rng(0), 500)
        >>> bool(layout.in_free_cell(goals).all())
        True
    """

    layout: MazeLayout
    low: tuple[float, float]
    high: tuple[float, float]

    @cached_property
    def acceptance(self) -> float:
        """Fraction of free cells among the cells of the sampling box (estimated on a fine lattice)."""
        axes = [np.linspace(lo, hi, 101) for lo, hi in zip(self.low, self.high, strict=True)]
        lattice = np.stack(np.meshgrid(*axes), axis=-1).reshape(-1, 2)
        return float(max(self.layout.in_free_cell(lattice).mean(), 1e-3))

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        return _rejection_sample(
            rng, n, _uniform(self.low, self.high), self.layout.in_free_cell, self.acceptance
        )

    def contains(self, xy) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64)
        return _in_box(xy, self.low, self.high) & self.layout.in_free_cell(xy)


@dataclass(frozen=True)
class FixedGoalSampler(GoalSampler):
    """One of a fixed set of goals per draw, uniformly (a single goal is always returned as is).

    Args:
        goals (tuple of tuples): the goals, ``(x, y)`` or ``(x, y, z)`` each.

    Examples:
        >>> import numpy as np
        >>> from torchrl_dhrl.envs import FixedGoalSampler
        >>> FixedGoalSampler(((0.0, 8.0),)).sample(np.random.default_rng(0), 2).tolist()
        [[0.0, 8.0], [0.0, 8.0]]
    """

    goals: tuple[tuple[float, float], ...]

    def __post_init__(self) -> None:
        if len(self.goals) == 0:
            raise ValueError("FixedGoalSampler needs at least one goal.")

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        goals = np.asarray(self.goals, dtype=np.float64)
        if len(goals) == 1:
            return np.repeat(goals, n, axis=0)
        return goals[rng.integers(len(goals), size=n)]

    def contains(self, xy) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64)
        goals = np.asarray(self.goals, dtype=np.float64)
        return (np.abs(xy[..., None, :] - goals).max(axis=-1) < 1e-9).any(axis=-1)


@dataclass(frozen=True)
class GaussianGoalSampler(GoalSampler):
    """Independent Gaussian goals per axis, ``mean + N(0, std)``, truncated to a box by rejection.

    The box keeps every goal inside the goal space (explicit goals are checked against the same bounds);
    with the box several standard deviations wide the truncation is immaterial.

    Args:
        mean (tuple of float): per-axis mean.
        std (tuple of float): per-axis standard deviation (positive).
        low (tuple of float): lower corner of the truncation box.
        high (tuple of float): upper corner of the truncation box.

    Examples:
        >>> import numpy as np
        >>> from torchrl_dhrl.envs import GaussianGoalSampler
        >>> sampler = GaussianGoalSampler((0.0, 0.25, 0.0), (0.1, 0.1, 0.1), (-1.0,) * 3, (1.0,) * 3)
        >>> goals = sampler.sample(np.random.default_rng(0), 20000)
        >>> np.abs(goals.mean(0) - (0.0, 0.25, 0.0)).max() < 0.005, goals.std(0).round(2).tolist()
        (np.True_, [0.1, 0.1, 0.1])
    """

    mean: tuple[float, ...]
    std: tuple[float, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]

    def __post_init__(self) -> None:
        if not (len(self.mean) == len(self.std) == len(self.low) == len(self.high)):
            raise ValueError("mean, std, low and high must have the same length.")
        if min(self.std) <= 0:
            raise ValueError(f"std must be positive, got {self.std}.")

    @cached_property
    def acceptance(self) -> float:
        """Probability mass of the truncation box."""
        mass = 1.0
        for mu, sigma, lo, hi in zip(self.mean, self.std, self.low, self.high, strict=True):
            cdf = [0.5 * (1.0 + math.erf((bound - mu) / (sigma * math.sqrt(2.0)))) for bound in (lo, hi)]
            mass *= cdf[1] - cdf[0]
        return float(max(mass, 1e-3))

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        mean, std = np.asarray(self.mean, dtype=np.float64), np.asarray(self.std, dtype=np.float64)
        return _rejection_sample(
            rng,
            n,
            lambda r, m: mean + std * r.standard_normal((m, mean.shape[0])),
            self.contains,
            self.acceptance,
        )

    def contains(self, points) -> np.ndarray:
        return _in_box(np.asarray(points, dtype=np.float64), self.low, self.high)
