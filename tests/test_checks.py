"""torchrl_dhrl.checks: the argument checks a constructor declares, run by it and runnable without building it."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
import torch

from torchrl_dhrl.checks import (
    argument_names,
    check_arguments,
    checked,
    choice,
    flag,
    integer,
    layer_sizes,
    number,
    vector,
)
from torchrl_dhrl.factory import make_high_level_buffer, make_low_level_buffer
from torchrl_dhrl.modules import (
    GaussianUniformExplorationModule,
    GoalConditionedCritic,
    HighLevelPolicy,
    LowLevelActor,
    SubgoalScheduler,
)
from torchrl_dhrl.objectives import make_optimizers
from torchrl_dhrl.planner import LandmarkGraph, LineOfSightDistance


def _accepts(check, value) -> bool:
    try:
        check("x", value)
    except ValueError:
        return False
    return True


@pytest.mark.parametrize("seed", range(5))
def test_number_agrees_with_the_interval_it_describes(seed):
    rng = random.Random(seed)
    for _ in range(200):
        low, high = sorted(rng.uniform(-3, 3) for _ in range(2))
        low_open, high_open = rng.random() < 0.5, rng.random() < 0.5
        check = number(low, high, low_open=low_open, high_open=high_open)
        # the bounds themselves (ties), values around them and outside
        for value in (low, high, low - 1e-9, high + 1e-9, rng.uniform(low, high), rng.uniform(-5, 5)):
            inside = (value > low if low_open else value >= low) and (value < high if high_open else value <= high)
            assert _accepts(check, value) == inside, (low, high, low_open, high_open, value)
            # a tensor is checked entry by entry; numpy scalars are numbers
            assert _accepts(check, torch.tensor([value, (low + high) / 2], dtype=torch.float64)) == inside
            assert _accepts(check, np.float64(value)) == inside


def test_number_refuses_what_is_not_a_real_number():
    check = number(0.0)
    for bad in (True, False, "1", None, [1.0], math.nan, torch.tensor([]), torch.tensor([1.0, math.nan])):
        assert not _accepts(check, bad), bad
    assert _accepts(number(0.0, optional=True), None)
    assert _accepts(check, math.inf) and not _accepts(number(0.0, 1.0), math.inf)


def test_integer_flag_choice_sizes_vector():
    assert [_accepts(integer(1), v) for v in (1, 7, 0, -1, 1.0, True, "2", None)] == [
        True, True, False, False, False, False, False, False,
    ]
    assert _accepts(integer(1, optional=True), None) and _accepts(integer(), -5)
    assert [_accepts(flag(), v) for v in (True, False, 1, 0, None, "true")] == [True, True] + [False] * 4
    assert _accepts(flag(optional=True), None) and not _accepts(flag(optional=True), 1)
    check = choice(("linear", "softplus"))
    assert _accepts(check, "linear") and not _accepts(check, "relu") and not _accepts(check, None)
    assert _accepts(choice((None, 1)), None) and not _accepts(choice((1, 2)), True)  # True == 1, not the choice
    assert [_accepts(layer_sizes(), v) for v in ((256, 256), [8], (), [0], [1.5], [True], "ab", 64)] == [
        True, True, True, False, False, False, False, False,
    ]
    assert [_accepts(vector(), v) for v in ([1, 2.5], (), torch.zeros(3), torch.zeros(2, 2), ["a"], [True], 3)] == [
        True, True, True, False, False, False, False,
    ]


def test_messages_name_the_argument_and_what_it_is():
    with pytest.raises(ValueError, match=r"^`cutoff` must be a number > 0, got 0\.$"):
        number(0.0, low_open=True)("cutoff", 0)
    with pytest.raises(ValueError, match=r"^`c` \(the thing\) must be an integer >= 2, got 1\.$"):
        integer(2, what="the thing")("c", 1)
    with pytest.raises(ValueError, match=r"must be None or a number in \[0, 1\], got 2"):
        number(0.0, 1.0, optional=True)("p", 2)


def test_checked_runs_before_the_body_and_with_the_defaults():
    calls = []

    def ordered(low, high):
        if low >= high:
            raise ValueError(f"`low` must be below `high`, got {low}, {high}.")

    @checked(ordered, low=number(), high=number(), steps=integer(1))
    def build(low, high=1.0, *, steps=3):
        calls.append((low, high, steps))
        return high - low

    assert build(0.0) == 1.0 and calls == [(0.0, 1.0, 3)]
    with pytest.raises(ValueError, match="below"):
        build(2.0)  # against the default high
    with pytest.raises(ValueError, match="`steps`"):
        build(0.0, steps=0)
    assert calls == [(0.0, 1.0, 3)]  # refused before the body ran
    # the dry run: the same checks, the relation only with both arguments known
    check_arguments(build, {"steps": 2})
    with pytest.raises(ValueError, match="below"):
        check_arguments(build, {"low": 5.0})
    with pytest.raises(TypeError, match="'step'"):
        check_arguments(build, {"step": 2})
    with pytest.raises(TypeError, match="no argument"):
        checked(x=number())(lambda y: y)


# Bad values of the components' hyperparameters: the dry run refuses exactly what the constructor refuses, with
# the same message, before anything is built.
COMPONENTS = [
    (LowLevelActor, {"observation_dim": 6, "goal_dim": 2, "action_dim": 2, "action_max": 1.0, "num_cells": (8,),
                     "goal_indices": (0, 1)},
     [("num_cells", [0]), ("num_cells", 8), ("relative_goal", 1), ("goal_indices", None)]),
    (GoalConditionedCritic, {"observation_dim": 6, "goal_dim": 2, "action_dim": 2, "action_max": 1.0,
                             "num_cells": (8,), "relative_goal": True, "goal_indices": (0, 1)},
     [("gamma", 1.0), ("gamma", 0.0), ("distance_output", "relu"), ("num_nets", 0), ("goal_indices", None)]),
    (GaussianUniformExplorationModule, {"low": -1.0, "high": 1.0},
     [("sigma", -0.1), ("uniform_prob", 1.5), ("uniform_prob", -0.1)]),
    (SubgoalScheduler, {"interval": 3}, [("interval", 0), ("interval", 2.5)]),
    (HighLevelPolicy, {"observation_dim": 6, "goal_dim": 2, "subgoal_low": [-1.0, -1.0], "subgoal_high": [1.0, 1.0],
                       "interval": 3, "num_cells": (8,)},
     [("interval", 0), ("noise_sigma", -1.0), ("subgoal_low", [2.0, 0.0]), ("subgoal_low", [0.0]),
      ("subgoal_low", ["a", "b"]), ("goal_dim", 3)]),
    (LandmarkGraph, {}, [("cutoff", 0.0), ("max_landmarks", 1), ("early_stop", -1.0), ("min_landmarks", -1)]),
    (LineOfSightDistance, {"speed": 0.15, "goal_indices": (0, 1)}, [("speed", 0.0), ("margin", -0.5)]),
    (make_low_level_buffer, {"buffer_size": 100, "batch_size": 10, "reward_threshold": 0.5},
     [("her_ratio", 1.5), ("batch_size", 101), ("reward_threshold", 0.0), ("buffer_size", 0)]),
    (make_high_level_buffer, {"buffer_size": 100, "batch_size": 10, "reward_threshold": 0.5},
     [("subgoal_test_ratio", 2.0), ("gradual_penalty", -1.0), ("subgoal_miss_penalty", -1.0)]),
]


@pytest.mark.parametrize("target, good, bad", COMPONENTS, ids=[getattr(c[0], "__name__", "") for c in COMPONENTS])
def test_the_dry_run_refuses_what_the_constructor_refuses(target, good, bad):
    target(**good)
    check_arguments(target, good)
    for name, value in bad:
        arguments = {**good, name: value}
        with pytest.raises(ValueError) as built:
            target(**arguments)
        with pytest.raises(ValueError) as checked_only:
            check_arguments(target, arguments)
        assert str(checked_only.value) == str(built.value), name
        assert f"`{name}`" in str(built.value) or name == "goal_indices" or name == "goal_dim"


def test_optimizers_check_their_learning_rates():
    from torch import nn

    class Loss(nn.Module):
        pass

    with pytest.raises(ValueError, match="`actor_lr` must be a number > 0, got 0"):
        make_optimizers(Loss(), actor_lr=0.0)
    assert argument_names(make_optimizers) == ("loss", "actor_lr", "critic_lr", "fused")
