"""Actors, stacked ensembles and exploration noise of torchrl_dhrl.modules."""

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential
from torch import nn
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_dhrl.modules import (
    EnsembleLinear,
    EnsembleMLP,
    GaussianUniformExplorationModule,
    GoalConditionedActorNet,
    HighLevelActor,
    LowLevelActor,
    make_low_level_policy,
)

OBS, GOAL = 7, 2


def _td(batch, obs_dim=OBS, goal_key="waypoint"):
    return TensorDict(
        {"observation": torch.randn(*batch, obs_dim) * 5, goal_key: torch.randn(*batch, GOAL) * 5}, batch
    )


def _manual_mlp(mlp, x):
    """Re-evaluates a torchrl MLP (Linear/ReLU stack) layer by layer with plain matmuls."""
    for layer in mlp:
        x = x @ layer.weight.T + layer.bias if isinstance(layer, nn.Linear) else torch.relu(x)
    return x


@pytest.mark.parametrize("batch", [(), (5,), (3, 4)])
def test_low_level_actor_bounds_and_batch_shapes(batch):
    torch.manual_seed(0)
    actor = LowLevelActor(OBS, GOAL, action_max=30.0, action_dim=8, num_cells=(16, 16))
    # Push the pre-tanh activations far out so the output saturates at the bounds.
    with torch.no_grad():
        actor.module.mlp[-1].weight.mul_(1000)
    action = actor(_td(batch))["action"]
    assert action.shape == (*batch, 8)
    assert (action.abs() <= 30.0).all()
    assert action.abs().max() > 29.0  # saturation reaches the bound: the scaling is action_max


def test_low_level_actor_relative_input_matches_manual():
    torch.manual_seed(1)
    actor = LowLevelActor(OBS, GOAL, action_max=2.0, action_dim=3, goal_indices=(3, 5), num_cells=(16,))
    td = _td((6,))
    out = actor(td)["action"]
    obs, wp = td["observation"], td["waypoint"]
    x = torch.cat([obs, wp - obs[:, [3, 5]]], -1)
    expected = 2.0 * torch.tanh(_manual_mlp(actor.module.mlp, x))
    torch.testing.assert_close(out, expected)
    # Translating the observation's achieved goal and the waypoint together changes only the
    # absolute part of the input, not the relative goal.
    x_abs = torch.cat([obs, wp], -1)
    assert not torch.allclose(out, 2.0 * torch.tanh(_manual_mlp(actor.module.mlp, x_abs)))


def test_low_level_actor_absolute_input_matches_manual():
    torch.manual_seed(2)
    actor = LowLevelActor(OBS, GOAL, action_max=1.0, action_dim=3, relative_goal=False, num_cells=(16,))
    td = _td((6,))
    expected = torch.tanh(_manual_mlp(actor.module.mlp, torch.cat([td["observation"], td["waypoint"]], -1)))
    torch.testing.assert_close(actor(td)["action"], expected)


def test_low_level_actor_bounded_spec_asymmetric_box_and_goal_key():
    torch.manual_seed(3)
    spec = Bounded(torch.tensor([-1.0, 0.0]), torch.tensor([3.0, 0.5]), shape=(2,))
    actor = LowLevelActor(OBS, GOAL, spec, goal_key="subgoal", num_cells=(16,))
    td = _td((64,), goal_key="subgoal")
    with torch.no_grad():
        actor.module.mlp[-1].weight.mul_(1000)
    a = actor(td)["action"]
    assert (a >= spec.space.low).all() and (a <= spec.space.high).all()
    # loc + scale * tanh: pre-activation 0 maps to the box centre.
    net = actor.module
    torch.testing.assert_close(net.loc, torch.tensor([1.0, 0.25]))
    torch.testing.assert_close(net.scale, torch.tensor([2.0, 0.25]))
    assert actor.in_keys == ["observation", "subgoal"]


def test_high_level_actor_box_and_relative_option():
    torch.manual_seed(4)
    actor = HighLevelActor(OBS, GOAL, [-4.0, -4.0], [20.0, 52.0], relative_goal=True, num_cells=(16,))
    td = _td((32,), goal_key="desired_goal")
    with torch.no_grad():
        actor.module.mlp[-1].weight.mul_(1000)
    sg = actor(td)["subgoal"]
    assert (sg[:, 0] >= -4).all() and (sg[:, 0] <= 20).all() and (sg[:, 1] <= 52).all()
    x = torch.cat([td["observation"], td["desired_goal"] - td["observation"][:, :2]], -1)
    expected = torch.tensor([8.0, 24.0]) + torch.tensor([12.0, 28.0]) * torch.tanh(
        _manual_mlp(actor.module.mlp, x)
    )
    torch.testing.assert_close(sg, expected)


def test_actor_input_errors():
    with pytest.raises(ValueError, match="exactly one"):
        LowLevelActor(OBS, GOAL)
    with pytest.raises(ValueError, match="goal_indices"):
        LowLevelActor(OBS, GOAL, action_max=1.0, action_dim=2, goal_indices=(0,))
    with pytest.raises(ValueError, match="exceed"):
        LowLevelActor(OBS, GOAL, action_max=1.0, action_dim=2, goal_indices=(0, OBS))
    with pytest.raises(ValueError, match="high > low"):
        HighLevelActor(OBS, GOAL, [1.0, 1.0], [0.0, 2.0])
    net = GoalConditionedActorNet(
        OBS, GOAL, -torch.ones(2), torch.ones(2), goal_indices=(0, 1), num_cells=(8,)
    )
    with pytest.raises(ValueError, match="last dimension 2"):
        net(torch.randn(3, OBS), torch.randn(3, 3))


def test_ensemble_linear_matches_per_member_linear():
    torch.manual_seed(5)
    layer = EnsembleLinear(6, 4, ensemble_size=3)
    x = torch.randn(10, 6)
    out = layer(x)
    for k in range(3):
        torch.testing.assert_close(out[k], x @ layer.weight[k] + layer.bias[k, 0])
    xs = torch.randn(3, 10, 6)
    out = layer(xs)
    for k in range(3):
        torch.testing.assert_close(out[k], xs[k] @ layer.weight[k] + layer.bias[k, 0])


def test_ensemble_mlp_members_are_independent_mlps():
    torch.manual_seed(6)
    mlp = EnsembleMLP(5, 1, ensemble_size=2, num_cells=(8, 8))
    x = torch.randn(4, 3, 5)
    out = mlp(x)
    assert out.shape == (2, 4, 3, 1)
    for k in range(2):
        h = x
        for i, layer in enumerate(mlp.layers):
            h = h @ layer.weight[k] + layer.bias[k, 0]
            if i < len(mlp.layers) - 1:
                h = torch.relu(h)
        torch.testing.assert_close(out[k], h)
    # Members differ (independent initialisation).
    assert not torch.allclose(out[0], out[1])


def _constant_action_td(n, value, dim):
    return TensorDict({"action": torch.full((n, dim), value)}, [n])


def test_exploration_statistics_match_reference_noise():
    torch.manual_seed(7)
    amax, dim, n = 30.0, 8, 20000
    noise = GaussianUniformExplorationModule(low=-amax, high=amax, sigma=0.1, uniform_prob=0.2)
    with set_exploration_type(ExplorationType.RANDOM):
        a = noise(_constant_action_td(n, 0.0, dim))["action"]
    assert (a.abs() <= amax).all()
    # A Gaussian draw (std 3) stays within 0.45 * amax = 4.5 std in every dim; a uniform one
    # leaves it with probability 1 - 0.45^8 ~ 0.998.
    replaced = (a.abs() > 0.45 * amax).any(-1)
    frac = replaced.float().mean().item()
    assert abs(frac - 0.2 * (1 - 0.45**dim)) < 0.015
    gaussian = a[~replaced]
    assert abs(gaussian.std().item() - 0.1 * amax) < 0.03 * 0.1 * amax
    assert abs(gaussian.mean().item()) < 0.05
    # Replaced actions are uniform on the box: mean 0, std amax / sqrt(3).
    uniform = a[replaced]
    assert abs(uniform.std().item() - amax / 3**0.5) < 0.05 * amax / 3**0.5


def test_exploration_whole_action_is_replaced():
    torch.manual_seed(8)
    noise = GaussianUniformExplorationModule(low=-1.0, high=1.0, sigma=0.0, uniform_prob=0.5)
    a = noise(_constant_action_td(4000, 0.25, 3))["action"]
    kept = (a == 0.25).all(-1)
    replaced = (a != 0.25).all(-1)
    # Every row is either untouched (sigma 0) or entirely replaced: never partially.
    assert bool((kept | replaced).all())
    assert abs(replaced.float().mean().item() - 0.5) < 0.04


@pytest.mark.parametrize("mode", [ExplorationType.DETERMINISTIC, ExplorationType.MODE, ExplorationType.MEAN])
def test_exploration_off_outside_random(mode):
    torch.manual_seed(9)
    actor = LowLevelActor(OBS, GOAL, action_max=30.0, action_dim=4, num_cells=(16,))
    policy = make_low_level_policy(actor)
    td = _td((50,))
    clean = actor(td.clone())["action"]
    with set_exploration_type(mode):
        torch.testing.assert_close(policy(td.clone())["action"], clean)
    with set_exploration_type(ExplorationType.RANDOM):
        assert not torch.allclose(policy(td.clone())["action"], clean)


def test_exploration_clips_to_box_and_relative_sigma():
    torch.manual_seed(10)
    spec = Bounded(torch.tensor([-1.0, 0.0]), torch.tensor([3.0, 10.0]), shape=(2,))
    noise = GaussianUniformExplorationModule(spec, sigma=0.5, uniform_prob=0.0)
    torch.testing.assert_close(noise.sigma, torch.tensor([1.0, 2.5]))  # 0.5 * half widths (2, 5)
    a = noise(TensorDict({"action": torch.tensor([[3.0, 10.0]]).expand(1000, 2).clone()}, [1000]))["action"]
    assert (a <= spec.space.high).all() and (a >= spec.space.low).all()
    assert (a == spec.space.high).float().mean() > 0.4  # about half the draws clip at the bound


def test_exploration_absolute_sigma_and_errors():
    noise = GaussianUniformExplorationModule(
        low=[-4.0, -4.0], high=[20.0, 52.0], sigma=2.0, relative_sigma=False
    )
    torch.testing.assert_close(noise.sigma, torch.tensor([2.0, 2.0]))
    with pytest.raises(ValueError, match="uniform_prob"):
        GaussianUniformExplorationModule(low=-1.0, high=1.0, uniform_prob=1.5)
    with pytest.raises(ValueError, match="sigma"):
        GaussianUniformExplorationModule(low=-1.0, high=1.0, sigma=-0.1)
    with pytest.raises(ValueError, match="last dimension"):
        noise(TensorDict({"action": torch.zeros(3, 3)}, [3]))


def test_exploration_in_sequential_with_nested_key():
    torch.manual_seed(11)
    actor = LowLevelActor(
        OBS, GOAL, action_max=1.0, action_dim=2, action_key=("agent", "action"), num_cells=(8,)
    )
    policy = TensorDictSequential(
        actor, GaussianUniformExplorationModule(actor.spec, action_key=("agent", "action"))
    )
    out = policy(_td((3, 2)))
    assert out["agent", "action"].shape == (3, 2, 2)


def test_exploration_uniform_prob_changes_without_recompiling():
    """``uniform_prob`` is read from a buffer by a compiled module: the recipe's phase change (1.0 in the
    warm-up, then 0.2 or 0.0) takes effect in the compiled graph and compiles nothing new."""
    from torch._dynamo.testing import CompileCounter

    noise = GaussianUniformExplorationModule(low=-1.0, high=1.0, sigma=0.0, uniform_prob=1.0)
    counter = CompileCounter()
    torch._dynamo.reset()
    compiled = torch.compile(noise, backend=counter, fullgraph=True)
    try:
        torch.manual_seed(11)
        for prob in (1.0, 0.2, 0.0, 0.5):
            noise.uniform_prob = prob
            assert noise.uniform_prob == prob and noise._uniform_prob.item() == pytest.approx(prob)
            a = compiled(_constant_action_td(4000, 0.25, 3))["action"]
            replaced = (a != 0.25).all(-1).float().mean().item()
            assert abs(replaced - prob) < 0.04, (prob, replaced)
        assert counter.frame_count == 1
    finally:
        torch._dynamo.reset()
    with pytest.raises(ValueError, match="uniform_prob"):
        noise.uniform_prob = -0.1
    assert noise.uniform_prob == 0.5  # the bad value was not applied
    assert "_uniform_prob" not in noise.state_dict()  # the recipe sets it per phase; checkpoints unchanged
