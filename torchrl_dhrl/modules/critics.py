"""Goal-conditioned twin critics with the temporal-distance parameterisation of DHRL."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torch.nn import functional as F
from torchrl.data import TensorSpec

from torchrl_dhrl.checks import checked, choice, flag, integer, layer_sizes, number

from ._utils import (
    box_loc_scale,
    call_with_params,
    check_last_dim,
    goal_input,
    register_goal_indices,
    relative_goal_needs_indices,
    resolve_box,
    routes_tensors_only,
)
from .actors import DEFAULT_NUM_CELLS
from .ensemble import EnsembleMLP

PARAMETERIZATIONS = ("distance", "q")
#: ``distance_output`` values: the network's raw output is the distance (the reference's ``DistCritic``) or
#: its softplus (a distance >= 0 by construction).
DISTANCE_OUTPUTS = ("linear", "softplus")
#: The default discount (the reference's); the losses and GoalDistance use it for critics that hold none.
DEFAULT_GAMMA = 0.99
#: The accepted discounts.
GAMMA = number(0.0, 1.0, low_open=True, high_open=True)
#: The checks of the critics' arguments (:func:`~torchrl_dhrl.checks.checked`).
critic_checks = checked(
    relative_goal_needs_indices,
    relative_goal=flag(),
    num_cells=layer_sizes(),
    num_nets=integer(1),
    parameterization=choice(PARAMETERIZATIONS),
    distance_output=choice(DISTANCE_OUTPUTS),
    gamma=GAMMA,
)


def _check_gamma(gamma: float) -> float:
    gamma = float(gamma)
    if not 0.0 < gamma < 1.0:
        raise ValueError(f"`gamma` must be in (0, 1), got {gamma}.")
    return gamma


def distance_to_q(distance: torch.Tensor, gamma: float) -> torch.Tensor:
    """``Q = -(1 - gamma^d) / (1 - gamma)``: the return of ``d`` steps of reward -1 followed by 0.

    Examples:
        >>> import torch
        >>> distance_to_q(torch.tensor([0.0, 1.0, 2.0]), 0.5)
        tensor([ 0.0000, -1.0000, -1.5000])
    """
    gamma = _check_gamma(gamma)
    # ``+ 0.0`` turns the -0.0 of d = 0 into 0.0.
    return torch.expm1(distance * math.log(gamma)) / (1.0 - gamma) + 0.0


def q_to_distance(q: torch.Tensor, gamma: float, max_distance: float | None = None) -> torch.Tensor:
    """Eq. (1) of DHRL: ``d = log_gamma(1 + (1 - gamma) Q)``, clamped to ``[0, max_distance]``.

    ``1 + (1 - gamma) Q <= 0`` (a value at or below ``-1 / (1 - gamma)``, an infinite
    distance) is guarded so the result stays finite: the argument of the log is floored at
    the float epsilon, which caps the distance at ``log(eps) / log(gamma)`` (about 1586 steps
    in float32 at ``gamma = 0.99``) unless a smaller ``max_distance`` is given. Positive
    values (possible with plain Q critics) give distance 0.

    Examples:
        >>> import torch
        >>> q_to_distance(torch.tensor([0.0, -1.0, -1.5, 3.0]), 0.5)
        tensor([0., 1., 2., 0.])
        >>> bool(torch.isfinite(q_to_distance(torch.tensor([-1e6]), 0.99)).all())
        True
    """
    gamma = _check_gamma(gamma)
    eps = torch.finfo(q.dtype).eps if q.is_floating_point() else torch.finfo(torch.float32).eps
    x = ((1.0 - gamma) * q).clamp(min=eps - 1.0)
    d = (torch.log1p(x) / math.log(gamma)).clamp(min=0.0) + 0.0
    if max_distance is not None:
        d = d.clamp(max=max_distance)
    return d


class GoalConditionedCriticNet(nn.Module):
    """An ensemble of goal-conditioned Q networks ``Q_k(s, a | g)`` with stacked weights.

    Input: ``observation ++ goal_input ++ scaled_action`` where the goal input is
    ``goal - observation[..., goal_indices]`` (relative) or the goal itself (absolute), and
    the action is scaled to ``[-1, 1]`` with its box (the low-level critic sees
    ``action / action_max``, the high-level critic the subgoal scaled from its box).

    With ``parameterization="distance"`` (default), each member outputs a distance ``d`` and
    ``Q = -(1 - gamma^d) / (1 - gamma)``. With ``distance_output="linear"`` (default, the reference
    implementation's ``DistCritic``) ``d`` is the raw output itself: it can be negative (``Q > 0``),
    which the targets (clamped at ``Q <= 0``) push back, and distance queries clamp it at 0 (Eq. 1,
    :func:`q_to_distance`). With ``"softplus"``, ``d = softplus(raw) >= 0``, so ``Q`` lies in
    ``(-1 / (1 - gamma), 0]`` by construction (this package's behaviour before 0.4). With ``"q"`` the
    raw output is Q.

    Args:
        observation_dim (int): observation size.
        goal_dim (int): goal size.
        action_low (Tensor): lower corner of the action box.
        action_high (Tensor): upper corner of the action box.

    Keyword Args:
        goal_indices (sequence of int, optional): achieved goal indices (relative mode).
        relative_goal (bool): relative (``True``, needs ``goal_indices``) or absolute goal input (``False``,
            default: the reference's critics see the goal itself).
        num_nets (int): ensemble size. Defaults to ``2`` (the TD3 twin).
        num_cells (sequence of int): hidden widths. Defaults to ``(256, 256, 256)``.
        activation_class (type): hidden activation. Defaults to ``nn.ReLU``.
        parameterization (str): ``"distance"`` or ``"q"``. Defaults to ``"distance"``.
        distance_output (str): ``"linear"`` or ``"softplus"``, the map from the raw output to the distance
            (``parameterization="distance"`` only). Defaults to ``"linear"`` (the reference's).
        gamma (float): discount, used by the distance parameterisation and Eq. (1).
            Defaults to ``0.99``.

    Examples:
        >>> import torch
        >>> net = GoalConditionedCriticNet(4, 2, -torch.ones(3), torch.ones(3), goal_indices=[0, 1],
        ...     num_cells=(16,), distance_output="softplus")
        >>> q = net(torch.randn(5, 4), torch.randn(5, 2), torch.rand(5, 3))
        >>> q.shape, bool((q <= 0).all())
        (torch.Size([5, 2]), True)
        >>> raw = torch.tensor([-1.0, 0.0, 2.0])  # the raw outputs as distances (the default)
        >>> GoalConditionedCriticNet(4, 2, -torch.ones(3), torch.ones(3), goal_indices=[0, 1]).q_from_raw(raw)
        tensor([ 1.0101,  0.0000, -1.9900])
    """

    @critic_checks
    def __init__(
        self,
        observation_dim: int,
        goal_dim: int,
        action_low: torch.Tensor,
        action_high: torch.Tensor,
        *,
        goal_indices: Sequence[int] | None = None,
        relative_goal: bool = False,
        num_nets: int = 2,
        num_cells: Sequence[int] = DEFAULT_NUM_CELLS,
        activation_class: type[nn.Module] = nn.ReLU,
        parameterization: str = "distance",
        distance_output: str = "linear",
        gamma: float = DEFAULT_GAMMA,
    ) -> None:
        super().__init__()
        self.observation_dim = observation_dim
        self.goal_dim = goal_dim
        self.action_dim = int(action_low.shape[-1])
        self.parameterization = parameterization
        self.distance_output = distance_output
        self.gamma = _check_gamma(gamma)
        register_goal_indices(self, relative_goal, goal_indices, goal_dim, observation_dim)
        loc, scale = box_loc_scale(action_low, action_high)
        self.register_buffer("action_loc", loc)
        self.register_buffer("action_scale", scale)
        self.ensemble = EnsembleMLP(
            observation_dim + goal_dim + self.action_dim,
            1,
            num_nets,
            num_cells=num_cells,
            activation_class=activation_class,
        )

    @property
    def num_nets(self) -> int:
        return self.ensemble.ensemble_size

    def features(self, observation: torch.Tensor, goal: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The network input ``observation ++ goal_input ++ scaled_action`` (``[*batch, in]``)."""
        check_last_dim("observation", observation, self.observation_dim)
        check_last_dim("goal", goal, self.goal_dim)
        check_last_dim("action", action, self.action_dim)
        shape = torch.broadcast_shapes(observation.shape[:-1], goal.shape[:-1], action.shape[:-1])
        observation = observation.expand(*shape, self.observation_dim)
        goal = goal.expand(*shape, self.goal_dim)
        action = action.expand(*shape, self.action_dim)
        scaled = (action - self.action_loc) / self.action_scale
        return torch.cat([observation, goal_input(observation, goal, self.goal_indices), scaled], -1)

    def q_from_features(self, x: torch.Tensor, per_member: bool = False) -> torch.Tensor:
        """Q of every member from :meth:`features`: ``[*batch, in]`` (or ``[E, *batch, in]``) -> ``[E, *batch]``."""
        return self.q_from_raw(self.ensemble(x, per_member=per_member).squeeze(-1))

    def q_from_raw(self, raw: torch.Tensor) -> torch.Tensor:
        """Q from the raw network outputs (the parameterisation's output map), elementwise."""
        if self.parameterization == "distance":
            return distance_to_q(raw if self.distance_output == "linear" else F.softplus(raw), self.gamma)
        return raw

    def forward(self, observation: torch.Tensor, goal: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Returns ``Q_k(s, a | g)`` of every member, ensemble dim last: ``[*batch, num_nets]``."""
        q = self.q_from_features(self.features(observation, goal, action))
        return q.movedim(0, -1)


class GoalConditionedCritic(TensorDictModule):
    """A goal-conditioned twin critic as a :class:`~tensordict.nn.TensorDictModule`.

    Reads ``observation_key``, ``goal_key`` and ``action_key`` (its ``in_keys``, in that order) and
    writes ``out_key`` with shape ``[*batch, num_nets]`` (one column per member of the twin; the
    members share one stacked-weight network, evaluated in a single batched matmul per layer). See
    :class:`GoalConditionedCriticNet` for the inputs and the distance parameterisation.

    The DHRL losses (:class:`~torchrl_dhrl.objectives.SQGCLoss`,
    :class:`~torchrl_dhrl.objectives.HighLevelLoss`) and
    :class:`~torchrl_dhrl.planner.GoalDistance` call their critics on these keys: they write the
    state, the goal the critic is trained or queried on and the action under the critic's
    ``in_keys`` and read the value back (at their ``state_action_value`` key, ``out_key``'s default), so
    one critic class serves any batch layout (the low-level policy and graph critics read two different
    goals of the same batch). Unless hooks are
    registered on it, a ``GoalConditionedCritic`` is evaluated on the tensors directly instead
    (the same computation, without building a TensorDict; the losses then also stack both twins
    of :class:`~torchrl_dhrl.objectives.SQGCLoss` into one ensemble off the CPU).

    The same class serves both levels: at the low level the action box is the action
    spec (the critic sees ``action / action_max``); at the high level the "action" is the
    subgoal and the box is the subgoal box (the critic sees it scaled to ``[-1, 1]``).

    Args:
        observation_dim (int): observation size.
        goal_dim (int): goal size.
        action_spec (Bounded, optional): the action box. Exclusive with ``action_max`` and
            ``action_low``/``action_high``.

    Keyword Args:
        action_max (float or Tensor, optional): symmetric box ``[-action_max, action_max]``.
        action_low (Tensor or sequence, optional): lower corner of the box.
        action_high (Tensor or sequence, optional): upper corner of the box.
        action_dim (int, optional): action size when scalar bounds are given.
        goal_indices (sequence of int, optional): where the achieved goal sits in the observation; needed with
            ``relative_goal=True``. Defaults to ``None``.
        relative_goal (bool): feed ``goal - observation[..., goal_indices]`` (``True``) or the goal as is
            (``False``, default: the reference's critics see the waypoint itself).
        num_nets (int): ensemble size. Defaults to ``2``.
        num_cells (sequence of int): hidden widths. Defaults to ``(256, 256, 256)``.
        activation_class (type): hidden activation. Defaults to ``nn.ReLU``.
        parameterization (str): ``"distance"`` (default) or ``"q"``.
        distance_output (str): ``"linear"`` (default, the reference's: the raw output is the distance) or
            ``"softplus"`` (a distance >= 0 by construction); see :class:`GoalConditionedCriticNet`.
        gamma (float): discount. Defaults to ``0.99``.
        observation_key (NestedKey): where the state is read. Defaults to ``"observation"``.
        goal_key (NestedKey): where the goal is read (the waypoint at the low level, the final goal at
            the high level). Defaults to ``"waypoint"``.
        action_key (NestedKey): where the action (the subgoal at the high level) is read. Defaults to
            ``"action"``.
        out_key (NestedKey): where the member values are written. Defaults to ``"state_action_value"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> critic = GoalConditionedCritic(6, 2, action_max=30.0, action_dim=8, num_cells=(32,))
        >>> td = TensorDict({"observation": torch.randn(4, 6), "waypoint": torch.randn(4, 2),
        ...                  "action": torch.rand(4, 8)}, [4])
        >>> critic(td)["state_action_value"].shape
        torch.Size([4, 2])
    """

    @critic_checks
    def __init__(
        self,
        observation_dim: int,
        goal_dim: int,
        action_spec: TensorSpec | None = None,
        *,
        action_max: float | torch.Tensor | None = None,
        action_low: torch.Tensor | Sequence[float] | None = None,
        action_high: torch.Tensor | Sequence[float] | None = None,
        action_dim: int | None = None,
        goal_indices: Sequence[int] | None = None,
        relative_goal: bool = False,
        num_nets: int = 2,
        num_cells: Sequence[int] = DEFAULT_NUM_CELLS,
        activation_class: type[nn.Module] = nn.ReLU,
        parameterization: str = "distance",
        distance_output: str = "linear",
        gamma: float = DEFAULT_GAMMA,
        observation_key: NestedKey = "observation",
        goal_key: NestedKey = "waypoint",
        action_key: NestedKey = "action",
        out_key: NestedKey = "state_action_value",
    ) -> None:
        low, high = resolve_box(
            spec=action_spec,
            low=action_low,
            high=action_high,
            max_abs=action_max,
            dim=action_dim,
            key=action_key,
        )
        net = GoalConditionedCriticNet(
            observation_dim,
            goal_dim,
            low,
            high,
            goal_indices=goal_indices if relative_goal else None,
            relative_goal=relative_goal,
            num_nets=num_nets,
            num_cells=num_cells,
            activation_class=activation_class,
            parameterization=parameterization,
            distance_output=distance_output,
            gamma=gamma,
        )
        super().__init__(net, in_keys=[observation_key, goal_key, action_key], out_keys=[out_key])

    @property
    def gamma(self) -> float:
        return self.module.gamma

    @property
    def num_nets(self) -> int:
        return self.module.num_nets

    @property
    def parameterization(self) -> str:
        return self.module.parameterization

    @property
    def distance_output(self) -> str:
        return self.module.distance_output


def check_critic(critic, role: str) -> None:
    """Checks the critic contract of the DHRL losses and of ``GoalDistance``.

    A critic is a :class:`~tensordict.nn.TensorDictModuleBase` reading three distinct keys -- the
    observation, the goal and the action, in that order -- and writing its value. Raises a
    ``TypeError`` naming ``role`` otherwise.
    """
    in_keys = getattr(critic, "in_keys", None)
    out_keys = getattr(critic, "out_keys", None)
    if (
        not isinstance(critic, TensorDictModuleBase)
        or in_keys is None
        or len(in_keys) != 3
        or len(set(in_keys)) != 3
        or not out_keys
    ):
        raise TypeError(
            f"`{role}` must be a critic TensorDictModule reading three distinct keys (observation, goal, "
            "action, in that order) and writing its value: a GoalConditionedCritic, or e.g. "
            "ValueOperator(MLP(...), in_keys=['observation', 'goal', 'action']); got "
            f"{type(critic).__name__} with in_keys={in_keys}, out_keys={out_keys}."
        )


def runs_on_tensors(critic: TensorDictModuleBase) -> bool:
    """Whether ``critic`` takes the fast path: a :class:`GoalConditionedCritic` without hooks.

    Its stacked twin is then evaluated on the tensors (``features`` -> ``q_from_features``), the
    computation its ``forward`` does, without building a TensorDict.
    """
    return (
        isinstance(critic, GoalConditionedCritic)
        and type(critic.module) is GoalConditionedCriticNet
        and routes_tensors_only(critic)
    )


def _one_value(value: torch.Tensor, batch: torch.Size) -> torch.Tensor:
    """A single-member critic's output ``[*batch, 1]`` (or ``[*batch]``) as ``[*batch]``."""
    if value.shape == (*batch, 1):
        return value.squeeze(-1)
    if value.shape != batch:
        raise ValueError(
            f"A critic other than GoalConditionedCritic is one member and must write one value per sample, "
            f"[*batch, 1] or [*batch] with batch {tuple(batch)}; got shape {tuple(value.shape)}. The losses "
            "make the twin by stacking its parameters (`num_qvalue_nets`)."
        )
    return value


def _critic_input(critic, observation, goal, action) -> TensorDict:
    return TensorDict(
        dict(zip(critic.in_keys, (observation, goal, action), strict=True)), batch_size=observation.shape[:-1]
    )


def _read_value(td, value_key: NestedKey, critic) -> torch.Tensor:
    value = td.get(value_key, None)
    if value is None:
        raise KeyError(
            f"The critic {type(critic).__name__} (out_keys={critic.out_keys}) wrote no {value_key!r} entry: "
            "point the loss at the critic's value with `loss.set_keys(state_action_value=...)` (GoalDistance: "
            "`value_key=`)."
        )
    return value


def critic_values(
    critic: TensorDictModuleBase,
    observation: torch.Tensor,
    goal: torch.Tensor,
    action: torch.Tensor,
    value_key: NestedKey = "state_action_value",
    *,
    params: TensorDictBase | None = None,
) -> torch.Tensor:
    """The values of every member of ``critic``, members first: ``[E, *batch]``.

    ``observation``, ``goal`` and ``action`` share the leading ``batch`` dims. A
    :class:`GoalConditionedCritic` holds its members (output ``[*batch, num_nets]``); any other
    critic is one member (``E = 1``) writing ``[*batch, 1]`` or ``[*batch]`` at ``value_key``.
    With ``params`` (laid out as ``TensorDict.from_module(critic)``) in place of the critic's own parameters,
    through :func:`torch.func.functional_call` (:func:`~torchrl_dhrl.modules._utils.call_with_params`);
    ``None``: its current parameters.
    """
    if runs_on_tensors(critic):
        net = critic.module
        if params is None:
            return net.q_from_features(net.features(observation, goal, action))
        return call_with_params(net, params["module"], observation, goal, action).movedim(-1, 0)
    td = call_with_params(critic, params, _critic_input(critic, observation, goal, action))
    value = _read_value(td, value_key, critic)
    if isinstance(critic, GoalConditionedCritic):
        return value.movedim(-1, 0)
    return _one_value(value, observation.shape[:-1]).unsqueeze(0)


def stacked_critic_values(
    critic: TensorDictModuleBase,
    params: TensorDictBase,
    observation: torch.Tensor,
    goal: torch.Tensor,
    action: torch.Tensor,
    value_key: NestedKey = "state_action_value",
    randomness: str = "error",
) -> torch.Tensor:
    """The values of ``E`` members whose parameters are stacked along dim 0 of ``params``: ``[E, *batch]``.

    The members (single-member critics, e.g. a :class:`~torchrl.modules.ValueOperator` whose
    parameters a loss stacked with ``convert_to_functional(..., expand_dim=E)``) are evaluated with
    :func:`torch.vmap` over ``params`` on the same inputs, as in :class:`~torchrl.objectives.TD3Loss`.
    """
    batch = observation.shape[:-1]

    def member(observation, goal, action, member_params):
        td = call_with_params(critic, member_params, _critic_input(critic, observation, goal, action))
        return _one_value(_read_value(td, value_key, critic), batch)

    return torch.vmap(member, (None, None, None, 0), randomness=randomness)(observation, goal, action, params)
