"""The one path from the recipe's configuration to the constructors: a key reaches an argument of the same name.

The keys of the groups ``low``, ``high``, ``planner``, ``fgs`` and ``gymnasium`` (``recipes/config/config.yaml``), and
the top-level keys that name an argument of :func:`~torchrl_dhrl.factory.make_environment`, of the updaters or of the
collector (the group ``top``), are the keyword arguments of the components the
group builds, listed in :data:`TARGETS`: a key reaches every target of
its group whose constructor takes an argument of its name, so that a new hyperparameter is a key in the
schema and an argument (with its :func:`~torchrl_dhrl.checks.checked` range) in the component, and nothing in
between. :data:`RENAMED` lists the few keys named otherwise than their argument (the recipe's flags predate
those names), :data:`RECIPE_KEYS` the keys the recipe itself reads (no constructor takes them); a key that is in
neither and reaches no constructor is an error (:func:`component_arguments`).

:func:`check_components` runs the components' own checks on the routed values before anything is built, and
names the configuration keys in the message (``high.c_h`` where :class:`~torchrl_dhrl.modules.SubgoalScheduler`
says ``interval``).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import torch

from torchrl_dhrl.checks import argument_names, check_arguments
from torchrl_dhrl.envs import GymnasiumGoalEnv
from torchrl_dhrl.factory import (
    make_collector,
    make_environment,
    make_eval_policy,
    make_high_level_buffer,
    make_low_level_buffer,
)
from torchrl_dhrl.modules import (
    GaussianUniformExplorationModule,
    GoalConditionedCritic,
    HighLevelPolicy,
    LowLevelActor,
)
from torchrl_dhrl.objectives import HighLevelLoss, SQGCLoss, make_optimizers
from torchrl_dhrl.planner import (
    FrontierGoalShifting,
    GoalDistance,
    GraphPlanner,
    LandmarkGraph,
    LineOfSightDistance,
    make_edge_rule,
)
from torchrl_dhrl.training import LossUpdater

from .resolve import resolve_speed

__all__ = [
    "RECIPE_KEYS",
    "RENAMED",
    "TARGETS",
    "ConfigRoutingError",
    "Target",
    "check_components",
    "component_arguments",
    "group_keys",
    "key_path",
]


class ConfigRoutingError(ValueError):
    """A configuration key that reaches no constructor and that the recipe does not read either."""


@dataclass(frozen=True)
class Target:
    """A constructor (class or function) that a configuration group's keys reach, by argument name.

    Args:
        build (callable): the class or function.

    Keyword Args:
        exclude (tuple of str): keys of the group that this target does not take even though it has an
            argument of that name (``low.relative_goal`` is the actor's; the critics take ``low.critic_goal``).
        convert (mapping): ``key -> (argument, function of the value)``, for a key whose value is not the
            argument's (``low.critic_goal="relative"`` -> the critics' ``relative_goal=True``).
    """

    build: Callable
    exclude: tuple[str, ...] = ()
    convert: Mapping[str, tuple[str, Callable[[Any], Any]]] = field(default_factory=dict)


#: The constructors each configuration group builds, by the name the recipe passes their arguments under
#: (``make_agent``'s keywords for the agent's parts).
TARGETS: dict[str, dict[str, Target]] = {
    "low": {
        "low_actor": Target(LowLevelActor),
        "low_critic": Target(
            GoalConditionedCritic,
            exclude=("relative_goal",),
            convert={"critic_goal": ("relative_goal", lambda value: value == "relative")},
        ),
        "exploration": Target(GaussianUniformExplorationModule),
        "sqgc_loss": Target(SQGCLoss),
        "low_buffer": Target(make_low_level_buffer),
        "low_optimizers": Target(make_optimizers),
        "low_updater": Target(LossUpdater),
    },
    "high": {
        "high_policy": Target(HighLevelPolicy),
        "high_critic": Target(GoalConditionedCritic),
        "high_loss": Target(HighLevelLoss),
        "high_buffer": Target(make_high_level_buffer),
        "high_optimizers": Target(make_optimizers),
        "high_updater": Target(LossUpdater),
    },
    "planner": {
        # planner.edge_rule names the rule: make_edge_rule builds it (checked there), the recipe gives it the graph
        "graph": Target(LandmarkGraph, exclude=("edge_rule",)),
        "edge_rule": Target(make_edge_rule),
        "planner": Target(GraphPlanner),
        "distance": Target(GoalDistance),
        "oracle": Target(LineOfSightDistance),
    },
    "fgs": {"goal_shifting": Target(FrontierGoalShifting)},
    "gymnasium": {"gymnasium_env": Target(GymnasiumGoalEnv)},
    # the top-level keys that name an argument of one of these (group_keys): the env's keys, the updaters' and the
    # acting policy's speed switches (the recipe resolves the device itself; the high level's capture_sampling is
    # `high.capture_sampling`)
    "top": {
        "environment": Target(make_environment, exclude=("device",)),
        "low_updater": Target(LossUpdater),
        "high_updater": Target(LossUpdater, exclude=("capture_sampling",)),
        "collector": Target(make_collector),
        "eval_policy": Target(make_eval_policy),
    },
}

#: Keys named otherwise than the argument they set: ``group.key -> argument``.
RENAMED = {
    "episode_length": "max_episode_steps",
    "low.hidden": "num_cells",
    "low.action_noise": "sigma",
    "low.target_noise": "target_noise_std",
    "high.hidden": "num_cells",
    "high.c_h": "interval",
    "high.subgoal_noise": "noise_sigma",
    "high.target_noise": "target_noise_std",
    "planner.oracle_speed": "speed",
    "planner.oracle_margin": "margin",
}

#: Keys of those groups that the recipe reads itself, with the reason (no constructor takes them).
RECIPE_KEYS = {
    "high.warmup_subgoals": "the recipe's warm-up: uniform subgoals or the policy's",
    "high.far_from_graph_factor": "x planner.cutoff: the high-level buffer's far_from_graph_threshold",
    "planner.enabled": "whether the recipe builds graphs at all",
    "planner.distance": "which distance the recipe builds (learned: GoalDistance; oracle: LineOfSightDistance)",
    "planner.candidates": "how many buffer states the recipe offers each graph rebuild",
    "planner.build_dtype": "resolved per device into LandmarkGraph's build_autocast_dtype",
    "fgs.enabled": "whether the recipe shifts goals at all",
    "gymnasium.eval_reset_options": "the test episodes' GymnasiumGoalEnv reset_options",
    "gymnasium.eval_goals": "the test episodes' GymnasiumGoalEnv goals",
}


#: Keys of :data:`RECIPE_KEYS` that hold the same kind of value as a target's argument, and are checked as it is.
CHECKED_AS = {
    "gymnasium.eval_reset_options": ("gymnasium_env", "reset_options"),
    "gymnasium.eval_goals": ("gymnasium_env", "goals"),
}


def key_path(group: str, key: str) -> str:
    """The dotted configuration key of ``key`` in ``group`` (the keys of ``top`` are top-level).

    Examples:
        >>> key_path("high", "c_h"), key_path("top", "episode_length")
        ('high.c_h', 'episode_length')
    """
    return key if group == "top" else f"{group}.{key}"


def group_keys(cfg: Mapping[str, Any], group: str) -> Mapping[str, Any]:
    """The keys of ``group`` that ``cfg`` holds, with their values (a checkpoint older than a group or a key has
    none); for ``top``, the top-level keys that name an argument of its targets (``make_environment``'s, the
    updaters', the collector's), so that a new env key is a key of the schema and an argument of
    ``make_environment``, and nothing in between.

    Examples:
        >>> group_keys({"seed": 3, "threads": 1, "high": {"c_h": 40}}, "top"), group_keys({"high": {"c_h": 40}}, "high")
        ({'seed': 3}, {'c_h': 40})
    """
    if group == "top":  # the top-level keys that reach one of its targets
        return {key: value for key, value in cfg.items() if key not in TARGETS and _routes(group, key, value)}
    return cfg.get(group, {})


def _routes(group: str, key: str, value: Any) -> list[tuple[str, str, Any]]:
    """``(target, argument, value)`` for each target of ``group`` that ``group.key`` reaches."""
    path = key_path(group, key)
    out = []
    for name, target in TARGETS[group].items():
        if key in target.exclude:
            continue
        if key in target.convert:
            argument, function = target.convert[key]
            out.append((name, argument, function(value)))
            continue
        argument = RENAMED.get(path, key)
        if argument in argument_names(target.build):
            out.append((name, argument, value))
    return out


def _route(cfg: Mapping[str, Any]) -> tuple[dict[str, dict[str, Any]], dict[str, dict[str, str]]]:
    """The arguments of every target and, for each, the key each argument came from."""
    arguments: dict[str, dict[str, Any]] = {name: {} for group in TARGETS.values() for name in group}
    sources: dict[str, dict[str, str]] = {name: {"goal_indices": "goal_indices"} for name in arguments}
    for group in TARGETS:
        for key, value in group_keys(cfg, group).items():
            if key_path(group, key) in RECIPE_KEYS:  # the recipe's, even where a constructor has an argument so named
                continue
            routes = _routes(group, key, value)
            if not routes:
                raise ConfigRoutingError(
                    f"`{key_path(group, key)}` reaches no constructor: none of {', '.join(TARGETS[group])} takes "
                    f"`{RENAMED.get(key_path(group, key), key)}`, and the recipe does not read it (RECIPE_KEYS)."
                )
            for name, argument, routed in routes:
                arguments[name][argument] = routed
                sources[name][argument] = key_path(group, key)
    return arguments, sources


def component_arguments(cfg: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """The keyword arguments of every target of :data:`TARGETS`, from the configuration's groups.

    Raises:
        ConfigRoutingError: for a key of a routed group that reaches no constructor and is not one of
            :data:`RECIPE_KEYS` (a key added to the schema whose argument was not added to a component).

    Examples:
        >>> cfg = {"low": {"hidden": [64], "critic_goal": "absolute"}, "high": {"c_h": 40},
        ...        "planner": {"cutoff": 30.0}, "fgs": {"noise": 3.0}}
        >>> args = component_arguments(cfg)
        >>> args["high_policy"], args["low_critic"], args["graph"]
        ({'interval': 40}, {'num_cells': [64], 'relative_goal': False}, {'cutoff': 30.0})
    """
    return _route(cfg)[0]


_QUOTED = re.compile(r"`(\w+)(?=[`=])")


def check_components(
    cfg: Mapping[str, Any],
    *,
    goal_dim: int | None = None,
    device: str | torch.device = "cpu",
    error: type[Exception] = ValueError,
) -> None:
    """Runs the range checks of every component the configuration reaches (:func:`~torchrl_dhrl.checks.check_arguments`),
    without building any, and raises ``error`` naming the configuration key instead of the argument.

    Keyword Args:
        goal_dim (int, optional): the env's goal size, when known (the subgoal box must match it).
        device (str or torch.device): the device the speed switches left at ``null`` are resolved for
            (:func:`~torchrl_dhrl.recipe.resolve_speed`), as the recipe builds with them. Defaults to ``"cpu"``.
        error (type): the exception to raise (the recipe's ``ConfigError``). Defaults to ``ValueError``.
    """
    cfg = resolve_speed(cfg, device)[0]
    routed, sources = _route(cfg)
    context = {"goal_indices": cfg.get("goal_indices")}
    if goal_dim is not None:
        context["goal_dim"] = goal_dim
    for targets in TARGETS.values():
        for name, target in targets.items():
            accepted = argument_names(target.build)
            given = {k: v for k, v in context.items() if k in accepted} | routed[name]
            try:
                check_arguments(target.build, given)
            except ValueError as err:
                raise error(_name_keys(str(err), sources[name])) from err
    for path, (name, argument) in CHECKED_AS.items():
        group, key = path.split(".")
        value = cfg.get(group, {}).get(key)
        group_targets = TARGETS[group]
        try:
            check_arguments(group_targets[name].build, {argument: value})
        except ValueError as err:
            raise error(_name_keys(str(err), {argument: path})) from err


def _name_keys(message: str, keys: Mapping[str, str]) -> str:
    """``message`` with each backquoted argument of ``keys`` replaced by its configuration key."""
    return _QUOTED.sub(lambda m: f"`{keys.get(m.group(1), m.group(1))}", message)
