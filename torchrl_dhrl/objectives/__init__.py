"""torchrl_dhrl.objectives: the DHRL losses (SQGC low level, TD3 high level) and their optimiser recipe."""

from .high_level import HighLevelLoss
from .optim import ACTOR_LR, CRITIC_LR, make_optimizers
from .sqgc import SQGCLoss

__all__ = ["ACTOR_LR", "CRITIC_LR", "HighLevelLoss", "SQGCLoss", "make_optimizers"]
