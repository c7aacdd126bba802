"""HighLevelLoss: the TD3-style loss of the DHRL high-level policy pi_hi(sg | s, g)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torchrl.data import TensorSpec

from torchrl_dhrl.checks import checked

from ._goal_td3 import LOSS_CHECKS, _CriticGroup, _GoalConditionedTD3Base


class HighLevelLoss(_GoalConditionedTD3Base):
    r"""TD3-style loss of the high-level policy, with the conventions of :class:`SQGCLoss`.

    One high-level transition spans ``c_h`` env steps: ``(s_t, g, sg_t, r_t, s_{t+c_h})``.
    The "action" is the subgoal; the critic sees it scaled to ``[-1, 1]`` from the subgoal
    box (a :class:`~torchrl_dhrl.modules.GoalConditionedCritic` built with
    ``action_low``/``action_high`` = the box). Targets are

    .. math::

        y = \mathrm{clamp}\big(r + \gamma \min_k Q'_k(s', \mathrm{clip}(\pi'(s', g) + \epsilon) \mid g),
        -\mathrm{clip\_return}, 0\big)

    and the actor loss is ``-Q_1(s, pi(s, g) | g) + action_l2 * mean(scaled_subgoal^2)``. As at the
    low level the bootstrap ignores ``done`` (episodes only truncate) unless ``use_terminated=True``,
    and the delayed actor is the training loop's schedule (:meth:`forward` computes every term;
    ``loss_terms(batch, update_actor=False)`` skips the actor's, as
    :class:`~torchrl_dhrl.training.LossUpdater` does on its off steps).
    Hindsight relabelling of goals and subgoals, subgoal testing and the gradual penalty are
    the replay buffer's business: this loss reads the rewards it is given.

    **Expected batch layout** (keys configurable with :meth:`set_keys`)::

        "observation"              [B, obs_dim]     s_t
        "desired_goal"             [B, goal_dim]    g (relabelled)
        "subgoal"                  [B, goal_dim]    sg_t (issued, or hindsight achieved goal)
        ("next", "observation")    [B, obs_dim]     s_{t+c_h}
        ("next", "reward")         [B, 1]
        ("next", "terminated")     [B, 1]           only with use_terminated=True

    **Critic contract** (as :class:`SQGCLoss`): a TensorDictModule reading
    ``(observation, goal, subgoal)`` from its three ``in_keys`` in that order and writing a Q value
    at ``tensor_keys.state_action_value``; the twin is a
    :class:`~torchrl_dhrl.modules.GoalConditionedCritic`'s own (fast path), or ``num_qvalue_nets``
    stacked copies of a single-member critic's parameters (vmap; the subgoal box then comes from
    ``action_spec`` or the actor's spec).

    Args:
        actor_network (TensorDictModule): the deterministic high-level actor reading
            ``(observation, goal)`` (e.g. :class:`~torchrl_dhrl.modules.HighLevelActor`, or
            ``HighLevelPolicy.actor``).
        critic (TensorDictModule): the high-level critic twin (see the critic contract).

    Keyword Args:
        gamma (float, optional): checked against a ``GoalConditionedCritic``'s. Defaults to the
            critic's, or ``0.99`` (the reference's) for other critics.
        num_qvalue_nets (int, optional): members stacked from a single-member critic. Defaults to ``2``.
        action_spec (TensorSpec, optional): the subgoal box, when neither the critic nor the actor
            holds one.
        clip_return (float, optional): lower target clamp ``-clip_return``. Defaults to ``80.0``.
        action_l2 (float): weight of the scaled-subgoal penalty. Defaults to ``0.0`` (the reference computes the
            penalty but never adds it to the loss).
        target_noise_std (float): std of the target-policy noise in goal units.
            Defaults to ``0.05``.
        target_noise_clip (float, optional): clip of that noise. Defaults to ``None``.
        target_action_clamp (bool): clamp the noisy target action to the action box. Defaults
            to ``False``, as the reference (whose target actions may leave the box by the noise).
        use_terminated (bool): mask the bootstrap with ``terminated``. Defaults to ``False``.
        loss_function (str): ``"l2"`` (default), ``"l1"`` or ``"smooth_l1"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.objectives import SoftUpdate
        >>> from torchrl_dhrl.modules import GoalConditionedCritic, HighLevelActor
        >>> low, high = [-4.0, -4.0], [20.0, 20.0]
        >>> actor = HighLevelActor(6, 2, low, high, num_cells=(32,))
        >>> critic = GoalConditionedCritic(6, 2, action_low=low, action_high=high, goal_key="desired_goal",
        ...     action_key="subgoal", relative_goal=False, num_cells=(32,))
        >>> loss = HighLevelLoss(actor, critic)
        >>> updater = SoftUpdate(loss, eps=0.995)
        >>> B = 8
        >>> data = TensorDict({"observation": torch.randn(B, 6), "desired_goal": torch.randn(B, 2),
        ...     "subgoal": torch.rand(B, 2) * 24 - 4, ("next", "observation"): torch.randn(B, 6),
        ...     ("next", "reward"): -torch.ones(B, 1)}, [B])
        >>> out = loss(data)
        >>> sorted(k for k in out.keys() if k.startswith("loss_"))
        ['loss_actor', 'loss_qvalue']
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys of :class:`HighLevelLoss` (set with ``set_keys``).

        Attributes:
            observation (NestedKey): the state; also read at ``("next", observation)``.
                Defaults to ``"observation"``.
            goal (NestedKey): the (relabelled) final goal. Defaults to ``"desired_goal"``.
            action (NestedKey): the subgoal. Defaults to ``"subgoal"``.
            reward (NestedKey): read at ``("next", reward)``. Defaults to ``"reward"``.
            terminated (NestedKey): read at ``("next", terminated)`` with ``use_terminated``.
                Defaults to ``"terminated"``.
            state_action_value (NestedKey): where the critic writes its value. Defaults to
                ``"state_action_value"``.
        """

        observation: NestedKey = "observation"
        goal: NestedKey = "desired_goal"
        action: NestedKey = "subgoal"
        reward: NestedKey = "reward"
        terminated: NestedKey = "terminated"
        state_action_value: NestedKey = "state_action_value"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    default_value_estimator = None
    out_keys = ["loss_qvalue", "loss_actor", "actor_updated", "q", "target", "distance"]

    critic_network: TensorDictModule
    critic_network_params: TensorDictParams
    target_critic_network_params: TensorDictParams

    @checked(**LOSS_CHECKS)
    def __init__(
        self,
        actor_network: TensorDictModule,
        critic: TensorDictModule,
        *,
        gamma: float | None = None,
        num_qvalue_nets: int | None = None,
        action_spec: TensorSpec | None = None,
        clip_return: float | None = 80.0,
        action_l2: float = 0.0,
        target_noise_std: float = 0.05,
        target_noise_clip: float | None = None,
        target_action_clamp: bool = False,
        use_terminated: bool = False,
        loss_function: str = "l2",
    ) -> None:
        super().__init__()
        self._init_common(
            actor_network,
            {"critic_network": critic},
            gamma=gamma,
            num_qvalue_nets=num_qvalue_nets,
            action_spec=action_spec,
            action_l2=action_l2,
            target_noise_std=target_noise_std,
            target_noise_clip=target_noise_clip,
            target_action_clamp=target_action_clamp,
            use_terminated=use_terminated,
            loss_function=loss_function,
            fuse_critics=False,
        )
        self.clip_return = clip_return

    def _compute_in_keys(self) -> list:
        k = self.tensor_keys
        keys = [k.observation, k.goal, k.action, ("next", k.observation), ("next", k.reward)]
        if self.use_terminated:
            keys.append(("next", k.terminated))
        return keys

    def value_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """The critic TD loss: ``(loss, metadata)`` with mean Q, target and Eq. (1) distance."""
        k = self.tensor_keys
        td = tensordict.reshape(-1) if tensordict.ndim != 1 else tensordict
        n = td.shape[0]
        reward = self._as_flat(self._get(td, ("next", k.reward), "the reward"), n, "reward")
        not_terminal = None
        if self.use_terminated:
            terminated = self._get(td, ("next", k.terminated), "the terminated flag")
            not_terminal = 1.0 - self._as_flat(terminated, n, "terminated").to(reward.dtype)
        group = _CriticGroup(
            "critic_network",
            self._get(td, k.goal, "the goal"),
            reward,
            None if self.clip_return is None else -float(self.clip_return),
            0.0,
        )
        ((q, y),) = self._critic_terms(
            self._get(td, k.observation, "the state"),
            self._get(td, k.action, "the subgoal"),
            self._get(td, ("next", k.observation), "the state c_h steps later"),
            not_terminal,
            [group],
        )
        return self._value_loss_of(q, y), self._diagnostics(None, q, y)

    def actor_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """The actor loss against the first critic member (critic detached): ``(loss, metadata)``."""
        k = self.tensor_keys
        td = tensordict.reshape(-1) if tensordict.ndim != 1 else tensordict
        return self._actor_terms(
            "critic_network", self._get(td, k.observation, "the state"), self._get(td, k.goal, "the goal")
        )

    def _value_entries(self, tensordict: TensorDictBase) -> dict:
        loss_qvalue, metadata = self.value_loss(tensordict)
        return {"loss_qvalue": loss_qvalue, **metadata}
