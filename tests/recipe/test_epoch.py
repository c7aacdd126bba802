"""evaluate_epoch's test-time measures that need more than the rollout's success: the share of the test steps and
episodes an agent spends upside down, against a direct count over the returned rollout; the recipe's wiring of it."""

import pytest
import torch
from _recipe import load_recipe, recipe_config
from torchrl_dhrl.envs import AntAgent

from torchrl_dhrl.factory import make_agent, make_environment
from torchrl_dhrl.recipe import evaluate_epoch


def _agent_and_env():
    torch.manual_seed(0)
    env = make_environment("PointMaze", max_episode_steps=20)
    agent = make_agent(
        env,
        goal_indices=[0, 1],
        high_policy={"subgoal_low": [-2.0, -2.0], "subgoal_high": [10.0, 10.0], "interval": 5, "num_cells": (16,)},
        high_critic={"num_cells": (16,)},
        low_actor={"num_cells": (16,)},
        low_critic={"num_cells": (16,)},
        graph={"cutoff": 5.0},
    )
    eval_env = make_environment("PointMaze", num_envs=3, eval=True, max_episode_steps=20, agent=agent)
    return agent, eval_env


def test_the_share_of_test_steps_and_episodes_upside_down_is_a_direct_count():
    agent, eval_env = _agent_and_env()
    kwargs = dict(env_name="PointMaze", reward_threshold=0.5, far_from_graph_threshold=15.0, flat=False)
    # a stand-in test: "upside down" where the point's x lies past its median over the episodes' states
    threshold = {}

    def past_x(observation):
        x = observation[..., 0]
        threshold.setdefault("x", x.median())
        return x > threshold["x"]

    metrics, result = evaluate_epoch(agent, eval_env, 20, upside_down=past_x, **kwargs)
    x = result.rollout["next", "observation"][..., 0]
    flipped = x > threshold["x"]
    assert 0.0 < metrics["eval/upside_down"] < 1.0
    assert metrics["eval/upside_down"] == pytest.approx(flipped.float().mean().item())
    assert metrics["eval/ended_upside_down"] == pytest.approx(flipped[:, -1].float().mean().item())
    metrics, _ = evaluate_epoch(agent, eval_env, 20, **kwargs)  # not measured without a test
    assert "eval/upside_down" not in metrics and "eval/ended_upside_down" not in metrics


def test_the_recipe_measures_the_ants_only():
    utils = load_recipe("dhrl_utils")
    ant = utils.evaluation_kwargs(recipe_config("env=AntMazeSmall", "preset=smoke"))["upside_down"]
    assert ant is AntAgent.is_upside_down
    assert utils.evaluation_kwargs(recipe_config("env=PointMaze", "preset=smoke"))["upside_down"] is None
    assert utils.build_episode_log(recipe_config("env=AntMaze", "preset=smoke")).upside_down is AntAgent.is_upside_down
