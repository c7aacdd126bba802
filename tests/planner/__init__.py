"""Tests of ``torchrl_dhrl.planner``."""
