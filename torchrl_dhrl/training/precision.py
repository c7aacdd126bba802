"""Which precision to compute in: the ``auto`` value of the recipe's ``update_dtype`` and ``planner.build_dtype``.

bfloat16 autocast pays off only where the hardware multiplies bfloat16 natively: CPUs with AVX512-BF16 or AMX,
CUDA GPUs of compute capability 8.0 and newer. Elsewhere PyTorch emulates it, and a bfloat16 update becomes many
times *slower* than a float32 one (measured 11-14x on an AVX2-only AMD EPYC, ``benchmarks/README.md``). ``auto``
therefore picks bfloat16 where it is native and float32 everywhere else.
"""

from __future__ import annotations

import torch

__all__ = ["PRECISIONS", "native_bfloat16", "resolve_precision"]

#: The fixed precision names and the autocast dtype each stands for (``None``: float32, no autocast). The name
#: ``"auto"`` is accepted besides them and resolved per device by :func:`resolve_precision`.
PRECISIONS = {"float32": None, "bfloat16": torch.bfloat16, "float16": torch.float16}

# CPU capability probes of torch (private, so looked up defensively: a missing probe counts as "no").
_CPU_BF16_PROBES = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")


def native_bfloat16(device: str | torch.device) -> bool:
    """Whether ``device`` computes bfloat16 matrix products natively (so bf16 autocast is faster, not slower).

    CPU: AVX512-BF16 or AMX tiles (``torch.cpu``'s capability probes; other CPUs, ARM included, answer
    ``False``). CUDA: :func:`torch.cuda.is_bf16_supported` without emulation (compute capability >= 8.0).
    Any other device type: ``False``.

    Args:
        device (str or torch.device): the device the networks live on.

    Examples:
        >>> native_bfloat16("meta")
        False
        >>> isinstance(native_bfloat16("cpu"), bool)
        True
    """
    device = torch.device(device)
    if device.type == "cpu":
        probes = (getattr(torch.cpu, name, None) for name in _CPU_BF16_PROBES)
        return any(bool(probe()) for probe in probes if probe is not None)
    if device.type == "cuda":
        return bool(torch.cuda.is_available() and torch.cuda.is_bf16_supported(including_emulation=False))
    return False


def resolve_precision(
    name: str,
    device: str | torch.device,
    *,
    choices: tuple[str, ...] | None = None,
) -> torch.dtype | None:
    """The autocast dtype of a precision name on ``device`` (``None``: float32, no autocast).

    Args:
        name (str): ``"float32"``, ``"bfloat16"``, ``"float16"`` or ``"auto"`` (bfloat16 where
            :func:`native_bfloat16`, else float32).

    Keyword Args:
        choices (tuple of str, optional): the names this caller accepts (default: those of :data:`PRECISIONS`
            and ``"auto"``).

    Raises:
        ValueError: ``name`` is not one of ``choices``.

    Examples:
        >>> resolve_precision("bfloat16", "cpu")
        torch.bfloat16
        >>> resolve_precision("auto", "meta") is None  # no native bfloat16 there: float32
        True
    """
    choices = (*PRECISIONS, "auto") if choices is None else choices
    if name not in choices:
        raise ValueError(f"precision must be one of {choices}, got {name!r}.")
    if name == "auto":
        return torch.bfloat16 if native_bfloat16(device) else None
    return PRECISIONS[name]
