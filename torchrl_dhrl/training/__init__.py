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
    AdaptiveThreads,
    available_cpus,
    cpu_busy_seconds,
    resolve_threads,
    set_threads,
    start_threads,
)
from .updates import (
    AUTOCAST_DTYPES,
    LossUpdater,
    NonFiniteLossError,
    compile_available,
)

__all__ = [
    "AUTOCAST_DTYPES",
    "AdaptiveThreads",
    "EvaluationResult",
    "LossUpdater",
    "ModuleTimer",
    "NonFiniteLossError",
    "PRECISIONS",
    "available_cpus",
    "compile_available",
    "cpu_busy_seconds",
    "evaluate",
    "goal_as_subgoal",
    "goal_as_waypoint",
    "native_bfloat16",
    "record_video",
    "resolve_precision",
    "resolve_threads",
    "set_threads",
    "start_threads",
]
