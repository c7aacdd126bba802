"""Validation of a DHRL training configuration, before anything is built or run."""

from __future__ import annotations

import copy
import difflib
import fnmatch
import importlib.util
import math
from collections.abc import Mapping
from typing import Any

import torch

from torchrl_dhrl.training import native_bfloat16, resolve_precision

from .routing import check_components

__all__ = [
    "BUILD_DTYPES",
    "CHOICES",
    "FAST_PATH",
    "GOAL_UNIT_KEYS",
    "ConfigError",
    "DISTANCES",
    "IMPLIED_WHEN_ABSENT",
    "LOGGER_BACKENDS",
    "FORK_MUTABLE_KEYS",
    "RESUME_MUTABLE_KEYS",
    "SEED_MAX",
    "SWITCHES",
    "REFERENCE_PATH",
    "UPDATE_DTYPES",
    "check_known_keys",
    "derive_goal_units",
    "check_resume_config",
    "describe_precisions",
    "policy_captured",
    "resolve_device",
    "resolve_speed",
    "run_precisions",
    "validate_config",
    "validate_env_name",
    "with_implied_keys",
]

#: Precisions of the distance evaluations of a graph rebuild (``planner.build_dtype``; ``auto``: bfloat16 where the
#: device has it natively, else float32; :func:`~torchrl_dhrl.training.resolve_precision`).
BUILD_DTYPES = ("float32", "bfloat16", "float16", "auto")
#: Precisions of the networks' updates (``update_dtype``; ``auto`` as for ``BUILD_DTYPES``).
UPDATE_DTYPES = ("float32", "bfloat16", "auto")
#: What the speed switches left at ``null`` become (:func:`resolve_speed`): with ``fast=true`` the fastest
#: combination measured safe on the device type (CUDA: the updates replayed as CUDA graphs, in bfloat16 where the
#: GPU has it natively, the low level's sampling captured in the graphs through ``capture_sampling=null``; a CPU:
#: eager float32, see docs/training.md), with ``fast=false`` the eager float32 reference path everywhere.
FAST_PATH = {
    "cuda": {"cudagraphs": True, "update_dtype": "auto"},
    "cpu": {"cudagraphs": False, "update_dtype": "float32"},
}
REFERENCE_PATH = {"cudagraphs": False, "update_dtype": "float32"}
#: Graph distances the recipe can plan with.
DISTANCES = ("learned", "oracle")
#: Logger back ends (``none`` logs nothing but the progress bar).
LOGGER_BACKENDS = ("csv", "wandb", "tensorboard", "none")
#: The largest ``seed`` (NumPy's global generator takes seeds in ``[0, 2**32 - 1]``).
SEED_MAX = 2**32 - 1
#: Keys that may differ between a checkpoint's configuration and the one resuming it, as
#: :func:`fnmatch.fnmatchcase` patterns over dotted keys: how long the run goes on, where and how it
#: writes (paths, progress bar, logger, pictures, checkpoint period) and how it computes (device,
#: threads, CUDA graphs, compilation, update and graph-build precision). Every other key defines the
#: experiment (environment, seed, networks, buffers, schedule, planner) and must match; see
#: :func:`check_resume_config`.
RESUME_MUTABLE_KEYS = (
    "total_steps",
    "progress",
    "run_dir",
    "resume",
    "device",
    "threads",
    "step_threads",
    "fast",
    "cudagraphs",
    "updates_per_graph",
    "compile",
    "capture_sampling",
    "high.capture_sampling",
    "compile_policy",
    "cudagraph_policy",
    "update_dtype",
    "planner.build_dtype",
    "logger.*",
    "plots.*",
    "checkpoint.*",
)
#: Keys that may also differ between a checkpoint's configuration and a run *forked* from it (``fork=<run>``: a new
#: run that starts from the checkpoint's state, see :func:`~torchrl_dhrl.recipe.start_run`): besides
#: :data:`RESUME_MUTABLE_KEYS`, the seed (the fork re-seeds its random streams, the test episodes' apart) and
#: the hyperparameters that no checkpointed state holds, read from the configuration by the objects built for
#: the fork: the high level's subgoal testing and gradual penalty (its relabelling) and when and how the
#: test episodes run. Not the learning rates, noise scales or network shapes, which the restored optimiser,
#: module and buffer states would silently overwrite.
FORK_MUTABLE_KEYS = RESUME_MUTABLE_KEYS + (
    "fork",
    "seed",
    "high.subgoal_test_ratio",
    "high.subgoal_test_threshold",
    "high.subgoal_miss_penalty",
    "high.gradual_penalty",
    "high.far_from_graph_factor",
    "schedule.eval_every_epochs",
    "schedule.eval_flat",
    "planner.edge_rule",
    "high.critic_candidates",
    "high.candidate_noise",
    "high.landmark_candidates",
)
#: Keys added after runs were checkpointed without them, with the value those runs were trained with: a
#: saved configuration without the key means that value (:func:`with_implied_keys`), so a checkpoint of an
#: older version resumes (and rebuilds, e.g. in the diagnosis scripts) with its own behaviour, and resuming it
#: under another value is refused like any other change of the experiment.
IMPLIED_WHEN_ABSENT = {
    "low.distance_output": "softplus",  # 0.3.x and before: softplus distances
    "high.distance_output": "softplus",
    "right_flipped_after": None,  # runs from before the switch: a flipped ant stayed flipped
    "reference_engine": False,  # runs from before the switch: MuJoCo 3's margins and capsule inertias
    "fork": None,  # runs from before the key: started afresh
    "planner.edge_rule": "cutoff",  # runs from before the switch: the reference's edges
    "high.critic_candidates": 0,  # runs from before the switch: the actor's subgoal issued as it is
    "high.candidate_noise": None,
    "high.landmark_candidates": False,
}
#: Keys the recipe reads itself with a fixed set of values (the first is the default; see docs/faithfulness.md).
#: The components check the values of the keys they take (:mod:`torchrl_dhrl.recipe.routing`).
CHOICES = {
    "low.critic_goal": ("absolute", "relative"),
    "high.warmup_subgoals": ("uniform", "policy"),
}
#: Boolean switches the recipe reads itself (see docs/faithfulness.md); the components check theirs.
SWITCHES = (
    "schedule.train_during_warmup",
    "schedule.eval_flat",
    "fgs.enabled",
    "planner.enabled",
    "reference_engine",
)


#: Keys measured in goal-space units: the built-in env files size them for their tasks; ``null`` means "derived
#: from the env's goal space" (:func:`derive_goal_units`, as ``env=gymnasium`` and ``env=custom`` do).
GOAL_UNIT_KEYS = (
    "high.subgoal_low",
    "high.subgoal_high",
    "high.subgoal_noise",
    "low.reward_threshold",
    "planner.reach_radius",
    "fgs.noise",
)


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
    - ``goal_indices=auto``: :func:`~torchrl_dhrl.envs.goal_indices_of` (``null`` when the goal is not in the
      observation).

    Raises:
        ConfigError: naming the key when the env cannot tell it (no success radius).
    """
    from torchrl_dhrl.envs import goal_extent, goal_indices_of

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
    low, high = goal_extent(env)
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
        "high.subgoal_low": [_round(v) for v in low],
        "high.subgoal_high": [_round(v) for v in high],
        "high.subgoal_noise": _round(extent / 12),
        "fgs.noise": _round(extent / 8),
        "low.reward_threshold": reward_threshold,
        "planner.reach_radius": reward_threshold,
    }
    for path in missing:
        put(path, derived[path])
    return notes


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


def _check_run_keys(cfg: Mapping) -> None:
    """Types of the keys that only steer the run (threads, paths, switches, logger names)."""
    threads = _get(cfg, "threads")
    if threads is not None:
        if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
            raise ConfigError(
                f"`threads` must be null (from the available cores) or an integer >= 1, got {threads!r}."
            )
    for path in ("run_dir", "resume") + (("fork",) if "fork" in cfg else ()):
        value = _get(cfg, path)
        if value is not None and (not isinstance(value, str) or not value):
            raise ConfigError(f"`{path}` must be null or a path, got {value!r}.")
    optional = tuple(key for key in ("compile", "compile_policy", "cudagraph_policy") if key in cfg)
    for path in ("progress", "plots.video") + optional:
        if not isinstance(_get(cfg, path), bool):
            raise ConfigError(f"`{path}` must be true or false, got {_get(cfg, path)!r}.")
    if not isinstance(_get(cfg, "logger.project"), str):
        raise ConfigError(f"`logger.project` must be a string, got {_get(cfg, 'logger.project')!r}.")
    group = cfg.get("logger", {}).get("group") if isinstance(cfg.get("logger"), Mapping) else None
    if group is not None and (not isinstance(group, str) or not group):
        raise ConfigError(f"`logger.group` must be null or a non-empty string, got {group!r}.")
    if _get(cfg, "logger.exp_name") is not None and not isinstance(_get(cfg, "logger.exp_name"), str):
        raise ConfigError(
            f"`logger.exp_name` must be null (dhrl_<env>_seed<seed>) or a string, got {_get(cfg, 'logger.exp_name')!r}."
        )


def _check_angle_features(cfg: Mapping, name: str, obs_dim: int | None) -> None:
    """``angle_features``: null or distinct observation indices (in range when ``obs_dim`` is known) outside
    ``goal_indices``."""
    angles, goals = _get(cfg, "angle_features"), _get(cfg, "goal_indices")
    if angles is None:
        return
    bound = math.inf if obs_dim is None else obs_dim
    if (
        not isinstance(angles, (list, tuple))
        or not angles
        or len(set(angles)) != len(angles)
        or any(isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < bound for i in angles)
        or set(angles) & set(goals or ())
    ):
        where = "" if obs_dim is None else f" in [0, {obs_dim})"
        raise ConfigError(
            f"`angle_features` must be null or distinct observation indices{where} outside `goal_indices` "
            f"({name}'s continuous joint angles, e.g. [4, 6] for Reacher3D), got {angles!r}."
        )


def _check_right_flipped(cfg: Mapping, name: str, spec) -> None:
    """``right_flipped_after``: null, or a positive number of env steps for an env whose agent can flip."""
    steps = _get(cfg, "right_flipped_after")
    if steps is None:
        return
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ConfigError(
            f"`right_flipped_after` must be null or a positive number of env steps, got {steps!r}."
        )
    if spec is None or not hasattr(getattr(spec, "agent", None), "upright_qpos"):
        raise ConfigError(
            f"`right_flipped_after` rights a flipped ant: it applies to the ant mazes only, not to {name}; "
            "leave it null."
        )


def _check_reference_engine(cfg: Mapping, name: str) -> None:
    """``reference_engine`` (a boolean, see :data:`SWITCHES`): ``true`` only where
    :func:`~torchrl_dhrl.envs.simulation.reference_engine_spec` accepts the env (an ant maze)."""
    if _get(cfg, "reference_engine") is not True:
        return
    from torchrl_dhrl.envs import ENVS
    from torchrl_dhrl.envs.simulation import reference_engine_spec

    if name not in ENVS:  # a registered user env: make_env refuses the option
        raise ConfigError(
            f"`reference_engine` is an option of the built-in ant mazes, not of {name}; leave it false."
        )
    try:
        reference_engine_spec(name)
    except ValueError as err:
        raise ConfigError(f"`reference_engine`: {err}") from err


def _check_against_env(cfg: Mapping, name: str) -> None:
    """Sizes that must agree with the environment's spec (read without building it) and with each other."""
    from torchrl_dhrl.envs import ENVS

    spec = ENVS.get(name)
    _check_right_flipped(cfg, name, spec)
    _check_reference_engine(cfg, name)
    if spec is None:  # a registered user env (or ``env_names`` given): its sizes are checked when it is built
        _check_angle_features(cfg, name, None)
        return
    goal_dim, obs_dim = spec.goal_dim, spec.obs_dim
    _check_angle_features(cfg, name, obs_dim)
    indices = _get(cfg, "goal_indices")
    if indices is not None:
        if (
            not isinstance(indices, (list, tuple))
            or len(indices) != goal_dim
            or len(set(indices)) != goal_dim
            or any(isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < obs_dim for i in indices)
        ):
            raise ConfigError(
                f"`goal_indices` must be null or {goal_dim} distinct indices in [0, {obs_dim}) (where {name}'s "
                f"{goal_dim}-D achieved goal sits in its {obs_dim}-D observation), got {indices!r}."
            )
    episode = _get(cfg, "episode_length") or spec.episode_length
    c_h = _get(cfg, "high.c_h")
    if c_h > episode:
        raise ConfigError(
            f"`high.c_h` ({c_h}) must be <= the episode length ({episode}): a subgoal lasts c_h env steps."
        )
    batch = _get(cfg, "num_envs") * episode
    if _get(cfg, "total_steps") < batch:
        raise ConfigError(
            f"`total_steps` ({_get(cfg, 'total_steps')}) must be >= one collector batch, num_envs x episode_length "
            f"= {_get(cfg, 'num_envs')} x {episode} = {batch} env steps (the collector yields whole episodes)."
        )


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


def _flatten(cfg: Mapping, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in cfg.items():
        if isinstance(value, Mapping) and value:
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def with_implied_keys(cfg: Mapping, implied: Mapping[str, Any] = IMPLIED_WHEN_ABSENT) -> dict:
    """A copy of a saved configuration with the keys it predates set to the values it was trained with.

    A key of ``implied`` (dotted, :data:`IMPLIED_WHEN_ABSENT` by default) that ``cfg`` lacks while holding its
    section (e.g. ``low``) is added with its implied value; everything else is copied as it is.

    Examples:
        >>> with_implied_keys({"low": {"gamma": 0.99}})["low"]
        {'gamma': 0.99, 'distance_output': 'softplus'}
        >>> with_implied_keys({"low": {"distance_output": "linear"}})["low"]["distance_output"]
        'linear'
    """
    out = copy.deepcopy(dict(cfg))
    for dotted, value in implied.items():
        *parents, leaf = dotted.split(".")
        node = out
        for part in parents:
            node = node.get(part) if isinstance(node, Mapping) else None
        if isinstance(node, dict) and leaf not in node:
            node[leaf] = value
    return out


def _unknown_keys(cfg: Mapping, schema: Mapping, prefix: str = "") -> list[str]:
    unknown = []
    for key, value in cfg.items():
        path = f"{prefix}{key}"
        if key not in schema:
            unknown.append(path)
        elif isinstance(schema[key], Mapping):
            if not isinstance(value, Mapping):
                keys = list(schema[key])
                listed = ", ".join(keys[:4]) + (", ..." if len(keys) > 4 else "")
                raise ConfigError(
                    f"`{path}` is a group of keys ({listed}); set one of them "
                    f"(e.g. `{path}.{keys[0] if keys else 'key'}=...`), got {value!r}."
                )
            unknown += _unknown_keys(value, schema[key], f"{path}.")
    return unknown


def check_known_keys(
    cfg: Mapping, schema: Mapping, *, source: str = "config.yaml", complete: bool = False
) -> None:
    """Rejects configuration keys that the schema does not define, nested ones included (and, with
    ``complete``, keys of the schema that the configuration lacks).

    Hydra lets ``+key=value`` (and ``++key=value``) add keys to the composed configuration; nothing
    reads them, so a misspelt ``+planner.cutof=10`` would otherwise be ignored without a word. The
    schema is the default configuration (the recipe passes ``recipes/config/config.yaml`` as loaded
    by OmegaConf), so keys added there are known at once. A schema value that is not a mapping (a
    number, a list, ``null``) accepts any value; :func:`validate_config` checks the values.

    Args:
        cfg (Mapping): the configuration to check, as plain containers.
        schema (Mapping): the configuration that defines the keys.

    Keyword Args:
        source (str): how the message names the schema. Defaults to ``"config.yaml"``.
        complete (bool): also require every key of the schema: the components' keys reach their constructors
            by name (:mod:`~torchrl_dhrl.recipe.routing`), where a missing one would silently take the
            constructor's default. Defaults to ``False``.

    Raises:
        ConfigError: naming every unknown key (with the closest known one, if any), a group of keys
            (e.g. ``low``) set to a plain value, or (``complete``) the first missing key.

    Examples:
        >>> schema = {"seed": 0, "low": {"gamma": 0.99, "hidden": [256]}}
        >>> check_known_keys({"seed": 3, "low": {"gamma": 0.9}}, schema)
        >>> try:
        ...     check_known_keys({"seed": 3, "low": {"gama": 0.9}}, schema)
        ... except ConfigError as err:
        ...     print(err)
        Unknown configuration key `low.gama` (not in config.yaml; did you mean `low.gamma`?). Keys cannot be added with `+key=value`: set existing ones with `key=value`.
    """
    unknown = _unknown_keys(cfg, schema)
    if not unknown:
        if complete:
            present = set(_flatten(cfg))
            for key in _flatten(schema):
                if key not in present and not any(p.startswith(f"{key}.") for p in present):
                    raise ConfigError(f"Missing configuration key `{key}` (defined in {source}).")
        return
    known = list(_flatten(schema))
    names = []
    for key in unknown:
        close = difflib.get_close_matches(key, known, n=1, cutoff=0.75)
        names.append((f"`{key}`", f"did you mean `{close[0]}`?" if close else ""))
    if len(names) == 1:
        name, hint = names[0]
        head = f"Unknown configuration key {name} (not in {source}{'; ' + hint if hint else ''})"
    else:
        listed = ", ".join(f"{name} ({hint})" if hint else name for name, hint in names)
        head = f"Unknown configuration keys {listed} (not in {source})"
    raise ConfigError(f"{head}. Keys cannot be added with `+key=value`: set existing ones with `key=value`.")


def _short(value: Any, width: int = 40) -> str:
    text = repr(value)
    return text if len(text) <= width else text[: width - 3] + "..."


def check_resume_config(
    saved: Mapping,
    current: Mapping,
    *,
    mutable: tuple[str, ...] = RESUME_MUTABLE_KEYS,
    what: str = "the checkpoint",
    action: str = "resume",
) -> list[str]:
    """Compares a checkpoint's configuration with the one resuming it.

    Keys matching a pattern of ``mutable`` (:data:`RESUME_MUTABLE_KEYS` by default: run length, outputs,
    logging, device and speed settings) may differ; any other key that both configurations hold must
    have the same value, or the resumed run would not be the one that was checkpointed (and would often
    fail loading it, e.g. other network sizes). A key of :data:`IMPLIED_WHEN_ABSENT` that the checkpoint
    predates is compared with the value the checkpoint was trained with. Other keys only one side holds (a
    checkpoint written before a key existed, or after one was removed) are not an error: the current value
    is used and reported.

    Args:
        saved (Mapping): the configuration stored in the checkpoint (under ``"config"``).
        current (Mapping): the configuration of the resuming run.

    Keyword Args:
        mutable (tuple of str): patterns of the keys that may differ. Defaults to
            :data:`RESUME_MUTABLE_KEYS`.
        what (str): how the error message names the checkpoint. Defaults to ``"the checkpoint"``.
        action (str): the configuration key that continues the checkpoint, for the error message: ``"resume"``
            (the default) or ``"fork"`` (with ``mutable=FORK_MUTABLE_KEYS``).

    Returns:
        one ``"key: old -> new"`` note per allowed difference (empty when nothing differs).

    Raises:
        ConfigError: listing every key that differs but may not, with both values, and the keys that may.

    Examples:
        >>> saved = {"seed": 0, "total_steps": 480, "low": {"hidden": [32, 32]}}
        >>> check_resume_config(saved, {"seed": 0, "total_steps": 960, "low": {"hidden": [32, 32]}})
        ['total_steps: 480 -> 960']
        >>> try:
        ...     check_resume_config(saved, {"seed": 0, "total_steps": 960, "low": {"hidden": [64]}})
        ... except ConfigError as err:
        ...     print(str(err)[:88])
        The checkpoint was trained with another configuration: low.hidden [32, 32] -> [64] ...
    """
    old, new = _flatten(saved), _flatten(current)
    # a checkpoint older than a key of IMPLIED_WHEN_ABSENT: the value it was trained with
    old |= {key: value for key, value in IMPLIED_WHEN_ABSENT.items() if key in new and key not in old}
    allowed, forbidden = [], []
    for key in sorted(old.keys() & new.keys()):
        if old[key] == new[key]:
            continue
        change = f"{key} {_short(old[key])} -> {_short(new[key])}"
        if any(fnmatch.fnmatchcase(key, pattern) for pattern in mutable):
            allowed.append(change.replace(" ", ": ", 1))
        else:
            forbidden.append(change)
    if forbidden:
        listed = "; ".join(forbidden[:6]) + (f"; and {len(forbidden) - 6} more" if len(forbidden) > 6 else "")
        raise ConfigError(
            f"{what[:1].upper()}{what[1:]} was trained with another configuration: {listed} "
            f"(saved -> now). On {action} only {', '.join(mutable)} may change; set the others back, or start "
            f"a new run without `{action}`."
        )
    allowed += [
        f"{key}: not in the checkpoint, {_short(new[key])} now" for key in sorted(new.keys() - old.keys())
    ]
    allowed += [
        f"{key}: {_short(old[key])} in the checkpoint, no longer a key"
        for key in sorted(old.keys() - new.keys())
    ]
    return allowed


def validate_env_name(cfg: Mapping, env_names: tuple[str, ...] | None = None) -> str:
    """``env_name``, checked: a built-in env, one registered with :func:`~torchrl_dhrl.envs.register_env` or
    ``gymnasium:<id>`` (the id is checked when the env is built); or one of ``env_names`` when given.

    Raises:
        ConfigError: listing the valid names.
    """
    hint = ""
    name = _get(cfg, "env_name")
    if env_names is None:
        from torchrl_dhrl.envs import ENV_NAMES, gymnasium_id, registered_env_names

        if gymnasium_id(name):
            return name
        env_names = (*ENV_NAMES, *registered_env_names())
        hint = (
            " (or register your own env with torchrl_dhrl.envs.register_env, or name a Gymnasium goal env "
            "gymnasium:<id>; see docs/goal_env.md)"
        )
    if name not in env_names:
        raise ConfigError(f"Unknown env_name {name!r}; choose one of: {', '.join(env_names)}{hint}.")
    return name


def validate_config(cfg: Mapping, env_names: tuple[str, ...] | None = None) -> None:
    """Checks a training configuration and raises :class:`ConfigError` with a clear message.

    Every check runs before any environment, network or file is created, so a typo costs
    nothing. ``env_names`` lists the valid environment names (defaults to every environment of
    :mod:`torchrl_dhrl.envs`, built in or registered with :func:`~torchrl_dhrl.envs.register_env`). The
    sizes of a registered env are checked when it is built (:func:`~torchrl_dhrl.recipe.make_environment`).

    Examples:
        >>> try:
        ...     validate_config({"env_name": "AntMase"}, env_names=("AntMaze",))
        ... except ConfigError as err:
        ...     print(err)
        Unknown env_name 'AntMase'; choose one of: AntMaze.
    """
    name = validate_env_name(cfg, env_names)
    seed = _number(cfg, "seed", integer=True)
    if not 0 <= seed <= SEED_MAX:
        raise ConfigError(f"`seed` must be an integer in [0, 2**32 - 1] (NumPy's seed range), got {seed}.")
    _check_run_keys(cfg)
    device = resolve_device(_get(cfg, "device"))
    if not isinstance(cfg.get("fast", True), bool):
        raise ConfigError(f"`fast` must be true or false, got {cfg.get('fast')!r}.")
    if cfg.get("cudagraphs") not in (None, True, False):
        raise ConfigError(
            f"`cudagraphs` must be null (fast path), true or false, got {cfg.get('cudagraphs')!r}."
        )
    if cfg.get("cudagraphs") and device.type != "cuda":
        raise ConfigError(f"`cudagraphs=true` needs a CUDA device, but `device` resolves to {device}.")
    if cfg.get("cudagraph_policy") and device.type != "cuda":
        raise ConfigError(f"`cudagraph_policy=true` needs a CUDA device, but `device` resolves to {device}.")
    update_dtype = cfg.get("update_dtype")
    if update_dtype is not None and update_dtype not in UPDATE_DTYPES:
        raise ConfigError(
            f"`update_dtype` must be null (fast path) or one of {tuple(UPDATE_DTYPES)}, got {update_dtype!r}."
        )
    speed = resolve_speed(cfg, device)[0]
    if cfg.get("capture_sampling") not in (None, True, False):
        raise ConfigError(
            f"`capture_sampling` must be null (auto), true or false, got {cfg.get('capture_sampling')!r}."
        )
    if "updates_per_graph" in cfg:
        per_graph = _number(cfg, "updates_per_graph", low=1, integer=True)
        if per_graph > 1 and not speed["cudagraphs"]:
            raise ConfigError(
                f"`updates_per_graph` {per_graph} > 1 needs cudagraphs=true (the updates one CUDA-graph replay "
                "runs); leave it at 1 without graphs."
            )
    _number(cfg, "total_steps", low=0, strict=True, integer=True)
    _number(cfg, "num_envs", low=1, integer=True)
    if "step_threads" in cfg:
        _number(cfg, "step_threads", low=1, integer=True)
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
    for path in SWITCHES:
        if not isinstance(_get(cfg, path), bool):
            raise ConfigError(f"`{path}` must be true or false, got {_get(cfg, path)!r}.")
    for path, choices in CHOICES.items():
        if _get(cfg, path) not in choices:
            raise ConfigError(f"`{path}` must be one of {choices}, got {_get(cfg, path)!r}.")

    for level in ("low", "high"):  # the components accept no hidden layer; the recipe's networks have some
        hidden = _get(cfg, f"{level}.hidden")
        if (
            not isinstance(hidden, (list, tuple))
            or not hidden
            or any(isinstance(h, bool) or not isinstance(h, int) or h < 1 for h in hidden)
        ):
            raise ConfigError(
                f"`{level}.hidden` must be a non-empty list of positive integers, got {hidden!r}."
            )
    # the components' own checks of the keys they take (by argument name; messages name the keys)
    from torchrl_dhrl.envs import ENVS

    spec = ENVS.get(name)
    check_components(cfg, goal_dim=None if spec is None else spec.goal_dim, error=ConfigError)
    _check_against_env(cfg, name)
    _number(cfg, "high.far_from_graph_factor", low=0.0, strict=True)
    distance = _get(cfg, "planner.distance")
    if distance not in DISTANCES:
        raise ConfigError(f"`planner.distance` must be one of {DISTANCES}, got {distance!r}.")
    if distance == "oracle" and _get(cfg, "goal_indices") is None:
        raise ConfigError(
            f"planner.distance=oracle needs the achieved goal inside the observation (goal_indices), "
            f"which {name} does not provide."
        )
    landmarks, candidates = (
        _get(cfg, "planner.max_landmarks"),
        _number(cfg, "planner.candidates", integer=True),
    )
    if candidates < landmarks:
        raise ConfigError(
            f"`planner.candidates` ({candidates}) must be >= `planner.max_landmarks` ({landmarks})."
        )
    if _get(cfg, "planner.build_dtype") not in BUILD_DTYPES:
        raise ConfigError(
            f"`planner.build_dtype` must be one of {tuple(BUILD_DTYPES)}, got {_get(cfg, 'planner.build_dtype')!r}."
        )

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
