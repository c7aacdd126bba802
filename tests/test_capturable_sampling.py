"""Capture-safe sampling: ``RelabelReplayBuffer.capturable_sampler`` and ``FutureGoalRelabel.capturable_relabel``.

The capture-safe path reads the whole preallocated storage with device-side counters, so that a CUDA graph
(``LossUpdater(cudagraphs=True)``) can replay sampling and relabelling with the update. Checked here on the CPU:
it relabels exactly as ``relabel_sample`` does (same coordinates, same random state) on storages that are
partly filled, full and wrapped, 1-D and ``[T, num_envs]``; it draws uniformly from the written records
(chi-square); it sees later writes without being rebuilt; ``torch.compile(fullgraph=True)`` traces it without a
graph break and never recompiles as the storage fills and wraps (the CPU's proxy for "no host synchronisation,
static shapes"); bad buffers are refused with the reason; and the updater's captured path (CudaGraphModule passes
through on a CPU) trains exactly as an eager updater fed by the same sampler.
"""

from __future__ import annotations

import warnings

import pytest
import torch
from scipy import stats
from test_relabel_future import SENTINEL, GoalStream, check_goals
from torchrl.data import LazyTensorStorage, SamplerWithoutReplacement

from torchrl_dhrl.data import FutureGoalRelabel, HindsightSubgoalRelabel, RelabelReplayBuffer
from torchrl_dhrl.modules import GoalConditionedCritic, LowLevelActor
from torchrl_dhrl.objectives import SQGCLoss, make_optimizers
from torchrl_dhrl.training import LossUpdater
from torchrl_dhrl.training.builders import make_high_level_buffer, make_low_level_buffer

OUT_KEYS = (
    "goal",
    "graph_goal",
    ("next", "goal"),
    ("next", "graph_goal"),
    ("next", "reward"),
    ("next", "graph_reward"),
)


def _filled_buffer(
    num_envs: int, capacity_rows: int, writes: int, horizon: int, window: int, seed: int, device="cpu"
):
    stream = GoalStream(num_envs=num_envs, min_len=2, max_len=30, seed=seed)
    ndim = 2 if num_envs > 1 else 1
    relabel = FutureGoalRelabel(window=window)
    rb = RelabelReplayBuffer(
        storage=LazyTensorStorage(capacity_rows * num_envs, ndim=ndim, device=device),
        relabel=[relabel],
        batch_size=128,
    )
    for _ in range(writes):
        batch = stream.batch(horizon)
        rb.extend((batch if ndim == 2 else batch.reshape(-1)).to(device))
    return rb, relabel, stream


@pytest.mark.parametrize("num_envs", [1, 3])
@pytest.mark.parametrize(
    "writes", [1, 3, 5, 9], ids=["partly-filled", "nearly-full", "wrapped", "wrapped-twice"]
)
def test_capturable_relabel_matches_relabel_sample(num_envs, writes):
    """Same coordinates and random state: the capture-safe relabelling writes exactly what ``relabel_sample``
    writes (windows, offsets, ratios, rewards), whether the storage is partly filled, full or wrapped."""
    for seed in range(4):
        rb, relabel, stream = _filled_buffer(num_envs, 40, writes, 11, window=7 + seed, seed=seed)
        index, _ = rb._sampler.sample(rb.storage, 512)  # the buffer's own draws
        index = torch.stack(index, -1) if isinstance(index, tuple) else index
        data = rb.storage[index.unbind(-1) if index.ndim > 1 else index]
        coords2d = index if index.ndim > 1 else index.unsqueeze(-1)
        torch.manual_seed(seed)
        expected = relabel.relabel_sample(data.clone(), index, rb.storage, newest_index=rb.newest_index)
        torch.manual_seed(seed)
        newest = torch.tensor(rb.newest_index)
        tensor_newest = relabel.relabel_sample(data.clone(), index, rb.storage, newest_index=newest)
        torch.manual_seed(seed)
        captured = relabel.capturable_relabel(rb.storage)(data.clone(), coords2d, newest)
        for key in OUT_KEYS:
            assert torch.equal(captured[key], expected[key]), key
            assert torch.equal(tensor_newest[key], expected[key]), key
        window = stream.expected_window(data["achieved_goal"], relabel.window)
        assert torch.equal(relabel.window_lengths(coords2d, rb.storage, newest), window)
        check_goals(captured, "graph_goal", window)
        assert check_goals(captured, "graph_goal").all()  # ratio 1.0: every graph goal relabelled


@pytest.mark.parametrize("num_envs", [1, 3])
def test_capturable_sampler_draws_written_records_uniformly(num_envs):
    rb, _, _ = _filled_buffer(num_envs, 64, 1, 37, window=5, seed=0)  # 37 of 64 rows written
    sample = rb.capturable_sampler(batch_size=4096)
    torch.manual_seed(0)
    index = torch.cat([sample()["index"] for _ in range(10)])
    time = index[:, 0] if num_envs > 1 else index
    assert int(time.min()) == 0 and int(time.max()) == 36  # every written row reachable, no unwritten one
    cells = time * num_envs + (index[:, 1] if num_envs > 1 else 0)
    counts = torch.bincount(cells, minlength=37 * num_envs).double()
    assert counts.numel() == 37 * num_envs
    assert stats.chisquare(counts.numpy()).pvalue > 1e-3


def test_capturable_sampler_follows_later_writes_and_the_seam():
    rb, relabel, stream = _filled_buffer(3, 40, 1, 10, window=9, seed=3)
    sample = rb.capturable_sampler(batch_size=512)
    rows, newest = rb._device_counters
    assert (int(rows), int(newest)) == (10, 9)
    for write in range(1, 9):  # fills the 40 rows at write 4, then wraps
        rb.extend(stream.batch(10))
        assert int(newest) == rb.newest_index and int(rows) == min(10 * (write + 1), 40)
        batch = sample()
        time = batch["index"][:, 0]
        assert int(time.max()) < int(rows)
        if write == 3:
            assert int(time.max()) >= 30  # the new rows are drawn without rebuilding the sampler
        window = stream.expected_window(batch["achieved_goal"], 9)  # ground truth, seam included
        assert torch.equal(relabel.window_lengths(batch["index"], rb.storage, rb.newest_index), window)
        check_goals(batch, "goal", window)
        relabelled = check_goals(batch, "graph_goal", window)
        assert relabelled.all()
        assert 0.7 < check_goals(batch, "goal").float().mean() < 0.9  # her_ratio 0.8
        assert (batch["desired_goal"] == SENTINEL).all()  # the stored goal is not overwritten


def test_capturable_sampler_compiles_whole_without_recompiling():
    """``torch.compile(fullgraph=True)``: no graph break (no host synchronisation) and no recompilation while the
    storage fills and wraps (nothing read on the host changes); with ``fallback_random`` the compiled sampler
    draws the eager one's batches."""
    from torchrl_dhrl.training.updates import compile_available

    if compile_available() is not None:
        pytest.skip(f"torch.compile unavailable here: {compile_available()}")
    rb, _, stream = _filled_buffer(2, 30, 1, 8, window=6, seed=5)
    sample = rb.capturable_sampler(batch_size=64)
    torch._dynamo.reset()
    compiled = torch.compile(sample, fullgraph=True, options={"fallback_random": True})
    with torch._dynamo.config.patch(error_on_recompile=True):
        for _ in range(6):  # 8, 16, ..., 48 rows written into 30: fills, then wraps
            rb.extend(stream.batch(8))
            torch.manual_seed(1)
            got = compiled()
            torch.manual_seed(1)
            expected = sample()
            for key in ("index", "graph_goal", "goal", ("next", "reward"), "observation"):
                assert torch.equal(got[key], expected[key]), key


def test_capturable_sampler_refuses_what_it_cannot_capture():
    stream = GoalStream(num_envs=2, min_len=3, max_len=9, seed=0)

    def buffer(**kwargs):
        kwargs.setdefault("relabel", [FutureGoalRelabel(window=4)])
        rb = RelabelReplayBuffer(storage=LazyTensorStorage(100, ndim=2), batch_size=8, **kwargs)
        return rb

    with pytest.raises(RuntimeError, match="written to"):
        buffer().capturable_sampler()
    rb = buffer()
    rb.extend(stream.batch(5))
    with pytest.raises(ValueError, match="batch_size must be a positive int, got 0"):
        rb.capturable_sampler(batch_size=0)
    without = buffer(sampler=SamplerWithoutReplacement())
    without.extend(stream.batch(5))
    with pytest.raises(RuntimeError, match="this buffer's sampler is SamplerWithoutReplacement"):
        without.capturable_sampler()
    hindsight = buffer(relabel=[HindsightSubgoalRelabel(subgoal_test_ratio=0.0)])
    hindsight.extend(stream.batch(5))
    with pytest.raises(RuntimeError, match="HindsightSubgoalRelabel has no capture-safe form"):
        hindsight.capturable_sampler()
    restored = buffer()
    restored.load_state_dict({k: v for k, v in rb.state_dict().items() if k != "_newest_index"})
    with pytest.raises(RuntimeError, match="newest written row is unknown"):
        restored.capturable_sampler()
    restored.extend(stream.batch(2))  # writing once more makes it known
    assert restored.capturable_sampler()()["index"].shape == (8, 2)


def test_capturable_sampler_after_a_restore():
    """A sampler built after ``load_state_dict`` draws from the restored rows with the restored seam."""
    rb, relabel, stream = _filled_buffer(2, 20, 5, 10, window=5, seed=2)  # wrapped: the seam matters
    restored = RelabelReplayBuffer(
        storage=LazyTensorStorage(40, ndim=2), relabel=[FutureGoalRelabel(window=5)], batch_size=256
    )
    restored.load_state_dict(rb.state_dict())
    torch.manual_seed(4)
    got = restored.capturable_sampler(batch_size=256)()
    torch.manual_seed(4)
    expected = rb.capturable_sampler(batch_size=256)()
    for key in ("index", "goal", "graph_goal", ("next", "graph_reward")):
        assert torch.equal(got[key], expected[key]), key
    window = stream.expected_window(got["achieved_goal"], 5)
    check_goals(got, "graph_goal", window)


def test_recipe_buffers_low_level_captures_high_level_does_not():
    low = make_low_level_buffer(buffer_size=200, batch_size=16, reward_threshold=0.5)
    stream = GoalStream(num_envs=1, min_len=3, max_len=9, seed=0)
    batch = stream.batch(20).rename_key_("desired_goal", "waypoint")
    low.extend(batch)
    out = low.capturable_sampler()()
    assert out["index"].shape == (16, 2) and out["goal"].shape == (16, 2)
    high = make_high_level_buffer(buffer_size=100, batch_size=8, reward_threshold=0.5)
    with pytest.raises(RuntimeError, match="HindsightSubgoalRelabel has no capture-safe form"):
        high.capturable_sampler()


# ---------------------------------------------------------------------------------------------- the updater
OBS, GOAL, ACT = 3, 2, 1


def _loss(seed=0):
    torch.manual_seed(seed)
    actor = LowLevelActor(OBS, GOAL, action_max=1.0, action_dim=ACT, goal_key="goal", num_cells=(16,))
    critics = [
        GoalConditionedCritic(OBS, GOAL, action_max=1.0, action_dim=ACT, num_cells=(16,), relative_goal=False)
        for _ in range(2)
    ]
    return SQGCLoss(actor, *critics)


def _low_buffer(seed=0):
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
    rb, _ = _low_buffer()
    eager_sampling = LossUpdater(loss, rb, make_optimizers(loss), cudagraphs=True, capture_sampling=False)
    eager_sampling.run(2)
    assert (
        eager_sampling.sampling_captured is False and eager_sampling.sampling_note == "capture_sampling=False"
    )
    # the high-level buffer cannot: auto samples eagerly and says why, True raises the buffer's reason
    high = make_high_level_buffer(buffer_size=100, batch_size=8, reward_threshold=0.5)
    loss = _loss()
    auto = LossUpdater(loss, high, make_optimizers(loss), cudagraphs=True)
    auto._setup_sampling()
    assert (
        auto.sampling_captured is False
        and "HindsightSubgoalRelabel has no capture-safe form" in auto.sampling_note
    )
    loss = _loss()
    required = LossUpdater(loss, high, make_optimizers(loss), cudagraphs=True, capture_sampling=True)
    with pytest.raises(RuntimeError, match="capturable_sampler"):
        required._setup_sampling()
    # a restore captures again, with a sampler built on the restored storage
    loss = _loss()
    captured = LossUpdater(loss, rb, make_optimizers(loss), cudagraphs=True)
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


@pytest.mark.slow
@pytest.mark.parametrize("graphs", [False, True], ids=["eager", "cudagraphs-pass-through"])
def test_updater_capture_sampling_compiled_agrees_with_eager(graphs_on_cpu, graphs):
    """``compile=True capture_sampling=True``, also with ``cudagraphs=True`` (whose CudaGraphModule passes its
    calls through on a CPU): the sampler compiled whole (same draws through the eager generator) and the compiled
    loss follow the eager updater to float round-off."""
    from torchrl_dhrl.training.updates import compile_available

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

    from torchrl_dhrl.training import ConfigError, validate_config

    with pytest.raises(
        ConfigError, match="`capture_sampling` must be null \\(auto\\), true or false, got 'yes'"
    ):
        validate_config(recipe_config("env=PointMaze", "device=cpu", "capture_sampling=yes"))
    for value, expected in (("true", True), ("false", False), ("null", None)):
        cfg = recipe_config("env=PointMaze", "preset=smoke", f"capture_sampling={value}")
        validate_config(cfg)
        agent = build_agent(cfg, torch.device("cpu"))
        low_rb, high_rb = build_replay_buffers(cfg, agent, torch.device("cpu"))
        low, high = build_updaters(cfg, agent, low_rb, high_rb)
        assert (low.capture_sampling, high.capture_sampling) == (expected, None)


def test_updater_capture_sampling_argument_errors():
    loss = _loss()
    rb, _ = _low_buffer()
    with pytest.raises(ValueError, match="`capture_sampling` must be None, True or False, got 'yes'"):
        LossUpdater(loss, rb, make_optimizers(loss), capture_sampling="yes")
    with pytest.raises(ValueError, match="needs the loss on a CUDA device"):
        LossUpdater(loss, rb, make_optimizers(loss), cudagraphs=True)
