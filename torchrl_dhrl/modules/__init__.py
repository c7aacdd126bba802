"""torchrl_dhrl.modules: DHRL actors, exploration, the c_h cadence and twin critics.

The learned distance built from the graph critics, :class:`~torchrl_dhrl.planner.GoalDistance`, lives
with the planner it serves, next to the distance protocol (:mod:`torchrl_dhrl.planner.distances`).
"""

from .actors import DEFAULT_NUM_CELLS, GoalConditionedActorNet, HighLevelActor, LowLevelActor
from .critics import GoalConditionedCritic, GoalConditionedCriticNet, distance_to_q, q_to_distance
from .ensemble import EnsembleLinear, EnsembleMLP
from .exploration import GaussianUniformExplorationModule
from .policies import HighLevelPolicy, make_low_level_policy
from .subgoal import NO_SUBGOAL, CriticGuidedSubgoal, SubgoalScheduler

__all__ = [
    "DEFAULT_NUM_CELLS",
    "NO_SUBGOAL",
    "CriticGuidedSubgoal",
    "EnsembleLinear",
    "EnsembleMLP",
    "GaussianUniformExplorationModule",
    "GoalConditionedActorNet",
    "GoalConditionedCritic",
    "GoalConditionedCriticNet",
    "HighLevelActor",
    "HighLevelPolicy",
    "LowLevelActor",
    "SubgoalScheduler",
    "distance_to_q",
    "make_low_level_policy",
    "q_to_distance",
]
