"""The Gymnasium goal-env front end of the mazes and the arm tasks: registration, env checker, seeding,
compute_reward, options."""

from __future__ import annotations

import warnings

import gymnasium as gym
import mujoco
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from tensordict import TensorDict
from torchrl_dhrl.envs import (
    ALL_GYM_IDS,
    ARM_GYM_IDS,
    ARM_NAMES,
    GYM_IDS,
    MAZE_NAMES,
    GymGoalEnv,
    get_arm_spec,
    get_maze_spec,
    make_env,
)


def test_registered_ids():
    assert GYM_IDS == tuple(f"dhrl/{name}-v0" for name in MAZE_NAMES)
    for gym_id in GYM_IDS:
        spec = gym.spec(gym_id)
        assert spec.max_episode_steps == get_maze_spec(gym_id).episode_length


@pytest.mark.parametrize("gym_id", GYM_IDS)
def test_gymnasium_check_env(gym_id):
    env = gym.make(gym_id)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # infinite observation bounds and the ant's +-30 action box only warn
        check_env(env.unwrapped, skip_render_check=True)
    obs, info = env.reset(seed=0)
    assert set(obs) == {"observation", "achieved_goal", "desired_goal"}
    assert all(v.dtype == np.float64 for v in obs.values())
    assert obs["observation"].shape == (get_maze_spec(gym_id).agent.obs_dim,)
    np.testing.assert_array_equal(obs["achieved_goal"], obs["observation"][:2])
    assert isinstance(info["is_success"], bool)


def test_seeding_and_determinism():
    env = gym.make("dhrl/AntMazeSmall-v0")
    actions = np.random.default_rng(0).uniform(-30, 30, size=(10, 8)).astype(np.float32)
    runs = []
    for seed in (1, 1, 2):
        obs, _ = env.reset(seed=seed)
        trajectory = [obs["observation"]]
        for action in actions:
            obs, *_ = env.step(action)
            trajectory.append(obs["observation"])
        runs.append(np.array(trajectory))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.array_equal(runs[0], runs[2])


def test_compute_reward_vectorised_and_consistent():
    env = gym.make("dhrl/PointMaze-v0").unwrapped
    rng = np.random.default_rng(0)
    ag, dg = rng.uniform(-1, 1, size=(3, 5, 2)), rng.uniform(-1, 1, size=(3, 5, 2))
    reward = env.compute_reward(ag, dg, [{}] * 15)
    assert reward.shape == (3, 5)
    np.testing.assert_array_equal(reward, -(np.linalg.norm(ag - dg, axis=-1) > 0.5).astype(float))
    obs, _ = env.reset(seed=0, options={"goal": [0.3, 0.0]})
    for _ in range(20):
        obs, reward, terminated, truncated, info = env.step(np.array([0.5, 0.0], dtype=np.float32))
        assert reward == env.compute_reward(obs["achieved_goal"], obs["desired_goal"], info)
        distance = np.linalg.norm(obs["achieved_goal"] - obs["desired_goal"])
        assert info["is_success"] == (distance <= 2.5) and not terminated and not truncated
    assert reward == -1.0  # it drove past the goal


def test_reset_options_and_errors():
    env = gym.make("dhrl/AntMazeComplex-v0")
    obs, _ = env.reset(seed=0, options={"goal": (40.0, 48.0)})
    np.testing.assert_array_equal(obs["desired_goal"], [40.0, 48.0])
    goals = {tuple(env.reset(options={"eval": True})[0]["desired_goal"]) for _ in range(40)}
    assert goals == set(get_maze_spec("AntMazeComplex").test_goals)
    train = env.reset(options={"eval": False})[0]["desired_goal"]
    assert tuple(train) not in goals
    assert tuple(gym.make("dhrl/AntMaze-v0", eval=True).reset(seed=0)[0]["desired_goal"]) == (0.0, 16.0)
    with pytest.raises(ValueError, match="outside"):
        env.reset(options={"goal": (60.0, 0.0)})
    with pytest.raises(ValueError, match="Unknown reset options"):
        env.reset(options={"goal_xy": (0.0, 0.0)})
    obs, _ = env.reset(seed=0, options={"start": (40.0, 8.0), "goal": (40.0, 48.0)})
    assert np.linalg.norm(obs["achieved_goal"] - (40.0, 8.0)) < 0.2
    np.testing.assert_array_equal(obs["desired_goal"], [40.0, 48.0])
    with pytest.raises(ValueError, match="inside a wall"):
        env.reset(options={"start": (8.0, 8.0)})
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action of shape"):
        env.step(np.zeros(2))
    with pytest.raises(ValueError, match="render_mode"):
        GymGoalEnv("AntMaze", render_mode="human")


def test_time_limit_is_truncation():
    env = GymGoalEnv("AntMaze", max_episode_steps=3)
    env.reset(seed=0)
    flags = [env.step(env.action_space.sample())[2:4] for _ in range(3)]
    assert flags == [(False, False), (False, False), (False, True)]
    wrapped = gym.make("dhrl/PointMaze-v0", max_episode_steps=2)
    wrapped.reset(seed=0)
    assert [wrapped.step(wrapped.action_space.sample())[3] for _ in range(2)] == [False, True]


def test_gym_and_torchrl_share_the_simulation():
    """Same state and actions -> the same observations through both front ends (float64 vs float32)."""
    gym_env = GymGoalEnv("AntMaze")
    obs, _ = gym_env.reset(seed=0)
    rl_env = make_env("AntMaze")
    rl_env.reset()
    # Copy the gym env's initial state into the TorchRL env's simulation.
    src, dst = gym_env.simulation, rl_env.simulation
    mujoco.mj_copyData(dst.datas[0], dst.model, src.datas[0])
    dst.observation[:] = src.observation
    dst.desired_goal[:] = src.desired_goal
    actions = np.random.default_rng(0).uniform(-30, 30, size=(5, 8)).astype(np.float32)
    for action in actions:
        obs, reward, _, _, info = gym_env.step(action)
        td = rl_env.step(TensorDict({"action": torch.from_numpy(action)[None]}, [1]))["next"]
        assert obs["observation"].dtype == np.float64 and td["observation"].dtype == torch.float32
        np.testing.assert_allclose(td["observation"][0].numpy(), obs["observation"], rtol=1e-6, atol=1e-6)
        assert float(td["reward"]) == reward and bool(td["is_success"]) == info["is_success"]


@pytest.mark.parametrize("gym_id", ["dhrl/PointMaze-v0", "dhrl/Reacher3D-v0"])
def test_model_and_data_are_the_live_mujoco_objects(gym_id):
    """As Gymnasium's MuJoCo envs: ``env.unwrapped.model`` / ``.data``, the objects the env steps."""
    env = gym.make(gym_id)
    base = env.unwrapped
    assert isinstance(base.model, mujoco.MjModel) and isinstance(base.data, mujoco.MjData)
    assert base.model is base.simulation.model and base.data is base.simulation.datas[0]
    obs, _ = env.reset(seed=0)
    data = base.data
    if gym_id == "dhrl/PointMaze-v0":  # observation = qpos ++ qvel
        np.testing.assert_array_equal(obs["observation"], np.concatenate([data.qpos, data.qvel]))
    qpos, time = data.qpos.copy(), data.time
    for _ in range(3):
        obs, *_ = env.step(env.action_space.high)
    assert base.data is data  # the same object, advanced in place
    assert data.time > time and not np.array_equal(data.qpos, qpos)
    if gym_id == "dhrl/PointMaze-v0":
        np.testing.assert_array_equal(obs["observation"][: base.model.nq], data.qpos)
    env.reset(seed=1)
    assert base.data is data and data.time == 0.0  # reset rewinds the same MjData


def test_arm_registered_ids():
    assert ARM_GYM_IDS == ("dhrl/Reacher3D-v0", "dhrl/UR3Obstacle-v0")
    assert ALL_GYM_IDS == GYM_IDS + ARM_GYM_IDS
    for gym_id in ARM_GYM_IDS:
        assert gym.spec(gym_id).max_episode_steps == 100


@pytest.mark.parametrize("gym_id", ARM_GYM_IDS)
def test_arm_gymnasium_check_env(gym_id):
    env = gym.make(gym_id)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # infinite observation bounds and the +-20 torque box only warn
        check_env(env.unwrapped, skip_render_check=True)
    obs, info = env.reset(seed=0)
    assert set(obs) == {"observation", "achieved_goal", "desired_goal"}
    assert all(v.dtype == np.float64 for v in obs.values())
    assert obs["achieved_goal"].shape == obs["desired_goal"].shape == (3,)
    assert env.observation_space.contains(obs) and isinstance(info["is_success"], bool)


@pytest.mark.parametrize("gym_id", ARM_GYM_IDS)
def test_arm_seeding_and_determinism(gym_id):
    env = gym.make(gym_id)
    actions = [env.action_space.sample() for _ in range(8)]
    runs = []
    for seed in (1, 1, 2):
        obs, _ = env.reset(seed=seed)
        trajectory = [obs["observation"]]
        for action in actions:
            trajectory.append(env.step(action)[0]["observation"])
        runs.append(np.array(trajectory))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.array_equal(runs[0], runs[2])


@pytest.mark.parametrize("name", ARM_NAMES)
def test_arm_compute_reward_vectorised_and_consistent(name):
    spec = get_arm_spec(name)
    env = GymGoalEnv(name)
    rng = np.random.default_rng(0)
    ag, dg = rng.normal(0, 0.2, size=(4, 6, 3)), rng.normal(0, 0.2, size=(4, 6, 3))
    reward = env.compute_reward(ag, dg, [{}] * 24)
    assert reward.shape == (4, 6)
    np.testing.assert_array_equal(
        reward, -(np.linalg.norm(ag - dg, axis=-1) > spec.reward_threshold).astype(float)
    )
    obs, _ = env.reset(seed=0, options={"goal": spec.typical_goal})
    rewards = []
    for _ in range(30):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert reward == env.compute_reward(obs["achieved_goal"], obs["desired_goal"], info)
        distance = np.linalg.norm(obs["achieved_goal"] - obs["desired_goal"])
        assert info["is_success"] == (distance <= spec.success_threshold) and not terminated and not truncated
        rewards.append(reward)
    assert set(rewards) <= {0.0, -1.0}


def test_arm_reset_options_and_errors():
    env = gym.make("dhrl/UR3Obstacle-v0")
    obs, _ = env.reset(seed=0, options={"goal": (0.4, 0.2, 0.1)})
    np.testing.assert_array_equal(obs["desired_goal"], [0.4, 0.2, 0.1])
    test_box = get_arm_spec("UR3Obstacle").test_goals
    goals = np.array([env.reset(options={"eval": True})[0]["desired_goal"] for _ in range(20)])
    assert test_box.contains(goals).all()
    train = np.array([env.reset(options={"eval": False})[0]["desired_goal"] for _ in range(20)])
    assert not test_box.contains(train).all()
    assert test_box.contains(gym.make("dhrl/UR3Obstacle-v0", eval=True).reset(seed=0)[0]["desired_goal"])
    with pytest.raises(ValueError, match="outside"):
        env.reset(options={"goal": (2.0, 0.0, 0.1)})
    with pytest.raises(ValueError, match="shape"):
        env.reset(options={"goal": (0.3, 0.1)})
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action of shape"):
        env.step(np.zeros(7))


@pytest.mark.parametrize("name", ARM_NAMES)
def test_arm_gym_and_torchrl_share_the_simulation(name):
    """Same state and actions -> the same observations through both front ends (float64 vs float32)."""
    gym_env = GymGoalEnv(name)
    gym_env.reset(seed=0)
    rl_env = make_env(name)
    rl_env.reset()
    src, dst = gym_env.simulation, rl_env.simulation
    mujoco.mj_copyData(dst.datas[0], dst.model, src.datas[0])
    dst.observation[:] = src.observation
    dst.desired_goal[:] = src.desired_goal
    for _ in range(5):
        action = gym_env.action_space.sample()
        obs, reward, _, _, info = gym_env.step(action)
        td = rl_env.step(TensorDict({"action": torch.from_numpy(action)[None]}, [1]))["next"]
        np.testing.assert_allclose(td["observation"][0].numpy(), obs["observation"], rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(td["achieved_goal"][0].numpy(), obs["achieved_goal"], rtol=1e-6, atol=1e-6)
        assert float(td["reward"]) == reward and bool(td["is_success"]) == info["is_success"]
