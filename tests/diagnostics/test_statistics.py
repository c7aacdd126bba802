"""Spearman's rank correlation against scipy, with ties, ``inf`` and ``nan``."""

import math

import pytest
import torch
from scipy.stats import spearmanr

from torchrl_dhrl.diagnostics import spearman_correlation


def test_spearman_matches_scipy_with_ties_and_inf():
    generator = torch.Generator().manual_seed(0)
    x = torch.randint(0, 6, (200,), generator=generator).float()
    y = x + torch.randint(0, 4, (200,), generator=generator).float()
    y[::17] = math.inf
    assert spearman_correlation(x, y) == pytest.approx(spearmanr(x.numpy(), y.numpy()).statistic, abs=1e-10)
    x[3] = math.nan
    keep = ~x.isnan()
    assert spearman_correlation(x, y) == pytest.approx(spearmanr(x[keep], y[keep]).statistic, abs=1e-10)
    assert math.isnan(spearman_correlation(torch.ones(5), torch.arange(5.0)))
    assert math.isnan(spearman_correlation(torch.ones(1), torch.ones(1)))
