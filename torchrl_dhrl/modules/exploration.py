"""Exploration noise of DHRL: additive Gaussian noise plus epsilon-uniform replacement, clipped to a box."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.data import TensorSpec
from torchrl.envs.utils import ExplorationType, exploration_type

from torchrl_dhrl.checks import checked, number

from ._utils import box_loc_scale, resolve_box

#: The accepted probabilities of a uniform action.
PROBABILITY = number(0.0, 1.0)


class GaussianUniformExplorationModule(TensorDictModuleBase):
    """Additive Gaussian noise, then with probability ``uniform_prob`` a uniform random action, clipped to a box.

    The DHRL reference explores with ``a + N(0, (0.1 * action_max)^2)``, and with probability
    0.2 replaces the *whole* action by one drawn uniformly from the action box; the result is
    clipped to the box. Used after an actor in a :class:`~tensordict.nn.TensorDictSequential`,
    like :class:`~torchrl.modules.AdditiveGaussianModule`. Noise is applied only when the
    exploration type is ``RANDOM`` (or unset, as inside a Collector); under
    ``DETERMINISTIC``, ``MODE`` or ``MEAN`` the module is the identity. Noise is drawn on the
    input's device.

    The same module perturbs subgoals: absolute noise in goal units (reference: 2 for the
    mazes, 0.1 for Reacher3D) with ``relative_sigma=False`` and ``uniform_prob=0``.

    Args:
        spec (TensorSpec, optional): a Bounded spec (or a Composite holding one at
            ``action_key``) giving the box. Exclusive with ``low``/``high``.

    Keyword Args:
        low (Tensor or float, optional): lower bounds of the box (scalars broadcast over
            the action dims).
        high (Tensor or float, optional): upper bounds of the box.
        sigma (float or Tensor): noise standard deviation. Defaults to ``0.1``.
        relative_sigma (bool): if ``True`` (default), ``sigma`` is a fraction of the box
            half-width ``(high - low) / 2`` (i.e. ``0.1 * action_max``); otherwise it is in the
            units of the action.
        uniform_prob (float): probability of replacing the whole action by a uniform draw
            from the box. Defaults to ``0.2``.
        action_key (NestedKey): the entry to perturb. Defaults to ``"action"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictSequential
        >>> from torchrl.envs.utils import ExplorationType, set_exploration_type
        >>> from torchrl_dhrl.modules import LowLevelActor
        >>> actor = LowLevelActor(6, 2, action_max=30.0, action_dim=2, goal_indices=[0, 1], num_cells=(32,))
        >>> policy = TensorDictSequential(actor, GaussianUniformExplorationModule(actor.spec))
        >>> td = TensorDict({"observation": torch.randn(4, 6), "waypoint": torch.randn(4, 2)}, [4])
        >>> with set_exploration_type(ExplorationType.RANDOM):
        ...     noisy = policy(td.clone())["action"]
        >>> with set_exploration_type(ExplorationType.DETERMINISTIC):
        ...     clean = policy(td.clone())["action"]
        >>> bool((noisy.abs() <= 30).all()), torch.equal(clean, actor(td.clone())["action"])
        (True, True)
    """

    @checked(sigma=number(0.0), uniform_prob=PROBABILITY)
    def __init__(
        self,
        spec: TensorSpec | None = None,
        *,
        low: torch.Tensor | float | None = None,
        high: torch.Tensor | float | None = None,
        sigma: float | torch.Tensor = 0.1,
        relative_sigma: bool = True,
        uniform_prob: float = 0.2,
        action_key: NestedKey = "action",
    ) -> None:
        super().__init__()
        low_t, high_t = resolve_box(spec=spec, low=low, high=high, key=action_key, allow_scalar=True)
        sigma_t = torch.as_tensor(sigma, dtype=torch.float32)
        _, half_width = box_loc_scale(low_t, high_t)
        self.register_buffer("low", low_t)
        self.register_buffer("high", high_t)
        self.register_buffer(
            "sigma", (sigma_t * half_width) if relative_sigma else sigma_t.expand_as(low_t).clone()
        )
        # the probability lives in a buffer (what the computation reads: changing it, e.g. at the end of the
        # warm-up, recompiles no compiled policy) mirrored by a Python float (read back without a sync)
        self.register_buffer("_uniform_prob", torch.tensor(float(uniform_prob)), persistent=False)
        self._uniform_prob_value = float(uniform_prob)
        self.action_key = action_key
        self.in_keys = [action_key]
        self.out_keys = [action_key]

    @property
    def uniform_prob(self) -> float:
        """The probability of a uniform action; settable (in place: a compiled policy picks it up as it is)."""
        return self._uniform_prob_value

    @uniform_prob.setter
    def uniform_prob(self, value: float) -> None:
        _check_probability(value)
        self._uniform_prob_value = float(value)
        self._uniform_prob.fill_(float(value))

    @staticmethod
    def _active() -> bool:
        mode = exploration_type()
        return mode is None or mode == ExplorationType.RANDOM

    def perturb(self, action: torch.Tensor) -> torch.Tensor:
        """Returns a noisy copy of ``action`` (``[*batch, dim]``), regardless of the exploration type."""
        if self.low.shape[-1] not in (1, action.shape[-1]):
            raise ValueError(
                f"{self.action_key!r} has last dimension {action.shape[-1]}, the box has {self.low.shape[-1]}."
            )
        device, dtype = action.device, action.dtype
        low = self.low.to(device=device, dtype=dtype)
        high = self.high.to(device=device, dtype=dtype)
        sigma = self.sigma.to(device=device, dtype=dtype)
        noisy = action + sigma * torch.randn_like(action)
        # drawn whatever the probability (0 replaces nothing): no branch on its value, so a compiled module
        # has no guard on it, and eager and compiled calls draw the same random numbers
        prob = self._uniform_prob.to(device=device, dtype=dtype)
        replace = torch.rand(*action.shape[:-1], 1, device=device, dtype=dtype) < prob
        uniform = low + (high - low) * torch.rand_like(action)
        noisy = torch.where(replace, uniform, noisy)
        return torch.maximum(torch.minimum(noisy, high), low)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self._active():
            tensordict.set(self.action_key, self.perturb(tensordict.get(self.action_key)))
        return tensordict

    def extra_repr(self) -> str:
        return (
            f"action_key={self.action_key!r}, uniform_prob={self.uniform_prob}, sigma={self.sigma.tolist()}"
        )


def _check_probability(value: float) -> None:
    PROBABILITY("uniform_prob", value)
