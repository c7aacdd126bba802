"""HighLevelLoss: TD3 targets on subgoals scaled from the box, clamps, the actor term, target nets."""

import copy
import warnings

import pytest
import torch
from tensordict import TensorDict
from torchrl.modules import MLP, ValueOperator
from torchrl.objectives import SoftUpdate

from torchrl_dhrl.modules import GoalConditionedCritic, HighLevelPolicy
from torchrl_dhrl.objectives import HighLevelLoss, make_optimizers

OBS, GOAL, GAMMA = 5, 2, 0.99
LOW, HIGH = torch.tensor([-4.0, -4.0]), torch.tensor([20.0, 52.0])


@pytest.fixture(autouse=True)
def _no_target_warning():
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="No target network updater")
        yield


def _nets(seed=0):
    torch.manual_seed(seed)
    policy = HighLevelPolicy(OBS, GOAL, LOW, HIGH, interval=10, num_cells=(32, 32))
    critic = GoalConditionedCritic(
        OBS,
        GOAL,
        action_low=LOW,
        action_high=HIGH,
        relative_goal=False,
        goal_key="desired_goal",
        action_key="subgoal",
        num_cells=(32, 32),
        gamma=GAMMA,
    )
    return policy.actor, critic


def _batch(n=48, reward=None, seed=1):
    g = torch.Generator().manual_seed(seed)
    return TensorDict(
        {
            "observation": torch.randn(n, OBS, generator=g) * 5,
            "desired_goal": torch.rand(n, GOAL, generator=g) * 20,
            "subgoal": LOW + (HIGH - LOW) * torch.rand(n, GOAL, generator=g),
            ("next", "observation"): torch.randn(n, OBS, generator=g) * 5,
            ("next", "reward"): -torch.ones(n, 1) if reward is None else reward,
        },
        [n],
    )


def test_value_loss_matches_manual_with_clamp():
    actor, critic = _nets()
    reward = torch.cat([torch.full((12, 1), 3.0), torch.full((12, 1), -200.0), -1.3 * torch.ones(24, 1)])
    data = _batch(reward=reward)
    loss = HighLevelLoss(actor, critic, target_noise_std=0.0, action_l2=0.01)
    out = loss(data)
    with torch.no_grad():
        nxt = actor(
            TensorDict(
                {"observation": data["next", "observation"], "desired_goal": data["desired_goal"]}, [48]
            )
        )
        nxt["subgoal"] = nxt["subgoal_proposal"]
        bootstrap = critic(nxt)["state_action_value"].min(-1).values
        y = (reward.squeeze(-1) + GAMMA * bootstrap).clamp(-80.0, 0.0)
    q = critic(data)["state_action_value"]
    torch.testing.assert_close(out["loss_qvalue"], ((q - y[:, None]) ** 2).mean(0).sum())
    assert y.max() == 0 and y.min() == -80
    torch.testing.assert_close(out["target"], y.mean())


def test_actor_loss_uses_scaled_subgoal_penalty_and_forward_computes_it():
    actor, critic = _nets()
    loss = HighLevelLoss(actor, critic, action_l2=0.3)
    data = _batch()
    # the delay is LossUpdater's (tests/training/test_updates.py): forward trains the actor on every call
    flags = [bool(loss(data)["actor_updated"]) for _ in range(3)]
    assert flags == [True, True, True]
    assert not bool(loss.loss_terms(data, update_actor=False)["actor_updated"])
    loss_actor, meta = loss.actor_loss(data)
    td = actor(TensorDict({"observation": data["observation"], "desired_goal": data["desired_goal"]}, [48]))
    sg = td["subgoal_proposal"]
    scaled = (sg - (HIGH + LOW) / 2) / ((HIGH - LOW) / 2)
    assert (scaled.abs() <= 1).all()
    td["subgoal"] = sg
    q1 = critic(td)["state_action_value"][:, 0]
    torch.testing.assert_close(loss_actor, -q1.mean() + 0.3 * scaled.pow(2).mean())
    torch.testing.assert_close(meta["actor_action_l2"], scaled.pow(2).mean())


def test_gradient_isolation_soft_update_and_state_dict():
    actor, critic = _nets()
    loss = HighLevelLoss(actor, critic, action_l2=0.01)
    updater = SoftUpdate(loss, eps=0.5)
    out = loss(_batch())
    out["loss_qvalue"].backward()
    assert all(p.grad is None for p in actor.parameters())
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in critic.parameters())
    loss.zero_grad()
    out["loss_actor"].backward()
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in critic.parameters())
    assert all(p.grad is not None for p in actor.parameters())
    optims = make_optimizers(loss)
    out = loss(_batch())
    (out["loss_qvalue"] + out["loss_actor"]).backward()
    for o in optims.values():
        o.step()
    before = loss.target_critic_network_params.clone()
    updater.step()
    assert not torch.equal(
        before["module", "ensemble", "layers", "0", "weight"],
        loss.target_critic_network_params["module", "ensemble", "layers", "0", "weight"],
    )
    actor2, critic2 = _nets(seed=9)
    loss2 = HighLevelLoss(actor2, critic2, target_noise_std=0.0, action_l2=0.01)
    loss2.load_state_dict(copy.deepcopy(loss.state_dict()))
    loss.target_noise_std = 0.0
    data = _batch(seed=3)
    out1, out2 = loss(data), loss2(data)
    for key in out1.keys():
        torch.testing.assert_close(out1[key], out2[key])


def test_high_level_keys_and_errors():
    actor, critic = _nets()
    loss = HighLevelLoss(actor, critic, action_l2=0.01)
    assert set(loss.in_keys) == {
        "observation",
        "desired_goal",
        "subgoal",
        ("next", "observation"),
        ("next", "reward"),
    }
    with pytest.raises(KeyError, match="subgoal"):
        loss(_batch().exclude("subgoal"))
    with pytest.raises(ValueError, match="clip_return"):
        HighLevelLoss(actor, critic, clip_return=-1.0, action_l2=0.01)
    narrow = GoalConditionedCritic(
        OBS,
        GOAL,
        action_low=[0.0, 0.0],
        action_high=[1.0, 1.0],
        num_cells=(8,),
        relative_goal=True,
        goal_indices=(0, 1),
    )
    with pytest.raises(ValueError, match="box"):
        HighLevelLoss(actor, narrow, action_l2=0.01)
    data = _batch().rename_key_("desired_goal", "g")
    loss.set_keys(goal="g")
    assert torch.isfinite(loss(data)["loss_qvalue"])


def test_value_operator_critic_matches_manual_td3():
    """Any TensorDictModule critic: one member, the loss stacks the twin; the subgoal box is the actor's."""
    actor, _ = _nets()
    mlp = MLP(in_features=OBS + 2 * GOAL, out_features=1, num_cells=[32], activation_class=torch.nn.ReLU)
    # ValueOperator names its output "state_value" unless an in_key is "action": name it for the loss
    critic = ValueOperator(
        mlp, in_keys=["observation", "desired_goal", "subgoal"], out_keys=["state_action_value"]
    )
    loss = HighLevelLoss(actor, critic, gamma=GAMMA, target_noise_std=0.0, action_l2=0.01)
    torch.testing.assert_close(loss.action_loc - loss.action_scale, LOW)  # from the actor's spec
    data = _batch()
    out = loss(data)
    params, target = loss.critic_network_params, loss.target_critic_network_params

    def q(p, sg):
        td = TensorDict(
            {"observation": data["observation"], "desired_goal": data["desired_goal"], "subgoal": sg}, [48]
        )
        return torch.stack([_member(p[i], td) for i in range(2)])

    def _member(p, td):
        with p.to_module(loss.critic_network):
            return loss.critic_network(td.clone())["state_action_value"].squeeze(-1)

    with torch.no_grad():
        td = TensorDict(
            {"observation": data["next", "observation"], "desired_goal": data["desired_goal"]}, [48]
        )
        sg = actor(td)["subgoal_proposal"]
        nxt = TensorDict(
            {"observation": data["next", "observation"], "desired_goal": data["desired_goal"], "subgoal": sg},
            [48],
        )
        bootstrap = torch.stack([_member(target[i], nxt) for i in range(2)]).min(0).values
        y = (data["next", "reward"].squeeze(-1) + GAMMA * bootstrap).clamp(-80.0, 0.0)
    torch.testing.assert_close(out["loss_qvalue"], ((q(params, data["subgoal"]) - y) ** 2).mean(-1).sum())
