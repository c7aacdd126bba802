"""Rank statistics of the diagnostics (torch only): Spearman's correlation with average ranks for ties."""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["spearman_correlation"]


def _average_ranks(x: Tensor) -> Tensor:
    """1-based ranks of ``x [n]``, ties sharing their average rank (``inf`` values tie as well)."""
    order = x.argsort()
    _, inverse, counts = torch.unique_consecutive(x[order], return_inverse=True, return_counts=True)
    ends = counts.cumsum(0).double()
    average = ends - (counts.double() - 1) / 2
    ranks = torch.empty(x.shape[0], dtype=torch.float64)
    ranks[order] = average[inverse]
    return ranks


def spearman_correlation(x: Tensor, y: Tensor) -> float:
    """Spearman's rank correlation of two ``[n]`` samples (average ranks for ties; pairs with a NaN dropped).

    ``inf`` values are ranked (as the largest); ``NaN`` when fewer than two pairs remain or a sample is
    constant.

    Examples:
        >>> import torch
        >>> x = torch.tensor([1.0, 2.0, 3.0, 4.0])
        >>> spearman_correlation(x, x ** 3), spearman_correlation(x, -x)
        (1.0, -1.0)
        >>> round(spearman_correlation(x, torch.tensor([1.0, 3.0, 2.0, float("inf")])), 3)
        0.8
    """
    x, y = x.flatten().double().cpu(), y.flatten().double().cpu()
    keep = ~(x.isnan() | y.isnan())
    x, y = x[keep], y[keep]
    if x.numel() < 2:
        return math.nan
    rx, ry = _average_ranks(x), _average_ranks(y)
    rx, ry = rx - rx.mean(), ry - ry.mean()
    norm = (rx.square().sum() * ry.square().sum()).sqrt()
    return (rx @ ry / norm).item() if norm > 0 else math.nan
