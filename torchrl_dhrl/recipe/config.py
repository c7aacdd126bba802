"""Validation of a DHRL training configuration's values, before anything is built or run.

The keys and their roles are in :mod:`~torchrl_dhrl.recipe.schema`; what they resolve to on a machine in
:mod:`~torchrl_dhrl.recipe.resolve`; the components check the values of the keys they take themselves
(:mod:`~torchrl_dhrl.recipe.routing`).
"""

from __future__ import annotations

import importlib.util
from collections.abc import Mapping

from .resolve import resolve_device, resolve_speed
from .routing import check_components
from .schema import (
    BUILD_DTYPES,
    CHOICES,
    DISTANCES,
    LOGGER_BACKENDS,
    SEED_MAX,
    SWITCHES,
    UPDATE_DTYPES,
    ConfigError,
    _get,
)

__all__ = ["validate_config", "validate_env_name"]


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


def _check_against_env(cfg: Mapping, name: str) -> None:
    """The recipe's sizes that must agree with the environment's spec (read without building it): a subgoal within
    an episode, a collector batch within the run. The env's own keys (the routing's group ``env``)
    are checked by :func:`~torchrl_dhrl.factory.make_environment`'s declarations (:func:`check_components`)."""
    from torchrl_dhrl.envs import ENVS

    spec = ENVS.get(name)
    if spec is None:  # a registered user env (or ``env_names`` given): its sizes are checked when it is built
        return
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
    sizes of a registered env are checked when it is built (:func:`~torchrl_dhrl.factory.make_environment`).

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
    # the components' own checks of the keys they take (by argument name; messages name the keys), the top-level keys
    # among them (the env's, the updaters' and the acting policy's speed switches, resolved for the device)
    from torchrl_dhrl.envs import ENVS

    spec = ENVS.get(name)
    check_components(cfg, goal_dim=None if spec is None else spec.goal_dim, device=device, error=ConfigError)
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
