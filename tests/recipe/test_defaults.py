"""The components' own defaults are the reference implementation's.

Every value of the schema (``recipes/config/config.yaml``, the paper preset) that reaches a constructor argument,
through the routing tables of :mod:`torchrl_dhrl.recipe.routing`, equals that argument's signature default, so
that the classes composed by hand (as the README shows) and :func:`~torchrl_dhrl.factory.make_agent` build the agent
the recipe trains. The exceptions are listed below with their reason; ``goal_indices`` has no default (where the
achieved goal sits is the env's to say).
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping, Sequence

import _recipe  # noqa: F401  (puts recipes/ on the path)
import pytest
import torch
from dhrl_utils import config_schema

from torchrl_dhrl.factory import make_agent, make_environment
from torchrl_dhrl.modules import GoalConditionedCritic, HighLevelPolicy, LowLevelActor
from torchrl_dhrl.planner import LineOfSightDistance
from torchrl_dhrl.recipe.routing import RENAMED, TARGETS, component_arguments

#: ``target.argument`` -> why the schema's value is the recipe's choice rather than the component's default.
RECIPE_CHOICES = {
    "high_updater.capture_sampling": "a speed switch, not the algorithm (the same distribution of batches): the "
    "schema keeps the high level's sampling eager on every device, its exact graph query costing 45x the eager one; "
    "the component's None captures it wherever the update is captured",
    "low_updater.cudagraphs": "a speed switch the recipe resolves per device (null: CUDA graphs on CUDA with fast=true, "
    "eager on a CPU); the component's False is the eager update, the same updates",
    "high_updater.cudagraphs": "as low_updater.cudagraphs",
    "environment.goal_indices": "where the env's achieved goal sits in its observation, the env's to say (each env "
    "file sets it); make_environment has no maze default",
    "oracle.margin": "ours (the reference has no oracle distance): the agent's radius, a per-task choice; the "
    "class's 0.0 is the bare geometry (MazeGeometry's wall tests)",
}
#: ``target.argument`` whose default ``None`` means another target's argument: checked against that one's default.
DEFERRED = {
    "sqgc_loss.gamma": ("low_critic", "gamma"),  # None: the critics' discount
    "high_loss.gamma": ("high_critic", "gamma"),
}


def _normal(value):
    """Sequences as tuples (the schema's lists, the signatures' tuples), mappings as dicts, recursively."""
    if isinstance(value, Mapping):
        return {k: _normal(v) for k, v in value.items()}
    if isinstance(value, Sequence) and not isinstance(value, str):
        return tuple(_normal(v) for v in value)
    return value


def _build(name: str):
    return next(targets[name].build for targets in TARGETS.values() if name in targets)


def _default(name: str, argument: str):
    build = _build(name)
    return inspect.signature(build.__init__ if inspect.isclass(build) else build).parameters[argument].default


def _routed() -> list[tuple[str, str, object]]:
    """``(target, argument, schema value)`` for every schema value routed to a constructor argument."""
    arguments = component_arguments(config_schema())
    return [(name, argument, value) for name, args in arguments.items() for argument, value in args.items()]


def _compared():
    """The routed values to compare: those of arguments with a default, the recipe's choices aside."""
    for name, argument, value in _routed():
        path = f"{name}.{argument}"
        if path not in RECIPE_CHOICES and _default(name, argument) is not inspect.Parameter.empty:
            yield pytest.param(name, argument, value, id=path)


@pytest.mark.parametrize(("name", "argument", "value"), list(_compared()))
def test_the_schema_value_is_the_signature_default(name, argument, value):
    default = _default(name, argument)
    path = f"{name}.{argument}"
    if default is None and path in DEFERRED:
        name, argument = DEFERRED[path]
        default = _default(name, argument)
    assert _normal(default) == _normal(value), (
        f"{_build(name).__qualname__}({argument}=...) defaults to {default!r}; the schema routes {value!r}"
    )


def test_the_comparison_covers_the_routing():
    """Not vacuous: dozens of values are compared, renamed ones among them; the arguments left out are required
    (sizes the user chooses per task: buffers, batches, the subgoal box, c_h) or listed above with a reason."""
    routed = _routed()
    compared = {param.id for param in _compared()}
    assert len(compared) > 50
    assert {argument for _, argument, _ in routed} >= set(RENAMED.values())
    renamed = {
        "low_actor.num_cells",
        "exploration.sigma",
        "high_policy.noise_sigma",
        "high_loss.target_noise_std",
    }
    assert renamed <= compared
    required = {f"{n}.{a}" for n, a, _ in routed if _default(n, a) is inspect.Parameter.empty}
    assert required == {
        "low_buffer.batch_size",
        "low_buffer.buffer_size",
        "low_buffer.reward_threshold",
        "high_buffer.batch_size",
        "high_buffer.buffer_size",
        "high_policy.interval",
        "high_policy.subgoal_low",
        "high_policy.subgoal_high",
        "oracle.speed",
        "environment.env_name",
    }
    # every exception names a routed argument whose default does differ (a stale entry would hide nothing)
    values = {f"{n}.{a}": v for n, a, v in routed}
    for path in RECIPE_CHOICES:
        assert path in values and _normal(_default(*path.split("."))) != _normal(values[path]), path
    assert set(DEFERRED) <= compared


def test_make_agent_builds_the_schema_agent_from_the_components_defaults():
    """``make_agent`` adds no defaults of its own: given the sizes only, its parts are the schema's (the low-level
    actor's goal relative, the critics' absolute, no high-level action penalty)."""
    schema = config_schema()
    env = make_environment("PointMaze")
    agent = make_agent(
        env,
        goal_indices=[0, 1],
        high_policy={
            "subgoal_low": [-2.0, -2.0],
            "subgoal_high": [10.0, 10.0],
            "interval": 5,
            "num_cells": (8,),
        },
        low_actor={"num_cells": (8,)},
        low_critic={"num_cells": (8,)},
        high_critic={"num_cells": (8,)},
    )
    assert agent.low_actor.module.relative_goal is schema["low"]["relative_goal"] is True
    critics_relative = schema["low"]["critic_goal"] == "relative"
    assert agent.sqgc_loss.policy_critic.module.relative_goal is critics_relative is False
    assert agent.sqgc_loss.graph_critic.module.relative_goal is False
    assert agent.high_loss.critic_network.module.relative_goal is False
    assert agent.high_policy.actor.module.relative_goal is False
    assert agent.high_loss.action_l2 == schema["high"]["action_l2"] == 0.0
    assert agent.sqgc_loss.action_l2 == schema["low"]["action_l2"]


def test_a_relative_goal_without_goal_indices_is_refused_naming_the_argument():
    """No maze default: where the achieved goal sits is the env's (``goal_indices_of``) or the recipe's to say."""
    with pytest.raises(ValueError, match="`relative_goal` needs `goal_indices`"):
        LowLevelActor(6, 2, action_max=1.0, action_dim=2)  # relative by default, as the reference's
    with pytest.raises(ValueError, match="`relative_goal` needs `goal_indices`"):
        GoalConditionedCritic(6, 2, action_max=1.0, action_dim=2, relative_goal=True)
    with pytest.raises(ValueError, match="`relative_goal` needs `goal_indices`"):
        HighLevelPolicy(6, 2, [-2.0, -2.0], [10.0, 10.0], interval=5, relative_goal=True)
    with pytest.raises(ValueError, match="`relative_goal` needs `goal_indices`"):
        make_agent(
            make_environment("PointMaze"),
            high_policy={"subgoal_low": [-2.0, -2.0], "subgoal_high": [10.0, 10.0], "interval": 5},
        )
    with pytest.raises(TypeError, match="goal_indices"):
        LineOfSightDistance(1.0)
    # the absolute defaults need none
    assert (
        GoalConditionedCritic(6, 2, action_max=1.0, action_dim=2, num_cells=(8,)).module.goal_indices is None
    )
    oracle = LineOfSightDistance(1.0, goal_indices=[2, 3])
    assert oracle(torch.tensor([0.0, 0.0, 1.0, 1.0]), torch.tensor([4.0, 5.0])).item() == pytest.approx(5.0)
