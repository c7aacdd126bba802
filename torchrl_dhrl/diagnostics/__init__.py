"""Diagnostics of DHRL runs, each module named for what it measures (not imported by ``import torchrl_dhrl``).

``reach`` (the low level's reach test), ``hierarchy`` (subgoal and waypoint statistics of an episode), ``exploration``
(how far the training episodes got), ``subgoal_landscape`` (the high-level critic over the subgoal box),
``planning_ablations`` (success with parts of the hierarchy bypassed), ``feasibility`` (subgoals in walls),
``coverage`` (landmark coverage), ``graph_quality`` (edges against the true geometry, distance ranking),
``reachability`` (the part of the graph a plan from the start can use), ``landmark_budget`` (graph quality
against the number of landmarks), ``statistics`` (rank correlation) and ``maze``
(the ``diag/...`` metrics the recipe logs, and :func:`graph_diagnosis` of a trained agent). The true geometry they
compare with is :mod:`torchrl_dhrl.envs.geometry`."""

from .coverage import (
    default_coverage_radius,
    landmark_coverage,
)
from .exploration import (
    EpisodeProgress,
    TrainingEpisodeLog,
    episode_progress,
    episodes_in_boxes,
    upside_down_by_episode,
)
from .feasibility import (
    feasibility_fractions,
)
from .graph_quality import (
    graph_quality,
)
from .hierarchy import (
    HIERARCHY_DIAG_KEYS,
    LEARNED_DISTANCE_DIAG_KEYS,
    hierarchy_diagnostics,
    subgoal_segments,
)
from .landmark_budget import (
    landmark_budget_sweep,
)
from .maze import (
    DIAG_KEYS,
    LANDSCAPE_DIAG_KEYS,
    GraphDiagnosis,
    graph_diagnosis,
    maze_epoch_diagnostics,
    maze_geometry,
    start_subgoal,
)
from .planning_ablations import (
    planning_ablations,
)
from .reach import (
    ReachResult,
    low_level_reach_test,
    reach_offsets,
    reach_test,
    summarize_reach,
    visible_offsets,
)
from .reachability import (
    graph_reach,
)
from .statistics import (
    spearman_correlation,
)
from .subgoal_landscape import (
    SubgoalLandscape,
    landscape_summary,
    subgoal_box,
    subgoal_landscape,
    subgoal_values,
)

__all__ = [
    "DIAG_KEYS",
    "EpisodeProgress",
    "GraphDiagnosis",
    "HIERARCHY_DIAG_KEYS",
    "LANDSCAPE_DIAG_KEYS",
    "LEARNED_DISTANCE_DIAG_KEYS",
    "ReachResult",
    "SubgoalLandscape",
    "TrainingEpisodeLog",
    "default_coverage_radius",
    "episode_progress",
    "episodes_in_boxes",
    "upside_down_by_episode",
    "feasibility_fractions",
    "graph_diagnosis",
    "graph_quality",
    "graph_reach",
    "hierarchy_diagnostics",
    "landmark_budget_sweep",
    "landmark_coverage",
    "landscape_summary",
    "low_level_reach_test",
    "maze_epoch_diagnostics",
    "maze_geometry",
    "planning_ablations",
    "reach_offsets",
    "reach_test",
    "spearman_correlation",
    "start_subgoal",
    "subgoal_box",
    "subgoal_landscape",
    "subgoal_segments",
    "subgoal_values",
    "summarize_reach",
    "visible_offsets",
]
