"""``auto`` precision: bfloat16 where the device multiplies it natively, float32 elsewhere (emulated bf16 is slow)."""

import pytest
import torch
from _recipe import load_recipe, recipe_config

from torchrl_dhrl.training import (
    ConfigError,
    describe_precisions,
    native_bfloat16,
    resolve_precision,
    run_precisions,
    validate_config,
)
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
    with pytest.raises(ConfigError, match=r"`update_dtype` must be one of \('float32', 'bfloat16', 'auto'\)"):
        validate_config(recipe_config("env=PointMaze", "device=cpu", "update_dtype=float16"))
    with pytest.raises(ConfigError, match="`planner.build_dtype` must be one of"):
        validate_config(recipe_config("env=PointMaze", "device=cpu", "planner.build_dtype=bf16"))


def test_the_cpu_preset_resumes_a_run_of_another_precision():
    # preset=cpu switched from bfloat16 to auto: a run checkpointed with bfloat16 must resume under the new preset
    from torchrl_dhrl.training import check_resume_config

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
