"""Validation of a DHRL training configuration, before anything is built or run."""

from __future__ import annotations

import importlib.util
from collections.abc import Mapping
from typing import Any

import torch

__all__ = [
    "BUILD_DTYPES",
    "ConfigError",
    "DISTANCES",
    "LOGGER_BACKENDS",
    "UPDATE_DTYPES",
    "resolve_device",
    "validate_config",
]

#: Precisions of the distance evaluations of a graph rebuild (``None``: the networks' own, float32).
BUILD_DTYPES = {"float32": None, "bfloat16": torch.bfloat16, "float16": torch.float16}
#: Precisions of the networks' updates (``update_dtype``; ``None``: full precision, float32).
UPDATE_DTYPES = {"float32": None, "bfloat16": torch.bfloat16}
#: Graph distances the recipe can plan with.
DISTANCES = ("learned", "oracle")
#: Logger back ends (``none`` logs nothing but the progress bar).
LOGGER_BACKENDS = ("csv", "wandb", "tensorboard", "none")


class ConfigError(ValueError):
    """A training configuration that cannot run; the message says which key and why."""


def _get(cfg: Mapping, path: str) -> Any:
    node: Any = cfg
    for part in path.split("."):
        if not isinstance(node, Mapping) or part not in node:
            raise ConfigError(f"Missing configuration key `{path}`.")
        node = node[part]
    return node


def _number(cfg: Mapping, path: str, *, low: float | None = None, strict: bool = False, integer=False):
    value = _get(cfg, path)
    kind = int if integer else (int, float)
    if isinstance(value, bool) or not isinstance(value, kind):
        raise ConfigError(f"`{path}` must be {'an integer' if integer else 'a number'}, got {value!r}.")
    if low is not None and (value <= low if strict else value < low):
        raise ConfigError(f"`{path}` must be {'>' if strict else '>='} {low}, got {value!r}.")
    return value


def _fraction(cfg: Mapping, path: str) -> float:
    value = _number(cfg, path, low=0.0)
    if value > 1:
        raise ConfigError(f"`{path}` must be in [0, 1], got {value!r}.")
    return value


def resolve_device(device: str | torch.device | None) -> torch.device:
    """``"auto"`` (or ``None``) -> CUDA when available, else CPU; anything else is checked.

    Examples:
        >>> resolve_device("cpu")
        device(type='cpu')
    """
    if device is None or str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(device)
    except RuntimeError as err:
        raise ConfigError(f"`device` must be 'auto', 'cpu', 'cuda' or 'cuda:N', got {device!r}.") from err
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(
            "`device` asks for CUDA but torch.cuda.is_available() is False; use device=auto or cpu."
        )
    return device


def validate_config(cfg: Mapping, env_names: tuple[str, ...] | None = None) -> None:
    """Checks a training configuration and raises :class:`ConfigError` with a clear message.

    Every check runs before any environment, network or file is created, so a typo costs
    nothing. ``env_names`` lists the valid environment names (defaults to every environment of
    :mod:`torchrl_dhrl.envs`).

    Examples:
        >>> try:
        ...     validate_config({"env_name": "AntMase"}, env_names=("AntMaze",))
        ... except ConfigError as err:
        ...     print(err)
        Unknown env_name 'AntMase'; choose one of: AntMaze.
    """
    if env_names is None:
        from torchrl_dhrl.envs import ENV_NAMES

        env_names = tuple(ENV_NAMES)
    name = _get(cfg, "env_name")
    if name not in env_names:
        raise ConfigError(f"Unknown env_name {name!r}; choose one of: {', '.join(env_names)}.")
    _number(cfg, "seed", integer=True)
    device = resolve_device(_get(cfg, "device"))
    if cfg.get("cudagraphs", False) and device.type != "cuda":
        raise ConfigError(f"`cudagraphs=true` needs a CUDA device, but `device` resolves to {device}.")
    update_dtype = cfg.get("update_dtype", "float32")
    if update_dtype not in UPDATE_DTYPES:
        raise ConfigError(f"`update_dtype` must be one of {tuple(UPDATE_DTYPES)}, got {update_dtype!r}.")
    if update_dtype != "float32" and cfg.get("cudagraphs", False):
        raise ConfigError(f"`update_dtype={update_dtype}` cannot be combined with `cudagraphs=true` (yet).")
    _number(cfg, "total_steps", low=0, strict=True, integer=True)
    _number(cfg, "num_envs", low=1, integer=True)
    length = _get(cfg, "episode_length")
    if length is not None:
        _number(cfg, "episode_length", low=1, integer=True)

    for key in ("epoch_episodes", "eval_episodes"):
        _number(cfg, f"schedule.{key}", low=1, integer=True)
    for key in ("warmup_episodes", "graph_start_epoch"):
        _number(cfg, f"schedule.{key}", low=0, integer=True)
    for key in ("graph_rebuild_epochs", "eval_every_epochs", "high_update_interval"):
        _number(cfg, f"schedule.{key}", low=1, integer=True)
    _number(cfg, "schedule.low_updates_per_step", low=0.0)

    for level in ("low", "high"):
        hidden = _get(cfg, f"{level}.hidden")
        if not hidden or any(isinstance(h, bool) or not isinstance(h, int) or h < 1 for h in hidden):
            raise ConfigError(
                f"`{level}.hidden` must be a non-empty list of positive integers, got {hidden!r}."
            )
        _number(cfg, f"{level}.batch_size", low=1, integer=True)
        _number(cfg, f"{level}.buffer_size", low=1, integer=True)
        _number(cfg, f"{level}.her_window", low=1, integer=True)
        _fraction(cfg, f"{level}.her_ratio")
        gamma = _number(cfg, f"{level}.gamma", low=0.0, strict=True)
        if gamma >= 1:
            raise ConfigError(f"`{level}.gamma` must be in (0, 1), got {gamma!r}.")
        _number(cfg, f"{level}.actor_lr", low=0.0, strict=True)
        _number(cfg, f"{level}.critic_lr", low=0.0, strict=True)
        _fraction(cfg, f"{level}.polyak")
        _number(cfg, f"{level}.target_update_interval", low=1, integer=True)
        _number(cfg, f"{level}.actor_update_interval", low=1, integer=True)
    _number(cfg, "low.action_noise", low=0.0)
    _fraction(cfg, "low.uniform_prob")
    _number(cfg, "low.reward_threshold", low=0.0, strict=True)

    c_h = _get(cfg, "high.c_h")
    if isinstance(c_h, bool) or not isinstance(c_h, int) or c_h < 1:
        raise ConfigError(f"`high.c_h` (the high-level interval) must be an integer >= 1, got {c_h!r}.")
    low, high = list(_get(cfg, "high.subgoal_low")), list(_get(cfg, "high.subgoal_high"))
    if len(low) != len(high) or not low:
        raise ConfigError(
            f"`high.subgoal_low` and `high.subgoal_high` must have the same length, got {low}, {high}."
        )
    if any(lo >= hi for lo, hi in zip(low, high, strict=True)):
        raise ConfigError(
            f"`high.subgoal_low` must be below `high.subgoal_high` on every axis, got {low}, {high}."
        )
    _number(cfg, "high.subgoal_noise", low=0.0)
    _fraction(cfg, "high.subgoal_test_ratio")
    _number(cfg, "high.subgoal_test_threshold", low=0.0, strict=True)
    _number(cfg, "high.subgoal_miss_penalty", low=0.0)
    if _get(cfg, "high.gradual_penalty") is not None:
        _number(cfg, "high.gradual_penalty", low=0.0)
    _number(cfg, "high.far_from_graph_factor", low=0.0, strict=True)

    distance = _get(cfg, "planner.distance")
    if distance not in DISTANCES:
        raise ConfigError(f"`planner.distance` must be one of {DISTANCES}, got {distance!r}.")
    if distance == "oracle" and _get(cfg, "goal_indices") is None:
        raise ConfigError(
            f"planner.distance=oracle needs the achieved goal inside the observation (goal_indices), "
            f"which {name} does not provide."
        )
    if _get(cfg, "low.relative_goal") and _get(cfg, "goal_indices") is None:
        raise ConfigError(f"low.relative_goal=true needs goal_indices, which {name} does not provide.")
    _number(cfg, "planner.cutoff", low=0.0, strict=True)
    landmarks = _number(cfg, "planner.max_landmarks", integer=True)
    if landmarks < 2:
        raise ConfigError(f"`planner.max_landmarks` must be >= 2 (a graph needs two nodes), got {landmarks}.")
    candidates = _number(cfg, "planner.candidates", integer=True)
    if candidates < landmarks:
        raise ConfigError(
            f"`planner.candidates` ({candidates}) must be >= `planner.max_landmarks` ({landmarks})."
        )
    _number(cfg, "planner.early_stop", low=0.0)
    _number(cfg, "planner.reach_radius", low=0.0, strict=True)
    if _get(cfg, "planner.build_dtype") not in BUILD_DTYPES:
        raise ConfigError(
            f"`planner.build_dtype` must be one of {tuple(BUILD_DTYPES)}, got {_get(cfg, 'planner.build_dtype')!r}."
        )
    _number(cfg, "planner.oracle_margin", low=0.0)
    _number(cfg, "planner.oracle_speed", low=0.0, strict=True)
    _number(cfg, "fgs.noise", low=0.0)

    backend = _get(cfg, "logger.backend")
    if backend not in LOGGER_BACKENDS:
        raise ConfigError(f"`logger.backend` must be one of {LOGGER_BACKENDS}, got {backend!r}.")
    if backend in ("wandb", "tensorboard") and importlib.util.find_spec(backend) is None:
        raise ConfigError(f"`logger.backend={backend}` needs the {backend} package: pip install {backend}.")
    if _get(cfg, "logger.wandb_mode") not in ("offline", "online"):
        raise ConfigError(
            f"`logger.wandb_mode` must be 'offline' or 'online', got {_get(cfg, 'logger.wandb_mode')!r}."
        )
    _number(cfg, "checkpoint.every_epochs", low=1, integer=True)
    _number(cfg, "plots.every_epochs", low=0, integer=True)
