"""The ``Examples:`` blocks of every public module run and give the documented results."""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import pytest
import torchrl_dhrl.envs

import torchrl_dhrl

# every module of the package, private helpers and package ``__init__``s aside
MODULES = sorted(
    info.name
    for package in (torchrl_dhrl, torchrl_dhrl.envs)  # envs/ is mapped into the package from the top level
    for info in pkgutil.walk_packages(package.__path__, f"{package.__name__}.")
    if not info.ispkg and not info.name.rsplit(".", 1)[-1].startswith("_")
)
# modules without public classes or functions that would carry an example
NO_EXAMPLES = {
    "torchrl_dhrl.envs.demo",
    "torchrl_dhrl.recipe.plots",  # pictures: tests/envs/test_plotting.py and the recipe tests
}


def test_module_list_is_complete():
    assert len(MODULES) > 40 and NO_EXAMPLES <= set(MODULES)


@pytest.mark.parametrize("module", [m for m in MODULES if m not in NO_EXAMPLES])
def test_docstring_examples(module):
    mod = importlib.import_module(module)
    result = doctest.testmod(mod, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert result.attempted > 0, f"{module} has no examples"
    assert result.failed == 0
