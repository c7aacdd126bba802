"""A newcomer's own env in the recipe: a registered env, a Gymnasium goal env by id, and what used to break late or
silently (the runpy launcher, a hidden max_episode_steps, float64, a wrong episode length, a stateless env's
resume, goal-unit keys inherited from AntMaze, a stray Hydra directory, config.yaml of a refused run)."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import numpy as np
import pytest
import torch
import yaml
from _point_square import PointSquare
from _recipe import RECIPES, TIMING_COLUMNS, load_recipe, metrics_rows, recipe_config
from torchrl.envs import Compose, TransformedEnv
from torchrl_dhrl.envs import register_env, unregister_env

from torchrl_dhrl.recipe import ConfigError

recipe = load_recipe()
SMOKE = ("preset=smoke", "device=cpu", "logger.backend=none", "plots.every_epochs=0", "threads=1")


class HiddenLength(PointSquare):
    """The tests' point square with a success radius, and without a ``max_episode_steps`` attribute of its own: the
    factory sets it on a TransformedEnv around it (the docs' tip), where the recipe must read it."""

    success_radius = 0.5

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        del self.max_episode_steps


def _factory(**options):
    def make(*, num_envs, seed, device, eval, max_episode_steps):  # noqa: A002
        claim = options.get("claim")
        length = max_episode_steps or 40
        dtype = options.get("dtype", torch.float32)
        inner = HiddenLength(num_envs, seed=seed, device=device, eval=eval, max_episode_steps=length, dtype=dtype)
        env = TransformedEnv(inner, Compose())  # the docs' tip: the length on the wrapper, not on the env
        env.max_episode_steps = claim or length
        return env

    return make


@pytest.fixture
def user_env():
    names = []

    def register(name, **options):
        register_env(name, _factory(**options), overwrite=True)
        names.append(name)
        return name

    yield register
    for name in names:
        unregister_env(name)


CUSTOM = ("env=custom", "high.c_h=10")


@pytest.mark.recipe
def test_a_registered_env_trains_with_derived_goal_units_and_its_length_on_a_wrapper(user_env, tmp_path, capsys):
    name = user_env("PointSquareT")
    out = recipe.train(recipe_config(*CUSTOM, f"env_name={name}", *SMOKE), run_dir=tmp_path / "run")
    assert out["env_steps"] == 480
    printed = capsys.readouterr().out
    assert f"Derived from {name}: goal_indices=[0, 1]" in printed and "low.reward_threshold=0.5" in printed
    saved = yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())
    assert saved["low"]["reward_threshold"] == 0.5 and saved["planner"]["reach_radius"] == 0.5
    low, high = saved["high"]["subgoal_low"], saved["high"]["subgoal_high"]
    assert all(-4.9 < v < -3.0 for v in low) and all(3.0 < v < 4.9 for v in high)  # the square, with a margin
    extent = max(h - lo for lo, h in zip(low, high, strict=True))  # derived, as for env=gymnasium
    assert saved["planner"]["oracle_margin"] == pytest.approx(extent / 48, rel=1e-3)


@pytest.mark.recipe
def test_a_stateless_env_resumes_with_a_warning(user_env, tmp_path):
    name = user_env("PointSquareW")
    cfg = recipe_config(*CUSTOM, f"env_name={name}", *SMOKE, "total_steps=240")
    recipe.train(cfg, run_dir=tmp_path / "run")
    cfg = recipe_config(*CUSTOM, f"env_name={name}", *SMOKE, f"resume={tmp_path / 'run'}")
    with pytest.warns(UserWarning, match=r"training env \(HiddenLength\) keeps no state"):
        recipe.train(cfg, run_dir=tmp_path / "run")


@pytest.mark.parametrize(
    "options, match",
    [
        ({"claim": 60}, r"max_episode_steps is 60, but the env truncated at step 40"),
        ({"dtype": torch.float64}, r"float64; expected torch.float32"),
    ],
)
def test_a_user_env_that_breaks_the_contract_is_refused_before_anything_is_written(user_env, tmp_path, options, match):
    name = user_env("PointSquareBad", **options)
    overrides = (*CUSTOM, f"env_name={name}", *SMOKE, "low.reward_threshold=0.5")
    with pytest.raises(ConfigError, match=match):
        recipe.train(recipe_config(*overrides, "goal_indices=[0,1]", "high.subgoal_low=[-4,-4]",
                                   "high.subgoal_high=[4,4]", "high.subgoal_noise=0.5", "planner.reach_radius=0.5",
                                   "fgs.noise=1.0"), run_dir=tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_a_user_env_with_antmaze_goal_units_is_refused(user_env, tmp_path):
    name = user_env("PointSquareA")
    with pytest.raises(ConfigError, match=r"default env file's values in goal units.*env=custom"):
        recipe.train(recipe_config(f"env_name={name}", "goal_indices=[0,1]", *SMOKE), run_dir=tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_a_user_env_whose_subgoal_box_misses_the_goal_size_names_the_key(user_env, tmp_path):
    name = user_env("PointSquareB")
    cfg = recipe_config(*CUSTOM, f"env_name={name}", *SMOKE, "high.subgoal_low=[-4,-4,-4]", "high.subgoal_high=[4,4,4]")
    with pytest.raises(ConfigError, match=r"`high.subgoal_low` must have 2 entries"):
        recipe.train(cfg, run_dir=tmp_path / "run")
    assert not (tmp_path / "run").exists()  # no config.yaml of a refused run


def _cli(*args, cwd):
    return subprocess.run(
        [sys.executable, str(RECIPES / "dhrl_antmaze.py"), *args],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=cwd,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )


def test_the_documented_runpy_launcher_finds_the_recipe_helpers(tmp_path):
    code = f"import runpy; ns = runpy.run_path({str(RECIPES / 'dhrl_antmaze.py')!r}); print(callable(ns['train']))"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, env=env)
    assert result.returncode == 0 and result.stdout.strip() == "True", result.stderr[-2000:]


@pytest.mark.recipe
def test_the_gymnasium_command_of_the_docs_trains_and_leaves_no_stray_hydra_directory(tmp_path):
    pytest.importorskip("gymnasium_robotics")
    run_dir = tmp_path / "umaze"
    result = _cli(
        "env=gymnasium", "env_name=gymnasium:PointMaze_UMaze-v3", "preset=smoke", f"run_dir={run_dir}", cwd=tmp_path
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "Derived from gymnasium:PointMaze_UMaze-v3: goal_indices=[0, 1]" in result.stdout
    assert "low.reward_threshold=0.45" in result.stdout
    assert len(metrics_rows(run_dir, TIMING_COLUMNS)) >= 2
    assert (run_dir / ".hydra" / "overrides.yaml").exists()  # Hydra's record of the job, moved into the run
    assert sorted(p.name for p in tmp_path.iterdir()) == ["umaze"]  # no outputs/<date>/<time>


@pytest.mark.recipe
def test_an_ant_maze_whose_observation_leaves_out_the_goal_starts_and_trains(tmp_path, capsys):
    """AntMaze_UMaze-v5 observes the torso without its x, y: the run used to stop at once (`low.relative_goal` needs
    `goal_indices`, got None); the adapter now puts the achieved goal first, and the recipe says so."""
    pytest.importorskip("gymnasium_robotics")
    cfg = recipe_config("env=gymnasium", "env_name=gymnasium:AntMaze_UMaze-v5", *SMOKE, "episode_length=10",
                        "total_steps=20")
    recipe.train(cfg, run_dir=tmp_path / "run")
    printed = capsys.readouterr().out
    assert (
        "gymnasium:AntMaze_UMaze-v5: its observation leaves out the achieved goal, so GymnasiumGoalEnv puts it first: "
        "observation[0:2] = achieved_goal (107 entries, the env's 105 after it)." in printed
    )
    assert "Derived from gymnasium:AntMaze_UMaze-v5: goal_indices=[0, 1]" in printed and "Done: 20 env steps" in printed
    assert yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())["goal_indices"] == [0, 1]
    assert (
        "gymnasium:AntMaze_UMaze-v5: its ant can flip over and nothing in the env rights it (the episode goes on with "
        "the ant on its back; train/upside_down logs how often): right_flipped_after=10 puts it back on its feet"
    ) in printed


@pytest.mark.recipe
def test_a_gymnasium_ant_maze_logs_its_upside_down_steps_and_right_flipped_after_rights_the_ant(tmp_path, capsys):
    """gymnasium-robotics' ant flips over (its gear-150 motors): the run logs the share of training steps spent upside
    down, as the built-in ant mazes' runs; ``right_flipped_after`` reaches the adapter (training and test envs)."""
    pytest.importorskip("gymnasium_robotics")
    base = ("env=gymnasium", "env_name=gymnasium:AntMaze_UMaze-v5", *SMOKE, "episode_length=10", "total_steps=20")
    utils = load_recipe("dhrl_utils")
    cfg = utils.resolve_goal_units(recipe_config(*base, "right_flipped_after=1"))
    assert "its ant can flip over" not in capsys.readouterr().out  # said only where nothing rights it
    assert utils.build_environment(cfg, torch.device("cpu")).right_flipped_after == 1
    assert utils.build_environment(cfg, torch.device("cpu"), eval=True).right_flipped_after == 1
    recipe.train(cfg, run_dir=tmp_path / "run")
    rows = metrics_rows(tmp_path / "run")
    shares = [float(r["train/upside_down"]) for r in rows if r.get("train/upside_down")]
    assert shares and all(0.0 <= s <= 1.0 for s in shares)
    point = recipe_config("env=gymnasium", "env_name=gymnasium:PointMaze_UMaze-v3", *SMOKE, "right_flipped_after=1")
    with pytest.raises(ConfigError, match="`right_flipped_after` rights a flipped ant: it applies to the ant mazes"):
        recipe.train(point, run_dir=tmp_path / "point")
    assert not (tmp_path / "point").exists()  # refused before the run began


GOAL_UNITS = ("goal_indices=[0,1]", "high.subgoal_low=[-2.0,-2.0]", "high.subgoal_high=[2.0,2.0]",
              "high.subgoal_noise=0.3", "low.reward_threshold=0.45", "planner.reach_radius=0.45", "fgs.noise=0.5",
              "planner.oracle_margin=0.125", "planner.oracle_speed=0.052")


@pytest.mark.parametrize("given", [(), GOAL_UNITS], ids=["derived", "given"])
def test_a_maze_made_to_end_its_episodes_is_refused_at_start_up(tmp_path, capsys, given):
    """`continuing_task:false` used to start and train, and to be refused only when an episode first reached its goal
    (hours in): the maze says so beforehand, and the run stops before anything is built or written, goal units
    derived or not."""
    pytest.importorskip("gymnasium_robotics")
    cfg = recipe_config("env=gymnasium", "env_name=gymnasium:PointMaze_UMaze-v3", *SMOKE,
                        "gymnasium.make_kwargs={continuing_task:false}", *given)
    with pytest.raises(ConfigError, match=(
        r"^env_name=gymnasium:PointMaze_UMaze-v3: PointMaze_UMaze-v3 has continuing_task=False "
        r"\(`gymnasium.make_kwargs`=\{'continuing_task': False\}\): it ends an episode itself .* accepted: "
        r"continuing_task=True \(the mazes' default: leave it out of `gymnasium.make_kwargs`, or set it there\)\.$"
    )) as refused:
        recipe.train(cfg, run_dir=tmp_path / "run")
    assert "\n" not in str(refused.value)
    assert "Threads:" not in capsys.readouterr().out  # refused before start_run's checks and lines
    assert not (tmp_path / "run").exists()


def test_goal_units_the_env_cannot_tell_are_named(user_env):
    from torchrl_dhrl.envs import make_env

    from torchrl_dhrl.recipe import derive_goal_units

    cfg = recipe_config("env=custom", "env_name=PointMaze")
    with pytest.raises(ConfigError, match=r"`low.reward_threshold` is null .* set low.reward_threshold"):
        derive_goal_units(cfg, make_env("PointMaze", seed=0))  # the built-in env has no success_radius
    cfg["low"]["reward_threshold"] = 0.5
    notes = derive_goal_units(cfg, make_env("PointMaze", seed=0))
    assert cfg["goal_indices"] == [0, 1] and cfg["planner"]["reach_radius"] == 0.5
    assert cfg["fgs"]["noise"] == pytest.approx(1.5 * cfg["high"]["subgoal_noise"], rel=1e-3)  # extent/8, /12
    assert [note.split("=")[0] for note in notes] == [
        "goal_indices", "high.subgoal_low", "high.subgoal_high", "high.subgoal_noise", "planner.reach_radius",
        "fgs.noise", "planner.oracle_margin", "planner.oracle_speed",
    ]
    assert cfg["planner"]["oracle_speed"] == 0.2  # PointMaze's top speed, as its env file sets it
    # no maze on the env: the agent's radius is a 48th of the subgoal box's largest side
    extent = max(h - lo for lo, h in zip(cfg["high"]["subgoal_low"], cfg["high"]["subgoal_high"], strict=True))
    assert cfg["planner"]["oracle_margin"] == pytest.approx(extent / 48, rel=1e-3)


def test_a_resumed_run_writes_where_it_wrote(tmp_path):
    from dhrl_utils import resumed_run_dir

    (tmp_path / "run" / "checkpoint").mkdir(parents=True)
    (tmp_path / "run" / "checkpoint" / "manifest.json").write_text("{}")
    assert resumed_run_dir({"resume": str(tmp_path / "run")}) == (tmp_path / "run").resolve()
    assert resumed_run_dir({"resume": str(tmp_path / "run" / "checkpoint")}) == (tmp_path / "run").resolve()
    assert resumed_run_dir({"resume": "auto"}) is None and resumed_run_dir({"resume": None}) is None
    assert resumed_run_dir({"resume": str(tmp_path / "run"), "fork": "x"}) is None  # a fork is a new run
    assert resumed_run_dir({"resume": str(tmp_path / "nothing")}) is None


@pytest.mark.recipe
def test_a_gymnasium_run_resumes_exactly(tmp_path):
    pytest.importorskip("gymnasium_robotics")
    gym = ("env=gymnasium", "env_name=gymnasium:PointMaze_UMaze-v3", *SMOKE)
    recipe.train(recipe_config(*gym), run_dir=tmp_path / "straight")
    recipe.train(recipe_config(*gym, "total_steps=240"), run_dir=tmp_path / "resumed")
    recipe.train(recipe_config(*gym, f"resume={tmp_path / 'resumed'}"), run_dir=tmp_path / "resumed")
    assert metrics_rows(tmp_path / "resumed", TIMING_COLUMNS) == metrics_rows(tmp_path / "straight", TIMING_COLUMNS)


def test_a_gymnasium_maze_run_measures_against_its_maze(tmp_path, capsys):
    """A gymnasium-robotics maze gets the built-in mazes' diagnostics: the agent's radius derived from its cells (an
    8th of a cell), the ``diag/...`` metrics against its walls and, with a fixed start cell, the training frontier
    (within the maze's farthest free point from the start); resets that start anywhere leave the frontier out."""
    pytest.importorskip("gymnasium_robotics")
    from torchrl_dhrl.envs import GymnasiumGoalEnv

    gym = ("env=gymnasium", "env_name=gymnasium:PointMaze_UMaze-v3", *SMOKE, "total_steps=240")
    start = ("gymnasium.reset_options={reset_cell:[3,1]}",)
    recipe.train(recipe_config(*gym, *start), run_dir=tmp_path / "fixed")
    printed = capsys.readouterr().out
    assert "planner.oracle_margin=0.125;" in printed and "planner.oracle_speed=0.05" in printed  # the point's top speed
    assert re.search(r"In goal units at the top speed 0\.05\d* per step: high\.c_h=(\d+) steps reach ([\d.]+), "
                     r"planner\.cutoff=30 steps 1\.5\d* \([\d.]+ and 1\.\d of its 1-unit cells\)\.", printed)
    planner = yaml.safe_load((tmp_path / "fixed" / "config.yaml").read_text())["planner"]
    assert planner["oracle_margin"] == 0.125 and 0.04 <= planner["oracle_speed"] <= 0.0523
    rows = metrics_rows(tmp_path / "fixed", TIMING_COLUMNS)
    geometry = GymnasiumGoalEnv("PointMaze_UMaze-v3", reset_options={"reset_cell": [3, 1]}).maze_geometry(margin=0.125)
    farthest = geometry.path_length(geometry.start, geometry.cell_centers[geometry.free]).max().item()
    frontier = [float(r["train/frontier"]) for r in rows]
    assert all(0.0 <= f <= farthest + 0.5 for f in frontier) and frontier == sorted(frontier)
    for key in ("diag/subgoals_in_walls", "diag/waypoints_in_walls", "diag/start_subgoal_feasible"):
        assert all(0.0 <= float(r[key]) <= 1.0 for r in rows), key
    assert any(float(r["diag/landmark_coverage"]) > 0 for r in rows)
    recipe.train(recipe_config(*gym), run_dir=tmp_path / "anywhere")
    rows = metrics_rows(tmp_path / "anywhere", TIMING_COLUMNS)
    assert "train/frontier" not in rows[-1] and 0.0 <= float(rows[-1]["diag/subgoals_in_walls"]) <= 1.0


def test_the_oracle_of_a_gymnasium_maze_is_blocked_by_its_walls():
    """``planner.distance=oracle`` (and the diagnostics' oracle) on a gymnasium-robotics maze: straight steps at
    ``planner.oracle_speed`` along a corridor, ``blocked`` through a wall cell of the env's own map (the U's inner
    wall between cells (1, 1) and (3, 1)); it was a wall-less line of sight."""
    pytest.importorskip("gymnasium_robotics")
    from dhrl_utils import oracle_distance
    from torchrl_dhrl.envs import GymnasiumGoalEnv

    cfg = recipe_config("env=gymnasium", "env_name=gymnasium:PointMaze_UMaze-v3", "goal_indices=[0,1]",
                        "planner.oracle_speed=0.05", "planner.oracle_margin=0.125")
    env = GymnasiumGoalEnv("PointMaze_UMaze-v3")
    maze = env._envs[0].unwrapped.maze
    assert maze.maze_map[2][1] == 1 and maze.maze_map[1][2] == 0  # a wall below (1, 1), a corridor to its right
    a, right, below = (torch.tensor(maze.cell_rowcol_to_xy(np.array(c)), dtype=torch.float32) for c in ((1, 1), (1, 2), (3, 1)))
    oracle = oracle_distance(cfg)
    d = oracle(torch.stack([a, a]), torch.stack([right, below]))
    assert d[0].item() == pytest.approx((right - a).norm().item() / 0.05) and d[1].item() == oracle.blocked
