"""Helpers to compose the recipe's Hydra configuration and import the recipe script in tests."""

from __future__ import annotations

import csv
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


#: metrics columns that measure wall-clock time (they differ between otherwise identical runs)
TIMING_COLUMNS = ("time/", "env_steps_per_s", "graph/build_s")


def metrics_rows(run_dir: Path, drop: tuple[str, ...] = ()) -> list[dict]:
    """The rows of a run's ``metrics.csv`` without the columns starting with ``drop`` (e.g. TIMING_COLUMNS)."""
    with (Path(run_dir) / "metrics.csv").open() as file:
        return [{k: v for k, v in row.items() if not k.startswith(drop)} for row in csv.DictReader(file)]
