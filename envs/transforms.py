"""Observation transforms for the paper's envs (TorchRL :class:`~torchrl.envs.Transform` s)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Composite, TensorSpec, Unbounded
from torchrl.envs.transforms import ObservationTransform

__all__ = ["AngleFeatures", "REACHER3D_CONTINUOUS_JOINTS"]

#: Observation indices of Reacher3D's two continuous (unlimited) joints, the forearm and wrist rolls.
REACHER3D_CONTINUOUS_JOINTS = (4, 6)


class AngleFeatures(ObservationTransform):
    """Encodes joint angles of an observation as ``(sin, cos)``: bounded, and the same for the same pose.

    The angle at each of ``indices`` is replaced by its sine, and the cosines are appended at the end of
    the observation (``obs_dim`` grows by ``len(indices)``; the other entries keep their positions, so a
    ``goal_indices`` slice of the observation is unchanged). Meant for continuous joints, whose raw angle
    grows without bound: Reacher3D's forearm and wrist rolls (:data:`REACHER3D_CONTINUOUS_JOINTS`) spin
    at up to 200 rad/s under full torque (damping 0.1) and reach 100-240 rad within an episode, inputs no
    critic has seen before; the reference implementation feeds them raw (the default here too, see
    ``docs/faithfulness.md``).

    Args:
        indices (sequence of int): the observation entries holding angles (radians).

    Keyword Args:
        in_keys (sequence of NestedKey): the observation entries to transform. Defaults to
            ``["observation"]``.

    Examples:
        >>> import math, torch
        >>> from tensordict import TensorDict
        >>> t = AngleFeatures([1])
        >>> td = t(TensorDict(observation=torch.tensor([[0.5, math.pi / 2, 2.0]]), batch_size=[1]))
        >>> td["observation"].round(decimals=4)
        tensor([[0.5000, 1.0000, 2.0000, -0.0000]])
        >>> from torchrl_dhrl.envs import make_env
        >>> from torchrl.envs import TransformedEnv
        >>> env = TransformedEnv(make_env("Reacher3D", num_envs=2, seed=0), AngleFeatures(REACHER3D_CONTINUOUS_JOINTS))
        >>> env.observation_spec["observation"].shape, env.reset()["observation"].shape
        (torch.Size([2, 19]), torch.Size([2, 19]))
    """

    def __init__(self, indices: Sequence[int], *, in_keys: Sequence[NestedKey] | None = None) -> None:
        indices = list(indices)
        if not indices or any(isinstance(i, bool) or not isinstance(i, int) for i in indices):
            raise ValueError(f"`indices` must be a non-empty sequence of ints, got {indices!r}.")
        if len(set(indices)) != len(indices):
            raise ValueError(f"`indices` must not repeat an entry, got {indices!r}.")
        in_keys = ["observation"] if in_keys is None else list(in_keys)
        super().__init__(in_keys=in_keys, out_keys=list(in_keys))
        self.register_buffer("indices", torch.tensor(indices, dtype=torch.long))

    def _apply_transform(self, observation: torch.Tensor) -> torch.Tensor:
        index = self.indices.to(observation.device)
        angles = observation.index_select(-1, index)
        out = observation.clone()
        out[..., index] = torch.sin(angles)
        return torch.cat([out, torch.cos(angles)], dim=-1)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        for key in self.in_keys:
            spec: TensorSpec = observation_spec[key]
            size = spec.shape[-1]
            bad = [int(i) for i in self.indices if not -size <= int(i) < size]
            if bad:
                raise ValueError(f"AngleFeatures: indices {bad} are outside the {size}-D entry {key!r}.")
            shape = (*spec.shape[:-1], size + len(self.indices))
            observation_spec[key] = Unbounded(shape=shape, dtype=spec.dtype, device=spec.device)
        return observation_spec

    def __repr__(self) -> str:
        return f"{type(self).__name__}(indices={self.indices.tolist()}, in_keys={self.in_keys})"
