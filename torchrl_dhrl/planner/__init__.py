"""torchrl_dhrl.planner."""
