"""torchrl-dhrl: DHRL (Lee et al., NeurIPS 2022) as TorchRL components.

Layout mirrors the algorithm's levels and TorchRL's kinds of parts:
``modules`` (actors, exploration, critics), ``objectives`` (SQGC and high-level losses),
``planner`` (temporal distances, landmark graph and edge rules, shortest paths, ``GraphPlanner`` transform,
FGS), ``data`` (relabelling for both replay buffers) and ``envs`` (the paper's MuJoCo tasks, the goal-env
contract ``check_goal_env``, ``register_env`` for user environments, ``GymnasiumGoalEnv`` for Gymnasium goal envs, ``plot_env`` and the ``AngleFeatures``
transform); from ``training`` (the recipe's machinery) the update step ``LossUpdater`` and ``evaluate``; and
``factory``, the reference agent and what trains it (``make_agent``, ``make_environment``, the buffers, the
updater, the collector), which know no configuration key.
"""

from torchrl_dhrl.data import *  # noqa: F403
from torchrl_dhrl.data import __all__ as _data_all
from torchrl_dhrl.envs import (
    GymnasiumGoalEnv,
    check_goal_env,
    goal_indices_of,
    make_env,
    plot_env,
    register_env,
)
from torchrl_dhrl.envs.transforms import AngleFeatures
from torchrl_dhrl.factory import *  # noqa: F403
from torchrl_dhrl.factory import __all__ as _factory_all
from torchrl_dhrl.modules import *  # noqa: F403
from torchrl_dhrl.modules import __all__ as _modules_all
from torchrl_dhrl.objectives import *  # noqa: F403
from torchrl_dhrl.objectives import __all__ as _objectives_all
from torchrl_dhrl.planner import *  # noqa: F403
from torchrl_dhrl.planner import __all__ as _planner_all
from torchrl_dhrl.training import LossUpdater, NonFiniteLossError, evaluate

__version__ = "0.4.0"

__all__ = [
    "AngleFeatures",
    "GymnasiumGoalEnv",
    "LossUpdater",
    "NonFiniteLossError",
    "check_goal_env",
    "evaluate",
    "goal_indices_of",
    "make_env",
    "plot_env",
    "register_env",
    *_data_all,
    *_factory_all,
    *_modules_all,
    *_objectives_all,
    *_planner_all,
]
