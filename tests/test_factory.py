"""The recipe's acting policy and collector with the capturable planner: no graph break in the policy, the
collector's ``compile_policy`` and the recipe's key."""

import pytest
import torch

from tests.planner.test_graph_planner import _agent, assert_same_collection


@pytest.mark.slow
def test_acting_policy_has_no_graph_break_with_a_capturable_planner():
    counts = {}
    for capturable in (False, True):
        agent, env = _agent(capturable)
        td = env.reset()
        for _ in range(2):  # past the first step (a plan exists; the tracking branch)
            td = env.step(agent.policy(td))["next"]
        torch._dynamo.reset()
        counts[capturable] = torch._dynamo.explain(agent.policy)(td.clone()).graph_break_count
    assert counts[True] == 0
    assert counts[False] > 0  # the host-side replanning branch


def test_make_collector_compile_policy_needs_a_capturable_planner():
    from torchrl_dhrl.factory import make_collector

    agent, env = _agent(False)
    with pytest.raises(ValueError, match="`compile_policy` needs a capturable planner"):
        make_collector(env, agent, 30, compile_policy=True)
    make_collector(env, agent, 30).shutdown()  # the default needs nothing


def test_capturable_agent_plans_on_a_graph_reserved_before_its_first_build():
    """``make_agent(capturable_planner=True)`` reserves the fixed-size graph: planning tensors before any landmark
    (the plans of no graph) and the first build of the planner from float32 candidates writes into them."""
    from torchrl_dhrl.factory import make_agent, make_environment

    env = make_environment("PointMaze", num_envs=2, seed=0, max_episode_steps=30)
    kwargs = {
        "high_policy": {
            "subgoal_low": [-2.0, -2.0],
            "subgoal_high": [10.0, 10.0],
            "interval": 5,
            "num_cells": (16,),
        },
        "low_actor": {"relative_goal": False},
    }
    plain = make_agent(env, goal_indices=[0, 1], **kwargs)
    assert plain.planner.graph.planning_tensors(capturable=True) is None  # nothing reserved, nothing fixed
    agent = make_agent(env, goal_indices=[0, 1], capturable_planner=True, **kwargs)
    graph = agent.planner.graph
    tensors = graph.planning_tensors(capturable=True)
    obs_dim = env.observation_spec["observation"].shape[-1]
    assert graph.num_landmarks == 0 and tensors.states.shape == (graph.max_landmarks, obs_dim)
    assert not tensors.valid.any()
    pointers = [t.data_ptr() for t in tensors]
    points = torch.rand(80, obs_dim, generator=torch.Generator().manual_seed(0)) * 12 - 2
    agent.planner.build(points, points[:, :2])
    assert graph.num_landmarks > 0
    assert [t.data_ptr() for t in graph.planning_tensors(capturable=True)] == pointers


def test_high_level_updates_sample_with_the_capture_safe_sampler_on_a_reserved_graph():
    """The recipe's high-level buffer on a planner with a reserved fixed-size graph offers the capture-safe sampler
    (gradual penalty included), and the updater trains with it (``capture_sampling=True``, the form the CUDA graphs
    capture); on a graph that is not fixed-size the sampler is refused, saying why."""
    from torchrl_dhrl.factory import make_collector, make_high_level_buffer, make_updater

    for fixed in (True, False):
        agent, env = _agent(fixed)
        collector = make_collector(env, agent, 30)
        rb = make_high_level_buffer(
            buffer_size=500, batch_size=32, reward_threshold=0.5, her_window=3, planner=agent.planner
        )
        it = iter(collector)
        for _ in range(2):
            rb.extend(next(it))
        collector.shutdown()
        updater = make_updater(
            agent.high_loss,
            rb,
            optimizers={"actor_lr": 1e-3, "critic_lr": 1e-3},
            capture_sampling=True,
            actor_after_critic_step=False,
        )
        if not fixed:
            with pytest.raises(RuntimeError, match="distance_from_graph has no capture-safe form here"):
                updater.run(4)
            continue
        before = [p.detach().clone() for p in agent.high_loss.parameters()]
        updater.run(4)
        assert (updater.sampling_captured, updater.sampling_note) == (True, "capture-safe sampler")
        assert any(not torch.equal(a, b) for a, b in zip(before, agent.high_loss.parameters(), strict=True))


def test_make_collector_cudagraph_policy_refusals():
    """``cudagraph_policy`` needs a capturable planner on a reserved graph and the env on CUDA; the refusals name
    what is missing (on a CUDA machine the capture itself is tested in tests/test_cuda.py)."""
    from torchrl_dhrl.factory import make_collector

    agent, env = _agent(False)
    with pytest.raises(ValueError, match="`cudagraph_policy` needs a capturable planner"):
        make_collector(env, agent, 30, cudagraph_policy=True)
    agent, env = _agent(True)
    with pytest.raises(ValueError, match="needs the env \\(and the policy\\) on a CUDA device, got cpu"):
        make_collector(env, agent, 30, cudagraph_policy={"warmup": 3})


def test_make_eval_policy_is_the_agents_policy_or_refuses_a_capture_it_cannot_make():
    from torchrl_dhrl.factory import make_eval_policy

    agent, _ = _agent(False)
    assert make_eval_policy(agent) is agent.policy and make_eval_policy(agent, cudagraph_policy=False) is agent.policy
    with pytest.raises(ValueError, match="`cudagraph_policy` needs a capturable planner"):
        make_eval_policy(agent, cudagraph_policy=True)
    agent, _ = _agent(True)
    with pytest.raises(ValueError, match="it needs the policy on a CUDA device, got cpu"):
        make_eval_policy(agent, cudagraph_policy=True)
    unreserved, _ = _agent(True)
    unreserved.planner.graph.fixed_size = False  # plans on the graph's own buffers, which a rebuild reallocates
    with pytest.raises(ValueError, match="fixed-size tensors that exist before the capture"):
        make_eval_policy(unreserved, cudagraph_policy=True)


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


@pytest.mark.slow
def test_compiled_collector_collects_what_the_eager_one_does():
    """The collector's ``compile_policy`` with a capturable planner: the same two batches as an eager
    collector with the host-branching planner (inductor's random ops falling back to eager's)."""
    from torch._inductor import config as inductor_config

    from torchrl_dhrl.factory import make_collector

    batches = {}
    for compiled in (False, True):
        torch.manual_seed(0)
        agent, env = _agent(compiled)
        torch.manual_seed(1)
        collector = make_collector(env, agent, 30, compile_policy={"warmup": 1} if compiled else False)
        with inductor_config.patch(fallback_random=True):
            it = iter(collector)
            batches[compiled] = torch.cat([next(it), next(it)])
        collector.shutdown()
    assert_same_collection(batches[True], batches[False])


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
