"""The training machinery the recipes share: config checks, factories, updaters, evaluation,
checkpoints and pictures."""

from .builders import (
    LOW_LEVEL_KEYS,
    DHRLAgent,
    make_agent,
    make_collector,
    make_environment,
    make_graph_distance,
    make_logger,
    make_replay_buffers,
    make_updaters,
)
from .checkpoint import checkpoint_file, get_rng_state, load_checkpoint, save_checkpoint, set_rng_state
from .config import DISTANCES, LOGGER_BACKENDS, ConfigError, resolve_device, validate_config
from .diagnostics import (
    ReachResult,
    low_level_reach_test,
    reach_offsets,
    reach_test_from_checkpoint,
    summarize_reach,
    visible_offsets,
)
from .evaluation import EvaluationResult, ModuleTimer, evaluate, record_video
from .goal_shift import GoalShiftOnReset
from .oracle import LineOfSightDistance
from .plots import graph_path_to_goal, plot_episode, plot_success_curve
from .updates import LossUpdater, NonFiniteLossError

__all__ = [
    "ConfigError",
    "DHRLAgent",
    "DISTANCES",
    "EvaluationResult",
    "GoalShiftOnReset",
    "LOGGER_BACKENDS",
    "LOW_LEVEL_KEYS",
    "LineOfSightDistance",
    "LossUpdater",
    "ModuleTimer",
    "NonFiniteLossError",
    "ReachResult",
    "checkpoint_file",
    "evaluate",
    "get_rng_state",
    "graph_path_to_goal",
    "load_checkpoint",
    "low_level_reach_test",
    "make_agent",
    "make_collector",
    "make_environment",
    "make_graph_distance",
    "make_logger",
    "make_replay_buffers",
    "make_updaters",
    "plot_episode",
    "plot_success_curve",
    "reach_offsets",
    "reach_test_from_checkpoint",
    "record_video",
    "resolve_device",
    "save_checkpoint",
    "set_rng_state",
    "summarize_reach",
    "validate_config",
    "visible_offsets",
]
