"""The recipe's configuration: every env composes and validates; bad input stops the recipe at start-up,
before anything is built or written, with one line naming the key.

Unit tests of the checks (values, device, seed, unknown keys, resume, run directory) and, through the command
line, the one-line message, the exit status 2 and the files left untouched."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest
import torch
from _recipe import RECIPES, load_recipe, recipe_config
from dhrl_utils import config_schema
from torchrl_dhrl.envs import ENV_NAMES

from torchrl_dhrl.recipe import (
    FAST_PATH,
    IMPLIED_WHEN_ABSENT,
    REFERENCE_PATH,
    RESUME_MUTABLE_KEYS,
    ConfigError,
    check_known_keys,
    check_resume_config,
    resolve_device,
    resolve_speed,
    validate_config,
    with_implied_keys,
)

recipe = load_recipe()
SMOKE = ("env=PointMaze", "preset=smoke", "plots.every_epochs=0", "device=cpu", "logger.backend=none")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A finished 80-step smoke run (its directory, holding its checkpoint)."""
    path = tmp_path_factory.mktemp("run")
    recipe.train(recipe_config(*SMOKE, "total_steps=80"), run_dir=path)
    return path


def _snapshot(path):
    return {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in sorted(path.rglob("*")) if p.is_file()}


# ---- values ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "override, match",
    [
        ("device=mps", "`device` must be 'auto', 'cpu', 'cuda' or 'cuda:N'.*'mps'"),
        ("device=meta", "`device` must be .*'meta'"),
        ("device=0", "`device` must be"),
        ("seed=-1", r"`seed` must be an integer in \[0, 2\*\*32 - 1\]"),
        ("seed=4294967296", r"`seed` .*\[0, 2\*\*32 - 1\]"),
        ("threads=0", "`threads` must be null .* or an integer >= 1"),
        ("threads=two", "`threads`"),
        ("updates_per_graph=0", "`updates_per_graph` must be >= 1"),
        ("step_threads=0", "`step_threads` must be >= 1"),
        ("updates_per_graph=4", "`updates_per_graph` 4 > 1 needs cudagraphs=true"),
        ("low.hidden=64", "`low.hidden` must be a non-empty list"),
        ("high.subgoal_low=[a,b]", "`high.subgoal_low` must be a list of numbers"),
        (
            "high.subgoal_low=[-1.0,-1.0,-1.0] high.subgoal_high=[9.0,9.0,9.0]",
            "`high.subgoal_low` must have 2 entries",
        ),
        ("goal_indices=[0,99]", r"`goal_indices` must be null or 2 distinct indices in \[0, 29\)"),
        ("goal_indices=[0,0]", "`goal_indices`"),
        ("total_steps=100", r"`total_steps` \(100\) must be >= one collector batch.*1 x 600"),
        ("high.c_h=601", r"`high.c_h` \(601\) must be <= the episode length \(600\)"),
        ("low.batch_size=3000000", r"`low.batch_size` \(3000000\) must be <= `low.buffer_size`"),
        ("progress=maybe", "`progress` must be true or false"),
        ("plots.video=1", "`plots.video` must be true or false"),
        ("logger.exp_name=5", "`logger.exp_name` must be null"),
        ("run_dir=5", "`run_dir` must be null or a path"),
        ("resume=5", "`resume` must be null or a path"),
        ("low.distance_output=relu", r"`low.distance_output` must be one of \('linear', 'softplus'\)"),
        ("high.distance_output=exp", "`high.distance_output` must be one of"),
    ],
)
def test_bad_values_name_the_key(override, match):
    with pytest.raises(ConfigError, match=match):
        validate_config(recipe_config("env=AntMaze", *override.split()))


def test_resolve_device_accepts_only_cpu_cuda_and_auto():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(None) == resolve_device("auto")
    for bad in ("mps", "meta", "xpu", "tpu", "cuda:x", 1):
        with pytest.raises(ConfigError, match="`device`"):
            resolve_device(bad)
    if torch.cuda.is_available():
        count = torch.cuda.device_count()
        assert resolve_device(f"cuda:{count - 1}") == torch.device("cuda", count - 1)
        with pytest.raises(ConfigError, match=f"only {count} CUDA device"):
            resolve_device(f"cuda:{count}")
    else:
        with pytest.raises(ConfigError, match="torch.cuda.is_available"):
            resolve_device("cuda:0")


def test_largest_seed_is_valid():
    validate_config(recipe_config("env=AntMaze", "seed=4294967295"))


# ---- keys ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("env", ENV_NAMES)
@pytest.mark.parametrize("preset", ["paper", "quick", "cpu", "cpu_paper_schedule", "smoke"])
def test_env_and_preset_files_only_set_keys_of_the_schema(env, preset):
    cfg = recipe_config(f"env={env}", f"preset={preset}")
    check_known_keys(cfg, config_schema())
    validate_config(cfg)


@pytest.mark.parametrize(
    "override, match",
    [
        ("+foo=1", "Unknown configuration key `foo`"),
        ("+low.foo=1", "Unknown configuration key `low.foo`"),
        ("++planner.cutof=3", "`planner.cutof` .*did you mean `planner.cutoff`"),
    ],
)
def test_added_keys_are_rejected(override, match, tmp_path):
    cfg = recipe_config(*SMOKE, override)
    with pytest.raises(ConfigError, match=match):
        recipe.train(cfg, run_dir=tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_schema_is_read_from_config_yaml():
    schema = config_schema()
    assert "defaults" not in schema and schema["threads"] is None and "hidden" in schema["low"]
    with pytest.raises(ConfigError, match="`low` is a group of keys"):
        check_known_keys({"low": 5}, schema)
    with pytest.raises(ConfigError, match="Unknown configuration keys `a`, `b.c`"):
        check_known_keys({"a": 1, "b": {"c": 2}}, {"b": {"d": 1}})


# ---- resume -------------------------------------------------------------------------------------------------


def test_check_resume_config():
    saved = {
        "seed": 0,
        "total_steps": 480,
        "device": "cpu",
        "logger": {"backend": "csv"},
        "low": {"hidden": [32]},
    }
    same = {**saved, "total_steps": 960, "device": "cuda", "logger": {"backend": "none"}, "new_key": True}
    notes = check_resume_config(saved, same)
    assert notes == [
        "device: 'cpu' -> 'cuda'",
        "logger.backend: 'csv' -> 'none'",
        "total_steps: 480 -> 960",
        "new_key: not in the checkpoint, True now",
    ]
    with pytest.raises(ConfigError, match=r"low.hidden \[32\] -> \[64\]; seed 0 -> 1 \(saved -> now\)"):
        check_resume_config(saved, {**same, "seed": 1, "low": {"hidden": [64]}})
    assert {"total_steps", "device", "run_dir", "resume", "threads", "logger.*", "plots.*"} <= set(
        RESUME_MUTABLE_KEYS
    )



@pytest.mark.parametrize(
    ("before", "after"),
    [(None, {"continuing_task": False}), ({"continuing_task": False}, None), ({}, {"a": 1}), ({"a": 1}, {})],
)
def test_a_key_that_becomes_a_group_is_compared_as_one_value(before, after):
    """``gymnasium.make_kwargs`` null -> {continuing_task: false} changes the env: refused on resume (its sub-keys are
    not "new keys"), allowed where the key is mutable, and reported as one change."""
    saved = {"seed": 0, "gymnasium": {"make_kwargs": before}, "logger": {"backend": before}}
    with pytest.raises(ConfigError, match=r"gymnasium.make_kwargs .* -> .* \(saved -> now\)"):
        check_resume_config(saved, {**saved, "gymnasium": {"make_kwargs": after}})
    notes = check_resume_config(saved, {**saved, "logger": {"backend": after}})
    assert notes == [f"logger.backend: {before!r} -> {after!r}"]
    assert check_resume_config(saved, {**saved, "gymnasium": {"make_kwargs": before, "new": 1}}) == [
        "gymnasium.new: not in the checkpoint, 1 now"
    ]

def test_a_checkpoint_older_than_a_key_is_compared_with_the_value_it_was_trained_with():
    # 0.3.x configurations have no `low/high.distance_output`: they were trained with softplus distances
    saved = {"seed": 0, "low": {"gamma": 0.99}, "high": {"gamma": 0.99}}
    linear = {
        "seed": 0,
        "low": {"gamma": 0.99, "distance_output": "linear"},
        "high": {"gamma": 0.99, "distance_output": "linear"},
    }
    with pytest.raises(
        ConfigError,
        match=r"high.distance_output 'softplus' -> 'linear'; low.distance_output 'softplus' -> 'linear'",
    ):
        check_resume_config(saved, linear)
    softplus = {
        "seed": 0,
        "low": {"gamma": 0.99, "distance_output": "softplus"},
        "high": {"gamma": 0.99, "distance_output": "softplus"},
    }
    assert check_resume_config(saved, softplus) == []
    assert set(IMPLIED_WHEN_ABSENT) == {
        "low.distance_output",
        "high.distance_output",
        "right_flipped_after",
        "reference_engine",
        "fork",
        "planner.edge_rule",
        "planner.unreachable",
        "high.critic_candidates",
        "high.candidate_noise",
        "high.landmark_candidates",
    }
    filled = with_implied_keys(saved)
    assert filled["low"]["distance_output"] == filled["high"]["distance_output"] == "softplus"
    assert "distance_output" not in saved["low"]  # a copy
    # no section, nothing implied below it; top-level keys are implied
    assert with_implied_keys({"seed": 0}) == {
        "seed": 0,
        "right_flipped_after": None,
        "reference_engine": False,
        "fork": None,
    }
    # runs from before `right_flipped_after`: a flipped ant stayed flipped; righting it on resume is refused
    assert check_resume_config(saved, {**softplus, "right_flipped_after": None}) == []
    with pytest.raises(ConfigError, match=r"right_flipped_after None -> 10"):
        check_resume_config(saved, {**softplus, "right_flipped_after": 10})
    # runs from before `fork` were not forked: no note when a run of this version resumes them
    assert check_resume_config(saved, {**softplus, "fork": None}) == []


@pytest.mark.recipe
def test_an_older_checkpoint_rebuilds_with_its_own_distance_output(run, monkeypatch):
    dhrl_utils = load_recipe("dhrl_utils")
    real = dhrl_utils.load_checkpoint

    def as_0_3(path, **kwargs):  # the same checkpoint, its configuration without the 0.4 keys
        state = real(path, **kwargs)
        for level in ("low", "high"):
            del state["config"][level]["distance_output"]
        return state

    _, agent = dhrl_utils.agent_from_checkpoint(run)
    assert (
        agent.sqgc_loss.policy_critic.distance_output
        == agent.high_loss.critic_network.distance_output
        == "linear"
    )
    monkeypatch.setattr(dhrl_utils, "load_checkpoint", as_0_3)
    cfg, agent = dhrl_utils.agent_from_checkpoint(run)
    assert cfg["low"]["distance_output"] == "softplus"
    assert agent.sqgc_loss.policy_critic.distance_output == "softplus"
    assert (
        agent.sqgc_loss.graph_critic.distance_output
        == agent.high_loss.critic_network.distance_output
        == "softplus"
    )


@pytest.mark.recipe
@pytest.mark.parametrize(
    "kind", ["corrupt", "truncated", "not_a_checkpoint", "tensor", "missing", "empty_dir"]
)
def test_bad_resume_names_resume_and_the_file(kind, run, tmp_path):
    path = tmp_path / f"{kind}.pt"
    if kind == "corrupt":
        path.write_bytes(b"garbage" * 100)
    elif kind == "truncated":
        shutil.copytree(run / "checkpoint", path)  # a checkpoint directory whose manifest is cut short
        manifest = path / "manifest.json"
        manifest.write_bytes(manifest.read_bytes()[:200])
    elif kind == "not_a_checkpoint":
        torch.save({"weights": torch.ones(2)}, path)
    elif kind == "tensor":
        torch.save(torch.ones(2), path)
    elif kind == "empty_dir":
        path.mkdir()
    before = _snapshot(run)
    cfg = recipe_config(*SMOKE, f"resume={path}")
    match = "`resume=.*" + ("no checkpoint at" if kind in ("missing", "empty_dir") else "not a")
    with pytest.raises(ConfigError, match=match) as info:
        recipe.train(cfg, run_dir=tmp_path / "out")
    assert str(path) in str(info.value)
    assert not (tmp_path / "out").exists() and _snapshot(run) == before


@pytest.mark.recipe
def test_resume_with_another_configuration_says_which_keys(run, tmp_path):
    before = _snapshot(run)
    cfg = recipe_config(*SMOKE, "low.hidden=[64]", "seed=3", f"resume={run}")
    with pytest.raises(ConfigError, match=r"low.hidden \[32, 32\] -> \[64\]; seed 0 -> 3.*only total_steps"):
        recipe.train(cfg, run_dir=run)  # in place: the checkpoint must survive
    assert _snapshot(run) == before


@pytest.mark.recipe
def test_resume_allows_the_mutable_keys(run, tmp_path, capsys):
    cfg = recipe_config(*SMOKE, "total_steps=160", "threads=1", "progress=true", f"resume={run}")
    start = recipe.start_up(cfg, run_dir=tmp_path / "continued")
    out = capsys.readouterr().out
    assert "Threads: 1 intra-op" in out and "threads=1 in the configuration" in out
    assert start.threads is None  # a fixed count: nothing to adapt
    assert "Resuming" in out and "total_steps: 80 -> 160" in out and "threads: None -> 1" in out
    assert start.resume == run / "checkpoint" and start.state["counters"]["env_steps"] == 80
    assert start.run_dir.is_dir()


# ---- run directory ------------------------------------------------------------------------------------------


@pytest.mark.recipe
def test_run_dir_with_a_checkpoint_is_not_overwritten(run):
    before = _snapshot(run)
    with pytest.raises(ConfigError, match="already holds a checkpoint, which this run would overwrite"):
        recipe.train(recipe_config(*SMOKE), run_dir=run)
    assert _snapshot(run) == before


def test_run_dir_that_is_a_file(tmp_path):
    (tmp_path / "file").write_text("x")
    for run_dir in (tmp_path / "file", tmp_path / "file" / "sub"):
        with pytest.raises(ConfigError, match="`run_dir`.*is a file, not a directory"):
            recipe.train(recipe_config(*SMOKE), run_dir=run_dir)
    assert (tmp_path / "file").read_text() == "x"


@pytest.mark.skipif(
    os.environ.get("MUJOCO_GL", "").lower() in ("egl", "osmesa"), reason="offscreen rendering is available"
)
def test_video_without_offscreen_rendering_fails_at_start_up(tmp_path):
    with pytest.raises(ConfigError, match="`plots.video=true` needs MuJoCo offscreen rendering"):
        recipe.train(recipe_config(*SMOKE, "plots.video=true"), run_dir=tmp_path / "run")
    assert not (tmp_path / "run").exists()


# ---- the command line ---------------------------------------------------------------------------------------


def _cli(*args, env=None, cwd=None):
    return subprocess.run(
        [sys.executable, str(RECIPES / "dhrl_antmaze.py"), *args],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "OMP_NUM_THREADS": "1", **(env or {})},
        cwd=cwd,
    )


@pytest.mark.recipe
@pytest.mark.parametrize(
    "override, expected",
    [
        ("high.c_h=0", "`high.c_h` (the high-level interval) must be an integer >= 1, got 0."),
        ("+low.foo=1", "Unknown configuration key `low.foo`"),
        pytest.param("seed=-1", "`seed` must be an integer in [0, 2**32 - 1]", marks=pytest.mark.slow),
        pytest.param("device=mps", "`device` must be 'auto', 'cpu'", marks=pytest.mark.slow),
    ],
)
def test_command_line_prints_one_line_and_exits_2(override, expected, tmp_path):
    result = _cli("preset=smoke", override, cwd=tmp_path)  # Hydra's default outputs/<date>/<time> in tmp_path
    assert result.returncode == 2, result.stderr[-2000:]
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("dhrl_antmaze.py: configuration error: "), result.stderr
    assert expected in lines[0] and "Traceback" not in result.stderr
    assert list(tmp_path.iterdir()) == []  # Hydra's output directory is removed again


@pytest.mark.recipe
def test_command_line_bad_resume_leaves_the_run_untouched(run, tmp_path):
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"garbage" * 100)
    before = _snapshot(run)
    result = _cli(
        "preset=smoke", f"resume={corrupt}", f"run_dir={run}", f"hydra.run.dir={tmp_path / 'hydra'}"
    )
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"`resume={corrupt}`" in result.stderr and "not a readable checkpoint" in result.stderr
    assert _snapshot(run) == before and not (tmp_path / "hydra").exists()


@pytest.mark.recipe
@pytest.mark.slow
def test_command_line_full_error_shows_the_traceback(tmp_path):
    result = _cli(
        "preset=smoke", "high.c_h=0", f"hydra.run.dir={tmp_path / 'hydra'}", env={"HYDRA_FULL_ERROR": "1"}
    )
    assert result.returncode != 0 and "Traceback" in result.stderr and "ConfigError" in result.stderr
    assert not (tmp_path / "hydra").exists()


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
        check_known_keys(cfg, config_schema(), complete=True)


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
    ("key", "env", "value", "ok"),
    [
        ("angle_features", "Reacher3D", "[4,6]", True),
        ("angle_features", "Reacher3D", "null", True),
        ("angle_features", "Reacher3D", "[4,4]", False),  # repeated
        ("angle_features", "Reacher3D", "[17]", False),  # outside the 17-D observation
        ("angle_features", "Reacher3D", "[]", False),
        ("angle_features", "Reacher3D", "[1.5]", False),
        ("angle_features", "AntMaze", "[0]", False),  # the achieved goal's (x, y) are not angles
        ("angle_features", "AntMaze", "[5,6]", True),
        ("right_flipped_after", "AntMaze", "10", True),
        ("right_flipped_after", "AntMazeComplex", "1", True),
        ("right_flipped_after", "AntMaze", "null", True),
        ("right_flipped_after", "PointMaze", "null", True),
        ("right_flipped_after", "AntMaze", "0", False),
        ("right_flipped_after", "AntMaze", "true", False),
        ("right_flipped_after", "AntMaze", "2.5", False),
        ("right_flipped_after", "PointMaze", "10", False),
        ("right_flipped_after", "Reacher3D", "10", False),
        ("reference_engine", "AntMaze", "true", True),
        ("reference_engine", "AntMazeBottleneck", "true", True),
        ("reference_engine", "AntMaze", "false", True),
        ("reference_engine", "PointMaze", "false", True),
        ("reference_engine", "PointMaze", "true", False),
        ("reference_engine", "Reacher3D", "true", False),
        ("reference_engine", "AntMaze", "1", False),
        ("reference_engine", "AntMaze", "null", False),
    ],
)
def test_env_dependent_keys_are_checked_against_the_env(key, env, value, ok):
    cfg = recipe_config(f"env={env}", f"{key}={value}")
    if ok:
        validate_config(cfg)
    else:
        with pytest.raises(ConfigError, match=key):
            validate_config(cfg)


# ---- speed: the fast path by default, fast=false for the eager float32 reference path ---------------------------


@pytest.mark.parametrize("device", ["cpu", "cuda", "meta"])
@pytest.mark.parametrize("fast", [True, False])
def test_resolve_speed(device, fast):
    """The switches at null take FAST_PATH's values for the device type (REFERENCE_PATH with fast=false or an
    unlisted device); explicit values are kept; resolving twice changes nothing."""
    cfg = {"fast": fast, "cudagraphs": None, "update_dtype": None, "compile": False}
    resolved, line = resolve_speed(cfg, device)
    table = FAST_PATH.get(device, REFERENCE_PATH) if fast else REFERENCE_PATH
    assert resolved == {**cfg, **table} and cfg["cudagraphs"] is None  # a copy
    assert line.startswith("Speed: cudagraphs=") and ("fast=false: the eager float32 reference path" in line)
    assert resolve_speed(resolved, device) == (
        resolved,
        "Speed: every speed switch set in the configuration.",
    )
    kept, _ = resolve_speed({**cfg, "cudagraphs": False, "update_dtype": "bfloat16"}, device)
    assert kept["cudagraphs"] is False and kept["update_dtype"] == "bfloat16"
    assert REFERENCE_PATH == {"cudagraphs": False, "update_dtype": "float32"}
    assert (
        FAST_PATH["cuda"] == {"cudagraphs": True, "update_dtype": "auto"}
        and FAST_PATH["cpu"] == REFERENCE_PATH
    )


def test_the_default_speed_on_this_cpu(tmp_path, capsys):
    """On a CPU the defaults resolve to eager float32 (the run prints why), and the run directory's config.yaml holds
    the resolved values; fast=false says it is the reference path."""
    cfg = recipe_config(*SMOKE, "total_steps=80")
    assert cfg["fast"] is True and cfg["cudagraphs"] is None and cfg["update_dtype"] is None
    start = recipe.start_up(cfg, run_dir=tmp_path)
    out = capsys.readouterr().out
    assert (
        "Speed: cudagraphs=false, update_dtype=float32 (fast=true on cpu: eager; fast=false: the eager" in out
    )
    assert "Precision: updates float32, graph builds float32." in out
    assert start.config["cudagraphs"] is False and start.config["update_dtype"] == "float32"
    written = (tmp_path / "config.yaml").read_text()
    assert "cudagraphs: false" in written and "update_dtype: float32" in written
    recipe.start_up(recipe_config(*SMOKE, "fast=false"), run_dir=tmp_path / "reference")
    assert "(fast=false: the eager float32 reference path)." in capsys.readouterr().out


@pytest.mark.parametrize(
    "override, match",
    [
        ("fast=maybe", "`fast` must be true or false"),
        ("cudagraphs=maybe", "`cudagraphs` must be null .*, true or false"),
        ("update_dtype=float16", r"`update_dtype` must be null \(fast path\) or one of"),
        ("cudagraphs=true", "`cudagraphs=true` needs a CUDA device"),
    ],
)
def test_speed_keys_refused(override, match):
    with pytest.raises(ConfigError, match=match):
        recipe.start_up(recipe_config(*SMOKE, override), write=False)
