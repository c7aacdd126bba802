"""Helpers to compose the recipe's Hydra configuration and import the recipe script in tests."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

RECIPES = Path(__file__).resolve().parents[1] / "recipes"
# the recipes import their helper module, ``recipes/dhrl_utils.py``, as the scripts' directory is on sys.path
if str(RECIPES) not in sys.path:
    sys.path.insert(0, str(RECIPES))


def recipe_config(*overrides: str) -> dict:
    """The recipe's configuration (as a plain dict) with Hydra-style overrides."""
    with initialize_config_dir(config_dir=str(RECIPES / "config"), version_base="1.3"):
        cfg = compose("config", overrides=list(overrides))
    return OmegaConf.to_container(cfg, resolve=True)


def load_recipe(name: str = "dhrl_antmaze"):
    """Imports ``recipes/<name>.py`` (the training recipe by default) as a module."""
    spec = importlib.util.spec_from_file_location(name, RECIPES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
