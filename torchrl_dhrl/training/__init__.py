"""The pieces of a DHRL training pipeline that are not components of the algorithm: the update step
:class:`LossUpdater` (optionally compiled, replayed as CUDA graphs, in mixed precision), :func:`evaluate` (test episodes
on fixed goals), the precision and CPU-thread helpers. The recipe's own machinery (configuration, start-up,
checkpoints, factories) is :mod:`torchrl_dhrl.recipe`; the measurements are :mod:`torchrl_dhrl.diagnostics`."""

from .evaluation import (
    EvaluationResult,
    ModuleTimer,
    evaluate,
    goal_as_subgoal,
    goal_as_waypoint,
    record_video,
)
from .precision import (
    PRECISIONS,
    native_bfloat16,
    resolve_precision,
)
from .threads import (
    available_cpus,
    resolve_threads,
    set_threads,
)
from .updates import (
    AUTOCAST_DTYPES,
    LossUpdater,
    NonFiniteLossError,
    compile_available,
)

__all__ = [
    "AUTOCAST_DTYPES",
    "EvaluationResult",
    "LossUpdater",
    "ModuleTimer",
    "NonFiniteLossError",
    "PRECISIONS",
    "available_cpus",
    "compile_available",
    "evaluate",
    "goal_as_subgoal",
    "goal_as_waypoint",
    "native_bfloat16",
    "record_video",
    "resolve_precision",
    "resolve_threads",
    "set_threads",
]
