"""``auto`` precision: bfloat16 where the device multiplies it natively, float32 elsewhere (emulated bf16 is
slow). Mixed-precision (bfloat16 autocast) updates: the networks' output layers stay in float32, the hidden
layers really run reduced, and a bf16 update stays close to the float32 one."""

import pytest
import torch
from _batches import sqgc_transitions
from _recipe import load_recipe, recipe_config
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from torchrl_dhrl.modules import EnsembleMLP, GoalConditionedActorNet, GoalConditionedCritic, LowLevelActor
from torchrl_dhrl.objectives import SQGCLoss, make_optimizers
from torchrl_dhrl.recipe import ConfigError, describe_precisions, run_precisions, validate_config
from torchrl_dhrl.training import LossUpdater, native_bfloat16, resolve_precision
from torchrl_dhrl.training.precision import _CPU_BF16_PROBES

recipe = load_recipe()


def _cpu_bf16(monkeypatch, avx512_bf16: bool, amx: bool = False) -> None:
    """Pretend the CPU has (or lacks) native bfloat16 units."""
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: avx512_bf16, raising=False)
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: amx, raising=False)


@pytest.mark.parametrize(("avx512_bf16", "amx"), [(False, False), (True, False), (False, True), (True, True)])
def test_native_bfloat16_on_cpu_follows_the_capability_probes(monkeypatch, avx512_bf16, amx):
    _cpu_bf16(monkeypatch, avx512_bf16, amx)
    assert native_bfloat16("cpu") is (avx512_bf16 or amx)
    assert native_bfloat16(torch.device("cpu")) is (avx512_bf16 or amx)


def test_native_bfloat16_without_the_probes_is_false(monkeypatch):
    # a torch without the private probes (or another platform): no claim of native bf16, float32 is safe
    for name in _CPU_BF16_PROBES:
        monkeypatch.delattr(torch.cpu, name, raising=False)
    assert native_bfloat16("cpu") is False
    assert resolve_precision("auto", "cpu") is None


def test_native_bfloat16_on_other_devices(monkeypatch):
    assert native_bfloat16("meta") is False
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert native_bfloat16("cuda") is False  # no CUDA: never native (and no error)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    asked = []

    def bf16_supported(including_emulation=True):
        asked.append(including_emulation)
        return not including_emulation  # an sm80+ GPU

    monkeypatch.setattr(torch.cuda, "is_bf16_supported", bf16_supported)
    assert native_bfloat16("cuda:0") is True and asked == [False]  # emulation does not count


@pytest.mark.parametrize("native", [False, True])
def test_resolve_precision(monkeypatch, native):
    _cpu_bf16(monkeypatch, native)
    assert resolve_precision("float32", "cpu") is None
    assert resolve_precision("bfloat16", "cpu") is torch.bfloat16  # explicit choices are kept as asked
    assert resolve_precision("float16", "cpu") is torch.float16
    assert resolve_precision("auto", "cpu") is (torch.bfloat16 if native else None)
    with pytest.raises(ValueError, match=r"precision must be one of \('float32', 'auto'\), got 'float16'"):
        resolve_precision("float16", "cpu", choices=("float32", "auto"))
    with pytest.raises(ValueError, match="got 'bf16'"):
        resolve_precision("bf16", "cpu")


@pytest.mark.parametrize("native", [False, True])
def test_run_precisions_of_a_configuration(monkeypatch, native):
    _cpu_bf16(monkeypatch, native)
    bf16 = torch.bfloat16 if native else None
    cfg = {"update_dtype": "auto", "planner": {"build_dtype": "auto"}}
    assert run_precisions(cfg, "cpu") == (bf16, bf16)
    # CUDA-graph updates take bfloat16 too (autocast without its weight cache in the captured update)
    assert run_precisions({**cfg, "cudagraphs": True}, "cpu") == (bf16, bf16)
    assert run_precisions({"planner": {"build_dtype": "float16"}}, "cpu") == (None, torch.float16)
    line = describe_precisions(cfg, "cpu")
    name = "bfloat16" if native else "float32"
    assert line == (
        f"Precision: updates {name}, graph builds {name} (auto: cpu {'has' if native else 'has no'} native bfloat16)."
    )
    assert describe_precisions(
        {"update_dtype": "bfloat16", "planner": {"build_dtype": "float32"}}, "cpu"
    ) == ("Precision: updates bfloat16, graph builds float32.")


def test_auto_is_accepted_by_the_config_check_and_bad_values_are_named():
    validate_config(
        recipe_config("env=PointMaze", "device=cpu", "update_dtype=auto", "planner.build_dtype=auto")
    )
    with pytest.raises(ConfigError, match=r"`update_dtype` must be null \(fast path\) or one of \('float32', 'bfloat16', 'auto'\)"):
        validate_config(recipe_config("env=PointMaze", "device=cpu", "update_dtype=float16"))
    with pytest.raises(ConfigError, match="`planner.build_dtype` must be one of"):
        validate_config(recipe_config("env=PointMaze", "device=cpu", "planner.build_dtype=bf16"))


def test_the_cpu_preset_resumes_a_run_of_another_precision():
    # preset=cpu switched from bfloat16 to auto: a run checkpointed with bfloat16 must resume under the new preset
    from torchrl_dhrl.recipe import check_resume_config

    saved = recipe_config(
        "env=AntMaze", "preset=cpu", "update_dtype=bfloat16", "planner.build_dtype=bfloat16"
    )
    notes = check_resume_config(saved, recipe_config("env=AntMaze", "preset=cpu"))
    assert notes == ["planner.build_dtype: 'bfloat16' -> 'auto'", "update_dtype: 'bfloat16' -> 'auto'"]


@pytest.mark.parametrize("native", [False, True])
def test_the_cpu_preset_builds_what_auto_resolves_to(monkeypatch, native):
    """``preset=cpu`` (``update_dtype=auto``, ``planner.build_dtype=auto``): both updaters and the graph build
    use bfloat16 exactly when the CPU has it natively."""
    _cpu_bf16(monkeypatch, native)
    cfg = recipe_config("env=PointMaze", "preset=cpu", "device=cpu", "compile=false")
    assert (cfg["update_dtype"], cfg["planner"]["build_dtype"]) == ("auto", "auto")
    parts = recipe.build_run(cfg, torch.device("cpu"))
    expected = torch.bfloat16 if native else None
    assert parts.low_updater.autocast_dtype is expected
    assert parts.high_updater.autocast_dtype is expected
    assert parts.agent.planner.graph.build_autocast_dtype is expected


OBS, GOAL, ACT, AMAX = 9, 2, 4, 3.0
bf16 = torch.autocast("cpu", dtype=torch.bfloat16)


def _record_dtypes(modules):
    """Forward hooks recording each module's output dtype (returns the log and the handles)."""
    log = {}
    handles = [
        m.register_forward_hook(lambda mod, args, out, name=name: log.setdefault(name, set()).add(out.dtype))
        for name, m in modules.items()
    ]
    return log, handles


def test_ensemble_hidden_layers_reduced_output_layer_full_precision():
    torch.manual_seed(0)
    mlp = EnsembleMLP(7, 1, ensemble_size=2, num_cells=(64, 64))
    x = torch.randn(300, 7)
    ref = mlp(x)
    log, handles = _record_dtypes({"hidden": mlp.layers[0]})
    with bf16:
        out = mlp(x)
        hidden = mlp.activation(mlp.layers[1](mlp.activation(mlp.layers[0](x))))
    for h in handles:
        h.remove()
    assert log == {"hidden": {torch.bfloat16}} and hidden.dtype == torch.bfloat16
    assert out.dtype == torch.float32 and out.shape == ref.shape
    # the output layer on those bf16 activations, in float64: matched closely, and not rounded to bf16
    last = mlp.layers[-1]
    exact = torch.baddbmm(last.bias.double(), hidden.double(), last.weight.double())
    torch.testing.assert_close(out.double(), exact, rtol=1e-3, atol=1e-4)
    assert (out == out.bfloat16().float()).float().mean() < 0.2
    assert not torch.equal(out, ref)  # really reduced
    torch.testing.assert_close(out, ref, rtol=0.05, atol=0.02)
    assert torch.equal(mlp(x), ref)  # outside autocast: unchanged


def test_actor_output_layer_full_precision_under_autocast():
    torch.manual_seed(0)
    net = GoalConditionedActorNet(OBS, GOAL, -torch.ones(ACT), torch.ones(ACT), goal_indices=[0, 1])
    obs, goal = torch.randn(200, OBS), torch.randn(200, GOAL)
    ref = net(obs, goal)
    assert torch.equal(ref, torch.tanh(net.mlp(torch.cat([obs, goal - obs[:, :2]], -1))))  # same as the MLP
    log, handles = _record_dtypes({"hidden": net.mlp[0], "out": net.mlp[-1]})
    with bf16:
        out = net(obs, goal)
    for h in handles:
        h.remove()
    assert log == {"hidden": {torch.bfloat16}, "out": {torch.float32}}
    assert out.dtype == torch.float32
    assert not torch.equal(out, ref)
    torch.testing.assert_close(out, ref, rtol=0.05, atol=0.02)


def _sqgc_setup(seed=0, cells=(64, 64)):
    torch.manual_seed(seed)
    actor = LowLevelActor(
        OBS, GOAL, action_max=AMAX, action_dim=ACT, goal_key="goal", num_cells=cells, goal_indices=(0, 1)
    )
    critics = [
        GoalConditionedCritic(
            OBS,
            GOAL,
            action_max=AMAX,
            action_dim=ACT,
            goal_key="goal",
            num_cells=cells,
            relative_goal=True,
            goal_indices=(0, 1),
        )
        for _ in range(2)
    ]
    loss = SQGCLoss(actor, *critics, target_noise_std=0.0)
    n = 256
    data = sqgc_transitions(n, OBS, GOAL, ACT, AMAX)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(n), batch_size=64)
    rb.extend(data)
    return loss, rb


def _train(autocast_dtype, steps=6, seed=0, watch=None, cudagraphs=False):
    """``steps`` updates on fixed samples; ``watch(loss)`` names modules whose output dtypes are logged."""
    loss, rb = _sqgc_setup(seed)
    log, handles = _record_dtypes(watch(loss) if watch else {})
    updater = LossUpdater(
        loss,
        rb,
        make_optimizers(loss),
        target_update_interval=3,
        autocast_dtype=autocast_dtype,
        cudagraphs=cudagraphs,
        actor_after_critic_step=False,
    )
    torch.manual_seed(7)  # same samples for every run
    outs = [updater.step() for _ in range(steps)]
    for h in handles:
        h.remove()
    return loss, outs, updater, log


def test_bfloat16_updates_run_reduced_and_stay_close_to_float32():
    loss32, outs32, _, _ = _train(None)
    # hidden matmuls of the critics and the actor really run in bf16 inside the updater's step
    loss16, outs16, updater, log = _train(
        torch.bfloat16,
        watch=lambda loss: {
            "critic_hidden": loss.policy_critic.module.ensemble.layers[0],
            "actor_hidden": loss.actor_network.module.mlp[0],
        },
    )
    assert log == {
        "critic_hidden": {torch.bfloat16},
        "actor_hidden": {torch.bfloat16},
    }
    # parameters and Adam state stay float32, and the bf16 steps move the weights like float32's
    # (Adam's step is about lr per weight whatever the gradient, so compare the update directions)
    init = _sqgc_setup()[0].state_dict()
    p32, p16 = loss32.state_dict(), loss16.state_dict()
    assert p32.keys() == p16.keys()
    compared = 0
    for key, start in init.items():
        if not start.is_floating_point():
            continue
        assert p16[key].dtype == torch.float32, key
        step32, step16 = (p32[key] - start).flatten(), (p16[key] - start).flatten()
        if "target" in key or step32.norm() == 0:
            continue
        compared += 1
        assert torch.nn.functional.cosine_similarity(step16, step32, 0) > 0.97, key
        assert (step16 - step32).norm() < 0.3 * step32.norm(), key
        assert not torch.equal(step16, step32), key  # really reduced
    assert compared >= 12  # actor and both critics, every layer
    for opt in updater.optimizers.values():
        for state in opt.state.values():
            assert state["exp_avg"].dtype == torch.float32
    for o32, o16 in zip(outs32, outs16, strict=True):
        for key in ("loss_policy_qvalue", "loss_graph_qvalue", "policy_q", "graph_q"):
            assert torch.isfinite(o16[key])
            torch.testing.assert_close(o16[key], o32[key], rtol=5e-3, atol=1e-4, msg=key)


def test_bfloat16_updates_are_deterministic():
    """Same seed, same bf16 steps, bit for bit (what an exact resume relies on)."""
    a = _train(torch.bfloat16, steps=4)[0]
    b = _train(torch.bfloat16, steps=4)[0]
    for key, value in a.state_dict().items():
        assert torch.equal(value, b.state_dict()[key]), key


@pytest.mark.parametrize("bad", [torch.float16, torch.float32, "bfloat16"])
def test_autocast_dtype_is_validated(bad):
    loss, rb = _sqgc_setup()
    with pytest.raises(ValueError, match="autocast_dtype"):
        LossUpdater(loss, rb, make_optimizers(loss), autocast_dtype=bad, actor_after_critic_step=False)


def test_bfloat16_updates_on_the_captured_path_equal_the_eager_ones(monkeypatch):
    """``cudagraphs=True`` with bfloat16: the captured update (run here through CudaGraphModule's CPU
    pass-through) multiplies its hidden layers in bfloat16 under autocast without the weight cache, and takes
    the eager bf16 updater's steps (capturable Adam apart: float round-off)."""
    import warnings

    monkeypatch.setattr(LossUpdater, "_check_cuda", lambda self: None)
    watch = lambda loss: {"critic_hidden": loss.policy_critic.module.ensemble.layers[0]}  # noqa: E731
    eager, eager_outs, _, _ = _train(torch.bfloat16, steps=8)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="This module is instantiated on a machine without CUDA")
        graphed, graphed_outs, updater, log = _train(torch.bfloat16, steps=8, watch=watch, cudagraphs=True)
    assert updater.cudagraphs and updater._graphs  # the captured path ran
    assert log == {"critic_hidden": {torch.bfloat16}}
    for key, value in eager.state_dict().items():
        torch.testing.assert_close(graphed.state_dict()[key], value, rtol=1e-5, atol=1e-6, msg=key)
    float32 = _train(None, steps=8)[0]
    assert not all(torch.equal(v, float32.state_dict()[k]) for k, v in graphed.state_dict().items())
    for got, expected in zip(graphed_outs, eager_outs, strict=True):
        torch.testing.assert_close(
            got["loss_policy_qvalue"], expected["loss_policy_qvalue"], rtol=1e-5, atol=1e-6
        )
