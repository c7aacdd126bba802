"""Whether a checkpoint's configuration may be continued (resume) or branched from (fork) by the current one, and
a saved configuration with the hyperparameters no checkpointed state holds changed (a saved agent's variant)."""

from __future__ import annotations

import copy
import fnmatch
from collections.abc import Mapping
from typing import Any

from .schema import IMPLIED_WHEN_ABSENT, RESUME_MUTABLE_KEYS, ConfigError, _flatten, keys_with_role

__all__ = ["check_resume_config", "with_changes"]


def _at(cfg: Mapping, path: str) -> Any:
    """The value at the dotted ``path`` of a nested configuration."""
    for part in path.split("."):
        cfg = cfg[part]
    return cfg


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
    predates is compared with the value the checkpoint was trained with. A key that is a value on one side and a
    group of keys on the other (``gymnasium.make_kwargs`` ``null`` -> ``{continuing_task: false}``) is compared as
    one value. Other keys only one side holds (a checkpoint written before a key existed, or after one was removed)
    are not an error: the current value is used and reported.

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
    # a key that is a value on one side and a group of keys on the other (null -> {continuing_task: false}): a change
    # of that key, compared as one value; its sub-keys are not "new" or "gone" keys
    folded = {}
    for key in old.keys() ^ new.keys():
        other = old if key in new else new
        parts = key.split(".")
        parent = next((".".join(parts[:i]) for i in range(1, len(parts)) if ".".join(parts[:i]) in other), None)
        if parent is not None:
            folded[parent] = (_at(saved, parent), _at(current, parent))
    for parent, (before, after) in folded.items():
        old = {k: v for k, v in old.items() if not k.startswith(f"{parent}.")} | {parent: before}
        new = {k: v for k, v in new.items() if not k.startswith(f"{parent}.")} | {parent: after}
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


def with_changes(saved: Mapping, changes: Mapping[str, Any]) -> dict:
    """A copy of a saved configuration with the dotted keys of ``changes`` set to their values, for the same trained
    agent acting otherwise (``recipes/evaluate.py --variant``: a saved agent re-evaluated with another edge rule).

    Only the hyperparameters no checkpointed state holds may change (role ``unsaved`` of
    :data:`~torchrl_dhrl.recipe.KEY_ROLES`, those a fork may change too): the trained networks and graph would
    silently keep their values of any other key. The values are not checked here (the recipe's
    :func:`~torchrl_dhrl.recipe.validate_config` does, naming the key).

    Raises:
        ConfigError: naming a key ``saved`` does not hold, or one that may not change, with the keys that may.

    Examples:
        >>> saved = {"planner": {"edge_rule": "cutoff", "cutoff": 30}, "high": {"lr": 1e-4}}
        >>> with_changes(saved, {"planner.edge_rule": "connected"})["planner"]
        {'edge_rule': 'connected', 'cutoff': 30}
        >>> try:
        ...     with_changes(saved, {"high.lr": 1e-3})
        ... except ConfigError as err:
        ...     print(str(err).split(";")[0])
        `high.lr` cannot change on a trained agent: its state holds it, or the run was trained under it
    """
    mutable = keys_with_role("unsaved")
    flat = _flatten(saved)
    out = copy.deepcopy(dict(saved))
    for key, value in changes.items():
        if key not in flat:
            raise ConfigError(f"`{key}` is not a key of the saved configuration; accepted: {', '.join(mutable)}.")
        if not any(fnmatch.fnmatchcase(key, pattern) for pattern in mutable):
            raise ConfigError(
                f"`{key}` cannot change on a trained agent: its state holds it, or the run was trained under it; "
                f"accepted: {', '.join(mutable)}."
            )
        *parents, last = key.split(".")
        node = out
        for part in parents:
            node = node[part]
        node[last] = value
    return out
