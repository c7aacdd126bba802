"""The reference implementation's behaviours that are the recipe's defaults, and the switches that select the
alternatives (docs/faithfulness.md): warm-up schedule and subgoals, twin choice, critic goal input, FGS trigger,
update order, target-action clamp, epoch layout and the first graph build."""

import copy

import numpy as np
import pytest
import torch
from _recipe import load_recipe, recipe_config
from dhrl_utils import build_agent, build_environment
from scipy.stats import kstest
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_dhrl.objectives import make_optimizers
from torchrl_dhrl.recipe import load_checkpoint, resolve_device
from torchrl_dhrl.training import LossUpdater

recipe = load_recipe()
SMOKE = ("env=PointMaze", "preset=smoke", "plots.every_epochs=0", "device=cpu", "logger.backend=none")


def _agent(*overrides):
    cfg = recipe_config(*SMOKE, *overrides)
    device = resolve_device("cpu")
    torch.manual_seed(cfg["seed"])  # the recipe's order: seed, spec env, agent
    return cfg, build_agent(cfg, device)


# ---------------------------------------------------------------- 1. no update during the warm-up
@pytest.mark.recipe
@pytest.mark.parametrize("train_during_warmup", [False, True])
def test_warmup_updates(train_during_warmup, tmp_path, monkeypatch):
    """Reference: no optimiser step and no parameter change in the warm-up (4 episodes = 2 batches of 2 x 40
    steps), then one low-level update per env step and one high-level update per 10, without catch-up."""
    calls = []
    real_run = LossUpdater.run

    def record(self, n):
        calls.append((type(self.loss).__name__, n))
        return real_run(self, n)

    monkeypatch.setattr(LossUpdater, "run", record)
    flag = f"schedule.train_during_warmup={str(train_during_warmup).lower()}"
    overrides = (*SMOKE, "schedule.warmup_episodes=4", flag)
    warm = tmp_path / "warm"
    recipe.train(recipe_config(*overrides, "total_steps=160"), run_dir=warm)  # the warm-up only
    state = load_checkpoint(warm / "checkpoint")
    cfg, fresh = _agent("schedule.warmup_episodes=4", flag)
    initial = fresh.state_dict()
    if not train_during_warmup:
        for level in ("low_updater", "high_updater"):
            assert state[level]["num_updates"] == 0
            for optimizer in state[level]["optimizers"].values():
                assert optimizer["state"] == {}  # Adam never stepped
        for part in ("sqgc_loss", "high_loss"):
            for key, value in initial[part].items():
                torch.testing.assert_close(state["agent"][part][key], value, rtol=0, atol=0, msg=key)
        assert {n for _, n in calls} == {0}
    else:
        assert state["low_updater"]["num_updates"] == 160 and state["high_updater"]["num_updates"] == 16
    calls.clear()
    full = tmp_path / "full"
    recipe.train(recipe_config(*overrides, "total_steps=320"), run_dir=full)
    state = load_checkpoint(full / "checkpoint")
    trained = 160 if not train_during_warmup else 320
    assert state["low_updater"]["num_updates"] == trained  # one per env step after the warm-up
    assert state["high_updater"]["num_updates"] == trained // 10
    low_calls = [n for name, n in calls if name == "SQGCLoss"]
    # one batch of 80 steps -> 80 updates: no burst of the warm-up's 160 after it
    assert low_calls == ([0, 0, 80, 80] if not train_during_warmup else [80, 80, 80, 80])


# ---------------------------------------------------------------- 2. warm-up subgoals
def _subgoals(agent, num=4000):
    td = TensorDict(
        {
            "observation": torch.randn(num, 6) * 3,
            "desired_goal": torch.rand(num, 2) * 12 - 2,
            "subgoal_step": torch.full((num, 1), -1),
        },
        [num],
    )
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        return agent.high_policy(td)["subgoal"]


def test_warmup_subgoals_uniform_in_the_box():
    cfg, agent = _agent()
    low, high = cfg["high"]["subgoal_low"], cfg["high"]["subgoal_high"]
    recipe.set_phase(cfg, agent, episodes=0)  # in the warm-up
    subgoals = _subgoals(agent)
    for axis in range(2):
        u = (subgoals[:, axis] - low[axis]) / (high[axis] - low[axis])
        assert kstest(u.numpy(), "uniform").pvalue > 1e-3
    # after the warm-up: the actor + Gaussian noise (clipped), far from uniform
    recipe.set_phase(cfg, agent, episodes=cfg["schedule"]["warmup_episodes"])
    u = (_subgoals(agent)[:, 0] - low[0]) / (high[0] - low[0])
    assert kstest(u.numpy(), "uniform").pvalue < 1e-6
    assert agent.exploration.uniform_prob == cfg["low"]["uniform_prob"]
    # high.warmup_subgoals=policy: the actor + noise during the warm-up too, uniform actions still
    cfg, agent = _agent("high.warmup_subgoals=policy")
    recipe.set_phase(cfg, agent, episodes=0)
    u = (_subgoals(agent)[:, 0] - low[0]) / (high[0] - low[0])
    assert kstest(u.numpy(), "uniform").pvalue < 1e-6
    assert agent.exploration.uniform_prob == 1.0


# ---------------------------------------------------------------- 3. twin member of the graph distance
def test_recipe_distance_uses_the_configured_twin_member():
    for twin in ("optimistic", "pessimistic"):
        cfg, agent = _agent(f"planner.twin={twin}")
        assert agent.planner.distance.twin == twin
    states, goals = torch.randn(50, 6) * 3, torch.rand(50, 2) * 12 - 2
    _, optimistic = _agent("planner.twin=optimistic")
    _, pessimistic = _agent("planner.twin=pessimistic")  # same seed: the same networks
    d_opt, d_pes = optimistic.planner.distance(states, goals), pessimistic.planner.distance(states, goals)
    assert (d_opt <= d_pes).all() and (d_opt < d_pes).any()


# ---------------------------------------------------------------- 4. low-level critic goal input
@pytest.mark.parametrize("critic_goal", ["absolute", "relative"])
def test_low_level_critics_goal_input(critic_goal):
    _, agent = _agent(f"low.critic_goal={critic_goal}")
    obs, goal = torch.randn(7, 6) * 3, torch.rand(7, 2) * 12 - 2
    action = torch.rand(7, 2) * 2 - 1
    loss = agent.sqgc_loss
    for name in ("policy_critic", "graph_critic"):
        net = getattr(loss, name).module
        with getattr(loss, f"{name}_params").to_module(getattr(loss, name)):
            features = net.features(obs, goal, action)
        goal_part = features[..., 6:8]
        expected = goal if critic_goal == "absolute" else goal - obs[:, :2]
        torch.testing.assert_close(goal_part.squeeze(0) if goal_part.ndim == 3 else goal_part, expected)
    # the actor sees the relative goal either way (low.relative_goal=true)
    assert agent.low_actor.module.relative_goal


def test_reacher_critics_and_actor_absolute():
    cfg = recipe_config("env=Reacher3D", "preset=smoke", "device=cpu")
    device = resolve_device("cpu")
    agent = build_agent(cfg, device)
    assert not agent.low_actor.module.relative_goal
    assert not agent.sqgc_loss.policy_critic.module.relative_goal


# ---------------------------------------------------------------- 6. FGS trigger reaches the env transform
@pytest.mark.parametrize("trigger", ["reachable", "near_graph"])
def test_fgs_trigger_from_config(trigger):
    cfg = recipe_config(*SMOKE, "fgs.enabled=true", f"fgs.trigger={trigger}")
    device = resolve_device("cpu")
    agent = build_agent(cfg, device)
    env = build_environment(cfg, device, agent=agent)
    shifts = [t for t in env.transform if hasattr(t, "fgs")]
    assert len(shifts) == 1 and shifts[0].fgs.trigger == trigger


# ---------------------------------------------------------------- 7. update order and target clamp
def _low_level_batch(agent, n=64):
    g = torch.Generator().manual_seed(3)
    return TensorDict(
        {
            "observation": torch.randn(n, 6, generator=g),
            "goal": torch.randn(n, 2, generator=g),
            "action": torch.rand(n, 2, generator=g) * 2 - 1,
            "graph_goal": torch.randn(n, 2, generator=g),
            ("next", "observation"): torch.randn(n, 6, generator=g),
            ("next", "reward"): -torch.ones(n, 1),
            ("next", "graph_reward"): -torch.ones(n, 1),
        },
        [n],
    )


def _fixed_sample_updater(cfg, loss, sample, after):
    updater = LossUpdater(
        loss,
        None,
        make_optimizers(loss),
        actor_update_interval=cfg["low"]["actor_update_interval"],
        actor_after_critic_step=after,
    )
    updater._sample = lambda: sample.clone()
    return updater


def test_actor_loss_after_the_critic_step_matches_a_manual_two_step_update():
    cfg, agent = _agent("low.actor_update_interval=1")
    loss = agent.sqgc_loss
    sample = _low_level_batch(agent)
    keys = loss.in_keys
    sample = sample.select(*[k for k in keys if k in sample.keys(True)])
    manual = copy.deepcopy(loss)
    optimizers = make_optimizers(manual, actor_lr=1e-4, critic_lr=1e-3)
    # manual reference order: critic losses, critic Adam step; then the actor loss on the updated critic
    torch.manual_seed(5)
    terms = manual.loss_terms(sample.clone(), update_actor=False)
    critic_total = sum(v for k, v in terms.items() if k.startswith("loss_"))
    optimizers["critic"].zero_grad()
    critic_total.backward()
    optimizers["critic"].step()
    actor_loss = manual.actor_loss(sample.clone())[0]
    optimizers["actor"].zero_grad()
    actor_loss.backward()
    optimizers["actor"].step()
    torch.manual_seed(5)
    out = _fixed_sample_updater(cfg, loss, sample, after=True).step()
    assert bool(out["actor_updated"])
    torch.testing.assert_close(out["loss_actor"], actor_loss.detach())
    for key, value in manual.state_dict().items():
        torch.testing.assert_close(loss.state_dict()[key], value, msg=key)
    # the joint order (one backward) takes its actor loss from the pre-step critic: another actor step
    joint_cfg, joint_agent = _agent("low.actor_update_interval=1")
    torch.manual_seed(5)
    joint_out = _fixed_sample_updater(joint_cfg, joint_agent.sqgc_loss, sample, after=False).step()
    assert not torch.equal(joint_out["loss_actor"], out["loss_actor"])
    actor_keys = [k for k in manual.state_dict() if k.startswith("actor_network_params")]
    assert any(
        not torch.equal(joint_agent.sqgc_loss.state_dict()[k], loss.state_dict()[k]) for k in actor_keys
    )
    critic_keys = [k for k in manual.state_dict() if k.startswith("policy_critic_params")]
    for key in critic_keys:  # the critic step itself is the same in both orders
        torch.testing.assert_close(joint_agent.sqgc_loss.state_dict()[key], loss.state_dict()[key], msg=key)


def test_delayed_actor_is_respected_in_the_sequential_order():
    cfg, agent = _agent()  # actor every 2nd update
    loss = agent.sqgc_loss
    sample = _low_level_batch(agent).select(
        *[k for k in loss.in_keys if k in _low_level_batch(agent).keys(True)]
    )
    updater = _fixed_sample_updater(cfg, loss, sample, after=True)
    flags = [bool(updater.step()["actor_updated"]) for _ in range(4)]
    assert flags == [False, True, False, True]


@pytest.mark.parametrize("clamp", [False, True])
def test_target_action_clamp(clamp):
    _, agent = _agent(f"low.target_action_clamp={str(clamp).lower()}", "low.target_noise=5.0")
    loss = agent.sqgc_loss
    with torch.no_grad():
        action = loss._target_action(torch.randn(500, 6), torch.randn(500, 2))
    high = (loss.action_loc + loss.action_scale).max()
    assert (action.abs().max() <= high + 1e-6) == clamp


# ---------------------------------------------------------------- epoch layout and the first graph build
def test_epochs_start_at_the_warmup_end_and_graph_after_seven():
    assert [recipe.epoch_of(e, 200, 15) for e in (15, 195, 200, 215, 305)] == [1, 13, 14, 15, 21]
    cfg = recipe_config("env=AntMaze")
    schedule = cfg["schedule"]
    first_build = schedule["warmup_episodes"] + schedule["graph_start_epoch"] * schedule["epoch_episodes"]
    assert first_build == 305  # the reference: `epoch > start_planning_epoch=5` after 200 warm-up episodes
    epochs_ending = [
        e for e in range(1, 400) if recipe.epoch_of(e, 200, 15) > recipe.epoch_of(e - 1, 200, 15)
    ]
    assert first_build in epochs_ending and 200 in epochs_ending
    assert np.diff([e for e in epochs_ending if e >= 200]).tolist() == [15] * (
        len([e for e in epochs_ending if e >= 200]) - 1
    )


# ---------------------------------------------------------------- the table documents every switch and its default
#: switch -> the official code's value, the recipe's default
OFFICIAL_DEFAULTS = {
    "schedule.train_during_warmup": False,
    "high.warmup_subgoals": "uniform",
    "planner.twin": "optimistic",
    "low.critic_goal": "absolute",
    "fgs.trigger": "reachable",
    "low.actor_after_critic_step": True,
    "high.actor_after_critic_step": True,
    "low.target_action_clamp": False,
    "high.target_action_clamp": False,
    "schedule.graph_start_epoch": 7,
    "high.action_l2": 0.0,
    "high.her_ratio": 1.0,
}


@pytest.mark.parametrize("env", ["AntMaze", "AntMazeComplex", "Reacher3D"])
def test_defaults_are_the_official_and_documented(env):
    from pathlib import Path

    text = (Path(__file__).parents[1] / "docs" / "faithfulness.md").read_text()
    cfg = recipe_config(f"env={env}")
    for path, value in OFFICIAL_DEFAULTS.items():
        node = cfg
        for part in path.split("."):
            node = node[part]
        assert node == value, path
        assert f"`{path}" in text, f"{path} is missing from docs/faithfulness.md"
    assert "`fgs.weighting" in text
