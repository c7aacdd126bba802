"""torchrl-dhrl: DHRL (Lee et al., NeurIPS 2022) as TorchRL components."""

__version__ = "0.1.0"
