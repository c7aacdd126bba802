"""Tests of ``torchrl_dhrl.objectives``."""
