"""torchrl_dhrl.objectives."""
