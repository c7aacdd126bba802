"""Tests of ``torchrl_dhrl.recipe`` and of the recipe scripts in ``recipes/``."""
