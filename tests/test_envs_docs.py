"""The ``Examples:`` blocks of the envs package run and give the documented results."""

from __future__ import annotations

import doctest
import importlib

import pytest

MODULES = [
    "agents",
    "arena",
    "arms",
    "goals",
    "gym_env",
    "layouts",
    "mazes",
    "plotting",
    "registry",
    "robots",
    "simulation",
    "task",
    "torchrl_env",
]


@pytest.mark.parametrize("module", MODULES)
def test_docstring_examples(module):
    mod = importlib.import_module(f"torchrl_dhrl.envs.{module}")
    result = doctest.testmod(mod, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert result.attempted > 0, f"{module} has no examples"
    assert result.failed == 0
