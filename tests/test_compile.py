"""``compile=True``: the compiled updates learn what the eager ones learn, and fall back where compile is unavailable."""

from __future__ import annotations

import pytest
import torch
from _batches import sqgc_transitions
from _recipe import recipe_config
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_dhrl.modules import GoalConditionedCritic, HighLevelActor, LowLevelActor
from torchrl_dhrl.objectives import HighLevelLoss, SQGCLoss, make_optimizers
from torchrl_dhrl.training import ConfigError, LossUpdater, validate_config
from torchrl_dhrl.training import updates as updates_module

OBS, GOAL, ACT, AMAX = 6, 2, 2, 1.0
needs_compile = pytest.mark.skipif(
    updates_module.compile_available() is not None,
    reason=f"torch.compile unavailable here: {updates_module.compile_available()}",
)


def _sqgc(seed: int = 0, cells=(32, 32)):
    torch.manual_seed(seed)
    actor = LowLevelActor(OBS, GOAL, action_max=AMAX, action_dim=ACT, goal_key="goal", num_cells=cells)
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
        return HighLevelLoss(actor, critic)

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
        updater = LossUpdater(loss, _low_buffer(), make_optimizers(loss), compile=True)
    assert not updater.compile
    torch.manual_seed(7)
    out = updater.step()  # eager, no compilation attempted
    assert torch.isfinite(out["loss_policy_qvalue"])


def test_compile_key_is_validated_and_reaches_the_updaters(monkeypatch):
    with pytest.raises(ConfigError, match="`compile` must be true or false"):
        validate_config(recipe_config("env=PointMaze", "device=cpu", "compile=yes"))
    cfg = recipe_config("env=PointMaze", "device=cpu", "compile=true", "cudagraphs=true")
    cfg["device"] = "cuda"  # past the CUDA check: the combination itself is accepted
    monkeypatch.setattr("torchrl_dhrl.training.config.resolve_device", lambda d: torch.device("cuda"))
    validate_config(cfg)
    from dhrl_utils import build_agent, build_replay_buffers, build_updaters

    cfg = recipe_config("env=PointMaze", "preset=smoke", "compile=true")
    agent = build_agent(cfg, torch.device("cpu"))
    low_rb, high_rb = build_replay_buffers(cfg, agent, torch.device("cpu"))
    expected = updates_module.compile_available() is None
    assert [u.compile for u in build_updaters(cfg, agent, low_rb, high_rb)] == [expected, expected]
    cfg = recipe_config("env=PointMaze", "preset=smoke")
    assert [u.compile for u in build_updaters(cfg, agent, low_rb, high_rb)] == [False, False]
