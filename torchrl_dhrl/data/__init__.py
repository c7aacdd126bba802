"""torchrl_dhrl.data."""
