"""Temporal distances of the graph level: the :class:`TemporalDistance` protocol and two of its kinds.

Everything in :mod:`torchrl_dhrl.planner` (farthest point sampling,
:class:`~torchrl_dhrl.planner.LandmarkGraph`, :class:`~torchrl_dhrl.planner.GraphPlanner`,
:class:`~torchrl_dhrl.planner.FrontierGoalShifting`) and the gradual penalty of the high level (through
:meth:`~torchrl_dhrl.planner.GraphPlanner.distance_from_graph`) reads the environment through one
callable, ``distance(states, goals) -> steps``. That callable is the swap point for ablations and new
ideas:

- :class:`GoalDistance`, DHRL's learned distance (Eq. 1 of the paper, from the graph critics);
- :class:`LineOfSightDistance`, an oracle (straight-line steps, blocked by obstacle boxes);
- any function or ``nn.Module`` that follows :class:`TemporalDistance`.
"""

from __future__ import annotations

import contextlib
import copy
import math
from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_dhrl.checks import checked, choice, integer, number
from torchrl_dhrl.modules._utils import (
    call_with_params,
    check_last_dim,
    check_positional_keys,
    routes_tensors_only,
    run_positional,
)
from torchrl_dhrl.modules.actors import GoalConditionedActorNet
from torchrl_dhrl.modules.critics import (
    DEFAULT_GAMMA,
    GoalConditionedCritic,
    check_critic,
    critic_values,
    q_to_distance,
    stacked_critic_values,
)

__all__ = [
    "AUTOCAST_DTYPES",
    "AutocastDistance",
    "GoalDistance",
    "LineOfSightDistance",
    "TWIN_CHOICES",
    "TemporalDistance",
]


@runtime_checkable
class TemporalDistance(Protocol):
    """The protocol of a graph distance: ``distance(states, goals) -> steps``.

    A temporal distance estimates how many environment steps the low level needs to bring the
    achieved goal from a *state* to a *goal*: it reads full observations on one side and goal-space
    points on the other, and need not be symmetric (``d(s_i -> g_j)`` and ``d(s_j -> g_i)`` differ).
    Plain functions, lambdas, callable objects and ``nn.Module`` instances all qualify; the
    planner keeps it as a plain attribute (never a submodule: its parameters, if any, belong to whoever
    trains it, and it is not part of the planner's ``state_dict()``).

    **Shapes.** ``states`` is ``Tensor[..., obs_dim]`` and ``goals`` is ``Tensor[..., goal_dim]``; their
    leading dims broadcast and the result is one distance per pair, ``Tensor[broadcast(...)]``. The
    library calls it with

    - aligned pairs: ``states[P, obs_dim]`` and ``goals[P, goal_dim]`` -> ``[P]``;
    - all pairs of two sets: ``states[M, 1, obs_dim]`` and ``goals[1, N, goal_dim]`` -> ``[M, N]``
      (in blocks of rows, so that one call sees at most ``LandmarkGraph.chunk_size`` pairs, or ``N``);
    - single points: ``states[obs_dim]`` and ``goals[goal_dim]`` -> a 0-d tensor (the recipe's
      ``graph/learned_distance_start_goal`` metric).

    **Values.** A floating tensor of distances in env steps, ``>= 0`` (negative values are clamped to
    ``0`` where a graph is built), on the device of ``states``. Large values (or ``inf``) mean
    "unreachable"; ``NaN`` is an error (farthest point sampling and
    :meth:`~torchrl_dhrl.planner.LandmarkGraph.set_distance_matrix` reject it). The planner calls it under
    ``torch.no_grad()``.

    **Reduced-precision building** (``LandmarkGraph(build_autocast_dtype=...)``) additionally needs a
    ``with_autocast(dtype)`` method (:class:`AutocastDistance`); nothing else is ever called.

    Examples:
        >>> import torch
        >>> from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph
        >>> def manhattan(states, goals):  # a user-written distance: 1 step per goal unit
        ...     return (goals - states[..., :2]).abs().sum(-1)
        >>> isinstance(manhattan, TemporalDistance)
        True
        >>> manhattan(torch.zeros(4, 1, 6), torch.ones(1, 3, 2)).shape
        torch.Size([4, 3])
        >>> points = torch.stack([torch.arange(5.0), torch.zeros(5)], -1)  # landmarks 1 step apart
        >>> planner = GraphPlanner(LandmarkGraph(cutoff=1.5), manhattan, goal_dim=2)
        >>> planner = planner.build(points, points.clone())
        >>> planner.plan(points[:1], torch.tensor([[4.0, 0.0]])).cost.item()
        4.0
    """

    def __call__(self, states: Tensor, goals: Tensor) -> Tensor:
        """``Tensor[..., obs_dim], Tensor[..., goal_dim] -> Tensor[...]``, estimated env steps."""
        ...


@runtime_checkable
class AutocastDistance(TemporalDistance, Protocol):
    """A :class:`TemporalDistance` with a reduced-precision variant, for ``build_autocast_dtype``.

    ``with_autocast(dtype)`` returns the same distance evaluated in ``dtype`` (``torch.bfloat16`` or
    ``torch.float16``; ``None``: full precision), e.g. :meth:`GoalDistance.with_autocast`.
    :class:`~torchrl_dhrl.planner.LandmarkGraph` uses it for the distance evaluations of a rebuild only;
    queries use the distance as given.

    Examples:
        >>> import torch
        >>> from torchrl_dhrl.modules import GoalConditionedCritic, LowLevelActor
        >>> actor = LowLevelActor(6, 2, action_max=1.0, action_dim=2, goal_indices=[0, 1], num_cells=(8,))
        >>> critic = GoalConditionedCritic(6, 2, action_max=1.0, action_dim=2, num_cells=(8,))
        >>> isinstance(GoalDistance(actor, critic), AutocastDistance)
        True
        >>> isinstance(lambda s, g: (g - s[..., :2]).norm(dim=-1), AutocastDistance)
        False
    """

    def with_autocast(self, dtype: torch.dtype | None) -> TemporalDistance:
        """The same distance evaluated under ``torch.autocast(dtype)`` (``None``: full precision)."""
        ...


#: Default number of (state, goal) pairs evaluated per forward pass on an accelerator.
DEFAULT_CHUNK_SIZE = 65536
#: Default number of pairs per forward pass on a CPU, where the activations of smaller chunks stay
#: in cache (measured 1.4x (float32) to 2x (bfloat16) faster per pair than 65536 with 3x256 networks).
DEFAULT_CPU_CHUNK_SIZE = 4096
#: Reduced-precision dtypes accepted by ``autocast_dtype``.
AUTOCAST_DTYPES = (torch.bfloat16, torch.float16)
#: Which member of the twin graph critic gives the distance (``twin`` of :class:`GoalDistance`):
#: ``"optimistic"`` the smaller distance (the larger Q; the reference implementation's
#: ``min(dist1, dist2)``), ``"pessimistic"`` the larger distance (the smaller Q, TD3's reading).
TWIN_CHOICES = ("optimistic", "pessimistic")


def _run_actor(
    actor: TensorDictModuleBase,
    states: torch.Tensor,
    goals: torch.Tensor,
    params: TensorDictBase | None = None,
) -> torch.Tensor:
    """The actor's action for aligned ``states`` and ``goals`` (with ``params`` in place of its own, if given).

    The library's actors (a plain ``TensorDictModule`` around a :class:`~torchrl_dhrl.modules.GoalConditionedActorNet`,
    without safety projection or hooks) are called on the tensors directly: the same
    computation without building a TensorDict per call. Other actors go through their in_keys.
    """
    if isinstance(getattr(actor, "module", None), GoalConditionedActorNet) and routes_tensors_only(actor):
        return call_with_params(actor.module, None if params is None else params["module"], states, goals)
    return run_positional(actor, states, goals, params=params)


def _autocast(device: torch.device, dtype: torch.dtype | None):
    """``torch.autocast`` to ``dtype`` on ``device`` (``None``: autocast disabled, also an outer one)."""
    if not torch.amp.is_autocast_available(device.type):
        if dtype is not None:
            raise RuntimeError(
                f"`autocast_dtype={dtype}` needs autocast, which {device.type} does not support."
            )
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=dtype, enabled=dtype is not None)


class GoalDistance:
    """``Dist(s -> g) = log_gamma(1 + (1 - gamma) max_k Q_k(s, pi(s, g) | g))``, clamped to ``>= 0``.

    Eq. (1) of DHRL evaluated with the *graph* critics at the actor's own deterministic,
    noise-free action (effectively a value function). By default (``twin="optimistic"``) the
    distance is the smaller of the twin's two distances (the larger Q), as in the reference
    implementation (``min(dist1, dist2)``); ``twin="pessimistic"`` takes the larger distance
    (the smaller Q, as TD3 does for its targets). It follows :class:`AutocastDistance` (a
    :class:`TemporalDistance` with :meth:`with_autocast`)::

        distance(states: Tensor[..., obs_dim], goals: Tensor[..., goal_dim]) -> Tensor[...]

    Leading dims broadcast, so all ``N x M`` pairs come from one call with
    ``distance(states[:, None], goals[None])``. Pairs are evaluated in chunks of
    ``chunk_size`` (gathered lazily from the broadcast view, so memory stays
    ``O(chunk_size)``), under ``torch.no_grad`` and ``ExplorationType.DETERMINISTIC``,
    on the parameters' device and in their dtype; the result is returned on the device of
    ``states``.
    Non-finite values are impossible: see :func:`~torchrl_dhrl.modules.q_to_distance`.

    **Critics.** The critic follows the critic contract of
    :class:`~torchrl_dhrl.objectives.SQGCLoss`: a TensorDictModule reading
    ``(observation, goal, action)`` from its three ``in_keys`` in that order and writing Q at
    ``value_key``. A :class:`~torchrl_dhrl.modules.GoalConditionedCritic` holds the twin and, without
    hooks, is evaluated on the tensors (the fast path). Any other critic is one member; its twin is
    ``critic_params`` with a leading member dim (the loss's stacked parameters, as
    :meth:`from_loss` passes them), evaluated with :func:`torch.vmap`. That generic path builds a
    TensorDict per chunk and runs every layer (also the output layer) under ``autocast_dtype``; it is
    slower than the fast path (no dimension checks on the inputs either: the critic does not declare
    its sizes).

    **Reduced precision.** By default everything runs in the parameters' dtype (an enclosing
    ``torch.autocast`` is disabled for the call). With ``autocast_dtype=torch.bfloat16`` (or
    ``torch.float16``) the hidden layers of the actor and the critic run under
    ``torch.autocast`` on the parameters' device, while their output layers and the
    conversion to a distance stay in the parameters' dtype, so the distance is not rounded to
    the reduced dtype. On a CPU with bfloat16 matrix units this is 2-3.5x faster per pair; the
    cost is a small error from the rounding of the inputs and hidden activations, close to
    absolute (a few tenths of a step at most in ``tests/planner/test_distances.py``), so small
    distances see the largest relative errors (bfloat16, 3x256 trained-like twin critic,
    pessimistic member: 0.1% median, 0.4% p99, 0.6% max; see ``benchmarks/bench_planner.py``).
    Meant for graph building
    (:class:`~torchrl_dhrl.planner.LandmarkGraph`'s ``build_autocast_dtype``); float16 is about
    8x more accurate than bfloat16 but needs activations below 65504 (and is slow on most CPUs).

    Args:
        actor (TensorDictModule): the deterministic low-level actor, reading
            ``(observation, goal)`` in the order of its ``in_keys`` (e.g. :class:`~torchrl_dhrl.modules.LowLevelActor`).
        critic (TensorDictModule): the graph critic pair
            (:class:`~torchrl_dhrl.modules.GoalConditionedCritic`), or a single-member critic
            whose members are the stacked ``critic_params`` (see above).

    Keyword Args:
        gamma (float, optional): the discount of Eq. (1). Defaults to the critic's.
        chunk_size (int, optional): pairs per forward pass. Defaults to ``4096`` on a CPU and
            ``65536`` on other devices (chosen per call from the parameters' device).
        max_distance (float, optional): an upper clamp on the distance.
        actor_params (TensorDictBase, optional): parameters to evaluate ``actor`` with, laid out as
            ``TensorDict.from_module(actor)`` (passed with :func:`torch.func.functional_call`; the module is
            never modified); used by :meth:`from_loss`.
        critic_params (TensorDictBase, optional): parameters to evaluate ``critic`` with; with a
            leading batch dim, the stacked parameters of the members (vmap).
        autocast_dtype (torch.dtype, optional): ``torch.bfloat16`` or ``torch.float16`` to run
            the networks under ``torch.autocast`` (see above). Defaults to ``None`` (full
            precision). :meth:`with_autocast` gives a copy with another setting.
        twin (str): ``"optimistic"`` (the smaller distance of the twin, the reference's) or
            ``"pessimistic"`` (the larger one). Defaults to ``"optimistic"``.
        value_key (NestedKey): where a critic called on its keys writes Q. Defaults to
            ``"state_action_value"`` (:meth:`from_loss`: the loss's ``state_action_value`` key).

    Examples:
        >>> import torch
        >>> from torchrl_dhrl.modules import GoalConditionedCritic, LowLevelActor
        >>> actor = LowLevelActor(6, 2, action_max=1.0, action_dim=2, goal_indices=[0, 1], num_cells=(32,))
        >>> critic = GoalConditionedCritic(6, 2, action_max=1.0, action_dim=2, num_cells=(32,))
        >>> distance = GoalDistance(actor, critic)
        >>> states, goals = torch.randn(5, 6), torch.randn(7, 2)
        >>> d = distance(states[:, None], goals[None])
        >>> d.shape, bool((d >= 0).all())
        (torch.Size([5, 7]), True)
    """

    @checked(
        gamma=number(0.0, 1.0, low_open=True, high_open=True, optional=True),
        chunk_size=integer(1, optional=True),
        max_distance=number(0.0, low_open=True, optional=True),
        twin=choice(TWIN_CHOICES),
    )
    def __init__(
        self,
        actor: TensorDictModuleBase,
        critic: TensorDictModuleBase,
        *,
        gamma: float | None = None,
        chunk_size: int | None = None,
        max_distance: float | None = None,
        actor_params: TensorDictBase | None = None,
        critic_params: TensorDictBase | None = None,
        autocast_dtype: torch.dtype | None = None,
        twin: str = "optimistic",
        value_key: NestedKey = "state_action_value",
    ) -> None:
        check_positional_keys(actor, 2, "actor")
        check_critic(critic, "critic")
        self.actor = actor
        self.critic = critic
        own_gamma = critic.gamma if isinstance(critic, GoalConditionedCritic) else DEFAULT_GAMMA
        self.gamma = own_gamma if gamma is None else float(gamma)
        if not 0.0 < self.gamma < 1.0:
            raise ValueError(f"`gamma` must be in (0, 1), got {self.gamma}.")
        self.chunk_size = chunk_size
        self.max_distance = max_distance
        self.actor_params = actor_params
        self.critic_params = critic_params
        self.autocast_dtype = self._check_autocast_dtype(autocast_dtype)
        self.twin = twin
        self.value_key = value_key

    @staticmethod
    def _check_autocast_dtype(dtype: torch.dtype | None) -> torch.dtype | None:
        if dtype is not None and dtype not in AUTOCAST_DTYPES:
            raise ValueError(
                f"`autocast_dtype` must be None, torch.bfloat16 or torch.float16, got {dtype!r}."
            )
        return dtype

    def with_autocast(self, dtype: torch.dtype | None) -> GoalDistance:
        """A shallow copy evaluated under ``torch.autocast(dtype)`` (``None``: full precision).

        The copy shares the networks and parameter containers (it follows training like the
        original); used by :class:`~torchrl_dhrl.planner.LandmarkGraph` for reduced-precision
        graph building.
        """
        other = copy.copy(self)
        other.autocast_dtype = self._check_autocast_dtype(dtype)
        return other

    @classmethod
    def from_loss(cls, loss, **kwargs) -> GoalDistance:
        """Builds the distance from an :class:`~torchrl_dhrl.objectives.SQGCLoss`'s current (non-target) parameters.

        The parameter containers are referenced, not copied: the distance follows training. Works with
        both critic kinds: a ``GoalConditionedCritic`` (fast path) and a single-member critic whose
        twin is the loss's stacked parameters (vmap, slower). Keyword arguments are passed to the
        constructor.
        """
        kwargs.setdefault("gamma", loss.gamma)
        kwargs.setdefault("value_key", loss.tensor_keys.state_action_value)
        return cls(
            loss.actor_network,
            loss.graph_critic,
            actor_params=loss.actor_network_params,
            critic_params=loss.graph_critic_params,
            **kwargs,
        )

    @property
    def observation_dim(self) -> int | None:
        """The critic's observation size (``None``: a critic that does not declare it)."""
        return self.critic.module.observation_dim if isinstance(self.critic, GoalConditionedCritic) else None

    @property
    def goal_dim(self) -> int | None:
        """The critic's goal size (``None``: a critic that does not declare it)."""
        return self.critic.module.goal_dim if isinstance(self.critic, GoalConditionedCritic) else None

    @property
    def _stacked(self) -> bool:
        """Whether ``critic_params`` stacks the members along a leading dim (evaluated with vmap)."""
        return self.critic_params is not None and self.critic_params.batch_dims > 0

    def _device_dtype(self) -> tuple[torch.device, torch.dtype]:
        """Where (and in which dtype) the critic's weights live: the computation follows them."""
        params = (
            self.critic_params.values(True, True)
            if self.critic_params is not None
            else self.critic.parameters()
        )
        floats = [p for p in params if p.is_floating_point()]
        weight = next((p for p in floats if isinstance(p, torch.nn.Parameter)), floats[0])
        return weight.device, weight.dtype

    def _evaluate(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """Distances of aligned pairs ``[n, obs_dim]``, ``[n, goal_dim]`` -> ``[n]``."""
        # the parameters are passed to the networks (torch.func.functional_call), never swapped into them around
        # the call: the evaluation then also runs inside a compiled torch.cond (the capturable planner's)
        action = _run_actor(self.actor, states, goals, self.actor_params)
        if self._stacked:
            q = stacked_critic_values(self.critic, self.critic_params, states, goals, action, self.value_key)
        else:
            # A GoalConditionedCritic without hooks runs on the tensors; under autocast its output layer
            # runs in full precision (EnsembleMLP), so the raw output -- the distance itself with the
            # distance parameterisation -- is not rounded.
            q = critic_values(self.critic, states, goals, action, self.value_key, params=self.critic_params)
        member = q.max(0) if self.twin == "optimistic" else q.min(0)  # over the members, [E, n]
        return q_to_distance(member.values, self.gamma, self.max_distance)

    def __call__(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        if self.observation_dim is not None:
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
        chunk_size = self.chunk_size
        if chunk_size is None:
            chunk_size = DEFAULT_CPU_CHUNK_SIZE if device.type == "cpu" else DEFAULT_CHUNK_SIZE
        with (
            torch.no_grad(),
            set_exploration_type(ExplorationType.DETERMINISTIC),
            _autocast(device, self.autocast_dtype),
        ):
            if n_pairs <= chunk_size:
                out = self._evaluate(
                    states_b.reshape(n_pairs, states.shape[-1]), goals_b.reshape(n_pairs, goals.shape[-1])
                )
            else:
                chunks = []
                for start in range(0, n_pairs, chunk_size):
                    flat = torch.arange(start, min(start + chunk_size, n_pairs), device=device)
                    index = torch.unravel_index(flat, shape)
                    chunks.append(self._evaluate(states_b[index], goals_b[index]))
                out = torch.cat(chunks)
        return out.reshape(shape).to(out_device)


class LineOfSightDistance:
    """``d(s -> g) = ||g - ag(s)|| / speed`` when the segment ``ag(s) -> g`` is free, else ``blocked``.

    The oracle counterpart of :class:`GoalDistance` (a :class:`TemporalDistance`:
    ``(states[..., obs_dim], goals[..., goal_dim]) -> steps[...]`` with broadcasting), for the
    "oracle graph distance" ablation and for tests. A plain Euclidean distance would let graph
    edges cross the mazes' walls (a 30-step cutoff spans the point agent's 4-unit wall), so
    segments that intersect an obstacle box (inflated by ``margin``) cost ``blocked`` instead.
    Intersection uses the slab test, vectorised over pairs and boxes.

    Args:
        speed (float): goal units covered per env step.

    Keyword Args:
        boxes (Tensor or sequence, optional): ``[W, 2, goal_dim]`` axis-aligned obstacle boxes
            (``boxes[:, 0]`` lower corners, ``boxes[:, 1]`` upper corners). Defaults to none.
        margin (float): inflation of every box (e.g. the agent's radius). Defaults to ``0.0``.
        goal_indices (sequence of int): where the achieved goal sits in the state (e.g. ``(0, 1)`` for the
            mazes' ``(x, y)``; :func:`~torchrl_dhrl.envs.goal_indices_of` reads it from an env). Required.
        blocked (float): the distance of a blocked pair. Defaults to ``inf``: unreachable, so a blocked pair is
            never an edge, a start connection or an exit of :class:`~torchrl_dhrl.planner.LandmarkGraph`. A finite
            value (``1e4`` in 0.4.0 and before) is a very long but usable distance: a landmark or a state that sees no
            other within the cutoff is then joined to every one it cannot see by the nearest-neighbour edge rule
            and the start fallback (which compare distances with the nearest one, ``1e4`` against ``1e4``).
        chunk_size (int): pairs per evaluation chunk. Defaults to ``65536``.

    Examples:
        >>> import torch
        >>> wall = torch.tensor([[[1.0, -5.0], [2.0, 5.0]]])  # a wall between x=1 and x=2
        >>> d = LineOfSightDistance(0.5, boxes=wall, goal_indices=[0, 1])
        >>> d(torch.zeros(2, 2), torch.tensor([[0.0, 3.0], [3.0, 0.0]])).tolist()
        [6.0, inf]
    """

    @checked(speed=number(0.0, low_open=True), margin=number(0.0), blocked=number(0.0, low_open=True))
    def __init__(
        self,
        speed: float,
        *,
        boxes: Tensor | Sequence | None = None,
        margin: float = 0.0,
        goal_indices: Sequence[int],
        blocked: float = math.inf,
        chunk_size: int = 65536,
    ) -> None:
        self.speed = float(speed)
        self.goal_indices = list(goal_indices)
        dim = len(self.goal_indices)
        boxes = torch.zeros(0, 2, dim) if boxes is None else torch.as_tensor(boxes, dtype=torch.float32)
        if boxes.ndim != 3 or boxes.shape[1:] != (2, dim):
            raise ValueError(f"`boxes` must be [W, 2, {dim}], got {tuple(boxes.shape)}.")
        self.boxes = torch.stack([boxes[:, 0] - margin, boxes[:, 1] + margin], 1)
        self.blocked = float(blocked)
        self.chunk_size = int(chunk_size)

    def with_autocast(self, dtype: torch.dtype | None) -> LineOfSightDistance:
        """This distance itself: geometry has no network to run in reduced precision.

        Lets a graph built with ``build_autocast_dtype`` (e.g. the recipe's ``planner.build_dtype=bfloat16``)
        use the oracle unchanged; its distances stay those of the inputs' dtype (float32 states: float32).

        Examples:
            >>> oracle = LineOfSightDistance(0.5, goal_indices=[0, 1])
            >>> oracle.with_autocast(torch.bfloat16) is oracle
            True
        """
        return self

    def crosses_obstacle(self, start: Tensor, end: Tensor) -> Tensor:
        """``[n]`` bool: does the segment ``start -> end`` (``[n, dim]``) cross any (inflated) box?"""
        boxes = self.boxes.to(start.device, start.dtype)
        if boxes.shape[0] == 0:
            return torch.zeros(start.shape[0], dtype=torch.bool, device=start.device)
        direction = (end - start).unsqueeze(1)  # [n, 1, dim]
        origin = start.unsqueeze(1)
        parallel = direction.abs() < 1e-12
        safe = torch.where(parallel, torch.ones_like(direction), direction)
        t0 = (boxes[:, 0] - origin) / safe  # [n, W, dim]
        t1 = (boxes[:, 1] - origin) / safe
        t_near = torch.minimum(t0, t1)
        t_far = torch.maximum(t0, t1)
        inside = (origin >= boxes[:, 0]) & (origin <= boxes[:, 1])  # for axes the segment is parallel to
        t_near = torch.where(parallel, torch.where(inside, -torch.inf, torch.inf), t_near)
        t_far = torch.where(parallel, torch.where(inside, torch.inf, -torch.inf), t_far)
        enter = t_near.amax(-1).clamp_min(0.0)
        leave = t_far.amin(-1).clamp_max(1.0)
        return (enter <= leave).any(-1)

    def __call__(self, states: Tensor, goals: Tensor) -> Tensor:
        achieved = states[..., self.goal_indices]
        shape = torch.broadcast_shapes(achieved.shape[:-1], goals.shape[:-1])
        dim = goals.shape[-1]
        start = achieved.expand(*shape, dim).reshape(-1, dim)
        end = goals.to(achieved.dtype).expand(*shape, dim).reshape(-1, dim)
        out = torch.empty(start.shape[0], dtype=achieved.dtype, device=achieved.device)
        for lo in range(0, start.shape[0], self.chunk_size):
            s, e = start[lo : lo + self.chunk_size], end[lo : lo + self.chunk_size]
            steps = (e - s).norm(dim=-1) / self.speed
            out[lo : lo + self.chunk_size] = torch.where(self.crosses_obstacle(s, e), self.blocked, steps)
        return out.reshape(shape)
