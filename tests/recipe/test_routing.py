"""torchrl_dhrl.recipe.routing: every configuration key of a component reaches the argument of its name, and a new
hyperparameter needs the schema and the component only."""

from __future__ import annotations

import pytest
import torch
from _recipe import recipe_config
from dhrl_utils import build_agent, build_replay_buffers, build_updaters, config_schema

from torchrl_dhrl.checks import argument_names
from torchrl_dhrl.recipe import ConfigError, validate_config
from torchrl_dhrl.recipe.routing import (
    RECIPE_KEYS,
    RENAMED,
    TARGETS,
    ConfigRoutingError,
    check_components,
    component_arguments,
    group_keys,
    key_path,
)

SMALL = ("env=PointMaze", "preset=smoke", "device=cpu")


def test_every_key_of_the_schema_reaches_a_constructor_or_the_recipe():
    schema = config_schema()
    routed = component_arguments(schema)  # raises for a key that reaches nothing
    reached = [
        (group, key)
        for group in TARGETS
        for key in group_keys(schema, group)
        if key_path(group, key) not in RECIPE_KEYS
    ]
    top = {key for group, key in reached if group == "top"}  # the top-level keys that reach a constructor
    assert top == {
        "env_name", "num_envs", "seed", "episode_length", "goal_indices", "angle_features", "right_flipped_after",
        "reference_engine", "step_threads", "cudagraphs", "updates_per_graph", "compile", "capture_sampling",
        "compile_policy", "cudagraph_policy",
    }
    # each such key reached at least one target, under its own name or its RENAMED argument
    for group, key in reached:
        path = key_path(group, key)
        argument = RENAMED.get(path, key)
        names = [name for name in TARGETS[group] if argument in routed[name] or key in routed[name]]
        converted = [name for name, t in TARGETS[group].items() if key in t.convert]
        assert names or converted, path
    for path in [*RECIPE_KEYS, *RENAMED]:
        group, key = path.split(".") if "." in path else ("top", path)
        assert key in group_keys(schema, group), f"{path} is not a key of config.yaml"
    for path, argument in RENAMED.items():  # a renamed key names an argument some target of its group takes
        group = path.split(".")[0] if "." in path else "top"
        assert any(argument in argument_names(t.build) for t in TARGETS[group].values()), path


def test_the_routed_values_are_the_configuration_values():
    cfg = recipe_config("env=AntMaze", "low.critic_goal=relative", "high.c_h=17", "low.hidden=[64,32]")
    args = component_arguments(cfg)
    assert args["high_policy"]["interval"] == 17 and args["high_policy"]["noise_sigma"] == 2.0
    assert args["low_actor"] == {"relative_goal": True, "num_cells": [64, 32]}
    assert args["low_critic"]["relative_goal"] is True and args["low_critic"]["num_cells"] == [64, 32]
    assert args["exploration"] == {"sigma": 0.1, "uniform_prob": 0.2}
    assert args["sqgc_loss"]["target_noise_std"] == 0.05 and args["sqgc_loss"]["sqgc"] is True
    assert args["low_buffer"]["batch_size"] == 1024 and args["high_buffer"]["her_window"] == 15
    assert args["low_optimizers"] == {"actor_lr": 1e-4, "critic_lr": 1e-3}
    assert args["graph"] == {
        "cutoff": 30.0,
        "max_landmarks": 300,
        "early_stop": 10.0,
        "unreachable": "nearest_landmark",
    }
    assert args["planner"] == {"reach_radius": 0.5} and args["distance"] == {"twin": "optimistic"}
    assert args["oracle"] == {
        "speed": cfg["planner"]["oracle_speed"],
        "margin": cfg["planner"]["oracle_margin"],
    }
    assert args["goal_shifting"] == {"noise": 3.0, "weighting": "path_length", "trigger": "reachable"}
    # the keys the recipe reads are routed nowhere, even where a constructor has an argument so named
    assert "distance" not in args["planner"] and "enabled" not in args["goal_shifting"]


def test_a_key_that_reaches_no_constructor_is_an_error():
    cfg = recipe_config("env=AntMaze")
    cfg["low"]["bogus_rate"] = 0.5
    with pytest.raises(ConfigRoutingError, match="`low.bogus_rate` reaches no constructor"):
        component_arguments(cfg)


def test_a_new_hyperparameter_needs_the_schema_and_the_component_only():
    """Keys the schema does not define today, named as their components' arguments, reach them unchanged."""
    cfg = recipe_config(*SMALL)
    cfg["low"]["target_noise_clip"] = 0.3  # SQGCLoss
    cfg["high"]["loss_function"] = "l1"  # HighLevelLoss
    cfg["planner"]["max_path_length"] = 7  # GraphPlanner
    cfg["fgs"]["temperature"] = 2.0  # FrontierGoalShifting
    cfg["low"]["fused"] = False  # make_optimizers
    validate_config(cfg)
    device = torch.device("cpu")
    agent = build_agent(cfg, device)
    assert agent.sqgc_loss.target_noise_clip == 0.3 and agent.high_loss.loss_function == "l1"
    assert agent.planner.max_path_length == 7
    assert component_arguments(cfg)["goal_shifting"]["temperature"] == 2.0
    low_rb, high_rb = build_replay_buffers(cfg, agent, device)
    build_updaters(cfg, agent, low_rb, high_rb)
    # and its range, declared on the component, is checked before anything is built, naming the key
    cfg["low"]["target_noise_clip"] = -1.0
    with pytest.raises(
        ConfigError, match=r"^`low.target_noise_clip` must be None or a number > 0, got -1.0\.$"
    ):
        validate_config(cfg)


@pytest.mark.parametrize(
    "override, key",
    [
        ("low.hidden=[0]", "low.hidden"),
        ("low.action_noise=-1.0", "low.action_noise"),
        ("low.target_noise=-1.0", "low.target_noise"),
        ("high.hidden=[16,0]", "high.hidden"),
        ("high.c_h=0", "high.c_h"),
        ("high.subgoal_noise=-2.0", "high.subgoal_noise"),
        ("high.target_noise=-1.0", "high.target_noise"),
        ("planner.oracle_speed=0", "planner.oracle_speed"),
        ("planner.oracle_margin=-1", "planner.oracle_margin"),
        ("low.critic_goal=relative low.relative_goal=false goal_indices=null", "low.critic_goal"),
        ("low.sqgc=1", "low.sqgc"),
        ("high.actor_after_critic_step=yes", "high.actor_after_critic_step"),
        ("fgs.trigger=near", "fgs.trigger"),
        ("planner.twin=average", "planner.twin"),
        ("high.gradual_penalty=-1.0", "high.gradual_penalty"),
        ("low.polyak=1.5", "low.polyak"),
        ("high.critic_lr=0", "high.critic_lr"),
    ],
)
def test_the_components_refusals_name_the_configuration_key(override, key):
    cfg = recipe_config("env=PointMaze", *override.split())
    with pytest.raises(ConfigError) as info:
        validate_config(cfg)
    message = str(info.value)
    assert message.startswith(f"`{key}") and "\n" not in message, message
    argument = RENAMED.get(key, key.split(".")[1])
    if argument != key.split(".")[1]:
        assert f"`{argument}`" not in message  # the argument is named after the key, not by its own name


def test_check_components_with_the_goal_size_of_a_built_env():
    cfg = recipe_config("env=PointMaze")
    check_components(cfg, goal_dim=2)
    with pytest.raises(ValueError, match=r"`high.subgoal_low` must have 3 entries"):
        check_components(cfg, goal_dim=3)
