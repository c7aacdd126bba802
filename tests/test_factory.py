"""torchrl_dhrl.factory: the acting policy and collector with the capturable planner (no graph break in the policy,
the collector's ``compile_policy`` and ``cudagraph_policy``), the capture-safe high-level sampler, and
``make_environment``'s argument checks."""

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


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"num_envs": 0}, "`num_envs` must be an integer >= 1"),
        ({"max_episode_steps": 0}, "`max_episode_steps` must be None or an integer >= 1"),
        ({"goal_indices": [0, 0]}, "`goal_indices` must be None or a list of distinct integers"),
        ({"goal_indices": [0, 29]}, r"`goal_indices` must be null or 2 distinct indices in \[0, 29\)"),
        ({"goal_indices": [0, 1], "angle_features": [1, 5]}, "`angle_features` must be distinct .* outside"),
        ({"angle_features": [29]}, r"`angle_features` must be distinct observation indices in \[0, 29\)"),
        ({"angle_features": []}, "`angle_features` must be None or a non-empty list"),
        ({"right_flipped_after": 0}, "`right_flipped_after` .* must be None or an integer >= 1"),
        ({"reference_engine": 1}, "`reference_engine` must be True or False"),
        ({"step_threads": 0}, "`step_threads` must be >= 1"),
    ],
)
def test_make_environment_refuses_a_bad_argument_before_building_anything(monkeypatch, kwargs, match):
    import torchrl_dhrl.factory as factory

    monkeypatch.setattr(factory, "make_env", lambda *a, **k: pytest.fail("make_env was called"))
    with pytest.raises(ValueError, match=match):
        factory.make_environment("AntMaze", **kwargs)


@pytest.mark.parametrize(
    "env, kwargs, match",
    [
        ("PointMaze", {"right_flipped_after": 10}, "`right_flipped_after` rights a flipped ant.*not to PointMaze"),
        ("Reacher3D", {"reference_engine": True}, "`reference_engine`: reference_engine emulates"),
        ("dhrl-test-unknown", {"reference_engine": True}, "`reference_engine` is an option of the built-in ant"),
        ("gymnasium:PointMaze_UMaze-v3", {"step_threads": 2}, "`step_threads` is an option of the built-in envs"),
    ],
)
def test_make_environment_refuses_an_option_of_another_env(monkeypatch, env, kwargs, match):
    import torchrl_dhrl.factory as factory

    monkeypatch.setattr(factory, "make_env", lambda *a, **k: pytest.fail("make_env was called"))
    with pytest.raises(ValueError, match=match):
        factory.make_environment(env, **kwargs)
