"""The recipe's keys of the factory's switches (``compile_policy``, ``cudagraph_policy``, ``high.capture_sampling``)
and of the env (its top-level keys checked by ``make_environment``'s declarations)."""

import pytest
import torch


def test_cudagraph_policy_key_is_validated():
    from _recipe import recipe_config

    from torchrl_dhrl.recipe import RESUME_MUTABLE_KEYS, ConfigError, policy_captured, validate_config

    assert "cudagraph_policy" in RESUME_MUTABLE_KEYS  # same plans: a resumed run may switch it
    with pytest.raises(ConfigError, match="`cudagraph_policy` must be true or false, got 'yes'"):
        validate_config(recipe_config("env=PointMaze", "device=cpu", "cudagraph_policy=yes"))
    with pytest.raises(
        ConfigError, match="`cudagraph_policy=true` needs a CUDA device, but `device` resolves to cpu"
    ):
        validate_config(recipe_config("env=PointMaze", "device=cpu", "cudagraph_policy=true"))
    cfg = recipe_config("env=PointMaze", "device=cpu")
    assert cfg["cudagraph_policy"] is False and not policy_captured(cfg)
    assert policy_captured({**cfg, "cudagraph_policy": True}) and policy_captured(
        {**cfg, "compile_policy": True}
    )


def test_compile_policy_key_is_validated_and_reaches_the_planner_and_collector():
    from _recipe import recipe_config
    from dhrl_utils import build_run

    from torchrl_dhrl.recipe import RESUME_MUTABLE_KEYS, ConfigError, validate_config

    assert "compile_policy" in RESUME_MUTABLE_KEYS  # same plans: a resumed run may switch it
    with pytest.raises(ConfigError, match="`compile_policy` must be true or false, got 'yes'"):
        validate_config(recipe_config("env=PointMaze", "device=cpu", "compile_policy=yes"))
    for value in (False, True):
        cfg = recipe_config("env=PointMaze", "preset=smoke", f"compile_policy={str(value).lower()}")
        validate_config(cfg)
        parts = build_run(cfg, torch.device("cpu"))
        assert parts.agent.planner.capturable is value
        assert parts.collector.compiled_policy is value
        parts.collector.shutdown()


@pytest.mark.recipe
@pytest.mark.slow
def test_recipe_runs_with_a_compiled_policy_and_resumes_without_it(tmp_path, capsys):
    from _recipe import load_recipe, metrics_rows, recipe_config

    recipe = load_recipe()
    overrides = ("env=PointMaze", "preset=smoke", "logger.backend=csv", "plots.every_epochs=0", "device=cpu")
    torch.manual_seed(0)
    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    recipe.train(recipe_config(*overrides, "total_steps=240", "compile_policy=true"), run_dir=tmp_path)
    assert "Acting: the policy compiled in the collector" in capsys.readouterr().out
    # one graph: nothing of the recipe's (e.g. a timing hook on the planner) breaks the compiled policy
    assert not torch._dynamo.utils.counters["graph_break"], dict(torch._dynamo.utils.counters["graph_break"])
    assert all("time/planner_ms_per_call" not in row for row in metrics_rows(tmp_path))
    summary = recipe.train(
        recipe_config(*overrides, "total_steps=480", f"resume={tmp_path}", "compile_policy=false"),
        run_dir=tmp_path,
    )
    printed = capsys.readouterr().out
    assert "Acting: the policy compiled" not in printed and "compile_policy" in printed  # the resume note
    assert summary["env_steps"] == 480 and 0.0 <= summary["eval/success"] <= 1.0
    timed = [row["time/planner_ms_per_call"] != "" for row in metrics_rows(tmp_path)]
    assert timed and timed[-1]  # the eager segment times the planner again


@pytest.mark.recipe
def test_recipe_high_capture_sampling_key(tmp_path, capsys):
    """``high.capture_sampling=true``: the recipe reserves a fixed-size graph, the high level trains with the
    capture-safe sampler (gradual penalty included) and says so; the default keeps ``rb.sample()``; a resumed run may
    switch it; bad values are refused before work starts."""
    from _recipe import load_recipe, recipe_config
    from dhrl_utils import build_run, high_sampling_captured

    from torchrl_dhrl.recipe import RESUME_MUTABLE_KEYS, ConfigError, validate_config

    assert "high.capture_sampling" in RESUME_MUTABLE_KEYS
    with pytest.raises(ConfigError, match="`high.capture_sampling` must be None, True or False, got 'yes'"):
        validate_config(recipe_config("env=PointMaze", "device=cpu", "high.capture_sampling=yes"))
    cpu = torch.device("cpu")
    default = recipe_config("env=PointMaze", "preset=smoke", "device=cpu")
    assert default["high"]["capture_sampling"] is False and not high_sampling_captured(default, cpu)
    assert not high_sampling_captured(recipe_config("env=PointMaze", "device=cpu", "high.capture_sampling=null"), cpu)
    parts = build_run(default, cpu)
    assert not parts.agent.planner.graph.fixed_size and parts.high_updater.capture_sampling is False
    parts.collector.shutdown()
    recipe = load_recipe()
    overrides = ("env=PointMaze", "preset=smoke", "logger.backend=csv", "plots.every_epochs=0", "device=cpu")
    recipe.train(recipe_config(*overrides, "total_steps=240", "high.capture_sampling=true"), run_dir=tmp_path)
    assert "Sampling, high level: capture-safe sampler." in capsys.readouterr().out
    summary = recipe.train(recipe_config(*overrides, "total_steps=480", f"resume={tmp_path}"), run_dir=tmp_path)
    assert summary["env_steps"] == 480 and "high.capture_sampling" in capsys.readouterr().out  # the resume note


def test_the_recipe_checks_the_env_keys_with_make_environments_declarations():
    """The env's top-level keys reach make_environment by name (episode_length as max_episode_steps) and its checks
    name the configuration key."""
    from _recipe import recipe_config

    from torchrl_dhrl.recipe import ConfigError, validate_config
    from torchrl_dhrl.recipe.routing import component_arguments

    cfg = recipe_config("env=AntMaze", "episode_length=300", "step_threads=2", "right_flipped_after=50")
    args = component_arguments(cfg)["environment"]
    assert args["env_name"] == "AntMaze" and args["max_episode_steps"] == 300
    assert args["step_threads"] == 2 and args["right_flipped_after"] == 50 and args["reference_engine"] is False
    with pytest.raises(ConfigError, match="`episode_length` must be None or an integer >= 1"):
        validate_config(recipe_config("env=AntMaze", "episode_length=0"))
