"""Tests of ``torchrl_dhrl.diagnostics``."""
