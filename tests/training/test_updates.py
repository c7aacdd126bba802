"""LossUpdater: the delayed actor and Polyak schedule, averages, state dicts, the NaN stop; ``compile=True``
(the compiled updates learn what the eager ones learn, and fall back where compile is unavailable); the
captured sampling path (CudaGraphModule passes through on a CPU) trains exactly as an eager updater fed by the
same capture-safe sampler."""

from __future__ import annotations

import warnings

import pytest
import torch
from _batches import sqgc_transitions
from _recipe import recipe_config
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from tests.data.test_relabel_buffer import _filled_buffer
from torchrl_dhrl.factory import make_high_level_buffer
from torchrl_dhrl.modules import GoalConditionedCritic, HighLevelActor, LowLevelActor
from torchrl_dhrl.objectives import HighLevelLoss, SQGCLoss, make_optimizers
from torchrl_dhrl.recipe import ConfigError, validate_config
from torchrl_dhrl.training import LossUpdater, NonFiniteLossError
from torchrl_dhrl.training import updates as updates_module


# ---------------------------------------------------------------- the schedule
def _high_level_setup(batch=8, num_cells=(16,)):
    low, high = [-4.0, -4.0], [20.0, 20.0]
    actor = HighLevelActor(6, 2, low, high, num_cells=num_cells)
    critic = GoalConditionedCritic(
        6,
        2,
        action_low=low,
        action_high=high,
        goal_key="desired_goal",
        action_key="subgoal",
        relative_goal=False,
        num_cells=num_cells,
    )
    loss = HighLevelLoss(actor, critic, action_l2=0.01)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=batch)
    n = 40
    rb.extend(
        TensorDict(
            {
                "observation": torch.randn(n, 6),
                "desired_goal": torch.randn(n, 2),
                "subgoal": torch.rand(n, 2) * 24 - 4,
                ("next", "observation"): torch.randn(n, 6),
                ("next", "reward"): -torch.ones(n, 1),
            },
            [n],
        )
    )
    return loss, rb


def _params(module):
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


def test_updater_delays_actor_steps_and_polyak():
    torch.manual_seed(0)
    loss, rb = _high_level_setup()
    updater = LossUpdater(
        loss, rb, make_optimizers(loss), polyak=0.5, target_update_interval=3, actor_after_critic_step=False
    )
    actor_keys = [k for k in loss.state_dict() if k.startswith("actor_network_params")]
    target_keys = [k for k in loss.state_dict() if k.startswith("target_critic")]
    before = _params(loss)
    out = updater.step()  # update 1: actor_update_interval=2 -> no actor step on the first call
    after = _params(loss)
    actor_moved = any(not torch.equal(before[k], after[k]) for k in actor_keys)
    assert bool(out["actor_updated"]) == actor_moved
    assert all(torch.equal(before[k], after[k]) for k in target_keys)  # targets wait for update 3
    updater.step()
    updater.step()
    assert updater.num_updates == 3
    later = _params(loss)
    assert any(not torch.equal(after[k], later[k]) for k in target_keys)
    # the Polyak rule: target <- 0.5 target + 0.5 online at update 3
    key = next(k for k in target_keys if k.endswith("weight"))
    online = later[key.replace("target_critic_network_params", "critic_network_params")]
    torch.testing.assert_close(later[key], 0.5 * after[key] + 0.5 * online)


def test_updater_run_averages_and_state_dict():
    torch.manual_seed(0)
    loss, rb = _high_level_setup()
    updater = LossUpdater(loss, rb, make_optimizers(loss), actor_after_critic_step=False)
    assert updater.run(0) is None
    means = updater.run(4)
    assert updater.num_updates == 4 and means["actor_updated"].item() == pytest.approx(0.5)
    state = updater.state_dict()
    other_loss, other_rb = _high_level_setup()
    other = LossUpdater(other_loss, other_rb, make_optimizers(other_loss), actor_after_critic_step=False)
    other.load_state_dict(state)
    assert other.num_updates == 4
    assert (
        other.optimizers["critic"].state_dict()["state"].keys()
        == state["optimizers"]["critic"]["state"].keys()
    )


def test_updater_stops_on_nan_before_changing_parameters():
    torch.manual_seed(0)
    loss, rb = _high_level_setup()
    rb.storage._storage["next", "reward"][:] = float("nan")
    updater = LossUpdater(loss, rb, make_optimizers(loss), actor_after_critic_step=False)
    before = _params(loss)
    with pytest.raises(NonFiniteLossError, match="non-finite loss"):
        updater.step()
    after = _params(loss)
    assert all(torch.equal(before[k], after[k]) for k in before if k != "update_count")
    with pytest.raises(ValueError, match="polyak"):
        LossUpdater(loss, rb, make_optimizers(loss), polyak=1.5, actor_after_critic_step=False)
    with pytest.raises(ValueError, match="optimizers"):
        LossUpdater(loss, rb, {"critic": None}, actor_after_critic_step=False)


def test_loss_terms_equal_forward_with_the_decision_given():
    """``loss_terms(td, update_actor)`` (the entry point of LossUpdater and of the CUDA graphs) is ``forward``
    with the actor term switched; neither counts anything."""
    loss, rb = _high_level_setup(batch=16)
    data = rb.sample()
    state = {k: v.clone() for k, v in loss.state_dict().items()}
    for call in range(1, 5):
        update_actor = call % 2 == 0
        torch.manual_seed(call)
        out = loss(data)  # every term, every call
        torch.manual_seed(call)
        terms = loss.loss_terms(data, update_actor=update_actor)
        assert bool(out["actor_updated"]) and bool(terms["actor_updated"]) == update_actor
        assert terms.keys() == out.keys()
        for key in out.keys():
            if update_actor or key not in ("loss_actor", "actor_updated"):
                assert torch.equal(out[key], terms[key]), key
    assert state.keys() == loss.state_dict().keys()  # no count in the loss
    assert all(torch.equal(v, loss.state_dict()[k]) for k, v in state.items())


@pytest.mark.parametrize("interval", [1, 2, 3])
def test_updater_owns_the_delayed_actor_schedule_and_resumes_it(interval):
    torch.manual_seed(0)
    loss, rb = _high_level_setup()
    updater = LossUpdater(
        loss, rb, make_optimizers(loss), actor_update_interval=interval, actor_after_critic_step=False
    )
    flags = [bool(updater.step()["actor_updated"]) for _ in range(5)]
    assert flags == [k % interval == 0 for k in range(1, 6)]
    state = updater.state_dict()
    other_loss, other_rb = _high_level_setup()
    resumed = LossUpdater(
        other_loss,
        other_rb,
        make_optimizers(other_loss),
        actor_update_interval=interval,
        actor_after_critic_step=False,
    )
    resumed.load_state_dict(state)
    assert resumed.actor_update_due() == (6 % interval == 0)
    assert [bool(resumed.step()["actor_updated"]) for _ in range(3)] == [k % interval == 0 for k in (6, 7, 8)]
    with pytest.raises(ValueError, match="actor_update_interval"):
        LossUpdater(loss, rb, make_optimizers(loss), actor_update_interval=0, actor_after_critic_step=False)


def test_old_checkpoints_with_the_loss_step_count_still_load():
    loss, _ = _high_level_setup()
    state = loss.state_dict()
    state["update_count"] = torch.tensor(7)  # written before the schedule moved to LossUpdater
    other, _ = _high_level_setup()
    other.load_state_dict(state)
    assert all(torch.equal(v, other.state_dict()[k]) for k, v in loss.state_dict().items())


def test_updater_cudagraphs_needs_a_cuda_loss():
    loss, rb = _high_level_setup()
    with pytest.raises(ValueError, match="needs the loss on a CUDA device"):
        LossUpdater(loss, rb, make_optimizers(loss), cudagraphs=True, actor_after_critic_step=False)


# ---------------------------------------------------------------- compile=True
OBS, GOAL, ACT, AMAX = 6, 2, 2, 1.0
needs_compile = pytest.mark.skipif(
    updates_module.compile_available() is not None,
    reason=f"torch.compile unavailable here: {updates_module.compile_available()}",
)


def _sqgc(seed: int = 0, cells=(32, 32)):
    torch.manual_seed(seed)
    actor = LowLevelActor(
        OBS, GOAL, action_max=AMAX, action_dim=ACT, goal_key="goal", num_cells=cells, goal_indices=(0, 1)
    )
    critics = [
        GoalConditionedCritic(
            OBS, GOAL, action_max=AMAX, action_dim=ACT, goal_key="goal", num_cells=cells, relative_goal=False
        )
        for _ in range(2)
    ]
    return SQGCLoss(actor, *critics)  # target noise on: compiled updates must draw the same noise


def _low_buffer(n: int = 512, batch: int = 64):
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(n), batch_size=batch)
    rb.extend(sqgc_transitions(n, OBS, GOAL, ACT, AMAX))
    return rb


def _run(compile_: bool, steps: int, actor_after_critic_step: bool):
    loss = _sqgc()
    updater = LossUpdater(
        loss,
        _low_buffer(),
        make_optimizers(loss),
        target_update_interval=3,
        actor_after_critic_step=actor_after_critic_step,
        compile=compile_,
    )
    torch.manual_seed(7)  # the same samples and target noise for both
    outs = [updater.step() for _ in range(steps)]
    return loss, outs, updater


@needs_compile
@pytest.mark.slow
@pytest.mark.parametrize("actor_after_critic_step", [True, False])
def test_compiled_updates_agree_with_eager_over_50_updates(actor_after_critic_step):
    eager, outs_e, _ = _run(False, 50, actor_after_critic_step)
    compiled, outs_c, updater = _run(True, 50, actor_after_critic_step)
    assert updater.compile and updater.num_updates == 50
    for key, value in eager.state_dict().items():
        if value.is_floating_point():
            torch.testing.assert_close(compiled.state_dict()[key], value, rtol=1e-4, atol=1e-5, msg=key)
    moved = sum(
        not torch.equal(v, _sqgc().state_dict()[k])
        for k, v in eager.state_dict().items()
        if v.is_floating_point()
    )
    assert moved > 10  # the comparison is not between untouched networks
    for out_e, out_c in zip(outs_e, outs_c, strict=True):
        assert bool(out_c["actor_updated"]) == bool(out_e["actor_updated"])
        for key in ("loss_policy_qvalue", "loss_graph_qvalue", "loss_actor", "policy_q", "graph_target"):
            torch.testing.assert_close(out_c[key], out_e[key], rtol=1e-4, atol=1e-5, msg=key)


@needs_compile
@pytest.mark.slow
def test_compiled_updates_are_deterministic():
    """Same seed, same compiled steps, bit for bit (what an exact resume of a compiled run relies on)."""
    a, outs_a, _ = _run(True, 12, actor_after_critic_step=True)
    b, outs_b, _ = _run(True, 12, actor_after_critic_step=True)
    for key, value in a.state_dict().items():
        assert torch.equal(value, b.state_dict()[key]), key
    assert all(
        torch.equal(x["loss_graph_qvalue"], y["loss_graph_qvalue"])
        for x, y in zip(outs_a, outs_b, strict=True)
    )


@needs_compile
@pytest.mark.slow
def test_compiled_high_level_update_agrees_with_eager():
    low, high = [-4.0, -4.0], [20.0, 20.0]

    def build():
        torch.manual_seed(1)
        actor = HighLevelActor(OBS, GOAL, low, high, num_cells=(32,))
        critic = GoalConditionedCritic(
            OBS,
            GOAL,
            action_low=low,
            action_high=high,
            goal_key="desired_goal",
            action_key="subgoal",
            relative_goal=False,
            num_cells=(32,),
        )
        return HighLevelLoss(actor, critic, action_l2=0.01)

    gen = torch.Generator().manual_seed(3)
    n = 200
    data = TensorDict(
        {
            "observation": torch.randn(n, OBS, generator=gen),
            "desired_goal": torch.randn(n, GOAL, generator=gen),
            "subgoal": torch.rand(n, GOAL, generator=gen) * 24 - 4,
            ("next", "observation"): torch.randn(n, OBS, generator=gen),
            ("next", "reward"): -torch.ones(n, 1),
        },
        [n],
    )
    results = []
    for compile_ in (False, True):
        loss = build()
        rb = TensorDictReplayBuffer(storage=LazyTensorStorage(n), batch_size=32)
        rb.extend(data)
        updater = LossUpdater(loss, rb, make_optimizers(loss), actor_after_critic_step=True, compile=compile_)
        torch.manual_seed(11)
        for _ in range(20):
            updater.step()
        results.append(loss.state_dict())
    for key, value in results[0].items():
        if value.is_floating_point():
            torch.testing.assert_close(results[1][key], value, rtol=1e-4, atol=1e-5, msg=key)


def test_compile_falls_back_with_a_message_where_unavailable(monkeypatch):
    monkeypatch.setattr(updates_module, "compile_available", lambda: "CppCompileError: no C++ compiler")
    loss = _sqgc()
    with pytest.warns(
        UserWarning, match="torch.compile does not work here.*no C\\+\\+ compiler.*running eagerly"
    ):
        updater = LossUpdater(
            loss, _low_buffer(), make_optimizers(loss), compile=True, actor_after_critic_step=False
        )
    assert not updater.compile
    torch.manual_seed(7)
    out = updater.step()  # eager, no compilation attempted
    assert torch.isfinite(out["loss_policy_qvalue"])


def test_compile_key_is_validated_and_reaches_the_updaters(monkeypatch):
    with pytest.raises(ConfigError, match="`compile` must be true or false"):
        validate_config(recipe_config("env=PointMaze", "device=cpu", "compile=yes"))
    cfg = recipe_config("env=PointMaze", "device=cpu", "compile=true", "cudagraphs=true")
    cfg["device"] = "cuda"  # past the CUDA check: the combination itself is accepted
    monkeypatch.setattr("torchrl_dhrl.recipe.config.resolve_device", lambda d: torch.device("cuda"))
    validate_config(cfg)
    from dhrl_utils import build_agent, build_replay_buffers, build_updaters

    cfg = recipe_config("env=PointMaze", "preset=smoke", "compile=true")
    agent = build_agent(cfg, torch.device("cpu"))
    low_rb, high_rb = build_replay_buffers(cfg, agent, torch.device("cpu"))
    expected = updates_module.compile_available() is None
    assert [u.compile for u in build_updaters(cfg, agent, low_rb, high_rb)] == [expected, expected]
    cfg = recipe_config("env=PointMaze", "preset=smoke")
    assert [u.compile for u in build_updaters(cfg, agent, low_rb, high_rb)] == [False, False]


# ---------------------------------------------------------------------------------------------- captured sampling
SAMPLER_OBS, SAMPLER_GOAL, SAMPLER_ACT = 3, 2, 1


def _loss(seed=0):
    torch.manual_seed(seed)
    actor = LowLevelActor(
        SAMPLER_OBS, SAMPLER_GOAL, action_max=1.0, action_dim=SAMPLER_ACT, goal_key="goal", num_cells=(16,),
        goal_indices=(0, 1),
    )
    critics = [
        GoalConditionedCritic(
            SAMPLER_OBS,
            SAMPLER_GOAL,
            action_max=1.0,
            action_dim=SAMPLER_ACT,
            num_cells=(16,),
            relative_goal=False,
        )
        for _ in range(2)
    ]
    return SQGCLoss(actor, *critics)


def _relabelled_low_buffer(seed=0):
    rb, _, stream = _filled_buffer(2, 50, 3, 10, window=6, seed=seed)
    return rb, stream


@pytest.fixture
def graphs_on_cpu(monkeypatch):
    """``cudagraphs=True`` on a CPU: CudaGraphModule passes its calls through, so the captured path runs as is."""
    monkeypatch.setattr(LossUpdater, "_check_cuda", lambda self: None)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="This module is instantiated on a machine without CUDA")
        warnings.filterwarnings("ignore", message="No target network updater")
        yield


def test_updater_capture_sampling_switch(graphs_on_cpu):
    loss = _loss()
    rb, _ = _relabelled_low_buffer()
    eager_sampling = LossUpdater(
        loss,
        rb,
        make_optimizers(loss),
        cudagraphs=True,
        capture_sampling=False,
        actor_after_critic_step=False,
    )
    eager_sampling.run(2)
    assert (
        eager_sampling.sampling_captured is False and eager_sampling.sampling_note == "capture_sampling=False"
    )
    # a high-level buffer whose gradual penalty queries a plain graph cannot: auto samples eagerly and says why,
    # True raises the buffer's reason
    from tests.data.test_high_level_transitions import SubgoalStream
    from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph

    plain = GraphPlanner(LandmarkGraph(), lambda s, g: (s[..., :2] - g).norm(dim=-1), 2)
    high = make_high_level_buffer(buffer_size=100, batch_size=8, reward_threshold=0.5, her_window=3, planner=plain)
    high.extend(SubgoalStream(num_envs=3, min_len=8, max_len=40, flag_prob=0.2, seed=11).batch(12))
    loss = _loss()
    auto = LossUpdater(loss, high, make_optimizers(loss), cudagraphs=True, actor_after_critic_step=False)
    auto._setup_sampling()
    assert (
        auto.sampling_captured is False
        and "distance_from_graph has no capture-safe form here" in auto.sampling_note
    )
    loss = _loss()
    required = LossUpdater(
        loss,
        high,
        make_optimizers(loss),
        cudagraphs=True,
        capture_sampling=True,
        actor_after_critic_step=False,
    )
    with pytest.raises(RuntimeError, match="needs a fixed_size graph"):
        required._setup_sampling()
    # a restore captures again, with a sampler built on the restored storage
    loss = _loss()
    captured = LossUpdater(loss, rb, make_optimizers(loss), cudagraphs=True, actor_after_critic_step=False)
    captured.run(3)
    assert captured.sampling_captured
    captured.load_state_dict(captured.state_dict())
    assert captured.sampling_captured is None and not captured._graphs
    captured.run(1)
    assert captured.sampling_captured


def _capture_run(
    graphs: bool,
    compile_: bool = False,
    steps: int = 12,
    *,
    capture_sampling: bool | None = True,
    actor_after_critic_step: bool = False,
    device="cpu",
    updates_per_graph: int = 1,
):
    """``steps`` updates of a fresh SQGC updater on a fresh low-level buffer, with new rows written halfway."""
    loss = _loss().to(device)
    rb, _, stream = _filled_buffer(2, 50, 3, 10, window=6, seed=0, device=device)
    updater = LossUpdater(
        loss,
        rb,
        make_optimizers(loss),
        target_update_interval=3,
        cudagraphs=graphs,
        compile=compile_,
        capture_sampling=capture_sampling,
        actor_after_critic_step=actor_after_critic_step,
        updates_per_graph=updates_per_graph,
    )
    torch.manual_seed(11)
    outs = [updater.run(steps // 2)]
    rb.extend(stream.batch(10).to(device))
    outs.append(updater.run(steps - steps // 2))
    return loss, updater, outs


@pytest.mark.parametrize("actor_after_critic_step", [False, True])
def test_updater_with_captured_sampling_trains_as_an_eager_updater(graphs_on_cpu, actor_after_critic_step):
    """The graphs sample themselves (``capture_sampling`` left to auto): 12 updates (two graphs, 4 target updates,
    writes in between) give the parameters and losses of an eager updater that draws from the same capture-safe
    sampler (``capture_sampling=True`` outside graphs)."""
    graph_loss, graph, graph_outs = _capture_run(
        graphs=True, capture_sampling=None, actor_after_critic_step=actor_after_critic_step
    )
    eager_loss, eager, eager_outs = _capture_run(
        graphs=False, actor_after_critic_step=actor_after_critic_step
    )
    assert graph.sampling_captured and graph.sampling_note == "sampling and relabelling captured"
    assert set(graph._graphs) == {False, True} and graph.num_updates == 12
    assert eager.sampling_captured and eager.sampling_note == "capture-safe sampler" and not eager._graphs
    for key, value in eager_loss.state_dict().items():
        assert torch.equal(graph_loss.state_dict()[key], value), key
    for got, expected in zip(graph_outs, eager_outs, strict=True):
        for key in expected.keys():
            assert torch.equal(got[key], expected[key]), key
    moved = sum(not torch.equal(v, _loss().state_dict()[k]) for k, v in eager_loss.state_dict().items())
    assert moved > 4


@pytest.mark.parametrize("actor_after_critic_step", [False, True])
@pytest.mark.parametrize("per_graph, steps, patterns", [(4, 12, 1), (5, 20, 4), (12, 12, 0)])
def test_updates_captured_together_equal_single_updates(
    graphs_on_cpu, actor_after_critic_step, per_graph, steps, patterns
):
    """``updates_per_graph=N``: N updates per replay (sampling and Polyak averaging inside), the remainder one by
    one, give the parameters and per-call losses of single-update graphs and of an eager updater, bit for bit."""
    kwargs = {"steps": steps, "capture_sampling": None, "actor_after_critic_step": actor_after_critic_step}
    chunk_loss, chunk, chunk_outs = _capture_run(graphs=True, updates_per_graph=per_graph, **kwargs)
    single_loss, single, single_outs = _capture_run(graphs=True, **kwargs)
    eager_loss, _, eager_outs = _capture_run(
        graphs=False, steps=steps, actor_after_critic_step=actor_after_critic_step
    )
    # two run() calls of steps/2: N=4 -> 4 + 2 singles each (one pattern: updates 1-4 and 7-10 match under
    # actor interval 2 and target interval 3); N=5 of 10 -> 5 + 5 (starts 1, 6, 11, 16: four phases of the
    # 6-update period); N=12 > 6 -> singles only
    assert len(chunk._chunk_graphs) == patterns and chunk.num_updates == single.num_updates == steps
    for pattern in chunk._chunk_graphs:
        assert len(pattern) == per_graph and any(target for _, target in pattern)
    for key, value in eager_loss.state_dict().items():
        assert torch.equal(chunk_loss.state_dict()[key], value), key
        assert torch.equal(single_loss.state_dict()[key], value), key
    for got, single_out, expected in zip(chunk_outs, single_outs, eager_outs, strict=True):
        assert set(got.keys()) == set(expected.keys())
        for key in expected.keys():
            assert torch.equal(got[key], expected[key]) and torch.equal(single_out[key], expected[key]), key


def test_updates_per_graph_needs_graphs_and_a_capture_safe_sampler(graphs_on_cpu):
    """Above 1 without ``cudagraphs`` is refused; a buffer sampled on the host (the high level's) keeps one update
    per replay, with the same results as ``updates_per_graph=1``."""
    loss = _loss()
    rb, _ = _relabelled_low_buffer()
    with pytest.raises(ValueError, match="`updates_per_graph` 4 > 1 needs cudagraphs=True"):
        LossUpdater(loss, rb, make_optimizers(loss), updates_per_graph=4, actor_after_critic_step=False)
    with pytest.raises(ValueError, match="updates_per_graph"):
        LossUpdater(
            loss,
            rb,
            make_optimizers(loss),
            cudagraphs=True,
            updates_per_graph=0,
            actor_after_critic_step=False,
        )
    results = []
    for per_graph in (1, 3):
        torch.manual_seed(0)
        loss = _loss()
        rb, _ = _relabelled_low_buffer()
        updater = LossUpdater(
            loss,
            rb,
            make_optimizers(loss),
            cudagraphs=True,
            capture_sampling=False,
            updates_per_graph=per_graph,
            actor_after_critic_step=False,
        )
        torch.manual_seed(1)
        out = updater.run(7)
        assert not updater._chunk_graphs and updater.num_updates == 7
        results.append((loss.state_dict(), out))
    for key, value in results[0][0].items():
        assert torch.equal(results[1][0][key], value), key
    assert all(torch.equal(results[1][1][k], v) for k, v in results[0][1].items())


@pytest.mark.slow
@pytest.mark.parametrize("graphs", [False, True], ids=["eager", "cudagraphs-pass-through"])
def test_updater_capture_sampling_compiled_agrees_with_eager(graphs_on_cpu, graphs):
    """``compile=True capture_sampling=True``, also with ``cudagraphs=True`` (whose CudaGraphModule passes its
    calls through on a CPU): the sampler compiled whole (same draws through the eager generator) and the compiled
    loss follow the eager updater to float round-off."""
    from torchrl_dhrl.training import compile_available

    if compile_available() is not None:
        pytest.skip(f"torch.compile unavailable here: {compile_available()}")
    eager_loss, _, eager_outs = _capture_run(graphs=False, steps=20)
    compiled_loss, compiled, compiled_outs = _capture_run(graphs=graphs, compile_=True, steps=20)
    assert compiled.compile and compiled.cudagraphs == graphs
    prefix = "sampling and relabelling captured" if graphs else "capture-safe sampler"
    assert compiled.sampling_note == prefix + ", compiled"
    for key, value in eager_loss.state_dict().items():
        if value.is_floating_point():
            torch.testing.assert_close(compiled_loss.state_dict()[key], value, rtol=1e-4, atol=1e-5, msg=key)
    for got, expected in zip(compiled_outs, eager_outs, strict=True):
        for key in ("loss_policy_qvalue", "loss_graph_qvalue", "loss_actor"):
            torch.testing.assert_close(got[key], expected[key], rtol=1e-4, atol=1e-5, msg=key)


def test_capture_sampling_key_is_validated_and_reaches_the_low_level_updater():
    from _recipe import recipe_config
    from dhrl_utils import build_agent, build_replay_buffers, build_updaters

    from torchrl_dhrl.recipe import ConfigError, validate_config

    with pytest.raises(
        ConfigError, match="`capture_sampling` must be null \\(auto\\), true or false, got 'yes'"
    ):
        validate_config(recipe_config("env=PointMaze", "device=cpu", "capture_sampling=yes"))
    for value, expected in (("true", True), ("false", False), ("null", None)):
        # the top-level key is the low level's; the high level's is high.capture_sampling (default false)
        for high_value, high_expected in (("false", False), (value, expected)):
            cfg = recipe_config(
                "env=PointMaze", "preset=smoke", f"capture_sampling={value}", f"high.capture_sampling={high_value}"
            )
            validate_config(cfg)
            agent = build_agent(cfg, torch.device("cpu"))
            low_rb, high_rb = build_replay_buffers(cfg, agent, torch.device("cpu"))
            low, high = build_updaters(cfg, agent, low_rb, high_rb)
            assert (low.capture_sampling, high.capture_sampling) == (expected, high_expected)


def test_updater_capture_sampling_argument_errors():
    loss = _loss()
    rb, _ = _relabelled_low_buffer()
    with pytest.raises(ValueError, match="`capture_sampling` must be None, True or False, got 'yes'"):
        LossUpdater(loss, rb, make_optimizers(loss), capture_sampling="yes", actor_after_critic_step=False)
    with pytest.raises(ValueError, match="needs the loss on a CUDA device"):
        LossUpdater(loss, rb, make_optimizers(loss), cudagraphs=True, actor_after_critic_step=False)
