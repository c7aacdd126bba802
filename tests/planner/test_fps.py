"""Farthest point sampling against a naive numpy implementation of Algorithm 2."""

import math

import numpy as np
import pytest
import torch

from torchrl_dhrl.planner import farthest_point_sampling


def asymmetric_distance(states, goals):
    """A directed, broadcasting distance: going right (+x) costs 30% more than going left."""
    delta = goals - states[..., :2]
    return delta.norm(dim=-1) + 0.3 * delta[..., 0].clamp_min(0)


def naive_fps(states, goals, distance, max_count, early_stop=0.0, min_count=None, start=0):
    """Reference FPS in numpy, one full distance row per landmark, float64 bookkeeping."""
    n = len(states)
    min_count = max_count // 10 if min_count is None else min_count
    dist_list = np.full(n, np.inf)
    selected = np.zeros(n, dtype=bool)
    chosen, current = [start], start
    while True:
        selected[current] = True
        row = (
            distance(torch.as_tensor(states[current]).expand(n, -1), torch.as_tensor(goals)).double().numpy()
        )
        dist_list = np.minimum(dist_list, row)
        if len(chosen) == n:
            return chosen, 0.0
        masked = np.where(selected, -np.inf, dist_list)
        current = int(np.argmax(masked))
        if len(chosen) >= max_count or (len(chosen) >= min_count and masked[current] < early_stop):
            return chosen, float(masked[current])
        chosen.append(current)


def make_candidates(n, seed, obs_dim=5):
    gen = torch.Generator().manual_seed(seed)
    states = torch.rand(n, obs_dim, generator=gen) * 20
    goals = states[:, :2] + 0.3 * torch.randn(n, 2, generator=gen)
    return states, goals


@pytest.mark.parametrize("strategy", ["dense", "lazy"])
@pytest.mark.parametrize("max_count,early_stop", [(60, 0.0), (400, 2.0), (400, 6.0)])
def test_matches_naive_greedy(strategy, max_count, early_stop):
    states, goals = make_candidates(1500, seed=0)
    expected, radius = naive_fps(states.numpy(), goals.numpy(), asymmetric_distance, max_count, early_stop)
    res = farthest_point_sampling(
        states, goals, asymmetric_distance, max_count, early_stop=early_stop, strategy=strategy, lazy_batch=64
    )
    assert res.indices.tolist() == expected
    assert res.radius.item() == pytest.approx(radius, rel=1e-5)
    # selection distances are non-increasing after the first (greedy property)
    sel = res.selection_distances
    assert math.isinf(sel[0]) and (sel[2:] <= sel[1:-1] + 1e-6).all()
    if early_stop > 0:  # stopped early: the remaining coverage radius is below the threshold
        assert len(expected) < max_count and res.radius.item() < early_stop


@pytest.mark.parametrize("strategy", ["dense", "lazy"])
def test_landmark_distances_are_the_evaluated_pairs(strategy):
    states, goals = make_candidates(400, seed=1)
    res = farthest_point_sampling(states, goals, asymmetric_distance, 40, strategy=strategy)
    idx = res.indices
    expected = asymmetric_distance(states[idx].unsqueeze(1), goals[idx].unsqueeze(0))
    known = ~torch.isnan(res.landmark_distances)
    torch.testing.assert_close(res.landmark_distances[known], expected[known])
    if strategy == "dense":
        assert known.all()
    else:  # the lazy strategy skips evaluations (that is its point); the graph fills the gaps
        assert 0 < known.float().mean() < 1


def test_lazy_evaluates_fewer_pairs_than_dense():
    states, goals = make_candidates(2000, seed=2)
    calls = {"dense": 0, "lazy": 0, "no_proxy": 0}

    def counting(mode):
        def dist(s, g):
            calls[mode] += s.shape[0]
            return asymmetric_distance(s, g)

        return dist

    dense = farthest_point_sampling(states, goals, counting("dense"), 200, strategy="dense")
    lazy = farthest_point_sampling(states, goals, counting("lazy"), 200, strategy="lazy")
    no_proxy = farthest_point_sampling(states, goals, counting("no_proxy"), 200, proxy=None)
    assert torch.equal(dense.indices, lazy.indices) and torch.equal(dense.indices, no_proxy.indices)
    assert calls["no_proxy"] < 0.8 * calls["dense"]
    # the goal proxy (measured: 10% of dense, 21% of no proxy)
    assert calls["lazy"] < 0.2 * calls["dense"] and calls["lazy"] < 0.4 * calls["no_proxy"]


def _random_proxy(landmark_goal, goals):
    gen = torch.Generator().manual_seed(int(landmark_goal.sum() * 1000) % 1000)
    return torch.rand(goals.shape[0], generator=gen)


PROXIES = {
    "goal": "goal",
    "none": None,
    "random": _random_proxy,
    "farthest_first": lambda landmark_goal, goals: -(goals - landmark_goal).norm(dim=-1),
    "nan_and_inf": lambda landmark_goal, goals: torch.where(
        goals[:, 0] > 10, torch.full_like(goals[:, 0], math.nan), torch.full_like(goals[:, 0], math.inf)
    ),
}


@pytest.mark.parametrize("proxy", list(PROXIES))
@pytest.mark.parametrize("lazy_batch", [1, 16, 10_000])
def test_lazy_selection_does_not_depend_on_the_proxy(proxy, lazy_batch):
    states, goals = make_candidates(500, seed=5)
    expected, radius = naive_fps(states.numpy(), goals.numpy(), asymmetric_distance, 60)
    res = farthest_point_sampling(
        states, goals, asymmetric_distance, 60, proxy=PROXIES[proxy], lazy_batch=lazy_batch
    )
    assert res.indices.tolist() == expected
    assert res.radius.item() == pytest.approx(radius, rel=1e-5)


@pytest.mark.parametrize("proxy", ["goal", None])
def test_lazy_knows_every_distance_to_earlier_landmarks(proxy):
    # A landmark is exact when selected: its distances from all earlier landmarks are known (the
    # graph reuses them), the ones from later landmarks are not (it is no longer a candidate).
    states, goals = make_candidates(600, seed=6)
    res = farthest_point_sampling(states, goals, asymmetric_distance, 50, proxy=proxy)
    known = ~torch.isnan(res.landmark_distances)
    earlier = torch.ones(50, 50, dtype=torch.bool).tril(-1).T  # [m, j] with m < j
    assert torch.equal(known & ~torch.eye(50, dtype=torch.bool), earlier)
    idx = res.indices
    expected = asymmetric_distance(states[idx].unsqueeze(1), goals[idx].unsqueeze(0))
    torch.testing.assert_close(res.landmark_distances[known], expected[known])


def test_proxy_and_lazy_batch_errors():
    states, goals = make_candidates(50, seed=7)
    with pytest.raises(ValueError, match="proxy"):
        farthest_point_sampling(states, goals, asymmetric_distance, 10, proxy="euclidean")
    with pytest.raises(ValueError, match="proxy"):
        farthest_point_sampling(states, goals, asymmetric_distance, 10, proxy=lambda a, b: b)
    for bad in (0, True, 2.0):
        with pytest.raises(ValueError, match="lazy_batch"):
            farthest_point_sampling(states, goals, asymmetric_distance, 10, lazy_batch=bad)
    # the dense strategy does not use the proxy
    res = farthest_point_sampling(
        states, goals, asymmetric_distance, 10, strategy="dense", proxy=lambda a, b: b
    )
    assert res.indices.numel() == 10


def test_ties_infinities_and_min_count():
    # four exact copies of two points: ties must go to the lowest index; inf distances are farthest
    pts = torch.tensor([[0.0, 0.0], [3.0, 0.0], [0.0, 0.0], [3.0, 0.0], [50.0, 50.0]])

    def walled(s, g):
        d = (g - s[..., :2]).norm(dim=-1)
        return torch.where((g[..., 0] > 40) ^ (s[..., 0] > 40), torch.full_like(d, math.inf), d)

    for strategy in ("dense", "lazy"):
        res = farthest_point_sampling(pts, pts.clone(), walled, 5, strategy=strategy)
        expected, _ = naive_fps(pts.numpy(), pts.numpy(), walled, 5)
        assert res.indices.tolist() == expected == [0, 4, 1, 2, 3]
        # early stop is ignored until min_count landmarks exist
        res = farthest_point_sampling(
            pts, pts.clone(), walled, 5, early_stop=100.0, min_count=3, strategy=strategy
        )
        assert res.indices.tolist() == [0, 4, 1]
        res = farthest_point_sampling(
            pts, pts.clone(), walled, 5, early_stop=100.0, min_count=0, strategy=strategy
        )
        assert res.indices.tolist() == [0, 4]  # the inf min-distance of point 4 is never "below" 100


def test_more_landmarks_than_candidates_and_single_candidate():
    states, goals = make_candidates(7, seed=3)
    for strategy in ("dense", "lazy"):
        res = farthest_point_sampling(states, goals, asymmetric_distance, 50, strategy=strategy)
        assert sorted(res.indices.tolist()) == list(range(7)) and res.radius.item() == 0.0
        one = farthest_point_sampling(states[:1], goals[:1], asymmetric_distance, 5, strategy=strategy)
        assert one.indices.tolist() == [0] and one.landmark_distances.shape == (1, 1)


def test_start_index_and_errors():
    states, goals = make_candidates(100, seed=4)
    res = farthest_point_sampling(states, goals, asymmetric_distance, 10, start_index=17)
    assert res.indices[0].item() == 17
    with pytest.raises(ValueError, match="start_index"):
        farthest_point_sampling(states, goals, asymmetric_distance, 10, start_index=100)
    with pytest.raises(ValueError, match="same number"):
        farthest_point_sampling(states, goals[:5], asymmetric_distance, 10)
    with pytest.raises(ValueError, match="strategy"):
        farthest_point_sampling(states, goals, asymmetric_distance, 10, strategy="fast")
    with pytest.raises(ValueError, match="max_count"):
        farthest_point_sampling(states, goals, asymmetric_distance, 0)
    with pytest.raises(ValueError, match="shape"):
        farthest_point_sampling(states, goals, lambda s, g: asymmetric_distance(s, g)[..., None], 10)
    with pytest.raises(ValueError, match="NaN"):
        farthest_point_sampling(states, goals, lambda s, g: torch.full(s.shape[:-1], math.nan), 10)
