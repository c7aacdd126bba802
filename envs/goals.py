"""Goal distributions of the mazes: vectorised rejection samplers and fixed test goals.

Every sampler draws ``n`` goals at once from a :class:`numpy.random.Generator` (``sample(rng, n)``, a float64
``[n, 2]`` array) and can say whether a point lies in its support (``contains(xy)``). Rejection samplers draw
candidates in numpy batches sized from their acceptance rate, so one call costs a handful of vectorised
draws, not one Python iteration per goal.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .layouts import MazeLayout

__all__ = ["GoalSampler", "BoxGoalSampler", "FreeCellGoalSampler", "FixedGoalSampler"]

# Safety factor on the number of candidates drawn per rejection round (given the acceptance rate).
_OVERSAMPLING = 1.25
# A rejection sampler gives up after this many rounds (only reachable with a near-empty support).
_MAX_ROUNDS = 1000


def _rejection_sample(rng: np.random.Generator, n: int, low, high, accept, acceptance: float) -> np.ndarray:
    """Draws ``n`` points uniformly in the box ``[low, high]`` kept by ``accept`` (vectorised rounds)."""
    low, high = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
    out = np.empty((n, low.shape[0]), dtype=np.float64)
    filled = 0
    for _ in range(_MAX_ROUNDS):
        if filled == n:
            return out
        remaining = n - filled
        candidates = rng.uniform(
            low, high, size=(int(np.ceil(remaining / acceptance * _OVERSAMPLING)) + 4, 2)
        )
        kept = candidates[accept(candidates)][:remaining]
        out[filled : filled + len(kept)] = kept
        filled += len(kept)
    if filled < n:
        raise RuntimeError("Rejection sampling failed: the goal region is (nearly) empty.")
    return out


class GoalSampler:
    """Base class of goal samplers: ``sample(rng, n) -> [n, 2]`` and ``contains(xy) -> bool [...]``."""

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        raise NotImplementedError

    def contains(self, xy) -> np.ndarray:
        raise NotImplementedError


@dataclass(frozen=True)
class BoxGoalSampler(GoalSampler):
    """Uniform goals in a box, minus open rectangles.

    Args:
        low (tuple of float): ``(x_min, y_min)`` of the box.
        high (tuple of float): ``(x_max, y_max)`` of the box.
        excluded (tuple of tuples): open rectangles ``(x_min, x_max, y_min, y_max)`` to reject; use
            ``-inf`` / ``inf`` for unbounded sides. Defaults to none.

    Examples:
        >>> import numpy as np
        >>> from torchrl_dhrl.envs import BoxGoalSampler
        >>> sampler = BoxGoalSampler((-2.0, -2.0), (10.0, 10.0), excluded=((-np.inf, 6.0, 2.0, 6.0),))
        >>> goals = sampler.sample(np.random.default_rng(0), 1000)
        >>> goals.shape, bool(sampler.contains(goals).all())
        ((1000, 2), True)
        >>> bool(((goals[:, 0] < 6) & (goals[:, 1] > 2) & (goals[:, 1] < 6)).any())
        False
    """

    low: tuple[float, float]
    high: tuple[float, float]
    excluded: tuple[tuple[float, float, float, float], ...] = ()

    def _in_excluded(self, xy: np.ndarray) -> np.ndarray:
        if not self.excluded:
            return np.zeros(xy.shape[:-1], dtype=bool)
        rect = np.asarray(self.excluded, dtype=np.float64)  # [R, 4]
        x, y = xy[..., 0, None], xy[..., 1, None]
        inside = (x > rect[:, 0]) & (x < rect[:, 1]) & (y > rect[:, 2]) & (y < rect[:, 3])
        return inside.any(axis=-1)

    @cached_property
    def acceptance(self) -> float:
        """Fraction of the box kept (rectangles assumed disjoint)."""
        low, high = np.asarray(self.low), np.asarray(self.high)
        area = np.prod(high - low)
        removed = 0.0
        for x0, x1, y0, y1 in self.excluded:
            w = max(0.0, min(x1, high[0]) - max(x0, low[0]))
            h = max(0.0, min(y1, high[1]) - max(y0, low[1]))
            removed += w * h
        return float(max(1.0 - removed / area, 1e-3))

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        return _rejection_sample(
            rng, n, self.low, self.high, lambda xy: ~self._in_excluded(xy), self.acceptance
        )

    def contains(self, xy) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64)
        low, high = np.asarray(self.low), np.asarray(self.high)
        in_box = ((xy >= low) & (xy <= high)).all(axis=-1)
        return in_box & ~self._in_excluded(xy)


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
        return _rejection_sample(rng, n, self.low, self.high, self.layout.in_free_cell, self.acceptance)

    def contains(self, xy) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64)
        in_box = ((xy >= np.asarray(self.low)) & (xy <= np.asarray(self.high))).all(axis=-1)
        return in_box & self.layout.in_free_cell(xy)


@dataclass(frozen=True)
class FixedGoalSampler(GoalSampler):
    """One of a fixed set of goals per draw, uniformly (a single goal is always returned as is).

    Args:
        goals (tuple of (x, y)): the goals.

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
