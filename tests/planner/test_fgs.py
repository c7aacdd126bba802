"""Frontier-based goal shifting: when it shifts, the sampling distribution of each weighting, and
``GoalShiftOnReset`` inside an env."""

import math

import numpy as np
import pytest
import torch
from scipy.stats import chisquare
from tensordict import TensorDict
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs
from torchrl_dhrl.envs import make_env

from torchrl_dhrl.planner import FrontierGoalShifting, GoalShiftOnReset, GraphPlanner, LandmarkGraph

# landmarks 0..5 on the x axis (one step apart) and an island {6: x=20, 7: x=21} unreachable from x=0
POINTS = torch.tensor([[float(x), 0.0] for x in (0, 1, 2, 3, 4, 5, 20, 21)])


# graph distance from a start at the origin: landmark k is k steps away; the island is unreachable
PATH_LENGTHS = np.array([0.0, 1, 2, 3, 4, 5, math.inf, math.inf])


def euclidean(states, goals):
    return (goals - states[..., :2]).norm(dim=-1)


@pytest.fixture
def planner():
    planner = GraphPlanner(LandmarkGraph(cutoff=1.5), euclidean, 2)
    planner.graph.set_landmarks(POINTS, POINTS.clone(), euclidean)
    return planner


def sample_landmarks(fgs, num, seed=0):
    """Shift ``num`` in-graph goals from the origin with zero noise; return the picked landmark ids."""
    fgs.generator = torch.Generator().manual_seed(seed)
    starts = torch.zeros(num, 2)
    goals = torch.tensor([[2.2, 0.3]]).expand(num, 2)
    new_goals, shifted = fgs.shift(starts, goals)
    assert shifted.all()
    ids = torch.cdist(new_goals, POINTS).argmin(-1)
    assert torch.allclose(new_goals, POINTS[ids])
    return np.bincount(ids.numpy(), minlength=len(POINTS))


@pytest.mark.parametrize(
    "trigger,expected",
    [
        # the reference's: a path start -> goal in the cutoff-expanded graph; (20.5, 1) is next to the
        # island {20, 21}, which the start cannot reach
        ("reachable", [True, False, False, False]),
        # the paper's: min_v d(v -> g) < cutoff (0.36, 7.1, 1.1, 1.6), reachable or not
        ("near_graph", [True, False, True, False]),
    ],
)
def test_shifts_only_goals_inside_the_graph(planner, trigger, expected):
    fgs = FrontierGoalShifting(
        planner, noise=0.0, trigger=trigger, generator=torch.Generator().manual_seed(0)
    )
    starts = torch.zeros(4, 2)
    goals = torch.tensor([[2.2, 0.3], [10.0, 10.0], [20.5, 1.0], [5.0, 1.6]])
    new_goals, shifted = fgs.shift(starts, goals)
    assert shifted.tolist() == expected
    assert torch.equal(new_goals[~shifted], goals[~shifted])
    empty = FrontierGoalShifting(GraphPlanner(LandmarkGraph(cutoff=1.5), euclidean, 2))
    same, none = empty.shift(starts, goals)
    assert torch.equal(same, goals) and not none.any()

    # a start connected to no landmark (infinite distances) has no positive weight: no shift
    def walled(states, goals):
        d = euclidean(states, goals)
        return torch.where(states[..., 1] > 40, torch.full_like(d, math.inf), d)

    planner.distance = walled
    _, shifted = FrontierGoalShifting(planner).shift(torch.tensor([[50.0, 50.0]]), goals[:1])
    assert not shifted.any()


def test_reachable_trigger_on_a_hand_made_graph(planner):
    """Each edge kind of the expanded graph on its own: start -> landmark -> goal, start -> goal directly."""
    fgs = FrontierGoalShifting(planner, trigger="reachable")
    near = FrontierGoalShifting(planner, trigger="near_graph")
    starts = torch.tensor([[0.0, 0.0], [10.0, 10.0], [10.0, 10.0], [3.0, 1.2], [20.0, 1.0], [0.0, 0.0]])
    goals = torch.tensor([[5.0, 1.4], [10.5, 10.5], [5.0, 0.0], [-1.0, 0.0], [21.0, 1.4], [21.0, 0.0]])
    # 0: via the chain 0..5 and landmark 5 (1.4 < 1.5); 1: start -> goal directly (0.71), no landmark near;
    # 2: the start reaches no landmark within the cutoff (no fallback edge in this test);
    # 3: start within 1.25 of landmark 3, goal 1.0 from landmark 0; 4: the island from inside;
    # 5: the island from the chain: no path
    assert fgs.covered(starts, goals).tolist() == [True, True, False, True, True, False]
    assert near.covered(starts, goals).tolist() == [True, False, True, True, True, True]
    # shift needs a positive weight too: start (10, 10) has fallback-connected landmarks, so row 1 shifts
    _, shifted = fgs.shift(starts, goals)
    assert shifted.tolist() == [True, True, False, True, True, False]
    with pytest.raises(ValueError, match="trigger"):
        FrontierGoalShifting(planner, trigger="always")


@pytest.mark.parametrize(
    "weighting,expected",
    [
        ("path_length", np.where(np.isfinite(PATH_LENGTHS), PATH_LENGTHS, 0.0)),
        ("reference", np.where(np.isfinite(PATH_LENGTHS), PATH_LENGTHS, 5000.0)),
        ("softmax", np.where(np.isfinite(PATH_LENGTHS), np.exp(PATH_LENGTHS / 2.0), 0.0)),
    ],
)
def test_sampling_distribution_matches_weighting(planner, weighting, expected):
    fgs = FrontierGoalShifting(planner, noise=0.0, weighting=weighting, temperature=2.0)
    probs = expected / expected.sum()
    torch.testing.assert_close(
        fgs.weights(torch.zeros(1, 2))[0] / fgs.weights(torch.zeros(1, 2))[0].sum(),
        torch.tensor(probs, dtype=torch.float32),
    )
    num = 6000
    counts = sample_landmarks(fgs, num)
    support = probs > 0
    assert counts[~support].sum() == 0
    assert chisquare(counts[support], probs[support] * num).pvalue > 1e-3
    if weighting == "reference":  # the 5000-weight rule: unreachable landmarks dominate
        assert counts[6:].sum() / num > 0.99
    else:
        assert counts[6:].sum() == 0 and counts[5] > counts[1]


def test_noise_bounds_clamping_and_determinism(planner):
    fgs = FrontierGoalShifting(planner, noise=3.0, low=-1.0, high=torch.tensor([4.5, 2.0]))
    goals = torch.tensor([[2.2, 0.3]]).expand(4000, 2)
    fgs.generator = torch.Generator().manual_seed(1)
    first, _ = fgs.shift(torch.zeros(4000, 2), goals)
    fgs.generator = torch.Generator().manual_seed(1)
    second, _ = fgs.shift(torch.zeros(4000, 2), goals)
    assert torch.equal(first, second)
    assert (first >= -1.0).all() and (first[:, 0] <= 4.5).all() and (first[:, 1] <= 2.0).all()
    unclamped = FrontierGoalShifting(planner, noise=3.0, generator=torch.Generator().manual_seed(2))
    shifted, _ = unclamped.shift(torch.zeros(4000, 2), goals)
    noise_y = shifted[:, 1]  # landmarks have y = 0: the y coordinate is pure U(-3, 3) noise
    assert noise_y.abs().max() <= 3.0 and noise_y.abs().max() > 2.9
    assert noise_y.mean().abs() < 0.1 and noise_y.var().item() == pytest.approx(
        3.0, rel=0.1
    )  # var U(-3,3) = 3


def test_tensordict_interface(planner):
    fgs = FrontierGoalShifting(planner, noise=0.0, out_goal_key="shifted_goal", generator=torch.Generator())
    td = TensorDict(
        observation=torch.zeros(2, 3, 2),
        desired_goal=torch.tensor([[2.2, 0.3], [10.0, 10.0], [0.0, 0.0]]).expand(2, 3, 2).clone(),
        batch_size=[2, 3],
    )
    out = fgs(td)
    assert out["goal_shifted"].shape == (2, 3, 1)
    assert out["goal_shifted"].squeeze(-1).tolist() == [[True, False, True]] * 2
    assert torch.equal(out["shifted_goal"][:, 1], td["desired_goal"][:, 1])
    assert fgs.in_keys == ["observation", "desired_goal"] and fgs.out_keys == ["shifted_goal", "goal_shifted"]
    assert not list(fgs.state_dict())  # no state of its own (the graph belongs to the planner)
    with pytest.raises(KeyError, match="desired_goal"):
        fgs(td.exclude("desired_goal"))
    with pytest.raises(ValueError, match="weighting"):
        FrontierGoalShifting(planner, weighting="uniform")
    with pytest.raises(TypeError, match="GraphPlanner"):
        FrontierGoalShifting(planner.graph)


# ---------------------------------------------------------------- FGS inside the env
def _line_planner():
    dist = lambda s, g: (g - s[..., :2]).norm(dim=-1) / 0.2  # noqa: E731
    planner = GraphPlanner(LandmarkGraph(cutoff=30.0, max_landmarks=20, early_stop=0.0), dist, goal_dim=2)
    ys = torch.linspace(0, 8, 41)
    line = torch.stack([torch.zeros_like(ys), ys], -1)  # covers PointMaze's test goal (0, 8)
    states = torch.cat([line, torch.zeros(41, 4)], -1)  # PointMaze observations: x, y, yaw, velocities
    return planner.build(states, line)


def test_goal_shift_on_reset_in_env():
    planner = _line_planner()
    fgs = FrontierGoalShifting(planner, noise=0.0, generator=torch.Generator().manual_seed(0))
    env = TransformedEnv(
        make_env("PointMaze", num_envs=3, seed=0, eval=True, max_episode_steps=5), GoalShiftOnReset(fgs)
    )
    check_env_specs(env)
    td = env.reset()
    assert td["goal_shifted"].all()  # the test goal (0, 8) is inside the graph
    for g in td["desired_goal"]:  # shifted goals are landmarks (noise 0)
        assert (planner.landmark_goals - g).norm(dim=-1).min() < 1e-5
    assert not torch.equal(td["desired_goal"], torch.tensor([0.0, 8.0]).expand(3, 2))
    rollout = env.rollout(5, auto_reset=False, tensordict=td)
    # the held goal replaces the env's goal at every step
    assert torch.equal(rollout["next", "desired_goal"], td["desired_goal"].unsqueeze(1).expand(3, 5, 2))
    # a partial reset shifts only the envs being reset
    held = rollout[:, -1]["next"].clone()
    planner.clear_graph()
    held["_reset"] = torch.tensor([[True], [False], [False]])
    out = env.reset(held)
    assert out["goal_shifted"].squeeze(-1).tolist() == [False, True, True]
    assert torch.equal(out["desired_goal"][1:], held["desired_goal"][1:])
    assert torch.equal(out["desired_goal"][0], torch.tensor([0.0, 8.0]))


def test_goal_shift_without_graph_keeps_goals_and_partial_reset():
    planner = GraphPlanner(LandmarkGraph(cutoff=30.0), lambda s, g: (g - s[..., :2]).norm(dim=-1), goal_dim=2)
    env = TransformedEnv(
        make_env("PointMaze", num_envs=2, seed=0, max_episode_steps=3),
        GoalShiftOnReset(FrontierGoalShifting(planner)),
    )
    td = env.reset()
    assert not td["goal_shifted"].any() and torch.equal(td["episode_goal"], td["desired_goal"])
    with pytest.raises(TypeError, match="FrontierGoalShifting"):
        GoalShiftOnReset(planner)
