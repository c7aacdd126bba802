"""The high-level cadence (a new subgoal every ``c_h`` env steps and at reset, held in between) and the
critic-guided choice of the subgoal among candidates."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import TensorDictPrimer

from torchrl_dhrl._unregistered import UnregisteredAttributes
from torchrl_dhrl.checks import checked, flag, integer, number

from ._utils import resolve_box
from .critics import critic_values, stacked_critic_values

#: The accepted high-level intervals ``c_h`` (env steps per subgoal).
INTERVAL = integer(1, what="the high-level interval")
#: The accepted numbers of perturbed candidates of a critic-guided subgoal (0: none).
CANDIDATES = integer(0, what="perturbed subgoal candidates scored by the high-level critic")

#: Value of the subgoal counter after a reset: no subgoal is in force yet.
NO_SUBGOAL = -1


class SubgoalScheduler(TensorDictModuleBase):
    """Holds a subgoal for ``interval`` (``c_h``) env steps and swaps in a fresh proposal on schedule.

    Reads a freshly proposed subgoal (``proposal_key``), the subgoal in force
    (``subgoal_key``) and the counter ``counter_key`` (the number of steps the held subgoal
    has already been in force before this step); writes the subgoal in force, ``new_subgoal``
    (bool ``[1]``, ``True`` when the proposal was adopted this step) and the updated counter
    (``0`` on the step a subgoal is issued, up to ``interval - 1``).

    A new subgoal is issued, independently per env of a batch, when

    * the counter is :data:`NO_SUBGOAL` (``-1``, the primer's value after a reset) or absent,
    * the counter says the held subgoal has served ``interval`` steps, or
    * ``step_count_key`` is present and equals 0 (first step of an episode).

    The held subgoal and the counter live in the tensordict, so they cross
    :func:`~torchrl.envs.utils.step_mdp`, batched envs, collectors and checkpoints. In an env,
    append :meth:`make_primer`: :class:`~torchrl.envs.TensorDictPrimer` resets them at each
    (partial) reset and carries the policy-written values into ``("next", ...)`` at every
    step (checked empirically with torchrl 0.14.1: rollouts and Collectors restart the
    cadence per env at each reset).

    Args:
        interval (int): ``c_h``, the number of env steps a subgoal is held (reference:
            30 AntMazeSmall, 40 AntMaze, 50 Bottleneck, 80 Complex, 10 Reacher3D).

    Keyword Args:
        goal_dim (int, optional): the subgoal size; lets :meth:`make_tensordict_primer`
            build the primer without arguments (TorchRL's ``get_primers_from_module`` and
            ``Collector(..., auto_register_policy_transforms=True)`` find it).
        proposal_key (NestedKey): the fresh proposal. Defaults to ``"subgoal_proposal"``.
        subgoal_key (NestedKey): the subgoal in force. Defaults to ``"subgoal"``.
        new_subgoal_key (NestedKey): Defaults to ``"new_subgoal"``.
        counter_key (NestedKey): Defaults to ``"subgoal_step"``.
        step_count_key (NestedKey, optional): an episode step counter (``StepCounter``);
            ``None`` to ignore it. Defaults to ``"step_count"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> scheduler = SubgoalScheduler(3)
        >>> td = TensorDict({"subgoal_step": torch.full((2, 1), -1)}, [2])
        >>> issued = []
        >>> for t in range(7):
        ...     td["subgoal_proposal"] = torch.full((2, 2), float(t))
        ...     td = scheduler(td)
        ...     issued.append(td["subgoal"][0, 0].item())
        >>> issued
        [0.0, 0.0, 0.0, 3.0, 3.0, 3.0, 6.0]
    """

    @checked(interval=INTERVAL)
    def __init__(
        self,
        interval: int,
        *,
        goal_dim: int | None = None,
        proposal_key: NestedKey = "subgoal_proposal",
        subgoal_key: NestedKey = "subgoal",
        new_subgoal_key: NestedKey = "new_subgoal",
        counter_key: NestedKey = "subgoal_step",
        step_count_key: NestedKey | None = "step_count",
    ) -> None:
        super().__init__()
        if goal_dim is not None and goal_dim < 1:
            raise ValueError(f"`goal_dim` must be positive, got {goal_dim}.")
        self.interval = interval
        self.goal_dim = goal_dim
        self.proposal_key = proposal_key
        self.subgoal_key = subgoal_key
        self.new_subgoal_key = new_subgoal_key
        self.counter_key = counter_key
        self.step_count_key = step_count_key
        self.in_keys = [proposal_key, subgoal_key, counter_key] + (
            [step_count_key] if step_count_key is not None else []
        )
        self.out_keys = [subgoal_key, new_subgoal_key, counter_key]

    def _issue(self, tensordict: TensorDictBase, proposal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(issue, counter)``: which envs adopt the proposal at this call (bool ``[*batch, 1]``) and the counter read."""
        flag_shape = (*proposal.shape[:-1], 1)
        counter = tensordict.get(self.counter_key, None)
        if counter is None:
            counter = torch.full(flag_shape, NO_SUBGOAL, dtype=torch.long, device=proposal.device)
        elif counter.shape != flag_shape:
            raise ValueError(
                f"{self.counter_key!r} must have shape {flag_shape}, got {tuple(counter.shape)}."
            )
        issue = (counter < 0) | (counter + 1 >= self.interval)
        if self.step_count_key is not None:
            step_count = tensordict.get(self.step_count_key, None)
            if step_count is not None:
                issue = issue | (step_count.reshape(flag_shape) == 0)
        return issue, counter

    def due(self, tensordict: TensorDictBase) -> torch.Tensor:
        """Which envs the next call issues a new subgoal to: bool ``[*batch, 1]`` (reads the proposal for its shape)."""
        return self._issue(tensordict, tensordict.get(self.proposal_key))[0]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        proposal = tensordict.get(self.proposal_key)
        issue, counter = self._issue(tensordict, proposal)
        held = tensordict.get(self.subgoal_key, None)
        subgoal = proposal if held is None else torch.where(issue, proposal, held)
        tensordict.set(self.subgoal_key, subgoal)
        tensordict.set(self.new_subgoal_key, issue)
        tensordict.set(self.counter_key, torch.where(issue, torch.zeros_like(counter), counter + 1))
        return tensordict

    def make_primer(
        self, goal_dim: int | None = None, *, dtype: torch.dtype = torch.float32
    ) -> TensorDictPrimer:
        """Returns the :class:`~torchrl.envs.TensorDictPrimer` that carries the held subgoal across steps.

        It primes ``subgoal`` (zeros, ``[goal_dim]``), ``new_subgoal`` (``False``) and the
        counter (:data:`NO_SUBGOAL`), expanded to the env's batch size. Append it to the env
        (``env.append_transform(scheduler.make_primer())``).

        Args:
            goal_dim (int, optional): the subgoal size. Defaults to the constructor's.

        Keyword Args:
            dtype (torch.dtype): the subgoal dtype. Defaults to ``torch.float32``.
        """
        goal_dim = self.goal_dim if goal_dim is None else goal_dim
        if goal_dim is None:
            raise ValueError("`goal_dim` is unknown: pass it here or to the SubgoalScheduler constructor.")
        primers = Composite()
        primers[self.subgoal_key] = Unbounded((goal_dim,), dtype=dtype)
        primers[self.new_subgoal_key] = Categorical(2, (1,), dtype=torch.bool)
        primers[self.counter_key] = Unbounded((1,), dtype=torch.long)
        default_value = {
            self.subgoal_key: 0.0,
            self.new_subgoal_key: 0.0,
            self.counter_key: float(NO_SUBGOAL),
        }
        return TensorDictPrimer(primers, default_value=default_value, expand_specs=True)

    def make_tensordict_primer(self) -> TensorDictPrimer:
        """The primer, found by :func:`torchrl.modules.utils.get_primers_from_module` (needs ``goal_dim``)."""
        return self.make_primer()

    def extra_repr(self) -> str:
        return f"interval={self.interval}, subgoal_key={self.subgoal_key!r}, counter_key={self.counter_key!r}"


def _static_shapes_only(device: torch.device) -> bool:
    """Whether the call is traced by ``torch.compile`` or captured into a CUDA graph: no host read, no skipped work."""
    return torch.compiler.is_compiling() or (
        device.type == "cuda" and torch.cuda.is_current_stream_capturing()
    )


class CriticGuidedSubgoal(UnregisteredAttributes, TensorDictModuleBase):
    """Replaces the actor's subgoal by the best of it and ``K`` candidates, scored by the high-level critic.

    Sits between the high-level actor and its exploration noise (:class:`HighLevelPolicy` with
    ``critic_candidates > 0`` or ``landmark_candidates=True``): it reads the actor's deterministic proposal
    (``proposal_key``), the state and the final goal, and scores together, in one critic call on a
    ``[*batch, N]`` batch,

    * the proposal itself (candidate ``0``),
    * ``num_candidates`` Gaussian perturbations of it, ``proposal + noise_sigma * N(0, I)`` clipped to the subgoal
      box (candidates ``1..K``; drawn with the global generator of the proposal's device, one
      ``torch.randn(*batch, K, goal_dim)`` per call), and
    * with ``landmark_candidates``, the goals of the graph's landmarks, clipped to the box (candidates
      ``K + 1..``), given by the :attr:`landmarks` callable.

    The score of a candidate is the smallest value over the critic's members (the twin's pessimistic value: an
    argmax over candidates favours those it overestimates), ``Q(s, candidate | g)``; a NaN score and an invalid
    landmark row score ``-inf``. The best candidate is written back at ``proposal_key``, and its index at
    ``index_key`` (int64 ``[*batch, 1]``; ``0``: the actor's own). **Ties** go to the actor's own subgoal, and
    among the other candidates to the lowest index. Exploration noise, if any, is added afterwards (it explores
    around the best), and the :class:`SubgoalScheduler` adopts the result only when a new subgoal is due.

    The choice acts in every exploration mode (also under ``ExplorationType.DETERMINISTIC``: it is part of the
    policy, not of its exploration) and is deterministic given the generator's state.

    Static shapes, no host read (``torch.compile``, CUDA-graph capture): ``N = 1 + K + L`` is fixed, ``L`` being
    the number of landmark rows the callable returns (a fixed-size graph's ``max_landmarks`` rows, with a
    ``valid`` mask). Eagerly, when a :attr:`due` callable says that no env of the batch is issued a new subgoal at
    this call (one host read), nothing is drawn or scored and the proposal passes unchanged (index ``0``); traced
    or captured, every call scores.

    Args:
        subgoal_low (Tensor or sequence of float): lower corner of the subgoal box.
        subgoal_high (Tensor or sequence of float): upper corner of the subgoal box.

    Keyword Args:
        num_candidates (int): ``K``, the perturbed candidates. Defaults to ``8``.
        noise_sigma (float or Tensor): std of the perturbations in goal units (per axis with a tensor).
            Defaults to ``2.0``.
        landmark_candidates (bool): the landmarks join the candidates. Defaults to ``False``.
        critic (TensorDictModule, optional): the high-level critic, reading ``(observation, goal, subgoal)`` from
            its three ``in_keys`` in that order (e.g. a :class:`~torchrl_dhrl.modules.GoalConditionedCritic`, or
            ``HighLevelLoss.critic_network``); required to act. Not a submodule (not in ``state_dict()`` nor
            ``parameters()``): it belongs to the learner. Settable.
        critic_params (TensorDictBase, optional): parameters to evaluate the critic with, laid out as
            ``TensorDict.from_module(critic)`` (e.g. ``HighLevelLoss.critic_network_params``, stacked along dim
            0 for a single-member critic); ``None``: the critic's own. Settable.
        landmarks (callable, optional): ``() -> (goals [L, goal_dim], valid [L] bool or None)``, or ``None`` while
            there is no landmark; required with ``landmark_candidates``. E.g. the planner's
            ``graph.planning_tensors(...)`` goals and valid mask (this module does not import the planner).
            Settable.
        due (callable, optional): ``tensordict -> bool [*batch, 1]``, the envs issued a new subgoal at this call
            (:meth:`SubgoalScheduler.due`); ``None``: score at every call. Settable.
        observation_key (NestedKey): Defaults to ``"observation"``.
        goal_key (NestedKey): the final goal. Defaults to ``"desired_goal"``.
        proposal_key (NestedKey): read and overwritten. Defaults to ``"subgoal_proposal"``.
        index_key (NestedKey, optional): where the chosen index is written; ``None``: nowhere. Defaults to
            ``"subgoal_candidate"``.
        value_key (NestedKey): where a critic other than a ``GoalConditionedCritic`` writes its value.
            Defaults to ``"state_action_value"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> # a critic that values subgoals by their distance to the goal
        >>> critic = TensorDictModule(lambda s, g, sg: -(sg - g).norm(dim=-1, keepdim=True),
        ...     in_keys=["observation", "desired_goal", "subgoal"], out_keys=["state_action_value"])
        >>> guide = CriticGuidedSubgoal([-4.0, -4.0], [20.0, 20.0], num_candidates=16, critic=critic)
        >>> td = TensorDict({"observation": torch.zeros(3, 6), "desired_goal": torch.full((3, 2), 8.0),
        ...                  "subgoal_proposal": torch.zeros(3, 2)}, [3])
        >>> _ = torch.manual_seed(0)
        >>> out = guide(td.clone())
        >>> bool(((out["subgoal_proposal"] - 8.0).norm(dim=-1) < 8.0 * 2 ** 0.5).all())
        True
        >>> out["subgoal_candidate"].shape
        torch.Size([3, 1])
        >>> guide.landmark_candidates = True
        >>> guide.landmarks = lambda: (torch.tensor([[8.0, 8.0], [30.0, 0.0]]), None)
        >>> guide(td.clone())["subgoal_candidate"].reshape(-1).tolist()  # the first landmark: 1 + K
        [17, 17, 17]
    """

    _unregistered = ("critic", "critic_params", "landmarks", "due")

    @checked(num_candidates=CANDIDATES, noise_sigma=number(0.0), landmark_candidates=flag())
    def __init__(
        self,
        subgoal_low: torch.Tensor | Sequence[float],
        subgoal_high: torch.Tensor | Sequence[float],
        *,
        num_candidates: int = 8,
        noise_sigma: float | torch.Tensor = 2.0,
        landmark_candidates: bool = False,
        critic: TensorDictModuleBase | None = None,
        critic_params: TensorDictBase | None = None,
        landmarks: Callable[[], tuple[torch.Tensor, torch.Tensor | None] | None] | None = None,
        due: Callable[[TensorDictBase], torch.Tensor] | None = None,
        observation_key: NestedKey = "observation",
        goal_key: NestedKey = "desired_goal",
        proposal_key: NestedKey = "subgoal_proposal",
        index_key: NestedKey | None = "subgoal_candidate",
        value_key: NestedKey = "state_action_value",
    ) -> None:
        super().__init__()
        low, high = resolve_box(low=subgoal_low, high=subgoal_high, name="subgoal")
        self.register_buffer("low", low)
        self.register_buffer("high", high)
        self.register_buffer(
            "sigma", torch.as_tensor(noise_sigma, dtype=torch.float32).expand_as(low).clone()
        )
        self.num_candidates = int(num_candidates)
        self.landmark_candidates = landmark_candidates
        self.critic = critic
        self.critic_params = critic_params
        self.landmarks = landmarks
        self.due = due
        self.observation_key = observation_key
        self.goal_key = goal_key
        self.proposal_key = proposal_key
        self.index_key = index_key
        self.value_key = value_key
        self.in_keys = [proposal_key, observation_key, goal_key]
        self.out_keys = [proposal_key] + ([index_key] if index_key is not None else [])

    @property
    def landmark_candidates(self) -> bool:
        """Whether the landmarks join the candidates (settable)."""
        return self._landmark_candidates

    @landmark_candidates.setter
    def landmark_candidates(self, value: bool) -> None:
        flag()("landmark_candidates", value)
        if not value and self.num_candidates == 0:
            raise ValueError(
                "A CriticGuidedSubgoal needs candidates: `num_candidates` >= 1 or `landmark_candidates=True`."
            )
        self._landmark_candidates = value

    def candidates(self, proposal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``(candidates [*batch, N, goal_dim], valid [N] bool or None)``: the proposal, its perturbations, the landmarks.

        Draws the perturbations (``torch.randn(*batch, K, goal_dim)``) from the global generator of the proposal's
        device.
        """
        device, dtype = proposal.device, proposal.dtype
        batch, dim = proposal.shape[:-1], proposal.shape[-1]
        if self.low.shape[-1] != dim:
            raise ValueError(
                f"{self.proposal_key!r} has last dimension {dim}, the subgoal box has {self.low.shape[-1]}."
            )
        low = self.low.to(device=device, dtype=dtype)
        high = self.high.to(device=device, dtype=dtype)
        parts = [proposal.unsqueeze(-2)]
        if self.num_candidates:
            noise = torch.randn(*batch, self.num_candidates, dim, device=device, dtype=dtype)
            perturbed = proposal.unsqueeze(-2) + self.sigma.to(device=device, dtype=dtype) * noise
            parts.append(torch.maximum(torch.minimum(perturbed, high), low))
        valid = None
        if self.landmark_candidates:
            if self.landmarks is None:
                raise RuntimeError(
                    "`landmark_candidates=True` needs the `landmarks` callable (() -> (goals [L, goal_dim], valid "
                    "[L] or None)): set it, e.g. to the planner graph's planning tensors."
                )
            found = self.landmarks()
            if found is not None:
                goals, mask = found
                goals = goals.to(device=device, dtype=dtype)
                if goals.ndim != 2 or goals.shape[-1] != dim:
                    raise ValueError(
                        f"The landmark goals must have shape [L, {dim}], got {tuple(goals.shape)}."
                    )
                goals = torch.maximum(torch.minimum(goals, high), low)
                parts.append(goals.expand(*batch, *goals.shape))
                if mask is not None:
                    own = torch.ones(1 + self.num_candidates, dtype=torch.bool, device=device)
                    valid = torch.cat([own, mask.to(device=device, dtype=torch.bool)])
        return torch.cat(parts, -2), valid

    def _values(
        self, observation: torch.Tensor, goal: torch.Tensor, candidates: torch.Tensor
    ) -> torch.Tensor:
        """The critic's members' values of the candidates: ``[E, *batch, N]``."""
        if self.critic is None:
            raise RuntimeError(
                "A CriticGuidedSubgoal scores its candidates with the high-level critic: set `critic` (e.g. "
                "HighLevelLoss.critic_network, with `critic_params` = its critic_network_params)."
            )
        shape = candidates.shape[:-1]
        observation = observation.unsqueeze(-2).expand(*shape, observation.shape[-1])
        goal = goal.unsqueeze(-2).expand(*shape, goal.shape[-1])
        params = self.critic_params
        if params is not None and params.batch_dims > 0:  # a single-member critic's stacked twin
            return stacked_critic_values(self.critic, params, observation, goal, candidates, self.value_key)
        return critic_values(self.critic, observation, goal, candidates, self.value_key, params=params)

    @torch.no_grad()
    def scores(
        self,
        observation: torch.Tensor,
        goal: torch.Tensor,
        candidates: torch.Tensor,
        valid: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """``[*batch, N]``: the smallest member value of each candidate, ``-inf`` where NaN or not ``valid``."""
        score = self._values(observation, goal, candidates).amin(0)
        score = torch.where(torch.isnan(score), float("-inf"), score)
        if valid is not None:
            score = torch.where(valid, score, float("-inf"))
        return score

    @staticmethod
    def select(scores: torch.Tensor) -> torch.Tensor:
        """``[*batch]`` int64: the best candidate of each row; ties: ``0`` (the actor's), then the lowest index."""
        best = scores.argmax(-1)
        own = scores[..., 0] >= scores.gather(-1, best.unsqueeze(-1)).squeeze(-1)
        return torch.where(own, torch.zeros_like(best), best)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        proposal = tensordict.get(self.proposal_key)
        batch, dim = proposal.shape[:-1], proposal.shape[-1]
        if (
            self.due is not None
            and not _static_shapes_only(proposal.device)
            and not bool(self.due(tensordict).any())
        ):  # eagerly, no env is issued a subgoal at this call: the proposal would not be adopted anywhere
            if self.index_key is not None:
                tensordict.set(
                    self.index_key, torch.zeros(*batch, 1, dtype=torch.long, device=proposal.device)
                )
            return tensordict
        candidates, valid = self.candidates(proposal)
        scores = self.scores(
            tensordict.get(self.observation_key), tensordict.get(self.goal_key), candidates, valid
        )
        index = self.select(scores)
        best = candidates.gather(-2, index.reshape(*batch, 1, 1).expand(*batch, 1, dim)).squeeze(-2)
        tensordict.set(self.proposal_key, best)
        if self.index_key is not None:
            tensordict.set(self.index_key, index.unsqueeze(-1))
        return tensordict

    def extra_repr(self) -> str:
        return (
            f"num_candidates={self.num_candidates}, landmark_candidates={self.landmark_candidates}, "
            f"noise_sigma={self.sigma.tolist()}"
        )
