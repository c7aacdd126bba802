"""GymnasiumGoalEnv: a Gymnasium goal env (gymnasium-robotics' PointMaze_UMaze-v3) as an env of the goal-env contract,
its exact state, its goal space; and check_goal_env's float32 and truncation checks."""

from __future__ import annotations

import pytest
import torch
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs
from torchrl_dhrl.envs import (
    GoalEnvError,
    GymnasiumGoalEnv,
    check_goal_env,
    goal_extent,
    goal_indices_of,
    gymnasium_id,
    make_env,
)

pytest.importorskip("gymnasium_robotics")
UMAZE = "PointMaze_UMaze-v3"


def test_the_adapter_meets_the_contract():
    env = make_env(f"gymnasium:{UMAZE}", num_envs=2, seed=0)
    assert isinstance(env, GymnasiumGoalEnv) and env.max_episode_steps == 300  # the env's TimeLimit
    check_goal_env(env, goal_indices=[0, 1], steps=3)
    check_env_specs(env)
    td = env.rollout(4)
    assert td["next", "observation"].dtype == torch.float32 and td["next", "is_success"].shape == (2, 4, 1)
    assert td["next", "step_count"][0, :, 0].tolist() == [1, 2, 3, 4]
    assert gymnasium_id(f"gymnasium:{UMAZE}") == UMAZE and gymnasium_id("PointMaze") is None


def test_episodes_truncate_at_max_episode_steps_and_reset_options_apply():
    env = GymnasiumGoalEnv(UMAZE, 1, seed=1, max_episode_steps=7, reset_options={"reset_cell": [3, 1]})
    check_goal_env(env, goal_indices=[0, 1], steps=15)  # truncation at 7 and 14, checked
    starts = torch.stack([env.reset()["achieved_goal"][0] for _ in range(5)])
    assert ((starts - torch.tensor([-1.0, -1.0])).abs() <= 0.26).all()  # cell (3, 1) of the U: (-1, -1) +- noise


def test_success_comes_from_the_env_info_or_a_distance():
    env = GymnasiumGoalEnv(UMAZE, 1, seed=0)
    assert env.success_radius() == pytest.approx(0.45, abs=1e-5)  # read from compute_reward
    td = env.reset()
    far = (td["achieved_goal"] - td["desired_goal"]).norm().item()
    env = GymnasiumGoalEnv(UMAZE, 1, seed=0, success_threshold=far + 1.0)
    assert env.reset()["is_success"].all() and env.success_radius() == far + 1.0


def test_the_state_dict_resumes_the_simulation_exactly():
    actions = torch.rand(12, 2, 2, generator=torch.Generator().manual_seed(0)) * 2 - 1
    env = GymnasiumGoalEnv(UMAZE, 2, seed=3)
    td = env.reset()
    for k in range(6):
        td = env.step(td.set("action", actions[k]))["next"]
    state = env.state_dict()
    straight = []
    for k in range(6, 12):
        td = env.step(td.set("action", actions[k]))["next"]
        straight.append(td.exclude("reward"))
    straight.append(env.reset())  # the next episode's goals come from the restored random streams too
    resumed = GymnasiumGoalEnv(UMAZE, 2, seed=99)
    resumed.reset()
    resumed.load_state_dict(state)
    td, out = resumed._output(), []
    for k in range(6, 12):
        td = resumed.step(td.set("action", actions[k]))["next"]
        out.append(td.exclude("reward"))
    out.append(resumed.reset())
    for a, b in zip(straight, out, strict=True):
        assert (a == b).all()


def test_goal_space_helpers():
    env = GymnasiumGoalEnv(UMAZE, 1, seed=0)
    assert goal_indices_of(env) == [0, 1]
    low, high = goal_extent(env, episodes=8)
    assert all(-2.2 < v < -1.0 for v in low) and all(1.0 < v < 2.2 for v in high)  # the U spans [-1.5, 1.5]^2
    assert goal_indices_of(make_env("Reacher3D", seed=0)) is None  # the arm's goal is not in its observation


def test_bad_arguments_and_envs_are_refused():
    with pytest.raises(ValueError, match="`success_threshold` must be None or a number > 0"):
        GymnasiumGoalEnv(UMAZE, success_threshold=0.0)
    with pytest.raises(ValueError, match="`reset_options`"):
        GymnasiumGoalEnv(UMAZE, reset_options=[1, 2])
    with pytest.raises(GoalEnvError, match="No Gymnasium env 'NoSuchMaze-v0'"):
        GymnasiumGoalEnv("NoSuchMaze-v0")
    with pytest.raises(GoalEnvError, match="Dict observation"):
        GymnasiumGoalEnv("Pendulum-v1")
    env = GymnasiumGoalEnv(UMAZE, 1, seed=0, make_kwargs={"continuing_task": False})
    env.reset()
    with pytest.raises(GoalEnvError, match="ended an episode itself"):
        for _ in range(300):  # reach the goal by brute force: from the goal's own cell, push towards it
            td = env._output()
            direction = (td["desired_goal"] - td["achieved_goal"]).clamp(-1, 1)
            env.step(td.set("action", direction))


def test_check_goal_env_wants_float32_and_the_true_episode_length():
    env64 = make_env("PointMaze", num_envs=1, seed=0, max_episode_steps=5)
    env64.observation_spec["observation"].dtype = torch.float64
    with pytest.raises(GoalEnvError, match=r"observation.*float64; expected torch.float32.*DoubleToFloat"):
        check_goal_env(env64, steps=0)
    # an env that claims 40 steps and truncates at 5 (and one that claims 3)
    for claim, what in ((40, "truncated at step 5"), (3, "did not truncate at step 3")):
        liar = TransformedEnv(make_env("PointMaze", num_envs=1, seed=0, max_episode_steps=5))
        liar.max_episode_steps = claim
        with pytest.raises(GoalEnvError, match=what):
            check_goal_env(liar, steps=12)
    truthful = TransformedEnv(make_env("PointMaze", num_envs=1, seed=0, max_episode_steps=5))
    truthful.max_episode_steps = 5
    check_goal_env(truthful, steps=12)


def test_fixed_goals_replace_the_env_goals_in_turn_for_rewards_and_success():
    env = GymnasiumGoalEnv(UMAZE, 2, seed=0, goals=[[1.0, 1.0], [-1.0, -1.0]], reset_options={"reset_cell": [3, 1]})
    first, second = env.reset(), env.reset()
    assert first["desired_goal"].tolist() == [[1.0, 1.0]] * 2 and second["desired_goal"].tolist() == [[-1.0, -1.0]] * 2
    # the second goal is in the start cell: success within 0.45, as the env itself judges it after a step
    distance = (second["achieved_goal"] - second["desired_goal"]).norm(dim=-1, keepdim=True)
    assert torch.equal(second["is_success"], distance <= 0.45)
    td = env.step(second.set("action", torch.zeros(2, 2)))["next"]
    distance = (td["achieved_goal"] - td["desired_goal"]).norm(dim=-1, keepdim=True)
    assert torch.equal(td["is_success"], distance <= 0.45) and td["desired_goal"].tolist() == [[-1.0, -1.0]] * 2
    with pytest.raises(ValueError, match="`goals` must be None or a goal"):
        GymnasiumGoalEnv(UMAZE, goals="north")


def test_the_recipe_names_a_bad_test_goal_key():
    from _recipe import recipe_config

    from torchrl_dhrl.recipe import ConfigError
    from torchrl_dhrl.recipe.routing import check_components

    cfg = recipe_config(f"env_name=gymnasium:{UMAZE}", "gymnasium.eval_goals=[[1.0,1.0],[-1.0,1.0]]")
    check_components(cfg, goal_dim=2, error=ConfigError)
    cfg["gymnasium"]["eval_goals"] = "north"
    with pytest.raises(ConfigError, match=r"^`gymnasium.eval_goals` must be None or a goal"):
        check_components(cfg, goal_dim=2, error=ConfigError)
