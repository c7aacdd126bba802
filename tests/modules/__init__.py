"""Tests of ``torchrl_dhrl.modules``."""
