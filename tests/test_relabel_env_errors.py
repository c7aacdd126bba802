"""The replay-buffer transforms refuse to go in an environment with a clear error (issue 14, item 3)."""

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import Compose, StepCounter, TransformedEnv
from torchrl_dhrl.envs import make_env

from torchrl_dhrl.data import FutureGoalRelabel, HighLevelTransitionBuilder, HindsightSubgoalRelabel

MESSAGE = "is not an environment transform"


def sample_transforms():
    return {
        "future": FutureGoalRelabel(),
        "hindsight": HindsightSubgoalRelabel(),
        "builder": HighLevelTransitionBuilder(),
    }


def point_maze():
    return make_env("PointMaze", num_envs=1, seed=0)


@pytest.mark.parametrize("name", ["future", "hindsight", "builder"])
def test_transformed_env_raises_the_clear_error(name):
    transform = sample_transforms()[name]
    with pytest.raises(RuntimeError, match=f"{type(transform).__name__} {MESSAGE}"):
        TransformedEnv(point_maze(), transform)
    # the transform was left without a container: still usable on samples / in a replay buffer
    assert transform.container is None and transform.parent is None


@pytest.mark.parametrize("name", ["future", "hindsight", "builder"])
def test_composed_or_appended_in_an_env_raises_the_clear_error(name):
    transform = sample_transforms()[name]
    with pytest.raises(RuntimeError, match=MESSAGE):
        TransformedEnv(point_maze(), Compose(StepCounter(), transform))
    transform = sample_transforms()[name]
    env = TransformedEnv(point_maze(), StepCounter())
    with pytest.raises(RuntimeError, match=MESSAGE):
        env.append_transform(transform)
    # a Compose built first and attached later
    compose = Compose(sample_transforms()[name])
    with pytest.raises(RuntimeError, match=MESSAGE):
        TransformedEnv(point_maze(), compose)


def test_still_fine_outside_an_environment():
    transforms = sample_transforms()
    compose = Compose(StepCounter(), transforms["hindsight"])  # a Compose without env is fine
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(8), transform=transforms["builder"])
    assert len(rb) == 0
    sample = TensorDict(
        {
            "subgoal": torch.ones(4, 2),
            "desired_goal": torch.zeros(4, 2),
            ("next", "achieved_goal"): torch.zeros(4, 2),
        },
        batch_size=[4],
    )
    out = compose[1](sample)
    assert out["next", "reward"].shape == (4, 1)
    with pytest.raises(RuntimeError, match=MESSAGE):
        transforms["hindsight"]._call(sample)
