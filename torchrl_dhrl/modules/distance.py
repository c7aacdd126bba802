"""The learned temporal distance of DHRL, Eq. (1), as a batched callable ``(states, goals) -> steps``."""

from __future__ import annotations

import contextlib
import math

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from ._utils import check_last_dim, check_positional_keys, run_positional
from .critics import GoalConditionedCritic, q_to_distance

#: Default number of (state, goal) pairs evaluated per forward pass.
DEFAULT_CHUNK_SIZE = 65536


class GoalDistance:
    """``Dist(s -> g) = log_gamma(1 + (1 - gamma) min_k Q_k(s, pi(s, g) | g))``, clamped to ``>= 0``.

    Eq. (1) of DHRL evaluated with the *graph* critics at the actor's own deterministic,
    noise-free action (effectively a value function), taking the pessimistic member of the
    twin (the minimum Q, i.e. the largest distance). This is the distance contract shared by
    the planner, farthest point sampling, FGS and the gradual penalty::

        distance(states: Tensor[..., obs_dim], goals: Tensor[..., goal_dim]) -> Tensor[...]

    Leading dims broadcast, so all ``N x M`` pairs come from one call with
    ``distance(states[:, None], goals[None])``. Pairs are evaluated in chunks of
    ``chunk_size`` (gathered lazily from the broadcast view, so memory stays
    ``O(chunk_size)``), under ``torch.no_grad`` and ``ExplorationType.DETERMINISTIC``,
    on the parameters' device and in their dtype; the result is returned on the device of
    ``states``.
    Non-finite values are impossible: see :func:`~torchrl_dhrl.modules.q_to_distance`.

    Args:
        actor (TensorDictModule): the deterministic low-level actor, reading
            ``(observation, goal)`` in the order of its ``in_keys`` (e.g. :class:`LowLevelActor`).
        critic (GoalConditionedCritic): the graph critic pair.

    Keyword Args:
        gamma (float, optional): the discount of Eq. (1). Defaults to the critic's.
        chunk_size (int): pairs per forward pass. Defaults to ``65536``.
        max_distance (float, optional): an upper clamp on the distance.
        actor_params (TensorDictBase, optional): parameters to swap into ``actor``
            (``TensorDict.to_module``); used by :meth:`from_loss`.
        critic_params (TensorDictBase, optional): parameters to swap into ``critic``.

    Examples:
        >>> import torch
        >>> from torchrl_dhrl.modules import GoalConditionedCritic, LowLevelActor
        >>> actor = LowLevelActor(6, 2, action_max=1.0, action_dim=2, num_cells=(32,))
        >>> critic = GoalConditionedCritic(6, 2, action_max=1.0, action_dim=2, num_cells=(32,))
        >>> distance = GoalDistance(actor, critic)
        >>> states, goals = torch.randn(5, 6), torch.randn(7, 2)
        >>> d = distance(states[:, None], goals[None])
        >>> d.shape, bool((d >= 0).all())
        (torch.Size([5, 7]), True)
    """

    def __init__(
        self,
        actor: TensorDictModuleBase,
        critic: GoalConditionedCritic,
        *,
        gamma: float | None = None,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        max_distance: float | None = None,
        actor_params: TensorDictBase | None = None,
        critic_params: TensorDictBase | None = None,
    ) -> None:
        check_positional_keys(actor, 2, "actor")
        if not isinstance(critic, GoalConditionedCritic):
            raise TypeError(f"`critic` must be a GoalConditionedCritic, got {type(critic).__name__}.")
        if chunk_size < 1:
            raise ValueError(f"`chunk_size` must be >= 1, got {chunk_size}.")
        if max_distance is not None and max_distance <= 0:
            raise ValueError(f"`max_distance` must be > 0, got {max_distance}.")
        self.actor = actor
        self.critic = critic
        self.gamma = critic.gamma if gamma is None else float(gamma)
        if not 0.0 < self.gamma < 1.0:
            raise ValueError(f"`gamma` must be in (0, 1), got {self.gamma}.")
        self.chunk_size = int(chunk_size)
        self.max_distance = max_distance
        self.actor_params = actor_params
        self.critic_params = critic_params

    @classmethod
    def from_loss(cls, loss, **kwargs) -> GoalDistance:
        """Builds the distance from an :class:`~torchrl_dhrl.objectives.SQGCLoss`'s current (non-target) parameters.

        The parameter containers are referenced, not copied: the distance follows training.
        Keyword arguments are passed to the constructor.
        """
        kwargs.setdefault("gamma", loss.gamma)
        return cls(
            loss.actor_network,
            loss.graph_critic,
            actor_params=loss.actor_network_params,
            critic_params=loss.graph_critic_params,
            **kwargs,
        )

    @property
    def observation_dim(self) -> int:
        return self.critic.module.observation_dim

    @property
    def goal_dim(self) -> int:
        return self.critic.module.goal_dim

    def _device_dtype(self) -> tuple[torch.device, torch.dtype]:
        """Where (and in which dtype) the critic's weights live: the computation follows them."""
        if self.critic_params is not None:
            weight = self.critic_params.get(("module", "ensemble", "layers", "0", "weight"))
        else:
            weight = self.critic.module.ensemble.layers[0].weight
        return weight.device, weight.dtype

    def _evaluate(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """Distances of aligned pairs ``[n, obs_dim]``, ``[n, goal_dim]`` -> ``[n]``."""
        action = run_positional(self.actor, states, goals)
        q = self.critic.module(states, goals, action)
        return q_to_distance(q.min(-1).values, self.gamma, self.max_distance)

    def __call__(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        check_last_dim("states", states, self.observation_dim)
        check_last_dim("goals", goals, self.goal_dim)
        try:
            shape = torch.broadcast_shapes(states.shape[:-1], goals.shape[:-1])
        except RuntimeError as err:
            raise ValueError(
                f"The leading dims of states {tuple(states.shape[:-1])} and goals "
                f"{tuple(goals.shape[:-1])} do not broadcast."
            ) from err
        out_device = states.device
        device, dtype = self._device_dtype()
        states_b = states.to(device=device, dtype=dtype).expand(*shape, states.shape[-1])
        goals_b = goals.to(device=device, dtype=dtype).expand(*shape, goals.shape[-1])
        n_pairs = math.prod(shape)
        swap_actor = (
            contextlib.nullcontext() if self.actor_params is None else self.actor_params.to_module(self.actor)
        )
        swap_critic = (
            contextlib.nullcontext()
            if self.critic_params is None
            else self.critic_params.to_module(self.critic)
        )
        with swap_actor, swap_critic, torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            if n_pairs <= self.chunk_size:
                out = self._evaluate(
                    states_b.reshape(n_pairs, states.shape[-1]), goals_b.reshape(n_pairs, goals.shape[-1])
                )
            else:
                chunks = []
                for start in range(0, n_pairs, self.chunk_size):
                    flat = torch.arange(start, min(start + self.chunk_size, n_pairs), device=device)
                    index = torch.unravel_index(flat, shape)
                    chunks.append(self._evaluate(states_b[index], goals_b[index]))
                out = torch.cat(chunks)
        return out.reshape(shape).to(out_device)
