"""Exploration noise (``GaussianUniformExplorationModule``): statistics, clipping, modes and keys."""

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType, set_exploration_type

from tests.modules.test_actors import GOAL, OBS, _td
from torchrl_dhrl.modules import GaussianUniformExplorationModule, LowLevelActor, make_low_level_policy


def _constant_action_td(n, value, dim):
    return TensorDict({"action": torch.full((n, dim), value)}, [n])


def test_exploration_statistics_match_reference_noise():
    torch.manual_seed(7)
    amax, dim, n = 30.0, 8, 20000
    noise = GaussianUniformExplorationModule(low=-amax, high=amax, sigma=0.1, uniform_prob=0.2)
    with set_exploration_type(ExplorationType.RANDOM):
        a = noise(_constant_action_td(n, 0.0, dim))["action"]
    assert (a.abs() <= amax).all()
    # A Gaussian draw (std 3) stays within 0.45 * amax = 4.5 std in every dim; a uniform one
    # leaves it with probability 1 - 0.45^8 ~ 0.998.
    replaced = (a.abs() > 0.45 * amax).any(-1)
    frac = replaced.float().mean().item()
    assert abs(frac - 0.2 * (1 - 0.45**dim)) < 0.015
    gaussian = a[~replaced]
    assert abs(gaussian.std().item() - 0.1 * amax) < 0.03 * 0.1 * amax
    assert abs(gaussian.mean().item()) < 0.05
    # Replaced actions are uniform on the box: mean 0, std amax / sqrt(3).
    uniform = a[replaced]
    assert abs(uniform.std().item() - amax / 3**0.5) < 0.05 * amax / 3**0.5


def test_exploration_whole_action_is_replaced():
    torch.manual_seed(8)
    noise = GaussianUniformExplorationModule(low=-1.0, high=1.0, sigma=0.0, uniform_prob=0.5)
    a = noise(_constant_action_td(4000, 0.25, 3))["action"]
    kept = (a == 0.25).all(-1)
    replaced = (a != 0.25).all(-1)
    # Every row is either untouched (sigma 0) or entirely replaced: never partially.
    assert bool((kept | replaced).all())
    assert abs(replaced.float().mean().item() - 0.5) < 0.04


@pytest.mark.parametrize("mode", [ExplorationType.DETERMINISTIC, ExplorationType.MODE, ExplorationType.MEAN])
def test_exploration_off_outside_random(mode):
    torch.manual_seed(9)
    actor = LowLevelActor(OBS, GOAL, action_max=30.0, action_dim=4, num_cells=(16,), goal_indices=(0, 1))
    policy = make_low_level_policy(actor)
    td = _td((50,))
    clean = actor(td.clone())["action"]
    with set_exploration_type(mode):
        torch.testing.assert_close(policy(td.clone())["action"], clean)
    with set_exploration_type(ExplorationType.RANDOM):
        assert not torch.allclose(policy(td.clone())["action"], clean)


def test_exploration_clips_to_box_and_relative_sigma():
    torch.manual_seed(10)
    spec = Bounded(torch.tensor([-1.0, 0.0]), torch.tensor([3.0, 10.0]), shape=(2,))
    noise = GaussianUniformExplorationModule(spec, sigma=0.5, uniform_prob=0.0)
    torch.testing.assert_close(noise.sigma, torch.tensor([1.0, 2.5]))  # 0.5 * half widths (2, 5)
    a = noise(TensorDict({"action": torch.tensor([[3.0, 10.0]]).expand(1000, 2).clone()}, [1000]))["action"]
    assert (a <= spec.space.high).all() and (a >= spec.space.low).all()
    assert (a == spec.space.high).float().mean() > 0.4  # about half the draws clip at the bound


def test_exploration_absolute_sigma_and_errors():
    noise = GaussianUniformExplorationModule(
        low=[-4.0, -4.0], high=[20.0, 52.0], sigma=2.0, relative_sigma=False
    )
    torch.testing.assert_close(noise.sigma, torch.tensor([2.0, 2.0]))
    with pytest.raises(ValueError, match="uniform_prob"):
        GaussianUniformExplorationModule(low=-1.0, high=1.0, uniform_prob=1.5)
    with pytest.raises(ValueError, match="sigma"):
        GaussianUniformExplorationModule(low=-1.0, high=1.0, sigma=-0.1)
    with pytest.raises(ValueError, match="last dimension"):
        noise(TensorDict({"action": torch.zeros(3, 3)}, [3]))


def test_exploration_in_sequential_with_nested_key():
    torch.manual_seed(11)
    actor = LowLevelActor(
        OBS,
        GOAL,
        action_max=1.0,
        action_dim=2,
        action_key=("agent", "action"),
        num_cells=(8,),
        goal_indices=(0, 1),
    )
    policy = TensorDictSequential(
        actor, GaussianUniformExplorationModule(actor.spec, action_key=("agent", "action"))
    )
    out = policy(_td((3, 2)))
    assert out["agent", "action"].shape == (3, 2, 2)


def test_exploration_uniform_prob_changes_without_recompiling():
    """``uniform_prob`` is read from a buffer by a compiled module: the recipe's phase change (1.0 in the
    warm-up, then 0.2 or 0.0) takes effect in the compiled graph and compiles nothing new."""
    from torch._dynamo.testing import CompileCounter

    noise = GaussianUniformExplorationModule(low=-1.0, high=1.0, sigma=0.0, uniform_prob=1.0)
    counter = CompileCounter()
    torch._dynamo.reset()
    compiled = torch.compile(noise, backend=counter, fullgraph=True)
    try:
        torch.manual_seed(11)
        for prob in (1.0, 0.2, 0.0, 0.5):
            noise.uniform_prob = prob
            assert noise.uniform_prob == prob and noise._uniform_prob.item() == pytest.approx(prob)
            a = compiled(_constant_action_td(4000, 0.25, 3))["action"]
            replaced = (a != 0.25).all(-1).float().mean().item()
            assert abs(replaced - prob) < 0.04, (prob, replaced)
        assert counter.frame_count == 1
    finally:
        torch._dynamo.reset()
    with pytest.raises(ValueError, match="uniform_prob"):
        noise.uniform_prob = -0.1
    assert noise.uniform_prob == 0.5  # the bad value was not applied
    assert "_uniform_prob" not in noise.state_dict()  # the recipe sets it per phase; checkpoints unchanged
