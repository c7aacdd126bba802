"""The goal-conditioned actors of torchrl_dhrl.modules: bounds, relative and absolute goal inputs, errors."""

import pytest
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.data import Bounded

from torchrl_dhrl.modules import GoalConditionedActorNet, HighLevelActor, LowLevelActor

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
    actor = LowLevelActor(OBS, GOAL, action_max=30.0, action_dim=8, num_cells=(16, 16), goal_indices=(0, 1))
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
    actor = LowLevelActor(OBS, GOAL, spec, goal_key="subgoal", num_cells=(16,), goal_indices=(0, 1))
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
    actor = HighLevelActor(
        OBS, GOAL, [-4.0, -4.0], [20.0, 52.0], relative_goal=True, num_cells=(16,), goal_indices=(0, 1)
    )
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
        LowLevelActor(OBS, GOAL, goal_indices=(0, 1))
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
