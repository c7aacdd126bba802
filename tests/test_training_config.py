"""The recipe's configuration: every env composes and validates; bad values fail before anything runs."""

import pytest
import torch
from _recipe import recipe_config
from torchrl_dhrl.envs import ENV_NAMES

from torchrl_dhrl.training import ConfigError, resolve_device, validate_config

REFERENCE = {  # c_h, high-level window, max landmarks, p2, warm-up episodes, FGS
    "AntMazeSmall": (30, 20, 300, 5.0, 200, False),
    "AntMaze": (40, 15, 300, 5.0, 200, False),
    "AntMazeBottleneck": (50, 12, 300, 1.5, 200, False),
    "AntMazeComplex": (80, 25, 500, 1.5, 700, True),
}


@pytest.mark.parametrize("env", ENV_NAMES)
def test_every_env_config_is_valid(env):
    cfg = recipe_config(f"env={env}")
    validate_config(cfg)
    assert cfg["env_name"] == env


@pytest.mark.parametrize("env", sorted(REFERENCE))
def test_env_configs_hold_the_reference_hyperparameters(env):
    cfg = recipe_config(f"env={env}")
    got = (
        cfg["high"]["c_h"],
        cfg["high"]["her_window"],
        cfg["planner"]["max_landmarks"],
        cfg["high"]["gradual_penalty"],
        cfg["schedule"]["warmup_episodes"],
        cfg["fgs"]["enabled"],
    )
    assert got == REFERENCE[env]
    # shared reference values
    assert cfg["low"]["batch_size"] == cfg["high"]["batch_size"] == 1024
    assert cfg["low"]["her_window"] == 150 and cfg["low"]["her_ratio"] == 0.8
    assert cfg["planner"]["cutoff"] == 30 and cfg["planner"]["candidates"] == 6000
    assert cfg["low"]["polyak"] == 0.995 and cfg["low"]["target_update_interval"] == 10
    assert cfg["schedule"]["epoch_episodes"] == 15 and cfg["schedule"]["eval_episodes"] == 10


def test_command_line_overrides_and_presets():
    cfg = recipe_config("env=AntMaze", "seed=3", "total_steps=1000000", "preset=quick", "low.sqgc=false")
    assert (cfg["seed"], cfg["total_steps"], cfg["low"]["sqgc"]) == (3, 1000000, False)
    assert cfg["low"]["batch_size"] == 256  # from the preset
    assert cfg["high"]["c_h"] == 40  # from the env file, untouched by the preset


@pytest.mark.parametrize(
    "override, match",
    [
        ("env_name=AntMase", "Unknown env_name 'AntMase'"),
        ("high.c_h=0", "high.c_h"),
        ("planner.cutoff=0", "planner.cutoff"),
        ("planner.max_landmarks=1", "max_landmarks"),
        ("planner.candidates=10", "planner.candidates"),
        ("planner.distance=magic", "planner.distance"),
        ("low.gamma=1.0", "low.gamma"),
        ("low.her_ratio=1.5", "low.her_ratio"),
        ("num_envs=0", "num_envs"),
        ("total_steps=0", "total_steps"),
        ("logger.backend=mlflow", "logger.backend"),
        ("high.subgoal_low=[20.0,20.0]", "below"),
        ("high.subgoal_low=[0.0]", "same length"),
        ("low.hidden=[]", "low.hidden"),
        ("device=tpu", "device"),
        ("planner.build_dtype=int8", "build_dtype"),
        ("planner.reach_radius=0", "reach_radius"),
    ],
)
def test_bad_values_get_a_clear_error(override, match):
    cfg = recipe_config("env=AntMaze", override)
    with pytest.raises(ConfigError, match=match):
        validate_config(cfg)


def test_missing_key():
    cfg = recipe_config("env=AntMaze")
    del cfg["planner"]["cutoff"]
    with pytest.raises(ConfigError, match="Missing configuration key `planner.cutoff`"):
        validate_config(cfg)


@pytest.mark.parametrize("bad", ["float16", "bf16", "float64"])
def test_update_dtype_is_checked(bad):
    with pytest.raises(ConfigError, match="update_dtype"):
        validate_config(recipe_config("env=AntMaze", "device=cpu", f"update_dtype={bad}"))
    validate_config(recipe_config("env=AntMaze", "device=cpu", "update_dtype=bfloat16"))


def test_cudagraphs_need_a_cuda_device():
    with pytest.raises(ConfigError, match="cudagraphs"):
        validate_config(recipe_config("env=AntMaze", "device=cpu", "cudagraphs=true"))
    validate_config(recipe_config("env=AntMaze", "device=cpu", "cudagraphs=false"))


def test_resolve_device():
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_device("cpu") == torch.device("cpu")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="CUDA"):
            resolve_device("cuda")


@pytest.mark.parametrize(
    "env, value, ok",
    [
        ("Reacher3D", "[4,6]", True),
        ("Reacher3D", "null", True),
        ("Reacher3D", "[4,4]", False),  # repeated
        ("Reacher3D", "[17]", False),  # outside the 17-D observation
        ("Reacher3D", "[]", False),
        ("Reacher3D", "[1.5]", False),
        ("AntMaze", "[0]", False),  # the achieved goal's (x, y) are not angles
        ("AntMaze", "[5,6]", True),
    ],
)
def test_angle_features_values(env, value, ok):
    cfg = recipe_config(f"env={env}", f"angle_features={value}")
    if ok:
        validate_config(cfg)
    else:
        with pytest.raises(ConfigError, match="angle_features"):
            validate_config(cfg)
