"""torchrl_dhrl.modules."""
