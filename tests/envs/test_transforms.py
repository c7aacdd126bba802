"""AngleFeatures, following TorchRL's transform test pattern: env (specs), no env, compose, model, replay buffer."""

import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import check_env_specs
from torchrl_dhrl.envs import make_env
from torchrl_dhrl.envs.transforms import REACHER3D_CONTINUOUS_JOINTS, AngleFeatures


def _reference(obs: np.ndarray, indices) -> np.ndarray:
    out = obs.copy()
    out[..., list(indices)] = np.sin(obs[..., list(indices)])
    return np.concatenate([out, np.cos(obs[..., list(indices)])], axis=-1)


@pytest.mark.parametrize("num_envs", [1, 3])
def test_trans_env_check(num_envs):
    env = TransformedEnv(
        make_env("Reacher3D", num_envs=num_envs, seed=0), AngleFeatures(REACHER3D_CONTINUOUS_JOINTS)
    )
    check_env_specs(env, seed=0)
    assert env.observation_spec["observation"].shape == (num_envs, 19)
    rollout = env.rollout(5)
    assert rollout["observation"].shape == (num_envs, 5, 19)
    assert rollout["next", "observation"].shape == (num_envs, 5, 19)


def test_env_matches_raw_observation():
    """The transformed env's observation is the raw one with sines in place and cosines appended."""
    raw = make_env("Reacher3D", num_envs=2, seed=3)
    env = TransformedEnv(
        make_env("Reacher3D", num_envs=2, seed=3), AngleFeatures(REACHER3D_CONTINUOUS_JOINTS)
    )
    torch.manual_seed(0)
    actions = torch.rand(30, 2, 7) * 40 - 20
    td_raw, td = raw.reset(), env.reset()
    for action in actions:
        td_raw = raw.step(td_raw.set("action", action))["next"]
        td = env.step(td.set("action", action))["next"]
        expected = _reference(td_raw["observation"].double().numpy(), REACHER3D_CONTINUOUS_JOINTS)
        np.testing.assert_allclose(td["observation"].double().numpy(), expected, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(td["achieved_goal"], td_raw["achieved_goal"])
    # the roll joints spin past +-pi under full torque: the raw angle leaves the circle, the features do not
    assert td_raw["observation"][:, list(REACHER3D_CONTINUOUS_JOINTS)].abs().max() > math.pi


def test_transform_no_env_property():
    """Many random observations (ties, zeros, huge angles): against numpy; periodic in 2 pi; unit circle."""
    g = torch.Generator().manual_seed(0)
    for trial in range(50):
        dim = int(torch.randint(2, 12, (1,), generator=g))
        k = int(torch.randint(1, dim, (1,), generator=g))
        indices = torch.randperm(dim, generator=g)[:k].tolist()
        obs = torch.randn(4, dim, generator=g, dtype=torch.float64) * (10.0 ** (trial % 4))
        if trial % 5 == 0:
            obs[:, indices] = 0.0
        t = AngleFeatures(indices)
        out = t(TensorDict(observation=obs, batch_size=[4]))["observation"]
        np.testing.assert_allclose(out.numpy(), _reference(obs.numpy(), indices), rtol=1e-12, atol=1e-12)
        assert out.shape == (4, dim + k)
        sin, cos = out[:, indices], out[:, dim:]
        torch.testing.assert_close(sin**2 + cos**2, torch.ones_like(sin))
        turns = torch.randint(-50, 50, (4, k), generator=g).double()
        shifted = obs.clone()
        shifted[:, indices] += 2 * math.pi * turns
        out2 = t(TensorDict(observation=shifted, batch_size=[4]))["observation"]
        torch.testing.assert_close(out2, out, rtol=0, atol=1e-9)  # the same pose, the same features
        untouched = [i for i in range(dim) if i not in indices]
        torch.testing.assert_close(out[:, untouched], obs[:, untouched], rtol=0, atol=0)


def test_transform_compose_and_model():
    obs = torch.randn(5, 6)
    td = TensorDict(observation=obs, batch_size=[5])
    composed = Compose(AngleFeatures([1]), AngleFeatures([2]))
    out = composed(td.clone())["observation"]
    assert out.shape == (5, 8)
    expected = _reference(_reference(obs.numpy(), [1]), [2])
    np.testing.assert_allclose(out.numpy(), expected, rtol=1e-6, atol=1e-6)
    model = TensorDictSequential(AngleFeatures([0, 3]))
    torch.testing.assert_close(
        model(td.clone())["observation"], AngleFeatures([0, 3])(td.clone())["observation"]
    )


def test_transform_rb():
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(10), transform=AngleFeatures([0]), batch_size=4)
    obs = torch.full((10, 3), math.pi)
    rb.extend(TensorDict(observation=obs, batch_size=[10]))
    sample = rb.sample()
    assert sample["observation"].shape == (4, 4)
    torch.testing.assert_close(sample["observation"][:, -1], -torch.ones(4))


def test_bad_input():
    with pytest.raises(ValueError, match="non-empty sequence of ints"):
        AngleFeatures([])
    with pytest.raises(ValueError, match="non-empty sequence of ints"):
        AngleFeatures([1.5])
    with pytest.raises(ValueError, match="must not repeat"):
        AngleFeatures([2, 2])
    with pytest.raises(ValueError, match="outside the 17-D entry"):
        _ = TransformedEnv(make_env("Reacher3D", seed=0), AngleFeatures([17])).observation_spec
    assert repr(AngleFeatures([4, 6])) == "AngleFeatures(indices=[4, 6], in_keys=['observation'])"
