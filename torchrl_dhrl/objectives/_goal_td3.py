"""Shared machinery of the DHRL TD3-style losses (goal-conditioned actor, stacked-weight twin critics)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torchrl.data import TensorSpec
from torchrl.envs.utils import set_exploration_type
from torchrl.objectives import LossModule
from torchrl.objectives.utils import distance_loss

from torchrl_dhrl.checks import choice, flag, integer, number
from torchrl_dhrl.modules._utils import box_loc_scale, check_positional_keys, resolve_box, run_positional
from torchrl_dhrl.modules.critics import (
    DEFAULT_GAMMA,
    GoalConditionedCritic,
    check_critic,
    critic_values,
    q_to_distance,
    runs_on_tensors,
    stacked_critic_values,
)

LOSS_FUNCTIONS = ("l2", "l1", "smooth_l1")
#: The checks of the arguments both goal-conditioned TD3 losses take (:func:`~torchrl_dhrl.checks.checked`).
LOSS_CHECKS = {
    "gamma": number(0.0, 1.0, low_open=True, high_open=True, optional=True),
    "num_qvalue_nets": integer(1, optional=True),
    "clip_return": number(0.0, low_open=True, optional=True),
    "action_l2": number(0.0),
    "target_noise_std": number(0.0),
    "target_noise_clip": number(0.0, low_open=True, optional=True),
    "target_action_clamp": flag(),
    "use_terminated": flag(),
    "loss_function": choice(LOSS_FUNCTIONS),
}
#: Members stacked from a single-member critic when ``num_qvalue_nets`` is not given (the TD3 twin).
DEFAULT_NUM_QVALUE_NETS = 2


@dataclass
class _CriticGroup:
    """One critic pair and the data it is trained on (a goal, a reward and the target clamp)."""

    name: str
    goal: torch.Tensor
    reward: torch.Tensor
    target_min: float | None
    target_max: float | None


def _ensemble_keys(params: TensorDictBase) -> list:
    return [
        key for key in params.keys(True, True) if "ensemble" in (key if isinstance(key, tuple) else (key,))
    ]


def _same_architecture(a: GoalConditionedCritic, b: GoalConditionedCritic) -> bool:
    """Whether two critics can be evaluated as one stacked ensemble (same inputs, widths and maths)."""
    na, nb = a.module, b.module
    if type(na) is not type(nb) or type(na.ensemble.activation) is not type(nb.ensemble.activation):
        return False
    scalars = (
        "observation_dim",
        "goal_dim",
        "action_dim",
        "parameterization",
        "distance_output",
        "gamma",
        "relative_goal",
    )
    if any(getattr(na, s) != getattr(nb, s) for s in scalars):
        return False
    for buf in ("goal_indices", "action_loc", "action_scale"):
        ba, bb = getattr(na, buf, None), getattr(nb, buf, None)
        if (ba is None) != (bb is None) or (ba is not None and not torch.equal(ba, bb)):
            return False
    shapes_a = [p.shape[1:] for p in na.ensemble.parameters()]
    shapes_b = [p.shape[1:] for p in nb.ensemble.parameters()]
    return shapes_a == shapes_b


def _actor_box(actor: TensorDictModule) -> tuple[torch.Tensor, torch.Tensor] | None:
    """``(low, high)`` of the actor's bounded output spec, or ``None`` when it has none."""
    spec = getattr(actor, "spec", None)
    if spec is None:
        return None
    try:
        entry = spec[actor.out_keys[0]]
    except (KeyError, TypeError):
        return None
    space = getattr(entry, "space", None)
    if space is None or not hasattr(space, "low"):
        return None
    return space.low, space.high


def _drop_legacy_update_count(module, state_dict, prefix, *args) -> None:
    """Checkpoints written before the delayed-actor count moved to ``LossUpdater`` hold ``update_count``."""
    state_dict.pop(f"{prefix}update_count", None)


class _GoalConditionedTD3Base(LossModule):
    """Common parts of :class:`SQGCLoss` and :class:`HighLevelLoss`.

    Subclasses register their critics with :meth:`_init_common` and describe, per call, which
    critic is trained on which goal/reward (:class:`_CriticGroup`).

    **Critics.** Each critic is a TensorDictModule reading ``(observation, goal, action)`` from its
    three ``in_keys`` (in that order, any names) and writing its value at
    ``tensor_keys.state_action_value``; the loss writes its batch's state, the critic's goal and the
    action under those keys and reads the value back. Two kinds:

    - a :class:`~torchrl_dhrl.modules.GoalConditionedCritic` holds its members (the stacked-weight
      twin, output ``[*B, num_nets]``); without hooks it is evaluated on the tensors directly (the
      fast path, optionally fused across critics);
    - any other critic is one member (output ``[*B, 1]``): the loss stacks ``num_qvalue_nets``
      copies of its parameters (``convert_to_functional(..., expand_dim=num_qvalue_nets)``, fresh
      draws as in :class:`~torchrl.objectives.TD3Loss`) and evaluates them with :func:`torch.vmap`.

    The loss keeps no step count: which calls train the actor (TD3's delay) is the caller's
    decision (:meth:`loss_terms`; :class:`~torchrl_dhrl.training.LossUpdater` owns the schedule).
    """

    actor_network: TensorDictModule
    actor_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams

    def _init_common(
        self,
        actor_network: TensorDictModule,
        critics: dict[str, TensorDictModule],
        *,
        gamma: float | None,
        num_qvalue_nets: int | None,
        action_spec: TensorSpec | None,
        action_l2: float,
        target_noise_std: float,
        target_noise_clip: float | None,
        target_action_clamp: bool,
        use_terminated: bool,
        loss_function: str,
        fuse_critics: bool | None,
    ) -> None:
        check_positional_keys(actor_network, 2, "actor_network")
        for name, critic in critics.items():
            check_critic(critic, name)
        own = {name: c for name, c in critics.items() if isinstance(c, GoalConditionedCritic)}
        for name, critic in own.items():
            if num_qvalue_nets is not None and num_qvalue_nets != critic.num_nets:
                raise ValueError(
                    f"`num_qvalue_nets`={num_qvalue_nets} differs from `{name}`'s {critic.num_nets} members: a "
                    "GoalConditionedCritic holds its twin (set `num_nets` when building it)."
                )
        gammas = {critic.gamma for critic in own.values()}
        if len(gammas) > 1:
            raise ValueError(f"All critics must share one gamma; got {sorted(gammas)}.")
        critic_gamma = gammas.pop() if gammas else None
        if gamma is not None and critic_gamma is not None and abs(float(gamma) - critic_gamma) > 1e-12:
            raise ValueError(
                f"`gamma`={gamma} differs from the critics' gamma={critic_gamma}: the distance "
                "parameterisation and Eq. (1) need the same discount. Build the critics with that gamma."
            )

        action_loc, action_scale = self._action_box(actor_network, own, action_spec)
        self.convert_to_functional(actor_network, "actor_network", create_target_params=True)
        members = DEFAULT_NUM_QVALUE_NETS if num_qvalue_nets is None else num_qvalue_nets
        for name, critic in critics.items():
            expand = None if name in own else members  # a single-member critic: stack its parameters
            self.convert_to_functional(critic, name, expand_dim=expand, create_target_params=True)
        self.register_buffer("action_loc", action_loc.detach().clone())
        self.register_buffer("action_scale", action_scale.detach().clone())
        self.register_load_state_dict_pre_hook(_drop_legacy_update_count)
        if critic_gamma is None:  # no critic holds a discount: the loss's (Eq. (1) needs it too)
            critic_gamma = DEFAULT_GAMMA if gamma is None else float(gamma)
            if not 0.0 < critic_gamma < 1.0:
                raise ValueError(f"`gamma` must be in (0, 1), got {gamma}.")
        self.gamma = critic_gamma
        self.action_l2 = float(action_l2)
        self.target_noise_std = float(target_noise_std)
        self.target_noise_clip = target_noise_clip
        self.target_action_clamp = bool(target_action_clamp)
        self.use_terminated = use_terminated
        self.loss_function = loss_function
        names = list(critics)
        self._critic_names = names
        self._stacked = {name: name not in own for name in names}
        self._ensemble_keys = {
            name: _ensemble_keys(getattr(self, f"{name}_params")) for name in names if name in own
        }
        fast = [runs_on_tensors(c) for c in critics.values()]
        first = next(iter(critics.values()))
        self._fusable = (
            len(critics) > 1 and all(fast) and all(_same_architecture(first, c) for c in critics.values())
        )
        self.fuse_critics = fuse_critics

    def _action_box(
        self,
        actor: TensorDictModule,
        own: dict[str, GoalConditionedCritic],
        action_spec: TensorSpec | None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The action box ``(loc, scale)``: from the critics that hold one, else ``action_spec``, else the actor's spec.

        All the boxes given must agree (the critics scale their action input with theirs, the loss clamps
        and penalises with it).
        """
        boxes = [
            (f"`{name}`'s action box", c.module.action_loc, c.module.action_scale) for name, c in own.items()
        ]
        if action_spec is not None:
            low, high = resolve_box(spec=action_spec, key=self.tensor_keys.action)
            boxes.append(("`action_spec`", *box_loc_scale(low, high)))
        actor_box = _actor_box(actor)
        if actor_box is not None:
            boxes.append(("the actor's box", *box_loc_scale(*actor_box)))
        if not boxes:
            raise ValueError(
                f"{type(self).__name__} needs the action box (target clamp, action penalty): pass "
                "`action_spec` (a Bounded spec), an actor with a bounded spec, or a GoalConditionedCritic."
            )
        name, loc, scale = boxes[0]
        for other, other_loc, other_scale in boxes[1:]:
            if not (
                torch.allclose(other_loc.to(loc), loc, atol=1e-5)
                and torch.allclose(other_scale.to(scale), scale, atol=1e-5)
            ):
                raise ValueError(
                    f"{other[0].upper()}{other[1:]} [{(other_loc - other_scale).tolist()}, "
                    f"{(other_loc + other_scale).tolist()}] differs from {name} [{(loc - scale).tolist()}, "
                    f"{(loc + scale).tolist()}]: build both from the same bounds."
                )
        return loc, scale

    # ------------------------------------------------------------------ keys
    def _forward_value_estimator_keys(self, **kwargs) -> None:
        self._in_keys = None

    @property
    def in_keys(self) -> list:
        if getattr(self, "_in_keys", None) is None:
            self._in_keys = self._compute_in_keys()
        return self._in_keys

    @in_keys.setter
    def in_keys(self, value) -> None:
        self._in_keys = value

    def _compute_in_keys(self) -> list:
        raise NotImplementedError

    def make_value_estimator(self, value_type=None, **hyperparams):
        raise NotImplementedError(
            f"{type(self).__name__} computes its one-step TD3 targets itself; the discount is the critics' "
            "gamma (set it when building the critics)."
        )

    @staticmethod
    def _get(tensordict: TensorDictBase, key: NestedKey, what: str) -> torch.Tensor:
        value = tensordict.get(key, None)
        if value is None:
            raise KeyError(
                f"The loss input has no {key!r} entry ({what}). Map your layout with `loss.set_keys(...)`; "
                f"present keys: {list(tensordict.keys(True, True))}."
            )
        return value

    @staticmethod
    def _as_flat(value: torch.Tensor, n: int, name: str) -> torch.Tensor:
        if value.numel() != n:
            raise ValueError(f"{name} must have one entry per sample ({n}), got shape {tuple(value.shape)}.")
        return value.reshape(n)

    @property
    def fusing(self) -> bool:
        """Whether the critics run as one stacked ensemble on this call.

        Only ``GoalConditionedCritic`` critics on the fast path (no hooks) with the same architecture
        can be fused. ``fuse_critics=None`` (auto) fuses off the CPU only: on CPU the fused four-member
        ensemble measured a few percent slower (larger activations fall out of cache, and the
        computation is matmul-bound anyway); on accelerators one launch per layer instead of
        two is the point.
        """
        if not self._fusable or self.fuse_critics is False:
            return False
        return bool(self.fuse_critics) or self.action_loc.device.type != "cpu"

    # ------------------------------------------------------------- networks
    def _actor(self, params: TensorDictBase, observation: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        with params.to_module(self.actor_network), set_exploration_type(self.deterministic_sampling_mode):
            return run_positional(self.actor_network, observation, goal)

    def _target_action(self, next_observation: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        """``pi'(s', g) + noise`` (no gradient), clamped to the action box if ``target_action_clamp``."""
        action = self._actor(self.target_actor_network_params, next_observation, goal)
        if self.target_noise_std > 0:
            noise = torch.randn_like(action) * self.target_noise_std
            if self.target_noise_clip is not None:
                noise = noise.clamp(-self.target_noise_clip, self.target_noise_clip)
            action = action + noise
        if not self.target_action_clamp:  # the reference: pi' is inside the box, the noise may leave it
            return action
        low, high = self.action_loc - self.action_scale, self.action_loc + self.action_scale
        return torch.maximum(torch.minimum(action, high), low)

    def _critic_q(
        self,
        name: str,
        params: TensorDictBase,
        observation: torch.Tensor,
        goal: torch.Tensor,
        action: torch.Tensor,
    ) -> torch.Tensor:
        """Q of every member of one critic, with ``params``, on its keys: ``[E, N]``.

        Stacked single-member critics run under :func:`torch.vmap` over their parameters; a
        ``GoalConditionedCritic`` runs once with ``params`` swapped in (on the tensors directly when it
        has no hooks). Everything runs inside ``to_module``, so the critics' buffers follow the loss's
        device.
        """
        module = getattr(self, name)
        value_key = self.tensor_keys.state_action_value
        if self._stacked[name]:
            return stacked_critic_values(
                module, params, observation, goal, action, value_key, randomness=self.vmap_randomness
            )
        with params.to_module(module):
            return critic_values(module, observation, goal, action, value_key)

    def _q_members(
        self,
        names: list[str],
        params: list[TensorDictBase],
        inputs: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]],
    ) -> list[torch.Tensor]:
        """Q of every member of each named critic on its own ``(observation, goal, action)``: ``[E_i, N]`` each.

        When :attr:`fusing`, the ensembles' weights are concatenated along the member dim
        and all critics run as one stacked ensemble (one batched matmul per layer).
        """
        if len(names) > 1 and self.fusing:
            fused = TensorDict()
            head = params[0]
            for key in head.keys(True, True):
                if key in self._ensemble_keys[names[0]]:
                    fused.set(key, torch.cat([p.get(key) for p in params], 0))
                else:
                    fused.set(key, head.get(key))
            sizes = [p.get(self._ensemble_keys[n][0]).shape[0] for n, p in zip(names, params, strict=True)]
            module = getattr(self, names[0])
            with fused.to_module(module):
                net = module.module
                x = torch.cat(
                    [
                        net.features(*inp).expand(size, -1, -1)
                        for inp, size in zip(inputs, sizes, strict=True)
                    ],
                    0,
                )
                q = net.q_from_features(x, per_member=True)
            return list(q.split(sizes, 0))
        return [self._critic_q(n, p, *inp) for n, p, inp in zip(names, params, inputs, strict=True)]

    def _critic_terms(
        self,
        observation: torch.Tensor,
        action: torch.Tensor,
        next_observation: torch.Tensor,
        not_terminal: torch.Tensor | None,
        groups: list[_CriticGroup],
    ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Predicted Q (``[E, N]``) and clamped TD3 targets (``[N]``) for each critic group."""
        names = [g.name for g in groups]
        n = observation.shape[0]
        with torch.no_grad():
            next_obs = next_observation.repeat(len(groups), 1)
            goals = torch.cat([g.goal for g in groups], 0)
            next_actions = self._target_action(next_obs, goals).split(n, 0)
            target_params = [getattr(self, f"target_{name}_params") for name in names]
            next_inputs = [(next_observation, g.goal, a) for g, a in zip(groups, next_actions, strict=True)]
            next_q = self._q_members(names, target_params, next_inputs)
            targets = []
            for g, q_next in zip(groups, next_q, strict=True):
                bootstrap = q_next.min(0).values
                if not_terminal is not None:
                    bootstrap = bootstrap * not_terminal
                target = g.reward + self.gamma * bootstrap
                targets.append(target.clamp(min=g.target_min, max=g.target_max))
        params = [getattr(self, f"{name}_params") for name in names]
        q = self._q_members(names, params, [(observation, g.goal, action) for g in groups])
        return list(zip(q, targets, strict=True))

    def _value_loss_of(self, q: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Sum over members of the mean TD loss of each member."""
        return distance_loss(q, target.expand_as(q), loss_function=self.loss_function).mean(-1).sum(0)

    def _actor_terms(
        self, critic_name: str, observation: torch.Tensor, goal: torch.Tensor
    ) -> tuple[torch.Tensor, dict]:
        """``-Q_1(s, pi(s, g) | g) + action_l2 * mean(scaled_action^2)``, critic parameters detached."""
        action = self._actor(self.actor_network_params, observation, goal)
        params = getattr(self, f"{critic_name}_params")
        if self._stacked[critic_name]:
            first = params.detach()[0]  # the first stacked member
        else:  # the first member of the critic's own ensemble
            first = TensorDict()
            for key in params.keys(True, True):
                value = params.get(key)
                first.set(key, value.detach()[:1] if key in self._ensemble_keys[critic_name] else value)
        module = getattr(self, critic_name)
        with first.to_module(module):
            q1 = critic_values(module, observation, goal, action, self.tensor_keys.state_action_value)[0]
        scaled = (action - self.action_loc) / self.action_scale
        penalty = scaled.pow(2).mean()
        loss = -q1.mean() + self.action_l2 * penalty
        return loss, {"actor_q": q1.detach().mean(), "actor_action_l2": penalty.detach()}

    def _value_entries(self, tensordict: TensorDictBase) -> dict:
        """The critic loss entries (``loss_*``) and diagnostics of :meth:`loss_terms`."""
        raise NotImplementedError

    def loss_terms(self, tensordict: TensorDictBase, update_actor: bool) -> TensorDictBase:
        """:meth:`forward` with the actor term on (``update_actor=True``) or off (a constant 0).

        TD3's delayed actor is the caller's schedule (:class:`~torchrl_dhrl.training.LossUpdater`'s
        ``actor_update_interval``): on steps without an actor update pass ``False``, which skips the
        actor's forward pass and gives ``loss_actor`` no gradient. Free of side effects; creates no
        tensor from host data and reads nothing back, so it can be captured in a CUDA graph (one graph
        per value of ``update_actor``).
        """
        entries = self._value_entries(tensordict)
        device = self.action_loc.device
        loss_actor = self.actor_loss(tensordict)[0] if update_actor else torch.zeros((), device=device)
        return TensorDict(
            {
                **entries,
                "loss_actor": loss_actor,
                "actor_updated": torch.full((), update_actor, dtype=torch.bool, device=device),
            },
            batch_size=[],
        )

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """All loss terms (critic losses, ``loss_actor``) and the diagnostics, as :class:`~torchrl.objectives.TD3Loss`.

        ``loss_terms(tensordict, update_actor=True)``: sum the ``loss_*`` entries and back-propagate
        once; the critic losses reach only the critics (targets are computed without gradient) and
        the actor loss only the actor (critic parameters are detached there). ``forward`` keeps no
        count: for TD3's delayed actor call :meth:`loss_terms` with ``update_actor=False`` on the
        steps without an actor update, as :class:`~torchrl_dhrl.training.LossUpdater` does.
        """
        return self.loss_terms(tensordict, update_actor=True)

    def _diagnostics(self, prefix: str | None, q: torch.Tensor, target: torch.Tensor) -> dict:
        """Mean Q, mean target and mean Eq. (1) distance (of the pessimistic member) of a critic pair."""
        q = q.detach()
        p = f"{prefix}_" if prefix else ""
        return {
            f"{p}q": q.mean(),
            f"{p}target": target.detach().mean(),
            f"{p}distance": q_to_distance(q.min(0).values, self.gamma).mean(),
        }
