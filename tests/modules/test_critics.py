"""Twin critics, the distance parameterisation and the learned distance (Eq. (1))."""

import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from torchrl_dhrl.modules import (
    GoalConditionedCritic,
    LowLevelActor,
    distance_to_q,
    make_low_level_policy,
    q_to_distance,
)
from torchrl_dhrl.planner import GoalDistance

OBS, GOAL, ACT = 6, 2, 3
GAMMA = 0.99


def _actor(seed=0, **kw):
    torch.manual_seed(seed)
    kw.setdefault("goal_indices", (0, 1))
    return LowLevelActor(OBS, GOAL, action_max=2.0, action_dim=ACT, num_cells=(32, 32), **kw)


def _critic(seed=1, **kw):
    torch.manual_seed(seed)
    kw.setdefault("num_cells", (32, 32))
    kw.setdefault("relative_goal", True)
    kw.setdefault("goal_indices", (0, 1))
    return GoalConditionedCritic(OBS, GOAL, action_max=2.0, action_dim=ACT, gamma=GAMMA, **kw)


def _member_mlp(critic, k, x):
    """Evaluates member ``k`` of the stacked ensemble with plain matmuls."""
    layers = critic.module.ensemble.layers
    for i, layer in enumerate(layers):
        x = x @ layer.weight[k] + layer.bias[k, 0]
        if i < len(layers) - 1:
            x = torch.relu(x)
    return x.squeeze(-1)


def _td(n):
    return TensorDict(
        {
            "observation": torch.randn(n, OBS) * 3,
            "waypoint": torch.randn(n, GOAL) * 3,
            "action": torch.rand(n, ACT) * 4 - 2,
        },
        [n],
    )


@pytest.mark.parametrize("relative", [True, False])
@pytest.mark.parametrize("output", ["linear", "softplus"])
def test_critic_matches_manual_features_and_distance_parameterisation(relative, output):
    critic = _critic(relative_goal=relative, goal_indices=(2, 4), distance_output=output)
    assert critic.distance_output == output
    td = _td(9)
    q = critic(td)["state_action_value"]
    assert q.shape == (9, 2)
    obs, g, a = td["observation"], td["waypoint"], td["action"]
    goal_in = g - obs[:, [2, 4]] if relative else g
    x = torch.cat([obs, goal_in, a / 2.0], -1)  # the critic sees action / action_max
    for k in range(2):
        raw = _member_mlp(critic, k, x)
        d = raw if output == "linear" else torch.nn.functional.softplus(raw)
        torch.testing.assert_close(q[:, k], -(1 - GAMMA**d) / (1 - GAMMA))
    assert not torch.allclose(q[:, 0], q[:, 1])


def test_distance_parameterisation_range_and_plain_q_option():
    critic = _critic(distance_output="softplus")
    with torch.no_grad():
        for layer in critic.module.ensemble.layers:
            layer.weight.mul_(30)  # huge raw outputs of both signs
    q = critic(_td(2000))["state_action_value"]
    assert (q <= 0).all() and (q >= -1 / (1 - GAMMA)).all()
    assert q.min() < -50 and q.max() > -1  # the range is actually used at both ends
    # the reference's linear output: a negative raw distance is a positive Q (the targets push it back)
    linear = _critic()
    assert linear.distance_output == "linear"
    raw = torch.tensor([-2.0, 0.0, 5.0, 400.0])
    torch.testing.assert_close(linear.module.q_from_raw(raw), distance_to_q(raw, GAMMA))
    assert linear.module.q_from_raw(raw)[0] > 0 and linear.module.q_from_raw(raw)[1] == 0
    with pytest.raises(ValueError, match="distance_output"):
        _critic(distance_output="relu")
    plain = _critic(parameterization="q")
    td = _td(5)
    x = torch.cat([td["observation"], td["waypoint"] - td["observation"][:, :2], td["action"] / 2], -1)
    torch.testing.assert_close(plain(td)["state_action_value"][:, 1], _member_mlp(plain, 1, x))


def test_high_level_critic_sees_subgoal_scaled_to_unit_box():
    torch.manual_seed(2)
    critic = GoalConditionedCritic(
        OBS, GOAL, action_low=[-4.0, -4.0], action_high=[20.0, 52.0], relative_goal=False, num_cells=(8,)
    )
    obs, g = torch.randn(4, OBS), torch.randn(4, GOAL)
    corners = torch.tensor([[-4.0, -4.0], [20.0, 52.0], [8.0, 24.0], [20.0, -4.0]])
    x = critic.module.features(obs, g, corners)
    torch.testing.assert_close(x[:, -2:], torch.tensor([[-1.0, -1.0], [1.0, 1.0], [0.0, 0.0], [1.0, -1.0]]))


def test_q_distance_round_trip_and_guards():
    d = torch.tensor([0.0, 0.5, 1.0, 7.0, 30.0, 300.0])
    torch.testing.assert_close(q_to_distance(distance_to_q(d, GAMMA), GAMMA), d, rtol=1e-4, atol=1e-3)
    # Eq. (1) against numpy in float64.
    q = torch.tensor([-0.5, -10.0, -63.0, -99.0])
    expected = np.log(1 + (1 - GAMMA) * q.double().numpy()) / np.log(GAMMA)
    np.testing.assert_allclose(q_to_distance(q, GAMMA).numpy(), expected, rtol=1e-4)
    # (1 - gamma) Q <= -1 would be log(<= 0): finite and large instead; positive Q gives 0.
    guarded = q_to_distance(torch.tensor([-100.0, -1e4, -math.inf, 5.0]), GAMMA)
    assert torch.isfinite(guarded).all()
    assert (guarded[:3] > 1000).all() and guarded[3] == 0
    assert q_to_distance(torch.tensor([-1e4]), GAMMA, max_distance=50.0).item() == 50.0
    with pytest.raises(ValueError, match="gamma"):
        q_to_distance(q, 1.0)


@pytest.mark.parametrize("twin", ["optimistic", "pessimistic"])
def test_goal_distance_equals_manual_eq1_with_graph_critics(twin):
    actor, critic = _actor(), _critic()
    distance = GoalDistance(actor, critic, twin=twin)
    states, goals = torch.randn(20, OBS) * 3, torch.randn(20, GOAL) * 3
    got = distance(states, goals)
    with torch.no_grad():
        td = TensorDict({"observation": states, "waypoint": goals}, [20])
        td = actor(td)  # the actor's own deterministic action
        q = critic(td)["state_action_value"].double().numpy()
    # each member's Eq. (1) distance separately, then the reference's min(dist1, dist2) or the max
    dist = np.maximum(np.log(1 + (1 - GAMMA) * q) / np.log(GAMMA), 0.0)
    expected = dist.min(-1) if twin == "optimistic" else dist.max(-1)
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-4, atol=1e-4)
    assert not got.requires_grad


@pytest.mark.parametrize("output", ["linear", "softplus"])
def test_goal_distance_twin_choice_on_a_hand_made_twin(output):
    """A twin whose members output fixed, different distances: the optimistic choice is the smaller."""
    actor, critic = _actor(), _critic(distance_output=output)
    with torch.no_grad():  # zero hidden->output weights: each member outputs (softplus of) its bias
        out = critic.module.ensemble.layers[-1]
        out.weight.zero_()
        out.bias.copy_(torch.tensor([3.0, 12.0]).reshape(out.bias.shape))
    states, goals = torch.randn(6, OBS), torch.randn(6, GOAL)
    soft = torch.tensor([3.0, 12.0])
    soft = soft if output == "linear" else torch.nn.functional.softplus(soft)
    optimistic = GoalDistance(actor, critic)(states, goals)
    pessimistic = GoalDistance(actor, critic, twin="pessimistic")(states, goals)
    torch.testing.assert_close(optimistic, soft[0].expand(6), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(pessimistic, soft[1].expand(6), rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match="twin"):
        GoalDistance(actor, critic, twin="mean")


def test_goal_distance_broadcasts_n_by_m_and_chunking_is_identical():
    actor, critic = _actor(), _critic()
    states, goals = torch.randn(13, OBS), torch.randn(11, GOAL)
    full = GoalDistance(actor, critic)(states[:, None], goals[None])
    assert full.shape == (13, 11)
    loop = torch.stack([GoalDistance(actor, critic)(s.expand(11, OBS), goals) for s in states])
    torch.testing.assert_close(full, loop, rtol=1e-6, atol=1e-6)
    chunked = GoalDistance(actor, critic, chunk_size=7)(states[:, None], goals[None])
    torch.testing.assert_close(chunked, full, rtol=1e-6, atol=1e-6)
    # Leading batch dims of any rank, and a single pair.
    batched = GoalDistance(actor, critic, chunk_size=5)(
        states[:12].reshape(3, 4, OBS)[:, :, None], goals[None, None]
    )
    assert batched.shape == (3, 4, 11)
    torch.testing.assert_close(batched.reshape(12, 11), full[:12], rtol=1e-6, atol=1e-6)
    assert GoalDistance(actor, critic)(states[0], goals[0]).shape == ()


def test_goal_distance_input_errors():
    actor, critic = _actor(), _critic()
    distance = GoalDistance(actor, critic)
    with pytest.raises(ValueError, match="last dimension"):
        distance(torch.randn(3, OBS + 1), torch.randn(3, GOAL))
    with pytest.raises(ValueError, match="broadcast"):
        distance(torch.randn(3, OBS), torch.randn(4, GOAL))
    with pytest.raises(TypeError, match="GoalConditionedCritic"):
        GoalDistance(actor, actor)
    with pytest.raises(ValueError, match="chunk_size"):
        GoalDistance(actor, critic, chunk_size=0)
    with pytest.raises(ValueError, match="exactly 2 keys"):
        GoalDistance(
            TensorDictModule(torch.nn.Identity(), in_keys=["observation"], out_keys=["action"]), critic
        )


def test_goal_distance_ignores_exploration_mode():
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    actor, critic = _actor(), _critic()
    distance = GoalDistance(actor, critic)
    states, goals = torch.randn(6, OBS), torch.randn(6, GOAL)
    with set_exploration_type(ExplorationType.RANDOM):
        a = distance(states, goals)
        # An actor wrapped with its exploration noise gives the noise-free distance too.
        b = GoalDistance(make_low_level_policy(actor), critic)(states, goals)
    torch.testing.assert_close(a, distance(states, goals))
    torch.testing.assert_close(b, a)


def test_goal_distance_follows_parameter_dtype_and_returns_on_input_device():
    actor, critic = _actor(), _critic()
    states, goals = torch.randn(5, OBS), torch.randn(5, GOAL)
    ref = GoalDistance(actor, critic)(states, goals)
    # float64 inputs are cast to the parameters' dtype.
    torch.testing.assert_close(GoalDistance(actor, critic)(states.double(), goals.double()), ref)
    actor.double()
    critic.double()
    out = GoalDistance(actor, critic)(states, goals)
    assert out.dtype == torch.float64 and out.device == states.device
    torch.testing.assert_close(out.float(), ref, rtol=1e-4, atol=1e-4)


def test_goal_distance_clamps_a_negative_linear_distance_at_zero():
    """The reference's queries: ``clamp(min(d1, d2), min=0)`` of the raw distances."""
    actor, critic = _actor(), _critic()
    with torch.no_grad():
        out = critic.module.ensemble.layers[-1]
        out.weight.zero_()
        out.bias.copy_(torch.tensor([-4.0, 7.0]).reshape(out.bias.shape))
    states, goals = torch.randn(5, OBS), torch.randn(5, GOAL)
    assert (GoalDistance(actor, critic)(states, goals) == 0).all()
    torch.testing.assert_close(
        GoalDistance(actor, critic, twin="pessimistic")(states, goals),
        torch.full((5,), 7.0),
        rtol=1e-4,
        atol=1e-4,
    )
