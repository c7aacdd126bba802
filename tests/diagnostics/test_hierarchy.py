"""hierarchy_diagnostics / subgoal_segments against a per-step Python reference over random rollouts."""

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from torchrl_dhrl.diagnostics import (
    HIERARCHY_DIAG_KEYS,
    LEARNED_DISTANCE_DIAG_KEYS,
    hierarchy_diagnostics,
    subgoal_segments,
)


def _rollout(B, T, dim, flags, seed):
    g = torch.Generator().manual_seed(seed)
    ag = torch.randn(B, T + 1, dim, generator=g)
    subgoal = torch.randn(B, T, dim, generator=g)
    # a subgoal is constant within its segment, as the policy holds it for c_h steps
    for b in range(B):
        for t in range(1, T):
            if not flags[b, t]:
                subgoal[b, t] = subgoal[b, t - 1]
    waypoint = subgoal.clone()
    follow = torch.rand(B, T, generator=g) < 0.4
    waypoint[follow] = torch.randn(int(follow.sum()), dim, generator=g)
    goal = torch.randn(B, 1, dim, generator=g).expand(B, T, dim)
    return TensorDict(
        achieved_goal=ag[:, :-1],
        desired_goal=goal,
        subgoal=subgoal,
        waypoint=waypoint,
        new_subgoal=flags.unsqueeze(-1),
        next=TensorDict(achieved_goal=ag[:, 1:], batch_size=[B, T]),
        batch_size=[B, T],
    )


def _reference(rollout, threshold):
    """Walks each row step by step, closing a segment when the next step issues a new subgoal."""
    ag = rollout["achieved_goal"].numpy()
    nag = rollout["next", "achieved_goal"].numpy()
    sg, g = rollout["subgoal"].numpy(), rollout["desired_goal"].numpy()
    flags = rollout["new_subgoal"].squeeze(-1).numpy()
    rows = {k: [] for k in ("sgd", "off", "end", "prog")}
    B, T = flags.shape
    for b in range(B):
        start = 0
        for t in range(T):
            last = t == T - 1 or flags[b, t + 1]
            if last:
                s = sg[b, start]
                rows["sgd"].append(np.linalg.norm(s - g[b, start]))
                rows["off"].append(np.linalg.norm(s - ag[b, start]))
                rows["end"].append(np.linalg.norm(nag[b, t] - s))
                rows["prog"].append(
                    np.linalg.norm(ag[b, start] - g[b, start]) - np.linalg.norm(nag[b, t] - g[b, start])
                )
                start = t + 1
    end = np.array(rows["end"])
    follow = (rollout["waypoint"].numpy() != sg).any(-1)
    return {
        "subgoal_goal_distance": np.mean(rows["sgd"]),
        "subgoal_offset": np.mean(rows["off"]),
        "subgoal_end_distance": end.mean(),
        "subgoal_reached": (end <= threshold).mean(),
        "segment_progress": np.mean(rows["prog"]),
        "graph_steps": follow.mean(),
    }


@pytest.mark.parametrize("seed", range(12))
def test_matches_reference_on_random_rollouts(seed):
    g = torch.Generator().manual_seed(100 + seed)
    B, T, dim = int(torch.randint(1, 4, (1,), generator=g)), int(torch.randint(1, 30, (1,), generator=g)), 3
    kind = seed % 4
    if kind == 0:  # every step issues
        flags = torch.ones(B, T, dtype=torch.bool)
    elif kind == 1:  # a single subgoal per episode (flag only at the start)
        flags = torch.zeros(B, T, dtype=torch.bool)
        flags[:, 0] = True
    else:  # random cadence; kind 3 also drops the first step's flag (a rollout cut mid-segment)
        flags = torch.rand(B, T, generator=g) < 0.3
        flags[:, 0] = kind == 2
    rollout = _rollout(B, T, dim, flags, seed)
    if kind == 3:
        rollout["new_subgoal"][:, 0] = False
        flags = flags.clone()
        flags[:, 0] = True  # the reference treats the first step as a start, as documented
        rollout_ref = rollout.clone()
        rollout_ref["new_subgoal"] = flags.unsqueeze(-1)
    else:
        rollout_ref = rollout
    threshold = 1.5
    out = hierarchy_diagnostics(rollout, threshold)
    ref = _reference(rollout_ref, threshold)
    assert set(out) == set(HIERARCHY_DIAG_KEYS)
    for key in HIERARCHY_DIAG_KEYS:
        assert out[key] == pytest.approx(float(ref[key]), rel=1e-5, abs=1e-6), key


def test_segments_one_start_and_end_each():
    g = torch.Generator().manual_seed(0)
    for _ in range(50):
        B, T = int(torch.randint(1, 5, (1,), generator=g)), int(torch.randint(1, 20, (1,), generator=g))
        flags = torch.rand(B, T, generator=g) < 0.5
        starts, ends = subgoal_segments(flags)
        assert starts.shape == ends.shape
        assert (starts <= ends).all()
        # segments tile the steps: consecutive, no gap, no overlap, never across rows
        assert (starts[1:] == ends[:-1] + 1).all()
        assert starts[0] == 0 and ends[-1] == B * T - 1
        assert ((starts // T) == (ends // T)).all()
        assert len(starts) == int(flags[:, 1:].sum()) + B


def test_perfect_hierarchy():
    """An agent that lands exactly on each subgoal, which is the goal: reached 1, goal distance 0."""
    T = 6
    goal = torch.tensor([3.0, 0.0])
    ag = torch.stack([torch.linspace(0, 3, T + 1), torch.zeros(T + 1)], -1)
    ag[3:] = goal
    rollout = TensorDict(
        achieved_goal=ag[:-1],
        desired_goal=goal.expand(T, 2),
        subgoal=goal.expand(T, 2),
        waypoint=goal.expand(T, 2),
        new_subgoal=torch.tensor([True, False, False, True, False, False]).unsqueeze(-1),
        next=TensorDict(achieved_goal=ag[1:], batch_size=[T]),
        batch_size=[T],
    )
    out = hierarchy_diagnostics(rollout, threshold=1e-6)
    assert out["subgoal_goal_distance"] == 0.0
    assert out["subgoal_reached"] == 1.0
    assert out["graph_steps"] == 0.0
    assert out["segment_progress"] == pytest.approx(1.5)  # 3 in the first segment, 0 in the second
    assert out["subgoal_offset"] == pytest.approx(1.5)


def test_bad_input():
    rollout = TensorDict(achieved_goal=torch.zeros(3, 2), batch_size=[3])
    with pytest.raises(KeyError, match="desired_goal"):
        hierarchy_diagnostics(rollout, 0.5)
    with pytest.raises(ValueError, match="time dimension"):
        subgoal_segments(torch.zeros(2, 0, dtype=torch.bool))


def test_learned_distances_against_reference():
    """The learned-distance entries: per-segment calls on the segment's first state and its subgoal."""
    g = torch.Generator().manual_seed(7)
    B, T = 3, 17
    flags = torch.rand(B, T, generator=g) < 0.3
    flags[:, 0] = True
    rollout = _rollout(B, T, 2, flags, 7)
    rollout["observation"] = torch.cat([rollout["achieved_goal"], torch.randn(B, T, 3, generator=g)], -1)
    landmarks = torch.randn(5, 2, generator=g)
    distance = lambda states, goals: 10 * (goals - states[..., :2]).norm(dim=-1)  # noqa: E731
    from_graph = lambda goals: 10 * torch.cdist(goals, landmarks).min(-1).values  # noqa: E731
    out = hierarchy_diagnostics(
        rollout, 0.5, distance=distance, distance_from_graph=from_graph, far_threshold=8.0
    )
    assert set(out) == set(HIERARCHY_DIAG_KEYS) | set(LEARNED_DISTANCE_DIAG_KEYS)
    learned, near = [], []
    for b in range(B):
        for t in range(T):
            if flags[b, t]:
                s = rollout["subgoal"][b, t]
                learned.append(distance(rollout["observation"][b, t], s).item())
                near.append(from_graph(s[None])[0].item())
    near = np.array(near)
    assert out["subgoal_learned_distance"] == pytest.approx(np.mean(learned), rel=1e-5)
    assert out["subgoal_graph_distance"] == pytest.approx(near.mean(), rel=1e-5)
    assert out["subgoals_far_from_graph"] == pytest.approx((near > 8.0).mean())
    # no graph yet: the planner's distance from the graph is infinite -> NaN, not inf
    no_graph = hierarchy_diagnostics(
        rollout,
        0.5,
        distance_from_graph=lambda goals: torch.full(goals.shape[:-1], float("inf")),
        far_threshold=8.0,
    )
    assert np.isnan(no_graph["subgoal_graph_distance"]) and np.isnan(no_graph["subgoals_far_from_graph"])
    assert "subgoal_learned_distance" not in no_graph
