"""Tests of ``torchrl_dhrl.training``."""
