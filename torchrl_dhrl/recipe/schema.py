"""The recipe's configuration schema: the keys, their roles and the values some of them take, the check that every
key is known, and the keys a saved configuration predates.

The schema of every key is ``recipes/config/config.yaml``; what this module adds is what a key *is* beyond its
value: its role on resume, in a fork and in aggregation (:data:`KEY_ROLES`, the one declaration the lists derive
from), the fixed choices and switches the recipe reads itself, the keys in goal units and the keys added after runs
were checkpointed without them (:data:`IMPLIED_WHEN_ABSENT`).
"""

from __future__ import annotations

import copy
import difflib
from collections.abc import Mapping
from typing import Any

__all__ = [
    "BUILD_DTYPES",
    "CHOICES",
    "DISTANCES",
    "FORK_MUTABLE_KEYS",
    "GOAL_UNIT_KEYS",
    "IGNORED_KEYS",
    "IMPLIED_WHEN_ABSENT",
    "KEY_ROLES",
    "LOGGER_BACKENDS",
    "RESOLVED_KEYS",
    "RESUME_MUTABLE_KEYS",
    "ROLES",
    "SEED_MAX",
    "SWITCHES",
    "UPDATE_DTYPES",
    "ConfigError",
    "check_known_keys",
    "keys_with_role",
    "with_implied_keys",
]

#: Precisions of the distance evaluations of a graph rebuild (``planner.build_dtype``; ``auto``: bfloat16 where the
#: device has it natively, else float32; :func:`~torchrl_dhrl.training.resolve_precision`).
BUILD_DTYPES = ("float32", "bfloat16", "float16", "auto")
#: Precisions of the networks' updates (``update_dtype``; ``auto`` as for ``BUILD_DTYPES``).
UPDATE_DTYPES = ("float32", "bfloat16", "auto")
#: Graph distances the recipe can plan with.
DISTANCES = ("learned", "oracle")
#: Logger back ends (``none`` logs nothing but the progress bar).
LOGGER_BACKENDS = ("csv", "wandb", "tensorboard", "none")
#: The largest ``seed`` (NumPy's global generator takes seeds in ``[0, 2**32 - 1]``).
SEED_MAX = 2**32 - 1
#: What each key that does not define the experiment is, declared once (``fnmatch`` patterns over dotted keys); the
#: lists below derive from it. Every other key defines the experiment (env, networks, buffers, schedule, planner)
#: and must match on resume and in a fork (:func:`~torchrl_dhrl.recipe.check_resume_config`).
#:
#: - ``run``: how the run is run (length, paths, progress bar, device, threads, speed switches, logger, pictures,
#:   checkpoint period): may change on resume and in a fork; never tells runs apart in aggregation.
#: - ``precision``: how the networks compute, ``auto`` resolved per machine: may change on resume and in a fork;
#:   runs are told apart by what it resolved to (:func:`~torchrl_dhrl.recipe.aggregate_runs`).
#: - ``seed``: may change in a fork (which re-seeds its random streams); never tells runs apart.
#: - ``origin``: the checkpoint a fork starts from: set in a fork.
#: - ``unsaved``: a hyperparameter that no checkpointed state holds, read by the objects built for a fork (the high
#:   level's subgoal testing and gradual penalty, when and how the test episodes run, the edge rule, the
#:   critic-guided subgoals, whether the env rights a flipped ant): may change in a fork, not on resume; tells runs
#:   apart. Not the learning rates, noise
#:   scales or network shapes, which the restored optimiser, module and buffer states would silently overwrite.
#: - ``outside``: not a key of the recipe (Hydra's own section): never tells runs apart.
KEY_ROLES = {
    "total_steps": "run",
    "progress": "run",
    "run_dir": "run",
    "resume": "run",
    "device": "run",
    "threads": "run",
    "step_threads": "run",
    "fast": "run",
    "cudagraphs": "run",
    "updates_per_graph": "run",
    "compile": "run",
    "capture_sampling": "run",
    "high.capture_sampling": "run",
    "compile_policy": "run",
    "cudagraph_policy": "run",
    "update_dtype": "precision",
    "planner.build_dtype": "precision",
    "logger.*": "run",
    "plots.*": "run",
    "checkpoint.*": "run",
    "fork": "origin",
    "seed": "seed",
    "high.subgoal_test_ratio": "unsaved",
    "high.subgoal_test_threshold": "unsaved",
    "high.subgoal_miss_penalty": "unsaved",
    "high.gradual_penalty": "unsaved",
    "high.far_from_graph_factor": "unsaved",
    "schedule.eval_every_epochs": "unsaved",
    "schedule.eval_flat": "unsaved",
    "planner.edge_rule": "unsaved",
    "planner.unreachable": "unsaved",
    "high.critic_candidates": "unsaved",
    "high.candidate_noise": "unsaved",
    "high.landmark_candidates": "unsaved",
    "right_flipped_after": "unsaved",
    "hydra.*": "outside",
}
#: The roles of :data:`KEY_ROLES`.
ROLES = ("run", "precision", "seed", "origin", "unsaved", "outside")


def keys_with_role(*roles: str) -> tuple[str, ...]:
    """The keys (patterns) of :data:`KEY_ROLES` that have one of ``roles``, in its order.

    Examples:
        >>> keys_with_role("precision")
        ('update_dtype', 'planner.build_dtype')
    """
    unknown = set(roles) - set(ROLES)
    if unknown:
        raise ValueError(f"Unknown key roles {sorted(unknown)}; known: {ROLES}.")
    return tuple(key for key, role in KEY_ROLES.items() if role in roles)


#: Keys that may differ between a checkpoint's configuration and the one resuming it (roles ``run`` and
#: ``precision``; see :func:`check_resume_config`).
RESUME_MUTABLE_KEYS = keys_with_role("run", "precision")
#: Keys that may also differ between a checkpoint's configuration and a run *forked* from it (``fork=<run>``: a new
#: run that starts from the checkpoint's state, see :func:`~torchrl_dhrl.recipe.start_run`): besides
#: :data:`RESUME_MUTABLE_KEYS`, the roles ``origin``, ``seed`` and ``unsaved``.
FORK_MUTABLE_KEYS = keys_with_role("run", "precision", "origin", "seed", "unsaved")
#: Keys that never make a variant when runs are aggregated (roles ``run``, ``seed``, ``outside``).
IGNORED_KEYS = keys_with_role("run", "seed", "outside")
#: Keys whose ``auto`` is resolved per machine: a run's variant holds what they resolved to, where its
#: provenance (:data:`~torchrl_dhrl.recipe.PROVENANCE_NAME`) says so alike for every start.
RESOLVED_KEYS = keys_with_role("precision")
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
    "planner.unreachable": "nearest_landmark",  # runs from before the switch: the reference's fallback
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
    "planner.oracle_margin",
    "planner.oracle_speed",
)


class ConfigError(ValueError):
    """A training configuration that cannot run; the message says which key and why."""


def _get(cfg: Mapping, path: str) -> Any:
    node: Any = cfg
    for part in path.split("."):
        if not isinstance(node, Mapping) or part not in node:
            raise ConfigError(f"Missing configuration key `{path}`.")
        node = node[part]
    return node


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
