"""Tests of ``torchrl_dhrl.data``."""
