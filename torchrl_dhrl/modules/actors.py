"""Deterministic goal-conditioned actors of both DHRL levels (pi_lo(a | s, wp) and pi_hi(sg | s, g))."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Bounded, Composite, TensorSpec
from torchrl.modules import MLP, Actor

from torchrl_dhrl.checks import checked, flag, layer_sizes

from ._utils import (
    box_loc_scale,
    check_last_dim,
    full_precision_output,
    goal_input,
    register_goal_indices,
    relative_goal_needs_indices,
    resolve_box,
)

#: Hidden widths of every DHRL network (reference: 3 x 256 ReLU).
DEFAULT_NUM_CELLS = (256, 256, 256)
#: The checks of the goal-conditioned networks' shared arguments (:func:`~torchrl_dhrl.checks.checked`).
goal_network_checks = checked(relative_goal_needs_indices, relative_goal=flag(), num_cells=layer_sizes())


class GoalConditionedActorNet(nn.Module):
    """``a = loc + scale * tanh(MLP(observation ++ goal_input))``, bounded to a box.

    The goal is fed relative to the achieved goal (``goal - observation[..., goal_indices]``)
    when ``relative_goal=True``, as is otherwise. Inside ``torch.autocast`` the hidden layers
    run in the autocast dtype and the output layer in the parameters' dtype.

    Args:
        observation_dim (int): observation size.
        goal_dim (int): goal size.
        low (Tensor): lower bounds of the output box, shape ``[out_dim]``.
        high (Tensor): upper bounds of the output box, shape ``[out_dim]``.

    Keyword Args:
        goal_indices (sequence of int, optional): where the achieved goal sits in the
            observation; required when ``relative_goal=True``.
        relative_goal (bool): relative (``True``) or absolute goal input.
        num_cells (sequence of int): hidden widths. Defaults to ``(256, 256, 256)``.
        activation_class (type): hidden activation. Defaults to ``nn.ReLU``.

    Examples:
        >>> import torch
        >>> net = GoalConditionedActorNet(4, 2, -torch.ones(3), torch.ones(3), goal_indices=[0, 1],
        ...     relative_goal=True, num_cells=(16,))
        >>> net(torch.randn(5, 4), torch.randn(5, 2)).shape
        torch.Size([5, 3])
    """

    def __init__(
        self,
        observation_dim: int,
        goal_dim: int,
        low: torch.Tensor,
        high: torch.Tensor,
        *,
        goal_indices: Sequence[int] | None = None,
        relative_goal: bool = True,
        num_cells: Sequence[int] = DEFAULT_NUM_CELLS,
        activation_class: type[nn.Module] = nn.ReLU,
    ) -> None:
        super().__init__()
        if observation_dim < 1 or goal_dim < 1:
            raise ValueError(f"Dimensions must be positive, got obs={observation_dim}, goal={goal_dim}.")
        self.observation_dim = observation_dim
        self.goal_dim = goal_dim
        self.out_dim = int(low.shape[-1])
        register_goal_indices(self, relative_goal, goal_indices, goal_dim, observation_dim)
        loc, scale = box_loc_scale(low, high)
        self.register_buffer("loc", loc)
        self.register_buffer("scale", scale)
        self.mlp = MLP(
            in_features=observation_dim + goal_dim,
            out_features=self.out_dim,
            num_cells=list(num_cells),
            activation_class=activation_class,
        )

    @property
    def low(self) -> torch.Tensor:
        return self.loc - self.scale

    @property
    def high(self) -> torch.Tensor:
        return self.loc + self.scale

    def forward(self, observation: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        check_last_dim("observation", observation, self.observation_dim)
        check_last_dim("goal", goal, self.goal_dim)
        if observation.shape[:-1] != goal.shape[:-1]:
            shape = torch.broadcast_shapes(observation.shape[:-1], goal.shape[:-1])
            observation = observation.expand(*shape, self.observation_dim)
            goal = goal.expand(*shape, self.goal_dim)
        x = torch.cat([observation, goal_input(observation, goal, self.goal_indices)], -1)
        return torch.addcmul(self.loc, self.scale, torch.tanh(self._mlp(x)))

    def _mlp(self, x: torch.Tensor) -> torch.Tensor:
        """The MLP; inside ``torch.autocast`` its output layer runs in the parameters' dtype."""
        *hidden, last = self.mlp  # torchrl's MLP: a Sequential ending with its output Linear
        for module in hidden:
            x = module(x)
        return full_precision_output(last, x)


class _BoxedGoalActor(Actor):
    """Shared construction of the two DHRL actors: a :class:`GoalConditionedActorNet` bounded to a box."""

    def _init_net(
        self,
        observation_dim,
        goal_dim,
        low,
        high,
        goal_indices,
        relative_goal,
        num_cells,
        activation_class,
        observation_key,
        goal_key,
        out_key,
    ) -> None:
        net = GoalConditionedActorNet(
            observation_dim,
            goal_dim,
            low,
            high,
            goal_indices=goal_indices if relative_goal else None,
            relative_goal=relative_goal,
            num_cells=num_cells,
            activation_class=activation_class,
        )
        spec = Composite({out_key: Bounded(low, high, shape=low.shape)})
        Actor.__init__(self, net, in_keys=[observation_key, goal_key], out_keys=[out_key], spec=spec)

    @property
    def low(self) -> torch.Tensor:
        return self.module.low

    @property
    def high(self) -> torch.Tensor:
        return self.module.high


class LowLevelActor(_BoxedGoalActor):
    """The deterministic low-level policy ``pi_lo(a | s, wp)`` as a TorchRL :class:`~torchrl.modules.Actor`.

    Reads ``observation`` and a goal entry (``"waypoint"`` by default; the no-graph phase
    feeds ``"subgoal"``) and writes ``action``, tanh-bounded to the action box. By default
    the goal input is relative, ``waypoint - observation[..., goal_indices]``
    (reference: relative for the mazes, absolute for Reacher3D).

    Add exploration with :class:`~torchrl_dhrl.modules.GaussianUniformExplorationModule`
    (or :func:`~torchrl_dhrl.modules.make_low_level_policy`).

    Args:
        observation_dim (int): observation size.
        goal_dim (int): goal size.
        action_spec (Bounded, optional): the action box (a Composite with an ``action_key``
            entry works too). Exclusive with ``action_max``.

    Keyword Args:
        action_max (float or Tensor, optional): a symmetric box ``[-action_max, action_max]``
            (reference: 30 for the ant, 20 for Reacher3D); needs ``action_dim``.
        action_dim (int, optional): action size when ``action_max`` is given.
        goal_indices (sequence of int, optional): where the achieved goal sits in the observation; needed with
            ``relative_goal=True`` (e.g. ``(0, 1)`` for the mazes' ``(x, y)``). Defaults to ``None``.
        relative_goal (bool): relative (default, needs ``goal_indices``) or absolute goal input.
        num_cells (sequence of int): hidden widths. Defaults to ``(256, 256, 256)``.
        activation_class (type): hidden activation. Defaults to ``nn.ReLU``.
        observation_key (NestedKey): Defaults to ``"observation"``.
        goal_key (NestedKey): Defaults to ``"waypoint"``.
        action_key (NestedKey): Defaults to ``"action"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> actor = LowLevelActor(6, 2, action_max=1.0, action_dim=2, goal_indices=[0, 1], num_cells=(32, 32))
        >>> td = TensorDict({"observation": torch.randn(3, 6), "waypoint": torch.randn(3, 2)}, [3])
        >>> actor(td)["action"].abs().max() <= 1.0
        tensor(True)
    """

    @goal_network_checks
    def __init__(
        self,
        observation_dim: int,
        goal_dim: int,
        action_spec: TensorSpec | None = None,
        *,
        action_max: float | torch.Tensor | None = None,
        action_dim: int | None = None,
        goal_indices: Sequence[int] | None = None,
        relative_goal: bool = True,
        num_cells: Sequence[int] = DEFAULT_NUM_CELLS,
        activation_class: type[nn.Module] = nn.ReLU,
        observation_key: NestedKey = "observation",
        goal_key: NestedKey = "waypoint",
        action_key: NestedKey = "action",
    ) -> None:
        low, high = resolve_box(spec=action_spec, max_abs=action_max, dim=action_dim, key=action_key)
        self._init_net(
            observation_dim,
            goal_dim,
            low,
            high,
            goal_indices,
            relative_goal,
            num_cells,
            activation_class,
            observation_key,
            goal_key,
            action_key,
        )


class HighLevelActor(_BoxedGoalActor):
    """The deterministic high-level policy ``pi_hi(sg | s, g)`` as a TorchRL :class:`~torchrl.modules.Actor`.

    Reads ``observation`` and ``desired_goal`` and writes a subgoal tanh-scaled to the
    subgoal box ``[subgoal_low, subgoal_high]`` (reference: ``[-4, 20]^2`` for AntMaze,
    ``[-4, 52]^2`` for AntMazeComplex). This is the bare network used by
    :class:`~torchrl_dhrl.objectives.HighLevelLoss`; for acting, use
    :class:`~torchrl_dhrl.modules.HighLevelPolicy`, which adds subgoal noise and the
    ``c_h`` cadence.

    Args:
        observation_dim (int): observation size.
        goal_dim (int): goal (and subgoal) size.
        subgoal_low (Tensor or sequence of float): lower corner of the subgoal box.
        subgoal_high (Tensor or sequence of float): upper corner of the subgoal box.

    Keyword Args:
        goal_indices (sequence of int, optional): where the achieved goal sits in the observation; needed with
            ``relative_goal=True``. Defaults to ``None``.
        relative_goal (bool): feed ``desired_goal - achieved`` (``True``) or the goal as is
            (``False``, default).
        num_cells (sequence of int): hidden widths. Defaults to ``(256, 256, 256)``.
        activation_class (type): hidden activation. Defaults to ``nn.ReLU``.
        observation_key (NestedKey): Defaults to ``"observation"``.
        goal_key (NestedKey): Defaults to ``"desired_goal"``.
        subgoal_key (NestedKey): output entry. Defaults to ``"subgoal"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> actor = HighLevelActor(6, 2, [-4.0, -4.0], [20.0, 20.0], num_cells=(32,))
        >>> td = TensorDict({"observation": torch.randn(3, 6), "desired_goal": torch.randn(3, 2)}, [3])
        >>> sg = actor(td)["subgoal"]
        >>> bool(((sg >= -4) & (sg <= 20)).all())
        True
    """

    @goal_network_checks
    def __init__(
        self,
        observation_dim: int,
        goal_dim: int,
        subgoal_low: torch.Tensor | Sequence[float],
        subgoal_high: torch.Tensor | Sequence[float],
        *,
        goal_indices: Sequence[int] | None = None,
        relative_goal: bool = False,
        num_cells: Sequence[int] = DEFAULT_NUM_CELLS,
        activation_class: type[nn.Module] = nn.ReLU,
        observation_key: NestedKey = "observation",
        goal_key: NestedKey = "desired_goal",
        subgoal_key: NestedKey = "subgoal",
    ) -> None:
        low, high = resolve_box(low=subgoal_low, high=subgoal_high, dim=goal_dim, name="subgoal")
        self._init_net(
            observation_dim,
            goal_dim,
            low,
            high,
            goal_indices,
            relative_goal,
            num_cells,
            activation_class,
            observation_key,
            goal_key,
            subgoal_key,
        )
