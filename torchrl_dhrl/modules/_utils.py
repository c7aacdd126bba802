"""Small shared helpers for the DHRL modules: boxes, goal inputs, input checks, the output layer's precision."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Bounded, Composite, TensorSpec


def resolve_box(
    *,
    spec: TensorSpec | None = None,
    low: torch.Tensor | float | Sequence[float] | None = None,
    high: torch.Tensor | float | Sequence[float] | None = None,
    max_abs: torch.Tensor | float | Sequence[float] | None = None,
    dim: int | None = None,
    key: NestedKey = "action",
    name: str = "action",
    allow_scalar: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Returns ``(low, high)`` float tensors of shape ``[dim]`` from exactly one box description.

    Args:
        spec (TensorSpec, optional): a :class:`~torchrl.data.Bounded` spec, or a
            :class:`~torchrl.data.Composite` holding one under ``key``.
        low, high (tensor or float, optional): explicit bounds (both required together).
        max_abs (tensor or float, optional): a symmetric box ``[-max_abs, max_abs]``.
        dim (int, optional): the last dimension of the box; required when scalars are given.
        key (NestedKey): the entry to read from a composite spec.
        name (str): a name used in error messages.
        allow_scalar (bool): return scalar bounds as shape ``[1]`` (broadcasting over any
            last dim) instead of requiring ``dim``.
    """
    given = [spec is not None, low is not None or high is not None, max_abs is not None]
    if sum(given) != 1:
        raise ValueError(
            f"Describe the {name} box with exactly one of `spec`, (`low`, `high`) or `max_abs`; "
            f"got spec={spec!r}, low={low!r}, high={high!r}, max_abs={max_abs!r}."
        )
    if spec is not None:
        if isinstance(spec, Composite):
            if key not in spec.keys(True, True):
                raise ValueError(f"The composite {name} spec has no entry {key!r}: {spec}.")
            spec = spec[key]
        if not isinstance(spec, Bounded):
            raise TypeError(f"The {name} spec must be a Bounded spec, got {type(spec).__name__}.")
        low_t = spec.space.low
        high_t = spec.space.high
        # Specs of batched envs carry the batch dims: the box is the same per env, keep the last dim.
        while low_t.ndim > 1:
            low_t, high_t = low_t[0], high_t[0]
    elif max_abs is not None:
        high_t = torch.as_tensor(max_abs, dtype=torch.get_default_dtype())
        if (high_t <= 0).any():
            raise ValueError(f"`max_abs` of the {name} box must be > 0, got {max_abs}.")
        low_t = -high_t
    else:
        if low is None or high is None:
            raise ValueError(f"Give both `low` and `high` for the {name} box.")
        low_t = torch.as_tensor(low, dtype=torch.get_default_dtype())
        high_t = torch.as_tensor(high, dtype=torch.get_default_dtype())
    low_t, high_t = torch.broadcast_tensors(low_t, high_t)
    if low_t.ndim == 0 and dim is None and allow_scalar:
        low_t, high_t = low_t.reshape(1), high_t.reshape(1)
    elif low_t.ndim == 0:
        if dim is None:
            raise ValueError(f"Scalar bounds of the {name} box need its dimension (`dim`).")
        low_t, high_t = low_t.expand(dim), high_t.expand(dim)
    if low_t.ndim != 1:
        raise ValueError(f"The {name} box must be 1-D, got bounds of shape {tuple(low_t.shape)}.")
    if dim is not None and low_t.shape[-1] != dim:
        raise ValueError(f"The {name} box has dimension {low_t.shape[-1]}, expected {dim}.")
    if not (high_t > low_t).all():
        raise ValueError(f"The {name} box needs high > low everywhere, got low={low_t}, high={high_t}.")
    return low_t.clone().float(), high_t.clone().float()


def box_loc_scale(low: torch.Tensor, high: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Returns the centre and half-width of a box, so that ``x = loc + scale * u`` maps [-1, 1] onto it."""
    return (high + low) / 2, (high - low) / 2


def relative_goal_needs_indices(relative_goal: bool, goal_indices) -> None:
    """A goal fed relative to the achieved goal needs ``goal_indices`` (a :func:`~torchrl_dhrl.checks.checked`
    relation of the goal-conditioned modules)."""
    if relative_goal and goal_indices is None:
        raise ValueError(
            "`relative_goal` needs `goal_indices` (where the achieved goal sits in the observation), got None."
        )


def as_goal_indices(goal_indices: Sequence[int] | torch.Tensor | None, goal_dim: int) -> torch.Tensor:
    """Validates the indices of the achieved goal inside the observation."""
    if goal_indices is None:
        raise ValueError("`goal_indices` is required for relative goal inputs.")
    idx = torch.as_tensor(goal_indices, dtype=torch.long).reshape(-1)
    if idx.numel() != goal_dim:
        raise ValueError(
            f"`goal_indices` must have one index per goal dimension ({goal_dim}), got {idx.tolist()}."
        )
    if (idx < 0).any():
        raise ValueError(f"`goal_indices` must be non-negative, got {idx.tolist()}.")
    return idx


def register_goal_indices(
    module: torch.nn.Module,
    relative_goal: bool,
    goal_indices: Sequence[int] | torch.Tensor | None,
    goal_dim: int,
    observation_dim: int,
) -> None:
    """Sets ``module.relative_goal`` and registers the validated ``goal_indices`` buffer (``None`` if absolute)."""
    module.relative_goal = relative_goal
    if not relative_goal:
        module.goal_indices = None
        return
    idx = as_goal_indices(goal_indices, goal_dim)
    if int(idx.max()) >= observation_dim:
        raise ValueError(f"`goal_indices` {idx.tolist()} exceed the observation size {observation_dim}.")
    module.register_buffer("goal_indices", idx)


def check_last_dim(name: str, tensor: torch.Tensor, expected: int) -> None:
    """Raises a ValueError when ``tensor`` is not a floating tensor of last dimension ``expected``."""
    if not isinstance(tensor, torch.Tensor):
        raise TypeError(f"`{name}` must be a tensor, got {type(tensor).__name__}.")
    if tensor.ndim == 0 or tensor.shape[-1] != expected:
        raise ValueError(f"`{name}` must have last dimension {expected}, got shape {tuple(tensor.shape)}.")
    if not tensor.is_floating_point():
        raise TypeError(f"`{name}` must be a floating tensor, got {tensor.dtype}.")


def goal_input(
    observation: torch.Tensor, goal: torch.Tensor, goal_indices: torch.Tensor | None
) -> torch.Tensor:
    """Returns the goal as a network sees it.

    With ``goal_indices`` the goal is made relative to the achieved goal,
    ``goal - observation[..., goal_indices]``; with ``None`` it is fed as is.
    """
    if goal_indices is None:
        return goal
    return goal - observation.index_select(-1, goal_indices)


def full_precision_output(layer: nn.Module, hidden: torch.Tensor) -> torch.Tensor:
    """``layer(hidden)`` in the layer's own dtype, also inside ``torch.autocast``.

    Under autocast the hidden layers run in the reduced dtype; the output layer (a few units)
    costs little in full precision and keeps the output -- a distance, a Q value, the
    pre-tanh action -- off the reduced dtype's grid (bfloat16 keeps 8 bits: up to 0.4%).
    Outside autocast this is ``layer(hidden)``.
    """
    if not autocast_enabled(hidden):
        return layer(hidden)
    with torch.autocast(hidden.device.type, enabled=False):
        return layer(hidden.to(layer.weight.dtype))


def autocast_enabled(tensor: torch.Tensor) -> bool:
    """Whether ``torch.autocast`` is on for the device of ``tensor``."""
    device_type = tensor.device.type
    return torch.amp.is_autocast_available(device_type) and torch.is_autocast_enabled(device_type)


def check_positional_keys(module: TensorDictModuleBase, n_in: int, role: str) -> None:
    """Checks a module follows the positional key contract used by the losses and distances."""
    in_keys = getattr(module, "in_keys", None)
    out_keys = getattr(module, "out_keys", None)
    if in_keys is None or out_keys is None:
        raise TypeError(f"The {role} must be a TensorDictModule with in_keys/out_keys, got {type(module)}.")
    if len(in_keys) != n_in or len(out_keys) < 1:
        raise ValueError(
            f"The {role} must read exactly {n_in} keys (observation, goal{', action' if n_in == 3 else ''}) "
            f"in that order and write its output first; got in_keys={in_keys}, out_keys={out_keys}. "
            "Pass the network itself (e.g. LowLevelActor), not a sequence that also plans or holds subgoals."
        )


def routes_tensors_only(module: TensorDictModuleBase) -> bool:
    """Whether calling ``module`` on a tensordict only routes its in_keys to ``module.module`` and back.

    True for a :class:`~tensordict.nn.TensorDictModule` (or :class:`~torchrl.modules.Actor`) whose
    ``forward`` is not overridden, without safety projection and without forward hooks on it or its
    network: evaluating ``module.module`` on the tensors is then the same computation, without building
    a TensorDict. The fast paths of the losses and of ``GoalDistance`` rely on it.
    """
    net = getattr(module, "module", None)
    return (
        type(module).forward is TensorDictModule.forward
        and isinstance(net, nn.Module)
        and not getattr(module, "safe", False)
        and not (module._forward_hooks or module._forward_pre_hooks)
        and not (net._forward_hooks or net._forward_pre_hooks)
    )


def call_with_params(module: nn.Module, params: TensorDictBase | None, *args):
    """``module(*args)`` with the parameters and buffers of ``params`` in place of the module's own.

    ``params`` is laid out as ``TensorDict.from_module(module)`` (e.g. a loss's ``actor_network_params``);
    ``None`` calls the module with its own. Evaluated with :func:`torch.func.functional_call`, which leaves the
    module as it was on return (also on an exception). Unlike ``with params.to_module(module):`` around the call,
    which ``torch.cond``'s branches refuse under ``torch.compile`` (a mutation from outside their scope), it also
    runs inside a compiled ``torch.cond``.
    """
    if params is None:
        return module(*args)
    return torch.func.functional_call(module, dict(params.flatten_keys(".").items()), args)


def run_positional(
    module: TensorDictModuleBase, *inputs: torch.Tensor, params: TensorDictBase | None = None
) -> torch.Tensor:
    """Runs a TensorDictModule on tensors given in the order of its in_keys; returns its first output.

    ``params`` (optional) replaces the module's parameters for the call (:func:`call_with_params`).
    """
    batch = inputs[0].shape[:-1]
    td = TensorDict(dict(zip(module.in_keys, inputs, strict=True)), batch_size=batch)
    return call_with_params(module, params, td).get(module.out_keys[0])
