"""Critic-guided subgoals (issue 57): the high level issues the best of its actor's subgoal and K candidates
(Gaussian perturbations, optionally the graph's landmarks) by its critic's value, before the exploration noise
and only when a subgoal is due; off (the default), the reference's policy bit for bit."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_dhrl.modules import (
    CriticGuidedSubgoal,
    GaussianUniformExplorationModule,
    GoalConditionedCritic,
    HighLevelActor,
    HighLevelPolicy,
    SubgoalScheduler,
)

OBS, GOAL = 5, 2
LOW, HIGH = [-4.0, -4.0], [20.0, 20.0]
BOX_LOW, BOX_HIGH = torch.tensor(LOW), torch.tensor(HIGH)


def _critic(seed=0, num_cells=(16, 16)):
    torch.manual_seed(seed)
    return GoalConditionedCritic(
        OBS, GOAL, action_low=LOW, action_high=HIGH, goal_key="desired_goal", action_key="subgoal",
        relative_goal=False, num_cells=num_cells,
    )  # fmt: skip


def _toward(target):
    """A one-member critic valuing a subgoal by minus its distance to ``target`` (a hand-made best subgoal)."""
    target = torch.as_tensor(target)
    return TensorDictModule(
        lambda s, g, sg: -(sg - target).norm(dim=-1, keepdim=True),
        in_keys=["observation", "desired_goal", "subgoal"],
        out_keys=["state_action_value"],
    )


def _policy(seed=1, **kwargs):
    torch.manual_seed(seed)
    return HighLevelPolicy(OBS, GOAL, LOW, HIGH, interval=3, num_cells=(16,), **kwargs)


def _td(batch=4, seed=2):
    g = torch.Generator().manual_seed(seed)
    return TensorDict(
        {
            "observation": torch.randn(batch, OBS, generator=g) * 5,
            "desired_goal": torch.rand(batch, GOAL, generator=g) * 20,
            "subgoal_step": torch.full((batch, 1), -1),
        },
        [batch],
    )


def _landmarks(num=6, invalid=(2, 4), seed=3):
    g = torch.Generator().manual_seed(seed)
    goals = torch.rand(num, GOAL, generator=g) * 30 - 6  # some outside the box: clipped
    valid = torch.ones(num, dtype=torch.bool)
    valid[list(invalid)] = False
    return goals, valid


# ----------------------------------------------------------------------------- the choice, against a loop
@pytest.mark.parametrize("with_landmarks", [False, True])
def test_batched_choice_matches_a_python_loop_over_envs_and_candidates(with_landmarks):
    """One critic call on ``[B, 1 + K + L]`` picks, per env, the candidate a loop over envs and candidates picks
    (the same perturbations, drawn from the same generator state: ``torch.randn(B, K, goal_dim)``), scoring each
    with the twin's smaller value; invalid landmark rows never win; landmarks are clipped to the box."""
    K, B = 6, 5
    critic = _critic()
    goals, valid = _landmarks()
    policy = _policy(
        critic_candidates=K, candidate_noise=3.0, critic=critic,
        landmark_candidates=with_landmarks, landmarks=lambda: (goals, valid),
    )  # fmt: skip
    td = _td(B)
    with set_exploration_type(ExplorationType.DETERMINISTIC):  # the issued subgoal is the chosen one
        torch.manual_seed(10)
        out = policy(td.clone())
    proposal = policy.actor(td.clone())["subgoal_proposal"]

    torch.manual_seed(10)
    noise = torch.randn(B, K, GOAL)
    expected_index, expected = [], []
    for b in range(B):
        candidates = [proposal[b]] + [
            torch.maximum(torch.minimum(proposal[b] + 3.0 * noise[b, k], BOX_HIGH), BOX_LOW) for k in range(K)
        ]
        usable = [True] * (1 + K)
        if with_landmarks:
            candidates += [torch.maximum(torch.minimum(g, BOX_HIGH), BOX_LOW) for g in goals]
            usable += valid.tolist()
        best, best_score = 0, None
        for n, candidate in enumerate(candidates):
            one = TensorDict(
                {
                    "observation": td["observation"][b],
                    "desired_goal": td["desired_goal"][b],
                    "subgoal": candidate,
                },
                [],
            )
            score = critic(one)["state_action_value"].min().item()
            if usable[n] and (best_score is None or score > best_score):  # strict: ties keep the earlier
                best, best_score = n, score
        expected_index.append(best)
        expected.append(candidates[best])
    assert out["subgoal_candidate"].reshape(-1).tolist() == expected_index
    torch.testing.assert_close(out["subgoal"], torch.stack(expected))
    assert any(i != 0 for i in expected_index)  # the choice is not trivially the actor's
    if with_landmarks:
        assert not any(1 + K + i in expected_index for i in (2, 4))
    assert out["new_subgoal"].all()


def test_scores_and_selection_rules():
    """Ties go to the actor's subgoal (index 0), then to the lowest index; NaN and invalid rows score -inf."""
    inf = float("inf")
    scores = torch.tensor([[1.0, 1.0, 0.5], [0.0, 2.0, 2.0], [-inf, -inf, -inf], [-1.0, 3.0, -2.0]])
    assert CriticGuidedSubgoal.select(scores).tolist() == [0, 1, 0, 1]
    guide = CriticGuidedSubgoal(LOW, HIGH, num_candidates=2, critic=_toward([0.0, 0.0]))
    candidates = torch.tensor([[[1.0, 0.0], [float("nan"), 0.0], [0.5, 0.0]]])
    score = guide.scores(torch.zeros(1, OBS), torch.zeros(1, GOAL), candidates)
    assert score[0, 1] == -inf and guide.select(score).tolist() == [2]
    masked = guide.scores(
        torch.zeros(1, OBS), torch.zeros(1, GOAL), candidates, torch.tensor([True, True, False])
    )
    assert guide.select(masked).tolist() == [0]


def test_ties_issue_the_actors_own_subgoal():
    """A critic that values every subgoal alike: the actor's subgoal is issued, as without the feature."""
    flat = TensorDictModule(
        lambda s, g, sg: torch.zeros(*sg.shape[:-1], 1), in_keys=["observation", "desired_goal", "subgoal"],
        out_keys=["state_action_value"],
    )  # fmt: skip
    policy = _policy(
        critic_candidates=8, critic=flat, landmark_candidates=True, landmarks=lambda: (_landmarks()[0], None)
    )
    td = _td()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        out = policy(td.clone())
    assert (out["subgoal_candidate"] == 0).all()
    assert torch.equal(out["subgoal"], policy.actor(td.clone())["subgoal_proposal"])


# ----------------------------------------------------------------------------- a better candidate is issued
def test_a_candidate_the_critic_prefers_replaces_the_actors_subgoal():
    """The actor proposes away from the critic's best subgoal: the guided policy issues a candidate of higher
    value (a perturbation, or the landmark at the critic's best), the plain policy the actor's own."""
    target = torch.tensor([15.0, -2.0])
    td = _td(6)
    plain = _policy()
    guided = _policy(critic_candidates=32, candidate_noise=4.0, critic=_toward(target))
    landmarked = _policy(
        critic_candidates=4, critic=_toward(target), landmark_candidates=True,
        landmarks=lambda: (torch.stack([torch.tensor([0.0, 0.0]), target]), None),
    )  # fmt: skip
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        torch.manual_seed(0)
        own = plain(td.clone())["subgoal"]
        torch.manual_seed(0)
        out = guided(td.clone())
        torch.manual_seed(0)
        to_landmark = landmarked(td.clone())
    assert torch.equal(own, guided.actor(td.clone())["subgoal_proposal"])  # same weights: same actor
    assert ((own - target).norm(dim=-1) > 3.0).all()  # the actor's subgoals are far from the best
    assert (out["subgoal_candidate"] > 0).all()
    assert ((out["subgoal"] - target).norm(dim=-1) < (own - target).norm(dim=-1)).all()
    assert (to_landmark["subgoal_candidate"] == 1 + 4 + 1).all()
    assert torch.equal(to_landmark["subgoal"], target.expand(6, 2))


def test_the_issued_subgoal_lies_in_the_box():
    """Perturbations and landmarks outside the box are clipped before scoring; the exploration noise too."""
    corner = torch.tensor([40.0, -30.0])  # the critic's best lies outside the box
    policy = _policy(
        critic_candidates=16, candidate_noise=50.0, critic=_toward(corner), landmark_candidates=True,
        landmarks=lambda: (torch.tensor([[40.0, -30.0], [-100.0, 100.0]]), None),
    )  # fmt: skip
    for mode in (ExplorationType.DETERMINISTIC, ExplorationType.RANDOM):
        with set_exploration_type(mode):
            torch.manual_seed(4)
            out = policy(_td(64))
        sg = out["subgoal"]
        assert ((sg >= BOX_LOW) & (sg <= BOX_HIGH)).all()
    # deterministic: the clipped landmark, the box corner nearest to the critic's best
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        out = policy(_td(3))
    assert torch.equal(out["subgoal"], torch.tensor([20.0, -4.0]).expand(3, 2))


# ----------------------------------------------------------------------------- noise, cadence, determinism
def test_exploration_noise_is_added_to_the_chosen_subgoal():
    """Scoring comes before the noise: the noisy issued subgoal is the exploration module's perturbation of the
    deterministic choice, drawn after the candidates (the same generator stream)."""
    policy = _policy(critic_candidates=5, critic=_critic())
    td = _td()
    torch.manual_seed(7)
    with set_exploration_type(ExplorationType.RANDOM):
        noisy = policy(td.clone())
    torch.manual_seed(7)
    chosen = policy.selector(policy.actor(td.clone()))["subgoal_proposal"]
    torch.testing.assert_close(noisy["subgoal"], policy.exploration.perturb(chosen), rtol=0, atol=0)
    assert not torch.equal(noisy["subgoal"], chosen)


def test_scoring_happens_only_when_a_subgoal_is_due():
    """The c_h cadence is the scheduler's as before: between issues the held subgoal stays; eagerly nothing is
    drawn or scored in the steps where no env is issued a subgoal (the generator is left as it was)."""
    calls = []

    def counting(s, g, sg):
        calls.append(tuple(sg.shape[:-1]))
        return -(sg - 10.0).norm(dim=-1, keepdim=True)

    critic = TensorDictModule(
        counting, in_keys=["observation", "desired_goal", "subgoal"], out_keys=["state_action_value"]
    )
    policy = _policy(critic_candidates=4, critic=critic)
    td = _td(2)
    issued = []
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for step in range(7):
            state = torch.get_rng_state()
            td = policy(td)
            new = bool(td["new_subgoal"].all())
            assert new == (step % 3 == 0)
            if not new:
                assert torch.equal(torch.get_rng_state(), state)
                assert (td["subgoal_candidate"] == 0).all()
            issued.append(td["subgoal"].clone())
    assert len(calls) == 3 and calls[0] == (2, 5)  # one critic call per issue, on [B, 1 + K]
    assert torch.equal(issued[1], issued[0]) and torch.equal(issued[2], issued[0])
    # a batch where only some envs are due is scored whole, the others keep their subgoal
    td["subgoal_step"] = torch.tensor([[2], [0]])
    held = td["subgoal"].clone()
    td = policy(td)
    assert td["new_subgoal"].reshape(-1).tolist() == [True, False] and torch.equal(td["subgoal"][1], held[1])


def test_deterministic_given_the_generator_state():
    policy = _policy(critic_candidates=6, critic=_critic())
    outs = []
    for _ in range(2):
        torch.manual_seed(21)
        with set_exploration_type(ExplorationType.RANDOM):
            outs.append(policy(_td()))
    assert torch.equal(outs[0]["subgoal"], outs[1]["subgoal"])
    assert torch.equal(outs[0]["subgoal_candidate"], outs[1]["subgoal_candidate"])


# ----------------------------------------------------------------------------- off: the reference's policy
def _reference_policy(noise=2.0):
    """Today's HighLevelPolicy, built from its parts: actor -> noise -> scheduler."""
    torch.manual_seed(1)
    actor = HighLevelActor(OBS, GOAL, LOW, HIGH, num_cells=(16,), subgoal_key="subgoal_proposal")
    exploration = GaussianUniformExplorationModule(
        low=actor.low, high=actor.high, sigma=noise, relative_sigma=False, uniform_prob=0.0,
        action_key="subgoal_proposal",
    )  # fmt: skip
    return TensorDictSequential(actor, exploration, SubgoalScheduler(3, goal_dim=GOAL))


@pytest.mark.parametrize("candidate_noise", [None, 5.0])
def test_off_is_the_reference_policy_bit_for_bit(candidate_noise):
    """``critic_candidates=0`` (the default) without landmarks: no selector, the same modules and state, and the
    same outputs and random draws over steps as today's actor -> noise -> scheduler (a critic given or not)."""
    policy = _policy(critic_candidates=0, candidate_noise=candidate_noise, critic=_critic())
    reference = _reference_policy()
    assert policy.selector is None and len(policy.module) == 3
    assert list(policy.state_dict()) == list(reference.state_dict())
    for key, value in reference.state_dict().items():
        assert torch.equal(policy.state_dict()[key], value), key
    mine, theirs = _td(), _td()
    torch.manual_seed(5)
    with set_exploration_type(ExplorationType.RANDOM):
        for _ in range(7):
            mine = policy(mine)
    after = torch.get_rng_state()
    torch.manual_seed(5)
    with set_exploration_type(ExplorationType.RANDOM):
        for _ in range(7):
            theirs = reference(theirs)
    assert torch.equal(torch.get_rng_state(), after)  # the same random draws
    assert set(mine.keys(True, True)) == set(theirs.keys(True, True))
    for key in theirs.keys(True, True):
        assert torch.equal(mine[key], theirs[key]), key


def test_argument_checks_and_missing_inputs():
    with pytest.raises(
        ValueError, match=r"`critic_candidates` \(perturbed subgoal candidates .*\) must be an integer >= 0"
    ):
        _policy(critic_candidates=-1)
    with pytest.raises(ValueError, match="`candidate_noise` must be None or a number >= 0, got -1.0"):
        _policy(critic_candidates=2, candidate_noise=-1.0)
    with pytest.raises(ValueError, match="`landmark_candidates` must be True or False, got 'yes'"):
        _policy(landmark_candidates="yes")
    with pytest.raises(ValueError, match="needs candidates"):
        CriticGuidedSubgoal(LOW, HIGH, num_candidates=0)
    with pytest.raises(RuntimeError, match="set `critic`"):
        _policy(critic_candidates=2)(_td())
    with pytest.raises(RuntimeError, match="needs the `landmarks` callable"):
        _policy(landmark_candidates=True, critic=_critic())(_td())
    # the critic, its parameters and the landmarks are the learner's and the planner's: not the policy's state
    policy = _policy(critic_candidates=2, critic=_critic())
    assert list(policy.selector.state_dict()) == ["low", "high", "sigma"]
    assert len(list(policy.parameters())) == len(list(_policy().parameters()))
    # candidate_noise=None: the subgoal noise's scale
    torch.testing.assert_close(policy.selector.sigma, torch.full((GOAL,), 2.0))


def test_critic_params_and_a_stacked_single_member_critic():
    """``critic_params`` replaces the critic's own parameters (the loss's, as the recipe wires it); a single-member
    critic's stacked twin is evaluated member by member (its smaller value scores)."""
    from torchrl_dhrl.objectives import HighLevelLoss

    policy = _policy(critic_candidates=6)
    loss = HighLevelLoss(policy.actor, _critic(3), action_l2=0.01)
    policy.selector.critic = loss.critic_network
    policy.selector.critic_params = loss.critic_network_params
    direct = _policy(critic_candidates=6, critic=_critic(3))
    out = {}
    for name, p in (("loss", policy), ("direct", direct)):
        torch.manual_seed(8)
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            out[name] = p(_td(16))
    assert torch.equal(out["loss"]["subgoal_candidate"], out["direct"]["subgoal_candidate"])
    with torch.no_grad():  # the loss's parameters move (an update): the policy's choice follows them
        for value in loss.critic_network_params.values(True, True):
            if isinstance(value, torch.nn.Parameter):
                value.mul_(-1.0)
    torch.manual_seed(8)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        flipped = policy(_td(16))
    assert not torch.equal(flipped["subgoal_candidate"], out["direct"]["subgoal_candidate"])

    from torchrl.modules import MLP, ValueOperator

    single = ValueOperator(
        MLP(in_features=OBS + 2 * GOAL, out_features=1, num_cells=[8]),
        in_keys=["observation", "desired_goal", "subgoal"],
        out_keys=["state_action_value"],
    )
    stacked_loss = HighLevelLoss(policy.actor, single, action_spec=None, action_l2=0.01)
    policy.selector.critic = stacked_loss.critic_network
    policy.selector.critic_params = stacked_loss.critic_network_params
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        out = policy(_td())
    assert out["subgoal_candidate"].shape == (4, 1)


# ----------------------------------------------------------------------------- torch.compile
def test_compiled_guided_policy_is_one_graph_and_agrees_with_eager():
    """``torch.compile(fullgraph=True)`` (Dynamo's graph run as traced): no graph break, no host read, and the same
    issued subgoals and choices as eager at every step; traced, every call scores (static shapes), so both draw
    from a generator reset before each call."""
    goals, valid = _landmarks()
    policy = _policy(
        critic_candidates=4, critic=_critic(), landmark_candidates=True, landmarks=lambda: (goals, valid)
    )
    graphs = []

    def traced_as_is(gm, example_inputs):
        graphs.append(gm)
        return gm.forward

    torch._dynamo.reset()
    try:
        compiled = torch.compile(policy, backend=traced_as_is, fullgraph=True)
        eager_td, compiled_td = _td(3), _td(3)
        with set_exploration_type(ExplorationType.RANDOM):
            for step in range(7):
                torch.manual_seed(100 + step)
                eager_td = policy(eager_td)
                torch.manual_seed(100 + step)
                compiled_td = compiled(compiled_td)
                for key in ("subgoal", "new_subgoal", "subgoal_step"):
                    torch.testing.assert_close(compiled_td[key], eager_td[key], msg=f"{key} at step {step}")
                if step % 3 == 0:
                    assert torch.equal(compiled_td["subgoal_candidate"], eager_td["subgoal_candidate"])
    finally:
        torch._dynamo.reset()
    assert graphs


@pytest.mark.slow
def test_inductor_compiled_guided_policy_agrees_with_eager():
    """The same under inductor's kernels (its random ops falling back to eager's, as the collector test does)."""
    from torch._inductor import config as inductor_config

    goals, valid = _landmarks()
    policy = _policy(
        critic_candidates=4, critic=_critic(), landmark_candidates=True, landmarks=lambda: (goals, valid)
    )
    torch._dynamo.reset()
    try:
        compiled = torch.compile(policy, fullgraph=True)
        eager_td, compiled_td = _td(3), _td(3)
        with inductor_config.patch(fallback_random=True), set_exploration_type(ExplorationType.RANDOM):
            for step in range(7):
                torch.manual_seed(200 + step)
                eager_td = policy(eager_td)
                torch.manual_seed(200 + step)
                compiled_td = compiled(compiled_td)
                torch.testing.assert_close(compiled_td["subgoal"], eager_td["subgoal"], msg=f"step {step}")
                assert torch.equal(compiled_td["subgoal_step"], eager_td["subgoal_step"])
                if step % 3 == 0:
                    assert torch.equal(compiled_td["subgoal_candidate"], eager_td["subgoal_candidate"])
    finally:
        torch._dynamo.reset()


@pytest.mark.slow
def test_recipe_agent_with_guided_subgoals_has_no_graph_break():
    """The recipe's acting policy (``make_agent(capturable_planner=True)``) with critic-guided subgoals and the
    landmarks of its reserved fixed-size graph (``max_landmarks`` rows, a valid mask): one graph."""
    from torchrl_dhrl.factory import make_agent, make_environment

    env = make_environment("PointMaze", num_envs=2, seed=0, max_episode_steps=30)
    agent = make_agent(
        env,
        goal_indices=[0, 1],
        high_policy={"subgoal_low": [-2.0, -2.0], "subgoal_high": [10.0, 10.0], "interval": 5, "num_cells": (16,),
                     "critic_candidates": 4, "landmark_candidates": True},
        high_critic={"num_cells": (16,)}, low_actor={"num_cells": (16,), "relative_goal": False},
        low_critic={"num_cells": (16,)}, capturable_planner=True,
    )  # fmt: skip
    selector = agent.high_policy.selector
    assert selector.critic is agent.high_loss.critic_network
    assert selector.critic_params is agent.high_loss.critic_network_params
    goals, valid = selector.landmarks()
    assert (
        goals.shape == (agent.planner.graph.max_landmarks, 2) and not valid.any()
    )  # reserved, no landmark yet
    points = torch.rand(
        60, env.observation_spec["observation"].shape[-1], generator=torch.Generator().manual_seed(0)
    )
    agent.planner.build(points * 12 - 2, (points * 12 - 2)[:, :2])
    assert int(selector.landmarks()[1].sum()) == agent.planner.graph.num_landmarks > 0
    env = make_environment("PointMaze", num_envs=2, seed=0, max_episode_steps=30, agent=agent)
    td = env.reset()
    for _ in range(2):
        td = env.step(agent.policy(td))["next"]
    torch._dynamo.reset()
    try:
        explanation = torch._dynamo.explain(agent.policy)(td.clone())
    finally:
        torch._dynamo.reset()
    assert explanation.graph_break_count == 0, explanation.break_reasons


# ----------------------------------------------------------------------------- the recipe's keys
def test_recipe_keys_reach_the_policy_and_bad_values_are_refused():
    from _recipe import recipe_config
    from dhrl_utils import build_agent

    from torchrl_dhrl.recipe import ConfigError, component_arguments, validate_config

    small = ("env=PointMaze", "preset=smoke", "device=cpu")
    default = recipe_config(*small)
    assert (default["high"]["critic_candidates"], default["high"]["candidate_noise"]) == (0, None)
    assert default["high"]["landmark_candidates"] is False
    assert build_agent(default, torch.device("cpu")).high_policy.selector is None  # the reference's policy
    cfg = recipe_config(
        *small, "high.critic_candidates=5", "high.candidate_noise=1.5", "high.landmark_candidates=true"
    )
    validate_config(cfg)
    args = component_arguments(cfg)["high_policy"]
    assert (args["critic_candidates"], args["candidate_noise"], args["landmark_candidates"]) == (5, 1.5, True)
    agent = build_agent(cfg, torch.device("cpu"))
    selector = agent.high_policy.selector
    assert selector.num_candidates == 5 and selector.landmark_candidates
    torch.testing.assert_close(selector.sigma, torch.full((2,), 1.5))
    assert selector.critic_params is agent.high_loss.critic_network_params
    assert selector.landmarks() is None  # no graph yet: the actor's subgoal and its perturbations only
    refused = {
        "high.critic_candidates=-1": "`high.critic_candidates` (perturbed subgoal candidates scored by the high-level "
        "critic) must be an integer >= 0, got -1.",
        "high.critic_candidates=2.5": "`high.critic_candidates` (perturbed subgoal candidates scored by the "
        "high-level critic) must be an integer >= 0, got 2.5.",
        "high.candidate_noise=-1": "`high.candidate_noise` must be None or a number >= 0, got -1.",
        "high.landmark_candidates=yes": "`high.landmark_candidates` must be True or False, got 'yes'.",
    }
    for override, message in refused.items():
        with pytest.raises(ConfigError) as info:
            validate_config(recipe_config(*small, override))
        assert str(info.value) == message and "\n" not in str(info.value)
