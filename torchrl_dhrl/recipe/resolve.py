"""What a configuration resolves to on the machine it runs on: the device, the speed switches left at ``null``,
the precisions, and the keys in goal units derived from the env."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from torchrl_dhrl.training import native_bfloat16, resolve_precision

from .schema import BUILD_DTYPES, GOAL_UNIT_KEYS, UPDATE_DTYPES, ConfigError, _get

__all__ = [
    "FAST_PATH",
    "REFERENCE_PATH",
    "derive_goal_units",
    "describe_precisions",
    "policy_captured",
    "resolve_device",
    "resolve_speed",
    "run_precisions",
]

#: What the speed switches left at ``null`` become (:func:`resolve_speed`): with ``fast=true`` the fastest
#: combination measured safe on the device type (CUDA: the updates replayed as CUDA graphs, in bfloat16 where the
#: GPU has it natively, the low level's sampling captured in the graphs through ``capture_sampling=null``; a CPU:
#: eager float32, see docs/training.md), with ``fast=false`` the eager float32 reference path everywhere.
FAST_PATH = {
    "cuda": {"cudagraphs": True, "update_dtype": "auto"},
    "cpu": {"cudagraphs": False, "update_dtype": "float32"},
}
REFERENCE_PATH = {"cudagraphs": False, "update_dtype": "float32"}


_DEVICES = "'auto', 'cpu', 'cuda' or 'cuda:N' (N < the number of visible CUDA devices)"


def resolve_device(device: str | torch.device | None) -> torch.device:
    """``"auto"`` (or ``None``) -> CUDA when available, else CPU; anything else is checked.

    Only the devices the recipe runs on are accepted: ``"cpu"``, ``"cuda"`` and ``"cuda:N"`` with ``N``
    below :func:`torch.cuda.device_count`. Other PyTorch devices (``"mps"``, ``"meta"``, ``"xpu"``, ...)
    raise :class:`ConfigError` here rather than deep inside TorchRL's specs or the replay buffers.

    Args:
        device (str, torch.device or None): the ``device`` configuration value.

    Returns:
        the :class:`torch.device` to build everything on.

    Raises:
        ConfigError: naming ``device``, the value and the accepted ones.

    Examples:
        >>> resolve_device("cpu")
        device(type='cpu')
        >>> try:
        ...     resolve_device("mps")
        ... except ConfigError as err:
        ...     print(err)
        `device` must be 'auto', 'cpu', 'cuda' or 'cuda:N' (...), got 'mps' (the recipe runs on CPU and CUDA only).
    """
    if device is None or str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if not isinstance(device, (str, torch.device)):
        raise ConfigError(f"`device` must be {_DEVICES}, got {device!r}.")
    try:
        resolved = torch.device(device)
    except RuntimeError as err:
        raise ConfigError(f"`device` must be {_DEVICES}, got {device!r}.") from err
    if resolved.type not in ("cpu", "cuda"):
        raise ConfigError(
            f"`device` must be {_DEVICES}, got {device!r} (the recipe runs on CPU and CUDA only)."
        )
    if resolved.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(
                f"`device={device}` asks for CUDA but torch.cuda.is_available() is False; use device=auto or cpu."
            )
        count = torch.cuda.device_count()
        if resolved.index is not None and resolved.index >= count:
            raise ConfigError(
                f"`device={device}`: only {count} CUDA device(s) are visible; use cuda:0"
                + (f" to cuda:{count - 1}." if count > 1 else ".")
            )
    return resolved


def policy_captured(cfg: Mapping) -> bool:
    """Whether the recipe's acting policy is compiled (``compile_policy``) or captured as a CUDA graph
    (``cudagraph_policy``): both need the capturable planner, and neither lets hooks time the planner.

    Examples:
        >>> policy_captured({"compile_policy": False}), policy_captured({"cudagraph_policy": True})
        (False, True)
    """
    return bool(cfg.get("compile_policy", False)) or bool(cfg.get("cudagraph_policy", False))


def resolve_speed(cfg: Mapping, device: str | torch.device) -> tuple[dict, str]:
    """The configuration with its speed switches left at ``null`` resolved for ``device``, and a start-up line.

    ``cudagraphs`` and ``update_dtype`` at ``null`` take the value of :data:`FAST_PATH` for the device's type when
    ``fast`` is true (the default), of :data:`REFERENCE_PATH` when it is false; a value set explicitly is kept.
    Idempotent: a resolved configuration comes back unchanged (and the line says so).

    Examples:
        >>> cfg = {"fast": True, "cudagraphs": None, "update_dtype": None}
        >>> resolve_speed(cfg, "cuda")[0]
        {'fast': True, 'cudagraphs': True, 'update_dtype': 'auto'}
        >>> resolve_speed({**cfg, "fast": False}, "cuda")[0]
        {'fast': False, 'cudagraphs': False, 'update_dtype': 'float32'}
        >>> resolve_speed({**cfg, "update_dtype": "bfloat16"}, "cpu")[1]
        'Speed: cudagraphs=false (fast=true on cpu: eager; fast=false: the eager float32 reference path).'
    """
    device = torch.device(device)
    fast = bool(cfg.get("fast", True))
    table = FAST_PATH.get(device.type, REFERENCE_PATH) if fast else REFERENCE_PATH
    resolved, chosen = dict(cfg), []
    for key, value in table.items():
        if resolved.get(key) is None:
            resolved[key] = value
            chosen.append(f"{key}={str(value).lower()}")
    if not chosen:
        return resolved, "Speed: every speed switch set in the configuration."
    why = (
        f"fast=true on {device.type}: {'the fast path' if device.type == 'cuda' else 'eager'}; fast=false: the eager "
        "float32 reference path"
        if fast
        else "fast=false: the eager float32 reference path"
    )
    return resolved, f"Speed: {', '.join(chosen)} ({why})."


def run_precisions(cfg: Mapping, device: str | torch.device) -> tuple[torch.dtype | None, torch.dtype | None]:
    """The autocast dtypes of a configuration's updates and graph builds on ``device`` (``None``: float32).

    Resolves ``update_dtype`` and ``planner.build_dtype`` (``auto``: bfloat16 where ``device`` has it natively,
    else float32; :func:`~torchrl_dhrl.training.resolve_precision`), CUDA-graph updates included.

    Examples:
        >>> import torch
        >>> run_precisions({"update_dtype": "bfloat16", "planner": {"build_dtype": "float32"}}, "cpu")
        (torch.bfloat16, None)
    """
    update_dtype = (
        resolve_speed(cfg, device)[0]["update_dtype"]
        if cfg.get("update_dtype") is None
        else cfg["update_dtype"]
    )
    update = resolve_precision(update_dtype, device, choices=UPDATE_DTYPES)
    build = resolve_precision(_get(cfg, "planner.build_dtype"), device, choices=BUILD_DTYPES)
    return update, build


def describe_precisions(cfg: Mapping, device: str | torch.device) -> str:
    """One start-up line: the precisions :func:`run_precisions` resolves to, and why when ``auto`` chose.

    Examples:
        >>> describe_precisions({"update_dtype": "float32", "planner": {"build_dtype": "float32"}}, "cpu")
        'Precision: updates float32, graph builds float32.'
    """
    update, build = run_precisions(cfg, device)
    line = f"Precision: updates {_dtype_name(update)}, graph builds {_dtype_name(build)}"
    if "auto" in (cfg.get("update_dtype"), _get(cfg, "planner.build_dtype")):
        has = "has" if native_bfloat16(device) else "has no"
        line += f" (auto: {torch.device(device).type} {has} native bfloat16)"
    return line + "."


def _dtype_name(dtype: torch.dtype | None) -> str:
    return "float32" if dtype is None else str(dtype).removeprefix("torch.")


def _round(value: float) -> float:
    return float(f"{value:.4g}")


def derive_goal_units(cfg: dict, env) -> list[str]:
    """Fills the ``null`` keys of :data:`GOAL_UNIT_KEYS` and ``goal_indices=auto`` of ``cfg`` (in place) from
    ``env``, an env of the goal-env contract, and returns one ``"key=value"`` note per derived key.

    - the subgoal box: :func:`~torchrl_dhrl.envs.goal_extent` (the env's goals and a random walk's states);
    - ``high.subgoal_noise`` and ``fgs.noise``: a 12th and an 8th of the box's largest side (AntMaze's 2 and 3
      for its 24-unit box);
    - ``low.reward_threshold``: the env's success radius (``env.success_radius``, a number or a method;
      :meth:`~torchrl_dhrl.envs.GymnasiumGoalEnv.success_radius` reads it from ``compute_reward``);
    - ``planner.reach_radius``: the reward threshold (as every built-in env);
    - ``planner.oracle_margin`` (the agent's radius: walls are inflated by it in the true geometry the maze
      diagnostics measure against): an 8th of the maze's cell size where the env has a maze
      (:meth:`~torchrl_dhrl.envs.GymnasiumGoalEnv.maze_geometry`: gymnasium-robotics' ``PointMaze_*`` 0.125,
      ``AntMaze_*`` 0.5, as the built-in PointMaze's 0.5 for its 4-unit cells), a 48th of the subgoal box's
      largest side elsewhere (AntMaze's 0.5 for its 24-unit box);
    - ``planner.oracle_speed`` (goal units per env step: the oracle distance's and the diagnostics' step count of a
      length): the agent's top speed, :func:`~torchrl_dhrl.envs.goal_speed` (gymnasium-robotics' point 0.052, its
      ants about 0.1; the built-in PointMaze's 0.2 and AntMaze's 0.1 as their env files set them);
    - ``goal_indices=auto``: :func:`~torchrl_dhrl.envs.goal_indices_of` (``null`` when the goal is not in the
      observation).

    Raises:
        ConfigError: naming the key when the env cannot tell it (no success radius).
    """
    from torchrl_dhrl.envs import goal_extent, goal_indices_of, goal_speed

    notes = []

    def put(path: str, value: Any) -> None:
        group, key = path.split(".") if "." in path else (None, path)
        (cfg[group] if group else cfg)[key] = value
        notes.append(f"{path}={value}")

    missing = [path for path in GOAL_UNIT_KEYS if _get(cfg, path) is None]
    indices = goal_indices_of(env) if cfg.get("goal_indices") == "auto" else None
    if not missing:
        if cfg.get("goal_indices") == "auto":
            put("goal_indices", indices)
        return notes
    maze_geometry = getattr(getattr(env, "base_env", env), "maze_geometry", None)
    maze = maze_geometry() if callable(maze_geometry) else None
    if any(path in missing for path in ("high.subgoal_low", "high.subgoal_high", "high.subgoal_noise", "fgs.noise")):
        low, high = goal_extent(env)  # a random walk: only when a value needs the env's box
    else:  # the configured subgoal box
        low, high = _get(cfg, "high.subgoal_low"), _get(cfg, "high.subgoal_high")
    extent = max(h - lo for lo, h in zip(low, high, strict=True))
    radius = getattr(env, "success_radius", None)
    radius = radius() if callable(radius) else radius
    reward_threshold = _get(cfg, "low.reward_threshold")
    if reward_threshold is None:
        if radius is None:
            raise ConfigError(
                f"`low.reward_threshold` is null (derived from the env), but {type(env).__name__} does not tell its "
                "success radius (no `success_radius`, no compute_reward to read it from); set low.reward_threshold."
            )
        reward_threshold = _round(radius)
    if cfg.get("goal_indices") == "auto":  # nothing is changed before every value is known
        put("goal_indices", indices)
    derived = {
        "high.subgoal_low": lambda: [_round(v) for v in low],
        "high.subgoal_high": lambda: [_round(v) for v in high],
        "high.subgoal_noise": lambda: _round(extent / 12),
        "fgs.noise": lambda: _round(extent / 8),
        "low.reward_threshold": lambda: reward_threshold,
        "planner.reach_radius": lambda: reward_threshold,
        "planner.oracle_margin": lambda: _round(maze.scale / 8 if maze is not None else extent / 48),
        "planner.oracle_speed": lambda: _round(goal_speed(env)),  # its own rollouts: only when needed
    }
    for path in missing:
        put(path, derived[path]())
    return notes
