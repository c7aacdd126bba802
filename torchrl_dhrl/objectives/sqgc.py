"""SQGCLoss: the low-level loss of DHRL with Separate Q-networks for Graph and Critic."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torchrl.data import TensorSpec

from torchrl_dhrl.checks import checked, flag, number

from ._goal_td3 import LOSS_CHECKS, _CriticGroup, _GoalConditionedTD3Base


class SQGCLoss(_GoalConditionedTD3Base):
    r"""The low-level TD3 loss of DHRL with Separate Q-networks for Graph and Critic (SQGC, Sec. 4.2).

    Two twin critics share one actor ``pi_lo(a | s, g)``:

    * the **policy critics** ``Q_critic`` train the actor; they learn from the *policy batch*,
      whose goals are relabelled with probability 0.8 (the rest keep the waypoint actually
      chased, so failures are seen);
    * the **graph critics** ``Q_graph`` give the temporal distances of the graph (Eq. (1),
      :class:`~torchrl_dhrl.planner.GoalDistance`); they learn from the *graph batch*, whose
      goals are all relabelled to future achieved goals, so failures never inflate distances.

    Each pair has target networks (update them with
    :class:`~torchrl.objectives.SoftUpdate`, reference ``eps=0.995`` every 10 updates). For
    each pair, with target actor ``pi'`` and target critics ``Q'``:

    .. math::

        y = \mathrm{clamp}\big(r + \gamma \min_k Q'_k(s', \mathrm{clip}(\pi'(s', g) + \epsilon) \mid g)\big),
        \quad \epsilon \sim \mathcal{N}(0, \sigma^2)

    clamped to ``[-clip_return, 0]`` for the policy critics and to ``<= 0`` for the graph
    critics (reference). Each member regresses ``y`` (summed over members, mean over
    samples). The actor loss is ``-Q_critic,1(s, pi(s, g) | g) + action_l2 * mean((a / action_max)^2)``
    on the policy batch, with the critic parameters detached.

    **TD3's delayed actor** is the training loop's schedule, not the loss's: :meth:`forward`
    computes every term on every call (as :class:`~torchrl.objectives.TD3Loss`) and keeps no
    count; ``loss_terms(batch, update_actor=False)`` skips the actor term.
    :class:`~torchrl_dhrl.training.LossUpdater` calls it so (``actor_update_interval``, reference 2).

    **No terminal states.** DHRL episodes only truncate, and the reference bootstraps
    through every transition, ignoring ``done``; so does this loss by default.
    ``use_terminated=True`` masks the bootstrap with ``("next", "terminated")``.

    **Expected batch layout** (all keys configurable with :meth:`set_keys`): one batch of
    transitions carrying *two* relabelled goals, as written by the relabelling transform::

        "observation"                 [B, obs_dim]
        "action"                      [B, action_dim]
        "goal"                        [B, goal_dim]   policy-batch goal (80% relabelled)
        "graph_goal"                  [B, goal_dim]   graph-batch goal (100% relabelled)
        ("next", "observation")       [B, obs_dim]
        ("next", "reward")            [B, 1]          r(ag_{t+1}, goal)
        ("next", "graph_reward")      [B, 1]          r(ag_{t+1}, graph_goal)
        ("next", "terminated")        [B, 1]          only read with use_terminated=True

    Any leading batch shape is accepted (it is flattened).

    **Critic contract.** Each critic is a :class:`~tensordict.nn.TensorDictModule` reading
    ``(observation, goal, action)`` from its three ``in_keys``, in that order (their names are the
    critic's own: the loss writes the batch's state, the pair's goal -- ``goal`` for the policy
    critics, ``graph_goal`` for the graph critics -- and the action under them), and writing a
    **Q value** (the return of the -1/0 rewards, in ``(-1/(1-gamma), 0]`` when learnt; Eq. (1) turns
    it into a distance) at ``tensor_keys.state_action_value``. The twin is either

    * inside the critic: a :class:`~torchrl_dhrl.modules.GoalConditionedCritic` (stacked-weight
      members, output ``[*B, num_nets]``, its distance parameterisation outputs Q as well). Without
      hooks it is evaluated on the tensors directly (the fast path: no TensorDict per call, and
      the four critics can run as one stacked ensemble, ``fuse_critics``); or
    * made by the loss: any other critic, e.g.
      ``ValueOperator(MLP(out_features=1), in_keys=["observation", "goal", "action"])``, is one
      member writing ``[*B, 1]``; the loss stacks ``num_qvalue_nets`` copies of its parameters
      (``convert_to_functional(..., expand_dim=num_qvalue_nets)``, each copy redrawn as in
      :class:`~torchrl.objectives.TD3Loss`; the critic module itself is not trained) and evaluates
      them with :func:`torch.vmap`. The action box then comes from ``action_spec`` or the actor's
      spec. This path is slower (a TensorDict and a vmap per call, no fusion).

    **Devices.** Everything runs where the loss's parameters are; ``loss.to(device)`` moves
    them (they are the networks' own parameters) and the buffers the loss swaps into the
    networks. As usual in TorchRL, build the acting networks on their device before the loss.

    Args:
        actor_network (TensorDictModule): the deterministic low-level actor reading
            ``(observation, goal)`` in the order of its ``in_keys`` and writing the action
            first (e.g. :class:`~torchrl_dhrl.modules.LowLevelActor`). Its parameters are
            shared, not copied: the acting policy follows training.
        policy_critic (TensorDictModule): the policy critic twin (see the critic contract).
        graph_critic (TensorDictModule): the graph critic twin (same action box and gamma).

    Keyword Args:
        gamma (float, optional): the discount. A ``GoalConditionedCritic`` owns its gamma (the
            distance parameterisation needs it): it is checked against the critics'. Defaults to the
            critics', or ``0.99`` when no critic holds one.
        num_qvalue_nets (int, optional): members stacked from a single-member critic. Defaults to
            ``2``; for a ``GoalConditionedCritic`` it must be ``None`` or its ``num_nets``.
        action_spec (TensorSpec, optional): the action box (a :class:`~torchrl.data.Bounded`
            spec, or a composite holding one at the action key), for the target clamp and the action
            penalty. Defaults to the critics' box, else the actor's spec; all given boxes must agree.
        clip_return (float, optional): lower clamp ``-clip_return`` of the policy critics'
            targets (reference 80); ``None`` for none. Defaults to ``80.0``.
        graph_clip_return (float, optional): lower clamp of the graph critics' targets;
            ``None`` (reference) for none.
        action_l2 (float): weight of the action penalty. Defaults to ``0.01``.
        target_noise_std (float): std of the target-policy noise, in action units
            (reference 0.05, unclipped). Defaults to ``0.05``.
        target_noise_clip (float, optional): clip of that noise; ``None`` (default) for none.
        target_action_clamp (bool): clamp the noisy target action to the action box. Defaults
            to ``False``, as the reference (whose target actions may leave the box by the noise).
        use_terminated (bool): mask the bootstrap with ``terminated``. Defaults to ``False``.
        sqgc (bool): ``False`` gives the paper's "without SQGC" ablation: the graph critics
            are trained on the policy batch (goal/reward keys) instead of the graph batch.
            Defaults to ``True``.
        loss_function (str): ``"l2"`` (default, reference MSE), ``"l1"`` or ``"smooth_l1"``.
        fuse_critics (bool, optional): evaluate the four critics as one stacked ensemble
            (weights concatenated along the member dim, one batched matmul per layer) when
            their architectures match; ``False`` evaluates the two twins separately (each
            still one stacked module). ``None`` (default) fuses off the CPU only: on a CPU
            the fused form measured a few percent slower (``benchmarks/bench_losses.py``).
            Only ``GoalConditionedCritic`` critics on the fast path fuse.

    :meth:`value_loss` and :meth:`actor_loss` are also exposed (like
    :class:`~torchrl.objectives.TD3Loss`) for loops that step the critics before computing the
    actor loss.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.objectives import SoftUpdate
        >>> from torchrl_dhrl.modules import GoalConditionedCritic, LowLevelActor
        >>> obs_dim, goal_dim, act_dim, B = 6, 2, 3, 8
        >>> actor = LowLevelActor(obs_dim, goal_dim, action_max=1.0, action_dim=act_dim, goal_indices=[0, 1],
        ...     num_cells=(32,))
        >>> make_critic = lambda: GoalConditionedCritic(obs_dim, goal_dim, action_max=1.0,
        ...     action_dim=act_dim, num_cells=(32,))
        >>> loss = SQGCLoss(actor, make_critic(), make_critic())
        >>> updater = SoftUpdate(loss, eps=0.995)
        >>> data = TensorDict({
        ...     "observation": torch.randn(B, obs_dim), "action": torch.rand(B, act_dim) * 2 - 1,
        ...     "goal": torch.randn(B, goal_dim), "graph_goal": torch.randn(B, goal_dim),
        ...     ("next", "observation"): torch.randn(B, obs_dim),
        ...     ("next", "reward"): -torch.ones(B, 1), ("next", "graph_reward"): -torch.ones(B, 1),
        ... }, [B])
        >>> out = loss(data)
        >>> sorted(k for k in out.keys() if k.startswith("loss_"))
        ['loss_actor', 'loss_graph_qvalue', 'loss_policy_qvalue']
        >>> sum(v for k, v in out.items() if k.startswith("loss_")).backward()

        Any TensorDictModule critic works; a plain TorchRL one is one member, the loss stacks the twin:

        >>> from torchrl.modules import MLP, ValueOperator
        >>> make_plain = lambda: ValueOperator(MLP(in_features=obs_dim + goal_dim + act_dim, out_features=1,
        ...     num_cells=[32]), in_keys=["observation", "waypoint", "action"])
        >>> plain = SQGCLoss(actor, make_plain(), make_plain())
        >>> plain.graph_critic_params.batch_size  # the twin: two stacked parameter sets
        torch.Size([2])
        >>> bool(plain.loss_terms(data, update_actor=False)["loss_actor"] == 0)  # a step without the actor
        True
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys of :class:`SQGCLoss` (set with ``set_keys``).

        Attributes:
            observation (NestedKey): the state; also read at ``("next", observation)``.
                Defaults to ``"observation"``.
            action (NestedKey): the action taken. Defaults to ``"action"``.
            goal (NestedKey): the policy-batch goal (80% relabelled). Defaults to ``"goal"``.
            reward (NestedKey): the policy-batch reward, read at ``("next", reward)``.
                Defaults to ``"reward"``.
            graph_goal (NestedKey): the graph-batch goal (100% relabelled).
                Defaults to ``"graph_goal"``.
            graph_reward (NestedKey): the graph-batch reward, read at ``("next", graph_reward)``.
                Defaults to ``"graph_reward"``.
            terminated (NestedKey): read at ``("next", terminated)`` with ``use_terminated``.
                Defaults to ``"terminated"``.
            state_action_value (NestedKey): where the critics write their value (read from the
                critics' output; the fast path evaluates the network directly). Defaults to
                ``"state_action_value"``.
        """

        observation: NestedKey = "observation"
        action: NestedKey = "action"
        goal: NestedKey = "goal"
        reward: NestedKey = "reward"
        graph_goal: NestedKey = "graph_goal"
        graph_reward: NestedKey = "graph_reward"
        terminated: NestedKey = "terminated"
        state_action_value: NestedKey = "state_action_value"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    default_value_estimator = None
    out_keys = [
        "loss_policy_qvalue",
        "loss_graph_qvalue",
        "loss_actor",
        "actor_updated",
        "policy_q",
        "policy_target",
        "policy_distance",
        "graph_q",
        "graph_target",
        "graph_distance",
    ]

    policy_critic: TensorDictModule
    policy_critic_params: TensorDictParams
    target_policy_critic_params: TensorDictParams
    graph_critic: TensorDictModule
    graph_critic_params: TensorDictParams
    target_graph_critic_params: TensorDictParams

    @checked(
        **LOSS_CHECKS,
        graph_clip_return=number(0.0, low_open=True, optional=True),
        sqgc=flag(),
        fuse_critics=flag(optional=True),
    )
    def __init__(
        self,
        actor_network: TensorDictModule,
        policy_critic: TensorDictModule,
        graph_critic: TensorDictModule,
        *,
        gamma: float | None = None,
        num_qvalue_nets: int | None = None,
        action_spec: TensorSpec | None = None,
        clip_return: float | None = 80.0,
        graph_clip_return: float | None = None,
        action_l2: float = 0.01,
        target_noise_std: float = 0.05,
        target_noise_clip: float | None = None,
        target_action_clamp: bool = False,
        use_terminated: bool = False,
        sqgc: bool = True,
        loss_function: str = "l2",
        fuse_critics: bool | None = None,
    ) -> None:
        super().__init__()
        if policy_critic is graph_critic:
            raise ValueError("`policy_critic` and `graph_critic` must be two separate modules.")
        self._init_common(
            actor_network,
            {"policy_critic": policy_critic, "graph_critic": graph_critic},
            gamma=gamma,
            num_qvalue_nets=num_qvalue_nets,
            action_spec=action_spec,
            action_l2=action_l2,
            target_noise_std=target_noise_std,
            target_noise_clip=target_noise_clip,
            target_action_clamp=target_action_clamp,
            use_terminated=use_terminated,
            loss_function=loss_function,
            fuse_critics=fuse_critics,
        )
        self.clip_return = clip_return
        self.graph_clip_return = graph_clip_return
        self.sqgc = sqgc

    def _compute_in_keys(self) -> list:
        k = self.tensor_keys
        keys = [k.observation, k.action, k.goal, ("next", k.observation), ("next", k.reward)]
        if self.sqgc:
            keys += [k.graph_goal, ("next", k.graph_reward)]
        if self.use_terminated:
            keys.append(("next", k.terminated))
        return keys

    def _unpack(self, tensordict: TensorDictBase) -> dict:
        k = self.tensor_keys
        td = tensordict.reshape(-1) if tensordict.ndim != 1 else tensordict
        n = td.shape[0]
        data = {
            "observation": self._get(td, k.observation, "the state"),
            "action": self._get(td, k.action, "the action taken"),
            "goal": self._get(td, k.goal, "the policy-batch goal"),
            "next_observation": self._get(td, ("next", k.observation), "the next state"),
            "reward": self._as_flat(
                self._get(td, ("next", k.reward), "the policy-batch reward"), n, "reward"
            ),
        }
        if self.sqgc:
            data["graph_goal"] = self._get(td, k.graph_goal, "the graph-batch goal")
            data["graph_reward"] = self._as_flat(
                self._get(td, ("next", k.graph_reward), "the graph-batch reward"), n, "graph reward"
            )
        else:
            data["graph_goal"], data["graph_reward"] = data["goal"], data["reward"]
        data["not_terminal"] = None
        if self.use_terminated:
            terminated = self._get(td, ("next", k.terminated), "the terminated flag")
            data["not_terminal"] = 1.0 - self._as_flat(terminated, n, "terminated").to(data["reward"].dtype)
        return data

    def value_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """The TD losses of both critic pairs: ``(loss_policy + loss_graph, metadata)``.

        ``metadata`` holds ``loss_policy_qvalue``, ``loss_graph_qvalue`` and the diagnostics
        (mean Q, mean target and mean Eq. (1) distance of both pairs).
        """
        d = self._unpack(tensordict)
        groups = [
            _CriticGroup("policy_critic", d["goal"], d["reward"], _neg(self.clip_return), 0.0),
            _CriticGroup(
                "graph_critic", d["graph_goal"], d["graph_reward"], _neg(self.graph_clip_return), 0.0
            ),
        ]
        (q_policy, y_policy), (q_graph, y_graph) = self._critic_terms(
            d["observation"], d["action"], d["next_observation"], d["not_terminal"], groups
        )
        loss_policy = self._value_loss_of(q_policy, y_policy)
        loss_graph = self._value_loss_of(q_graph, y_graph)
        metadata = {
            "loss_policy_qvalue": loss_policy,
            "loss_graph_qvalue": loss_graph,
            **self._diagnostics("policy", q_policy, y_policy),
            **self._diagnostics("graph", q_graph, y_graph),
        }
        return loss_policy + loss_graph, metadata

    def actor_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """The actor loss on the policy batch against the first policy critic: ``(loss, metadata)``."""
        k = self.tensor_keys
        td = tensordict.reshape(-1) if tensordict.ndim != 1 else tensordict
        observation = self._get(td, k.observation, "the state")
        goal = self._get(td, k.goal, "the policy-batch goal")
        return self._actor_terms("policy_critic", observation, goal)

    def _value_entries(self, tensordict: TensorDictBase) -> dict:
        return self.value_loss(tensordict)[1]  # the metadata holds both pairs' losses


def _neg(value: float | None) -> float | None:
    return None if value is None else -float(value)
