"""Each key's role is declared once (``KEY_ROLES``): the resume, fork and aggregation lists derive from it, and the
table of docs/training.md says the same."""

from __future__ import annotations

import fnmatch
import re
from pathlib import Path

import pytest

from torchrl_dhrl.recipe import (
    FORK_MUTABLE_KEYS,
    IGNORED_KEYS,
    KEY_ROLES,
    RESOLVED_KEYS,
    RESUME_MUTABLE_KEYS,
    ROLES,
    ConfigError,
    check_resume_config,
    keys_with_role,
)
from torchrl_dhrl.recipe.aggregate import variant_of

DOCS = Path(__file__).resolve().parents[2] / "docs" / "training.md"
SCHEMA = Path(__file__).resolve().parents[2] / "recipes" / "config" / "config.yaml"


def test_every_role_is_known_and_the_lists_derive_from_the_roles():
    assert set(KEY_ROLES.values()) <= set(ROLES)
    assert set(RESUME_MUTABLE_KEYS) == {k for k, r in KEY_ROLES.items() if r in ("run", "precision")}
    assert set(FORK_MUTABLE_KEYS) - set(RESUME_MUTABLE_KEYS) == {
        k for k, r in KEY_ROLES.items() if r in ("seed", "origin", "unsaved")
    }
    assert set(IGNORED_KEYS) == {k for k, r in KEY_ROLES.items() if r in ("run", "seed", "outside")}
    assert RESOLVED_KEYS == ("update_dtype", "planner.build_dtype")
    with pytest.raises(ValueError, match="Unknown key roles"):
        keys_with_role("runs")


def test_every_role_pattern_names_keys_of_the_schema():
    """A pattern that matches no key of config.yaml is a role given to nothing (a renamed or removed key)."""
    import yaml

    def flat(node, prefix=""):
        for key, value in node.items():
            if isinstance(value, dict) and value:
                yield from flat(value, f"{prefix}{key}.")
            else:
                yield f"{prefix}{key}"

    keys = list(flat({k: v for k, v in yaml.safe_load(SCHEMA.read_text()).items() if k != "defaults"}))
    orphans = [p for p, r in KEY_ROLES.items() if r != "outside" and not fnmatch.filter(keys, p)]
    assert not orphans


def test_the_roles_act_as_declared():
    """A key of each role behaves as its role says on resume, in a fork and in aggregation."""
    saved = {"seed": 0, "total_steps": 10, "high": {"gradual_penalty": 5.0, "hidden": [8]}}
    check_resume_config(saved, {**saved, "total_steps": 20})  # run: resume may change it
    for changed in ({"seed": 1}, {"high": {**saved["high"], "gradual_penalty": 1.5}}):
        with pytest.raises(ConfigError):
            check_resume_config(saved, {**saved, **changed})  # seed, unsaved: not on resume
        check_resume_config(
            saved, {**saved, **changed}, mutable=FORK_MUTABLE_KEYS, action="fork"
        )  # in a fork
    with pytest.raises(ConfigError):  # an experiment key: neither
        check_resume_config(
            saved,
            {**saved, "high": {**saved["high"], "hidden": [16]}},
            mutable=FORK_MUTABLE_KEYS,
            action="fork",
        )

    class Run:
        def __init__(self, **config):
            self.env, self.config = "PointMaze", config

    runs = [
        Run(seed=0, threads=1, **{"high.gradual_penalty": 5.0}),
        Run(seed=1, threads=2, **{"high.gradual_penalty": 1.5}),
    ]
    assert variant_of(runs[0], runs) == "high.gradual_penalty=5.0"  # seed, run: ignored; unsaved: told apart


def test_the_docs_table_is_the_declaration():
    text = DOCS.read_text("utf-8")
    section = text[text.index("### Key roles") :]
    section = section[: section.index("\n## ")]
    documented = {}
    for role, keys in re.findall(r"^\| `(\w+)` \| ([^|]*) \|", section, flags=re.MULTILINE):
        for key in re.findall(r"`([^`]+)`", keys):
            documented[key] = role
    assert documented == KEY_ROLES
