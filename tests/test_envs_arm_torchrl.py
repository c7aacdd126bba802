"""The arm tasks through the TorchRL factory: specs, seeding, goals, reward/success consistency, time limit."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import stats
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs, step_mdp
from torchrl_dhrl.envs import (
    ARM_NAMES,
    ENV_NAMES,
    MAZE_NAMES,
    ArmSpec,
    GoalEnv,
    GoalSimulation,
    get_arm_spec,
    get_env_spec,
    make_env,
    sparse_reward,
)

OBS_DIMS = {"Reacher3D": 17, "UR3Obstacle": 15}


def test_names_and_specs():
    assert ARM_NAMES == ("Reacher3D", "UR3Obstacle")
    assert ENV_NAMES == MAZE_NAMES + ARM_NAMES
    reacher, ur3 = get_arm_spec("Reacher3D"), get_arm_spec("dhrl/UR3Obstacle-v0")
    assert isinstance(get_env_spec("Reacher3D"), ArmSpec)
    assert (reacher.episode_length, reacher.success_threshold, reacher.reward_threshold) == (100, 0.25, 0.25)
    assert reacher.agent.timestep == 0.01 and reacher.agent.frame_skip == 2 and reacher.agent.ctrl_limit == 20
    assert (ur3.episode_length, ur3.success_threshold, ur3.reward_threshold) == (100, 0.08, 0.08)
    for spec in (reacher, ur3):
        assert spec.goal_dim == 3 and spec.obs_dim == OBS_DIMS[spec.name]


@pytest.mark.parametrize("num_envs", [1, 3])
@pytest.mark.parametrize("name", ARM_NAMES)
def test_check_env_specs(name, num_envs):
    env = make_env(name, num_envs=num_envs, seed=0, max_episode_steps=2)
    check_env_specs(env)
    td = env.reset()
    assert td["observation"].shape == (num_envs, OBS_DIMS[name]) and td["observation"].dtype == torch.float32
    assert td["achieved_goal"].shape == (num_envs, 3) and td["achieved_goal"].dtype == torch.float32
    assert td["desired_goal"].shape == (num_envs, 3) and td["desired_goal"].dtype == torch.float32
    assert td["is_success"].dtype == torch.bool and td["is_success"].shape == (num_envs, 1)
    assert td["step_count"].dtype == torch.int64 and (td["step_count"] == 0).all()
    assert env.action_spec.shape == (num_envs, get_arm_spec(name).agent.action_dim)


def test_observation_layouts():
    """Reacher3D: 7 joint angles, the goal, 7 joint velocities. UR3Obstacle: flange position, angles, velocities."""
    env = make_env("Reacher3D", num_envs=2, seed=0)
    td = env.rollout(3, break_when_any_done=False)
    sim = env.simulation
    torch.testing.assert_close(td["next", "observation"][:, -1, 7:10], td["desired_goal"][:, -1])
    np.testing.assert_allclose(sim.observation[:, :7], [d.qpos for d in sim.datas])
    np.testing.assert_allclose(sim.observation[:, 10:], [d.qvel for d in sim.datas])
    env = make_env("UR3Obstacle", num_envs=2, seed=0)
    td = env.rollout(3, break_when_any_done=False)
    sim = env.simulation
    assert torch.equal(td["next", "achieved_goal"], td["next", "observation"][..., :3])
    np.testing.assert_allclose(sim.observation[:, 3:9], [d.qpos for d in sim.datas])
    np.testing.assert_allclose(sim.observation[:, 9:], [d.qvel for d in sim.datas])


def _rollout(env, actions):
    td = env.reset()
    out = []
    for action in actions:
        td = env.step(td.set("action", action))
        out.append(td["next"].clone())
        td = step_mdp(td)
    return torch.stack(out, 1)


@pytest.mark.parametrize("name", ARM_NAMES)
def test_seeding_is_deterministic(name):
    torch.manual_seed(0)
    env = make_env(name, num_envs=2)
    actions = env.action_spec.rand((5,))
    runs = []
    for seed in (3, 3, 4):
        env.set_seed(seed)
        runs.append(_rollout(env, actions))
    assert (runs[0] == runs[1]).all()
    assert not torch.equal(runs[0]["observation"], runs[2]["observation"])
    assert not torch.equal(runs[0]["desired_goal"][0], runs[0]["desired_goal"][1])
    a, b = make_env(name, num_envs=2, seed=7).reset(), make_env(name, num_envs=2, seed=7).reset()
    assert (a == b).all()
    # Env i's stream depends only on (seed, i): env 0 of a 2-env batch starts like a 1-env env.
    torch.testing.assert_close(make_env(name, seed=7).reset()["observation"][0], a["observation"][0])


def test_reacher_goal_distribution():
    """Train and test goals: (0, 0.25, 0) + N(0, 0.1) per axis, through env resets (one RNG stream per env)."""
    env = make_env("Reacher3D", num_envs=400, seed=0)
    for eval_goals in (False, True):
        env.eval_goals = eval_goals
        goals = env.reset()["desired_goal"].double().numpy()
        np.testing.assert_allclose(goals.mean(0), [0.0, 0.25, 0.0], atol=0.02)  # 4 standard errors
        np.testing.assert_allclose(goals.std(0), 0.1, rtol=0.12)
        for axis, mean in enumerate((0.0, 0.25, 0.0)):
            # standardised first: some scipy versions reject loc/scale args for "norm"
            assert stats.kstest((goals[:, axis] - mean) / 0.1, "norm").pvalue > 1e-3
    sampler = get_arm_spec("Reacher3D").train_goals
    many = sampler.sample(np.random.default_rng(0), 20000)
    np.testing.assert_allclose(many.mean(0), [0.0, 0.25, 0.0], atol=0.003)
    np.testing.assert_allclose(many.std(0), 0.1, rtol=0.02)


def test_ur3_goal_distributions():
    spec = get_arm_spec("UR3Obstacle")
    env = make_env("UR3Obstacle", num_envs=300, seed=0, eval=True)
    test = env.reset()["desired_goal"].double().numpy()
    low, high = np.array(spec.test_goals.low), np.array(spec.test_goals.high)
    assert ((test >= low) & (test <= high)).all()
    for axis in range(3):  # uniform in the test box, behind the fence (y > 0) inside the bin
        assert stats.kstest((test[:, axis] - low[axis]) / (high[axis] - low[axis]), "uniform").pvalue > 1e-3
    fence, front, far = spec.boards
    assert (test[:, 1] > fence.center[1] + 0.05).all() and (test[:, 1] < far.center[1] - 0.05).all()
    assert (test[:, 0] < front.center[0] - 0.05).all() and (test[:, 2] < 2 * fence.half_size[2]).all()
    # Train goals cover both sides of the fence and keep 5 cm away from every board.
    train = spec.train_goals.sample(np.random.default_rng(0), 5000)
    assert (train[:, 1] < 0).mean() > 0.3 and (train[:, 1] > 0).mean() > 0.3
    for board in spec.boards:
        inside = (np.abs(train - board.center) < np.array(board.half_size) + 0.05).all(-1)
        assert not inside.any()


@pytest.mark.parametrize("name", ARM_NAMES)
def test_reward_success_and_time_limit(name):
    spec = get_arm_spec(name)
    env = make_env(name, num_envs=2, seed=1, max_episode_steps=6)
    torch.manual_seed(1)
    rollout = env.rollout(13, break_when_any_done=False)
    nxt = rollout["next"]
    distance = (nxt["achieved_goal"] - nxt["desired_goal"]).norm(dim=-1, keepdim=True)
    expected = sparse_reward(nxt["achieved_goal"].numpy(), nxt["desired_goal"].numpy(), spec.reward_threshold)
    torch.testing.assert_close(nxt["reward"], torch.from_numpy(expected)[..., None].float())
    assert torch.equal(nxt["is_success"], distance <= spec.success_threshold)
    assert torch.equal(nxt["done"], nxt["truncated"]) and not nxt["terminated"].any()
    assert nxt["truncated"][0, :, 0].tolist() == [t % 6 == 5 for t in range(13)]
    # The default time limit is the task's 100 steps.
    full = make_env(name, seed=0)
    assert full.max_episode_steps == 100
    flags = full.rollout(100, break_when_any_done=False)["next", "truncated"][0, :, 0]
    assert flags.nonzero().flatten().tolist() == [99]


@pytest.mark.parametrize("name", ARM_NAMES)
def test_success_threshold_boundary(name):
    """Goals just inside / outside the thresholds around the achieved goal give success and reward 0 / -1."""
    spec = get_arm_spec(name)
    sim = GoalSimulation(name, 4, seed=0)
    sim.reset()
    direction = np.array([1.0, 2.0, -2.0]) / 3.0
    radii = np.array([0.99, 1.01, 0.5, 3.0]) * spec.success_threshold
    sim.desired_goal[:] = sim.achieved_goal + radii[:, None] * direction
    reward, success = sim.evaluate()
    assert success.tolist() == [True, False, True, False]
    assert reward.tolist() == [0.0, -1.0, 0.0, -1.0]  # reward and success radii coincide for the arms


def test_explicit_goals_and_errors():
    env = make_env("UR3Obstacle", num_envs=2, seed=0)
    goals = torch.tensor([[0.375, 0.18, 0.1], [0.3, -0.2, 0.3]])
    td = env.reset(TensorDict({"desired_goal": goals}, [2]))
    torch.testing.assert_close(td["desired_goal"], goals)
    np.testing.assert_allclose(env.simulation.datas[0].mocap_pos[0], [0.375, 0.18, 0.1])  # the marker follows
    with pytest.raises(
        ValueError, match=r"outside the UR3Obstacle arena: goals must be in x in .*z in \[0.0, 0.7\]"
    ):
        env.reset(TensorDict({"desired_goal": torch.tensor([[0.0, 0.0, 0.9], [0.0, 0.0, 0.1]])}, [2]))
    with pytest.raises(ValueError, match="shape"):
        env.reset(TensorDict({"desired_goal": torch.zeros(2, 2)}, [2]))
    with pytest.raises(ValueError, match="expects an 'action' of shape"):
        env.step(td.set("action", torch.zeros(2, 7)))
    with pytest.raises(ValueError, match="Valid names: .*Reacher3D, UR3Obstacle"):
        make_env("UR5Obstacle")
    assert isinstance(make_env("dhrl/Reacher3D-v0"), GoalEnv)


def test_reacher_reset_is_noise_free():
    """As in the reference: every episode starts at the zero posture, at rest (no qpos or qvel noise)."""
    spec = get_arm_spec("Reacher3D")
    assert spec.agent.init_qpos == (0.0,) * 7 and spec.agent.qpos_noise == spec.agent.qvel_noise == 0.0
    sim = GoalSimulation("Reacher3D", 300, seed=0)
    sim.reset()
    assert not sim.observation[:, :7].any() and not sim.observation[:, 10:].any()


# How far a limited joint may pass its range in a random episode. Reacher3D keeps the reference model's soft
# joint limits (MuJoCo's default solref/solimp): its light upper-arm roll and wrist flex (about 0.05 kg m^2
# of joint-space inertia) overshoot by up to ~0.3 rad when random +-20 N m torques throw them at a limit.
LIMIT_SLACK = {"Reacher3D": 0.4, "UR3Obstacle": 0.05}


@pytest.mark.parametrize("name", ARM_NAMES)
def test_random_rollout_is_stable(name):
    """A full episode of uniformly random actions: finite, joints within their (soft) limits, the arm moves."""
    spec = get_arm_spec(name)
    env = make_env(name, num_envs=4, seed=0)
    torch.manual_seed(0)
    rollout = env.rollout(spec.episode_length, break_when_any_done=False)
    assert torch.isfinite(rollout["next", "observation"]).all()
    moved = (rollout["next", "achieved_goal"][:, -1] - rollout["achieved_goal"][:, 0]).norm(dim=-1)
    assert (moved > 0.02).all()
    model = env.simulation.model
    qpos = np.array([d.qpos for d in env.simulation.datas])
    limited = model.jnt_limited.astype(bool)
    low, high = model.jnt_range[limited].T
    slack = LIMIT_SLACK[name]
    assert ((qpos[:, limited] > low - slack) & (qpos[:, limited] < high + slack)).all()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("name", ARM_NAMES)
def test_cuda_device(name):
    env = make_env(name, num_envs=2, seed=0, device="cuda")
    check_env_specs(env)
    td = env.rollout(3)
    assert td["achieved_goal"].device.type == "cuda" and td["next", "reward"].device.type == "cuda"
