"""Tests of ``torchrl_dhrl.envs``."""
