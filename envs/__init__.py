"""The DHRL paper's MuJoCo environments (installed as ``torchrl_dhrl.envs``)."""
