"""The goal-env contract: ``check_goal_env``, ``register_env`` and the recipe trained on a user-made env.

The env below is written here, not taken from ``torchrl_dhrl.envs``: a point mass in an open square, a
plain TorchRL ``EnvBase`` registered by the tests only.
"""

import csv

import pytest
import torch
from _point_square import PointSquare, make_point_square
from _recipe import load_recipe, recipe_config
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs.utils import check_env_specs
from torchrl.testing.mocking_classes import ContinuousActionVecMockEnv
from torchrl_dhrl.envs import (
    ENV_NAMES,
    GoalEnvError,
    check_goal_env,
    make_env,
    register_env,
    registered_env_names,
    unregister_env,
)

from torchrl_dhrl.recipe import ConfigError, load_checkpoint, validate_config

NAME = "PointSquare"
#: The env-specific keys of an env/<Name>.yaml, as Hydra overrides (the smoke preset sets the rest).
OVERRIDES = (
    f"env_name={NAME}",
    "goal_indices=[0,1]",
    "high.subgoal_low=[-4.0,-4.0]",
    "high.subgoal_high=[4.0,4.0]",
    "planner.oracle_speed=0.3",
)


@pytest.fixture
def registered():
    register_env(NAME, make_point_square)
    yield NAME
    unregister_env(NAME)


# ------------------------------------------------------------------ the contract
@pytest.mark.parametrize(
    "name, indices", [("PointMaze", [0, 1]), ("Reacher3D", None), ("UR3Obstacle", [0, 1, 2])]
)
def test_builtin_envs_meet_the_contract(name, indices):
    check_goal_env(make_env(name, num_envs=2, seed=0, max_episode_steps=5), goal_indices=indices, steps=6)


def test_the_user_env_meets_the_contract_and_torchrl_specs():
    env = PointSquare(3, seed=0, max_episode_steps=4)
    check_env_specs(env)
    check_goal_env(env, goal_indices=[0, 1], steps=5)  # across an automatic reset
    check_goal_env(PointSquare(seed=0), steps=0)  # specs only
    with pytest.raises(TypeError, match="EnvBase"):
        check_goal_env(object())


class _FloatSuccess(PointSquare):
    def _out(self, **extra):
        return super()._out(**extra).set("is_success", torch.zeros(*self.batch_size, 1))


class _NoTimeLimit(PointSquare):
    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        del self.max_episode_steps


class _DoneWithoutFlags(PointSquare):
    def _step(self, tensordict):
        out = super()._step(tensordict)
        return out.set("done", torch.ones_like(out["done"]))


@pytest.mark.parametrize(
    "make, match",
    [
        (ContinuousActionVecMockEnv, "observation_spec has no 'achieved_goal' entry"),
        (
            lambda: type("ThreeDGoals", (PointSquare,), {"goal_dim": 3})(2, max_episode_steps=3),
            r"desired_goal.*goal_dim = 3.*achieved_goal and desired_goal must have the same size",
        ),
        (
            lambda: _spec_variant("is_success", Unbounded((2, 1))),
            r"is_success.*float32; expected torch\.bool",
        ),
        (
            lambda: _spec_variant("step_count", Unbounded((2,), dtype=torch.int64)),
            r"step_count.*shape \(2,\)",
        ),
        (lambda: _NoTimeLimit(2), "max_episode_steps is None; expected the episode length"),
        (lambda: _action_variant(Unbounded((2, 2))), "action.*Bounded"),
        (lambda: _action_variant(Bounded(-torch.inf, torch.inf, (2, 2))), "infinite bounds"),
        (lambda: _FloatSuccess(2, max_episode_steps=3), r"rollout's 'is_success' is torch\.float32"),
        (lambda: _DoneWithoutFlags(2, max_episode_steps=3), r"done must equal terminated \| truncated"),
    ],
)
def test_check_goal_env_names_the_key_and_what_is_accepted(make, match):
    with pytest.raises(GoalEnvError, match=match) as info:
        check_goal_env(make())
    assert "docs/goal_env.md" in str(info.value)


def _spec_variant(key, spec):
    env = PointSquare(2, max_episode_steps=3)
    env.observation_spec = Composite({**env.observation_spec, key: spec}, shape=env.batch_size)
    return env


def _action_variant(spec):
    env = PointSquare(2, max_episode_steps=3)
    env.action_spec = spec
    return env


def test_goal_indices_are_checked_on_the_rollout():
    env = PointSquare(2, seed=0)
    check_goal_env(env, goal_indices=[0, 1])
    with pytest.raises(GoalEnvError, match=r"observation\[\.\.\., \[1, 0\]\] is not the achieved_goal"):
        check_goal_env(env, goal_indices=[1, 0])
    with pytest.raises(GoalEnvError, match="outside the 2-D observation"):
        check_goal_env(env, goal_indices=[0, 5])


# ------------------------------------------------------------------ the registry
def test_register_env_makes_the_env_available_to_make_env(registered):
    assert NAME in registered_env_names() and NAME not in ENV_NAMES
    env = make_env(NAME, num_envs=3, seed=1, eval=True, max_episode_steps=7)
    assert isinstance(env, PointSquare) and env.batch_size == (3,) and env.max_episode_steps == 7
    assert env.reset()["desired_goal"].tolist() == [[3.0, 3.0]] * 3
    first = make_env(NAME, num_envs=2, seed=4).reset()["desired_goal"]
    assert torch.equal(first, make_env(NAME, num_envs=2, seed=4).reset()["desired_goal"])  # seeded
    with pytest.raises(ValueError, match="already registered"):
        register_env(NAME, make_point_square)
    register_env(NAME, make_point_square, overwrite=True)
    with pytest.raises(ValueError, match="built-in"):
        register_env("PointMaze", make_point_square)
    with pytest.raises(TypeError, match="callable"):
        register_env("Other", 3)
    with pytest.raises(ValueError, match="was registered"):
        unregister_env("Other")


def test_make_env_checks_what_a_factory_returns():
    register_env("Broken", lambda **kw: PointSquare(1))  # ignores num_envs
    register_env("NotAnEnv", lambda **kw: "env")
    register_env(
        "ThreeD", lambda num_envs, **kw: type("ThreeDGoals", (PointSquare,), {"goal_dim": 3})(num_envs)
    )
    try:
        with pytest.raises(GoalEnvError, match=r"batch_size \(1,\) for num_envs=2"):
            make_env("Broken", num_envs=2)
        with pytest.raises(TypeError, match="not an EnvBase"):
            make_env("NotAnEnv")
        with pytest.raises(GoalEnvError, match="desired_goal"):
            make_env("ThreeD", num_envs=2)
    finally:
        for name in ("Broken", "NotAnEnv", "ThreeD"):
            unregister_env(name)


def test_validate_config_accepts_registered_names_and_rejects_others(registered):
    cfg = recipe_config("preset=smoke", *OVERRIDES)
    validate_config(cfg)
    unregister_env(NAME)
    try:
        with pytest.raises(
            ConfigError, match=f"Unknown env_name '{NAME}'; choose one of: PointMaze.*register_env"
        ):
            validate_config(cfg)
    finally:
        register_env(NAME, make_point_square)
    with pytest.raises(
        ConfigError, match=rf"Unknown env_name 'PointSqare'; .*UR3Obstacle, {NAME} \(or register"
    ):
        validate_config({**cfg, "env_name": "PointSqare"})


# ------------------------------------------------------------------ the recipe on the user env
@pytest.mark.recipe
def test_recipe_smoke_run_on_a_registered_user_env(registered, tmp_path):
    recipe = load_recipe()
    torch.manual_seed(0)
    cfg = recipe_config("preset=smoke", "logger.backend=csv", "device=cpu", *OVERRIDES)
    summary = recipe.train(cfg, run_dir=tmp_path)
    with (tmp_path / "metrics.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert [int(r["env_steps"]) for r in rows] == [80 * k for k in range(1, 7)]  # 2 envs x 40 steps a batch
    assert int(rows[0]["graph/landmarks"]) == 0 and all(
        2 <= int(r["graph/landmarks"]) <= 12 for r in rows[1:]
    )
    for r in rows:
        assert 0.0 <= float(r["eval/success"]) <= float(r["eval/any_success"]) <= 1.0
    assert torch.isfinite(torch.tensor(float(rows[-1]["low/loss_graph_qvalue"])))
    assert (
        "diag/subgoals_in_walls" not in rows[0] and "diag/edges_crossing_walls" not in rows[0]
    )  # mazes only
    assert summary["eval/success"] == float(rows[-1]["eval/success"])
    assert len(list((tmp_path / "episodes").glob("epoch_*.png"))) == 6  # drawn without a scene
    state = load_checkpoint(tmp_path / "checkpoint")
    assert state["counters"]["env_steps"] == 480 and state["config"]["env_name"] == NAME


@pytest.mark.recipe
def test_recipe_stops_on_a_registered_env_that_breaks_the_contract(registered, tmp_path):
    recipe = load_recipe()
    smoke = ("preset=smoke", "logger.backend=csv", "device=cpu", *OVERRIDES)
    with pytest.raises(
        ConfigError, match=r"env_name=PointSquare: PointSquare: observation\[\.\.\., \[1, 0\]\]"
    ):
        recipe.train(recipe_config(*smoke, "goal_indices=[1,0]"), run_dir=tmp_path)
    register_env(NAME, lambda **kw: make_point_square(cls=_FloatSuccess, **kw), overwrite=True)
    with pytest.raises(ConfigError, match=r"env_name=PointSquare: _FloatSuccess: a rollout's 'is_success'"):
        recipe.train(recipe_config(*smoke), run_dir=tmp_path)
    assert not (tmp_path / "metrics.csv").exists() and not (tmp_path / "checkpoint").exists()


def test_a_missing_key_says_what_to_add():
    from torchrl.envs import TransformedEnv
    from torchrl.envs.transforms import ExcludeTransform
    from torchrl.testing.mocking_classes import ContinuousActionVecMockEnv

    with pytest.raises(GoalEnvError, match=r"no 'achieved_goal' entry.*GymnasiumGoalEnv"):
        check_goal_env(ContinuousActionVecMockEnv(), steps=0)
    env = TransformedEnv(make_env("PointMaze", seed=0), ExcludeTransform("step_count"))
    with pytest.raises(GoalEnvError, match=r"no 'step_count' entry.*StepCounter\(max_steps=T\)"):
        check_goal_env(env, steps=0)
