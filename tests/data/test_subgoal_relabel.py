"""Tests of HindsightSubgoalRelabel and of the full high-level relabelling pipeline."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import RenameTransform

from tests.data.test_high_level_transitions import SubgoalStream
from torchrl_dhrl.data import (
    FutureGoalRelabel,
    HighLevelTransitionBuilder,
    HindsightSubgoalRelabel,
    RelabelReplayBuffer,
)

P1, P2, FAR = 1.3, 5.0, 90.0


def high_level_sample(n: int, seed: int = 0) -> TensorDict:
    generator = torch.Generator().manual_seed(seed)
    return TensorDict(
        {
            "subgoal": torch.randn(n, 2, generator=generator) * 5,
            "desired_goal": torch.randn(n, 2, generator=generator) * 5,
            ("next", "achieved_goal"): torch.randn(n, 2, generator=generator) * 5,
        },
        batch_size=[n],
    )


def sparse(achieved, goal):
    return torch.where((achieved - goal).norm(dim=-1, keepdim=True) > 0.5, -1.0, 0.0)


def test_hindsight_action_ratio_and_values():
    torch.manual_seed(0)
    n = 20_000
    sample = high_level_sample(n)
    original = sample.clone()
    out = HindsightSubgoalRelabel(subgoal_test_ratio=0.2)(sample)
    tested = out["subgoal_test"].squeeze(-1)
    fraction = 1 - tested.double().mean().item()
    assert abs(fraction - 0.8) < 4 * math.sqrt(0.8 * 0.2 / n)
    assert torch.equal(out["subgoal"][~tested], original["next", "achieved_goal"][~tested])
    assert torch.equal(out["subgoal"][tested], original["subgoal"][tested])
    # hindsight samples: the sparse reward of the segment's final achieved goal vs the goal
    torch.testing.assert_close(
        out["next", "reward"][~tested],
        sparse(original["next", "achieved_goal"], original["desired_goal"])[~tested],
    )


def penalty_cases() -> tuple[TensorDict, dict[str, torch.Tensor]]:
    """Four tested subgoals: (missed?, far?) x goal reached / not reached by the segment."""
    achieved = torch.zeros(8, 2)
    subgoal = torch.tensor([[0.5, 0.0], [3.0, 0.0], [0.5, 0.0], [3.0, 0.0]]).repeat(2, 1)  # miss thr 1
    far = torch.tensor([False, False, True, True]).repeat(2)
    goal = torch.cat([torch.zeros(4, 2), torch.full((4, 2), 7.0)])  # reached (r=0) / not (r=-1)
    sample = TensorDict(
        {"subgoal": subgoal, "desired_goal": goal, ("next", "achieved_goal"): achieved, "far": far}, [8]
    )
    missed = torch.tensor([False, True, False, True]).repeat(2)
    sparse_reward = torch.cat([torch.zeros(4), -torch.ones(4)])
    return sample, {"missed": missed, "far": far, "sparse": sparse_reward}


def graph_distance_from_far_flags(far: torch.Tensor):
    lookup = {(0.5, False): 10.0, (3.0, False): 20.0, (0.5, True): 200.0, (3.0, True): 300.0}

    def distance_from_graph(goals):
        # the subgoals themselves do not tell far ones apart: encode the far flag in the query order
        return torch.tensor([lookup[(g[0].item(), bool(f))] for g, f in zip(goals, far, strict=True)])

    return distance_from_graph


@pytest.mark.parametrize("requires_miss", [False, True])
def test_subgoal_testing_rewards_per_case(requires_miss):
    sample, case = penalty_cases()
    relabel = HindsightSubgoalRelabel(
        graph_distance_from_far_flags(case["far"]),
        subgoal_test_ratio=1.0,
        subgoal_miss_penalty=P1,
        gradual_penalty=P2,
        far_from_graph_threshold=FAR,
        far_penalty_requires_miss=requires_miss,
    )
    out = relabel(sample.clone())
    reward = out["next", "reward"].squeeze(-1)
    missed, far, sparse_reward = case["missed"], case["far"], case["sparse"]
    if requires_miss:  # paper, Algorithms 1 and 4
        expected = torch.where(missed & far, -P2, torch.where(missed, -P1, sparse_reward))
    else:  # reference code: the gradual penalty overrides, reached or not
        expected = torch.where(far, -P2, torch.where(missed, -P1, sparse_reward))
    torch.testing.assert_close(reward, expected)
    assert torch.equal(out["subgoal"], sample["subgoal"])  # tested subgoals are kept


def test_gradual_penalty_needs_a_graph_and_a_query():
    sample, case = penalty_cases()
    expected_no_graph = torch.where(case["missed"], -P1, case["sparse"])
    for relabel in (
        HindsightSubgoalRelabel(
            lambda goals: torch.full((goals.shape[0],), float("inf")), subgoal_test_ratio=1.0
        ),
        HindsightSubgoalRelabel(None, subgoal_test_ratio=1.0),
        HindsightSubgoalRelabel(
            graph_distance_from_far_flags(case["far"]), subgoal_test_ratio=1.0, gradual_penalty=None
        ),
    ):
        out = relabel(sample.clone())
        torch.testing.assert_close(out["next", "reward"].squeeze(-1), expected_no_graph)
    # once a graph exists, the same relabeller penalises far subgoals
    relabel = HindsightSubgoalRelabel(None, subgoal_test_ratio=1.0)
    relabel.distance_from_graph = graph_distance_from_far_flags(case["far"])
    assert (relabel(sample.clone())["next", "reward"].squeeze(-1)[case["far"]] == -P2).all()


def test_distance_queried_on_tested_subgoals_only_without_grad():
    torch.manual_seed(1)
    calls = []

    def distance_from_graph(goals):
        calls.append((goals.clone(), torch.is_grad_enabled()))
        return goals.norm(dim=-1) * 20

    sample = high_level_sample(500, seed=1)
    out = HindsightSubgoalRelabel(distance_from_graph)(sample.clone())
    tested = out["subgoal_test"].squeeze(-1)
    assert len(calls) == 1
    goals, grad_enabled = calls[0]
    assert not grad_enabled
    assert torch.equal(goals, sample["subgoal"][tested])
    far = goals.norm(dim=-1) * 20 > FAR
    assert (out["next", "reward"][tested][far] == -P2).all()
    calls.clear()
    HindsightSubgoalRelabel(distance_from_graph, subgoal_test_ratio=0.0)(sample.clone())
    assert not calls


@pytest.mark.parametrize("batch_size", [[], [4], [6, 4]])
def test_batch_shapes(batch_size):
    torch.manual_seed(2)
    shape = torch.Size(batch_size)
    sample = TensorDict(
        {
            "subgoal": torch.randn(*shape, 2),
            "desired_goal": torch.randn(*shape, 2),
            ("next", "achieved_goal"): torch.randn(*shape, 2),
        },
        batch_size=shape,
    )
    out = HindsightSubgoalRelabel(lambda g: g.norm(dim=-1) * 100)(sample.clone())
    assert out["subgoal"].shape == (*shape, 2)
    assert out["next", "reward"].shape == (*shape, 1)
    assert out["subgoal_test"].shape == (*shape, 1)
    tested = out["subgoal_test"].squeeze(-1)
    assert torch.equal(
        torch.where(tested.unsqueeze(-1), sample["subgoal"], sample["next", "achieved_goal"]), out["subgoal"]
    )


def test_inside_replay_buffer_and_composed():
    torch.manual_seed(3)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=32)
    rb.append_transform(HindsightSubgoalRelabel())  # a pure sample transform: works inside the buffer
    rb.append_transform(RenameTransform([("next", "reward")], [("next", "high_reward")]))
    rb.extend(high_level_sample(100, seed=3))
    out = rb.sample()
    assert ("next", "high_reward") in out.keys(True) and "subgoal_test" in out.keys()
    tested = out["subgoal_test"].squeeze(-1)
    assert torch.equal(out["subgoal"][~tested], out["next", "achieved_goal"][~tested])


def test_pipeline_goals_same_episode_within_high_level_window():
    """Builder -> 1-D buffer -> FutureGoalRelabel (episode markers) -> HindsightSubgoalRelabel."""
    torch.manual_seed(4)
    window = 3
    stream = SubgoalStream(num_envs=3, min_len=8, max_len=40, flag_prob=0.2, seed=11)
    relabel = [
        FutureGoalRelabel(
            her_ratio=1.0,
            window=window,
            out_keys=["desired_goal"],
            reward_keys=None,
            traj_key="episode_id",
            step_count_key="segment_index",
        ),
        HindsightSubgoalRelabel(lambda g: torch.full(g.shape[:1], float("inf"))),
    ]
    rb = RelabelReplayBuffer(
        storage=LazyTensorStorage(60),
        transform=HighLevelTransitionBuilder(),
        relabel=relabel,
        batch_size=2048,
    )
    segment_of_end: dict[tuple[int, int], int] = {}  # (uid, end step + 1) -> segment index
    for _ in range(15):  # the 60-record buffer wraps around
        rb.extend(stream.batch(12))
        stored = rb[:]
        for uid_end, index in zip(
            stored["next", "achieved_goal"].long().tolist(), stored["segment_index"].tolist(), strict=True
        ):
            segment_of_end[tuple(uid_end)] = index[0]
        if len(rb) == 0:
            continue
        sample = rb.sample()
        uid = sample["achieved_goal"][:, 0].long()
        goal = sample["desired_goal"].long()
        assert (goal[:, 0] == uid).all(), "high-level goal from another episode"
        goal_segment = torch.tensor([segment_of_end[tuple(g)] for g in goal.tolist()])
        ahead = goal_segment - sample["segment_index"].squeeze(-1)
        assert (ahead >= 0).all() and (ahead < window).all()
        assert torch.equal(sample["next", "desired_goal"], sample["desired_goal"].float())
        tested = sample["subgoal_test"].squeeze(-1)
        torch.testing.assert_close(
            sample["next", "reward"][~tested],
            sparse(sample["next", "achieved_goal"], sample["desired_goal"])[~tested],
        )
    assert rb.storage._is_full


def _reserved_planner(num_landmarks: int, seed: int = 0):
    """A GraphPlanner on a reserved fixed-size graph, the distance ten steps per goal unit."""
    from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph

    def distance(states, goals):
        return (states[..., :2] - goals).norm(dim=-1) * 10

    graph = LandmarkGraph(cutoff=30.0, max_landmarks=24, fixed_size=True).reserve(4, 2)
    planner = GraphPlanner(graph, distance, 2, capturable=True)
    if num_landmarks:
        points = torch.rand(num_landmarks, 2, generator=torch.Generator().manual_seed(seed)) * 10 - 5
        graph.set_landmarks(torch.cat([points, torch.zeros_like(points)], -1), points, distance)
    return planner


def _written_storage(n: int = 64) -> LazyTensorStorage:
    storage = LazyTensorStorage(n)
    storage.set(torch.arange(n), high_level_sample(n, seed=9))
    return storage


@pytest.mark.parametrize("requires_miss", [False, True])
def test_capturable_relabel_equals_forward(requires_miss):
    """The capture-safe relabelling (every row queried, static shapes) writes what ``forward`` writes from the same
    random state: subgoals, rewards and test flags, with the gradual penalty's query on a reserved graph (no
    landmark, then 3 and 12), without a graph query and without a gradual penalty; over random batches."""
    import functools

    storage = _written_storage()
    penalties = {"far": 0, "missed": 0}
    for num in (0, 3, 12):
        planner = _reserved_planner(num, seed=num)
        query = functools.partial(planner.distance_from_graph, at_most=FAR)
        for distance, penalty in ((query, P2), (None, P2), (query, None)):
            relabel = HindsightSubgoalRelabel(
                distance, sparse, gradual_penalty=penalty, far_penalty_requires_miss=requires_miss
            )
            captured = relabel.capturable_relabel(storage)
            for seed in range(4):
                sample = high_level_sample(int(torch.randint(1, 300, ())), seed=seed)
                sample["subgoal"] = sample["subgoal"] * 4  # some far from the landmarks
                torch.manual_seed(seed)
                eager = relabel(sample.clone())
                torch.manual_seed(seed)
                mine = captured(sample.clone(), torch.zeros(sample.shape[0], 1, dtype=torch.long), torch.tensor(0))
                for key in ("subgoal", ("next", "reward"), "subgoal_test"):
                    assert torch.equal(mine[key], eager[key]), (num, penalty, key)
                rewards = eager["next", "reward"]
                penalties["far"] += int((rewards == -P2).sum())
                penalties["missed"] += int((rewards == -P1).sum())
    assert penalties["far"] > 0 and penalties["missed"] > 0  # both penalties exercised


def test_capturable_relabel_refuses_a_query_without_a_capture_safe_form():
    from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph

    storage = _written_storage()
    plain = HindsightSubgoalRelabel(lambda goals: goals.norm(dim=-1))
    with pytest.raises(RuntimeError, match="distance_from_graph has no capture-safe form"):
        plain.capturable_relabel(storage)
    unreserved = GraphPlanner(LandmarkGraph(), lambda s, g: (s[..., :2] - g).norm(dim=-1), 2)
    with pytest.raises(RuntimeError, match="needs a fixed_size graph whose planning tensors exist"):
        HindsightSubgoalRelabel(unreserved.distance_from_graph).capturable_relabel(storage)


@pytest.mark.slow
def test_capturable_high_level_sampler_compiles_whole():
    """A high-level buffer (the transition builder on writes, future goals by episode, subgoal testing with the
    gradual penalty on a reserved graph) offers the capture-safe sampler; compiled with ``fullgraph=True`` (no
    graph break: no host synchronisation) it draws what the eager sampler draws (random ops on the eager
    generator); a sample-side transform is still refused."""
    import functools

    from torch._inductor import config as inductor_config

    planner = _reserved_planner(10)
    stream = SubgoalStream(num_envs=3, min_len=8, max_len=40, flag_prob=0.2, seed=11)
    relabel = [
        FutureGoalRelabel(
            sparse,
            her_ratio=0.8,
            window=3,
            out_keys=["desired_goal"],
            reward_keys=None,
            traj_key="episode_id",
            step_count_key="segment_index",
        ),
        HindsightSubgoalRelabel(functools.partial(planner.distance_from_graph, at_most=FAR), sparse),
    ]
    rb = RelabelReplayBuffer(
        storage=LazyTensorStorage(200), transform=HighLevelTransitionBuilder(), relabel=relabel, batch_size=64
    )
    for _ in range(4):
        rb.extend(stream.batch(12))
    sample = rb.capturable_sampler()
    torch.manual_seed(0)
    eager = sample()
    compiled = torch.compile(sample, fullgraph=True)
    with inductor_config.patch(fallback_random=True):
        torch.manual_seed(0)
        mine = compiled()
    for key in ("index", "subgoal", "desired_goal", ("next", "reward"), "subgoal_test"):
        assert torch.equal(mine[key], eager[key]), key
    tested = eager["subgoal_test"].squeeze(-1)
    assert torch.equal(eager["subgoal"][~tested], eager["next", "achieved_goal"][~tested])
    rb.append_transform(RenameTransform([("next", "reward")], [("next", "high_reward")]))
    with pytest.raises(RuntimeError, match="does not run the buffer's sample-side `transform`"):
        rb.capturable_sampler()


def test_errors():
    with pytest.raises(ValueError, match="subgoal_test_ratio"):
        HindsightSubgoalRelabel(subgoal_test_ratio=1.5)
    with pytest.raises(ValueError, match="penalty"):
        HindsightSubgoalRelabel(subgoal_miss_penalty=-1.3)
    with pytest.raises(ValueError, match="penalty"):
        HindsightSubgoalRelabel(gradual_penalty=-5.0)
    with pytest.raises(TypeError, match="callable"):
        HindsightSubgoalRelabel(distance_from_graph=3)
    relabel = HindsightSubgoalRelabel(lambda g: torch.zeros(3), subgoal_test_ratio=1.0)
    with pytest.raises(ValueError, match="distance_from_graph must return"):
        relabel(high_level_sample(5))
    with pytest.raises(KeyError, match="subgoal"):
        HindsightSubgoalRelabel()(high_level_sample(5).exclude("subgoal"))
    bad = high_level_sample(5)
    bad["desired_goal"] = torch.zeros(5, 3)
    with pytest.raises(ValueError, match="same dimension"):
        HindsightSubgoalRelabel()(bad)
    with pytest.raises(RuntimeError, match="not an environment transform"):
        HindsightSubgoalRelabel()._call(high_level_sample(2))
