"""Acting policies: the actors composed with their exploration (and, for the high level, the c_h cadence)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from tensordict.utils import NestedKey
from torch import nn
from torchrl.envs import TensorDictPrimer

from torchrl_dhrl.checks import checked, flag, layer_sizes, number, vector

from ._utils import relative_goal_needs_indices
from .actors import DEFAULT_NUM_CELLS, HighLevelActor
from .exploration import GaussianUniformExplorationModule
from .subgoal import CANDIDATES, INTERVAL, CriticGuidedSubgoal, SubgoalScheduler


def _subgoal_box(subgoal_low, subgoal_high) -> None:
    low, high = list(map(float, subgoal_low)), list(map(float, subgoal_high))
    if len(low) != len(high) or not low:
        raise ValueError(
            f"`subgoal_low` and `subgoal_high` must have the same length, got {low}, {high}."
        )
    if any(lo >= hi for lo, hi in zip(low, high, strict=True)):
        raise ValueError(f"`subgoal_low` must be below `subgoal_high` on every axis, got {low}, {high}.")


def _subgoal_box_size(goal_dim, subgoal_low) -> None:
    if len(subgoal_low) != goal_dim:
        raise ValueError(
            f"`subgoal_low` must have {goal_dim} entries (the goal space is {goal_dim}-D), got {list(subgoal_low)}."
        )


class HighLevelPolicy(TensorDictSequential):
    """The acting high-level policy: ``pi_hi`` -> [critic-guided choice] -> subgoal noise -> hold for ``c_h`` steps.

    A :class:`~tensordict.nn.TensorDictSequential` of three small modules (four with critic-guided
    subgoals), exposed as attributes:

    * :attr:`actor` -- a :class:`HighLevelActor` writing the deterministic proposal to
      ``proposal_key`` (this is the network to give to
      :class:`~torchrl_dhrl.objectives.HighLevelLoss`);
    * :attr:`selector` -- only with ``critic_candidates > 0`` or ``landmark_candidates=True`` (``None``
      otherwise): a :class:`CriticGuidedSubgoal` that scores the proposal together with
      ``critic_candidates`` Gaussian perturbations of it (std ``candidate_noise``, clipped to the box) and,
      optionally, the graph's landmarks, in one call of the high-level critic, and replaces the proposal by
      the best (ties: the actor's own). It needs the ``critic`` (and ``landmarks``), given here or set on
      :attr:`selector` later (:func:`~torchrl_dhrl.factory.make_agent` does). It runs before the noise, which
      then explores around the best candidate; eagerly it scores only in the steps where some env is issued a
      new subgoal (see :class:`CriticGuidedSubgoal`). Our improvement, off by default: the reference issues
      the actor's subgoal;
    * :attr:`exploration` -- absolute Gaussian noise in goal units, clipped to the subgoal
      box, active only under ``ExplorationType.RANDOM`` (off under ``DETERMINISTIC``);
    * :attr:`scheduler` -- a :class:`SubgoalScheduler` that adopts the (noisy) proposal only
      every ``interval`` steps and at reset, so noise only matters on issuing steps.

    It writes ``subgoal``, ``new_subgoal`` (bool ``[1]``) and ``subgoal_step`` (int64 ``[1]``), and with
    a :attr:`selector` ``subgoal_candidate`` (int64 ``[1]``, the chosen candidate; ``0``: the actor's).
    Append :meth:`make_primer` to the env so the held subgoal crosses steps and resets
    (:func:`torchrl.modules.utils.get_primers_from_module` finds it too).

    Args:
        observation_dim (int): observation size.
        goal_dim (int): goal size.
        subgoal_low (Tensor or sequence of float): lower corner of the subgoal box.
        subgoal_high (Tensor or sequence of float): upper corner of the subgoal box.
        interval (int): ``c_h``, env steps per subgoal.

    Keyword Args:
        noise_sigma (float or Tensor): absolute subgoal noise std in goal units
            (reference: 2 for the mazes, 0.1 for Reacher3D). Defaults to ``2.0``.
        goal_indices (sequence of int, optional): where the achieved goal sits in the observation; needed with
            ``relative_goal=True``. Defaults to ``None``.
        relative_goal (bool): relative goal input for ``pi_hi``. Defaults to ``False``.
        num_cells (sequence of int): hidden widths. Defaults to ``(256, 256, 256)``.
        activation_class (type): hidden activation. Defaults to ``nn.ReLU``.
        observation_key (NestedKey): Defaults to ``"observation"``.
        goal_key (NestedKey): the final goal. Defaults to ``"desired_goal"``.
        subgoal_key (NestedKey): Defaults to ``"subgoal"``.
        proposal_key (NestedKey): Defaults to ``"subgoal_proposal"``.
        new_subgoal_key (NestedKey): Defaults to ``"new_subgoal"``.
        counter_key (NestedKey): Defaults to ``"subgoal_step"``.
        step_count_key (NestedKey, optional): Defaults to ``"step_count"``.
        critic_candidates (int): ``K``, perturbed candidates scored by the critic; ``0`` with
            ``landmark_candidates=False``: no :attr:`selector`, the reference's policy. Defaults to ``0``.
        candidate_noise (float or Tensor, optional): std of the perturbations in goal units; ``None``:
            ``noise_sigma``. Defaults to ``None``.
        landmark_candidates (bool): the graph's landmarks join the candidates. Defaults to ``False``.
        critic (TensorDictModule, optional): the high-level critic that scores the candidates (see
            :class:`CriticGuidedSubgoal`); not a submodule.
        critic_params (TensorDictBase, optional): the parameters to evaluate ``critic`` with.
        landmarks (callable, optional): ``() -> (goals [L, goal_dim], valid [L] or None)`` or ``None``.
        candidate_key (NestedKey): where the chosen candidate's index is written. Defaults to
            ``"subgoal_candidate"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> policy = HighLevelPolicy(6, 2, [-4.0, -4.0], [20.0, 20.0], interval=3, num_cells=(32,))
        >>> td = TensorDict({"observation": torch.randn(2, 6), "desired_goal": torch.randn(2, 2),
        ...                  "subgoal_step": torch.full((2, 1), -1)}, [2])
        >>> flags = [policy(td)["new_subgoal"].all().item() for _ in range(6)]
        >>> flags
        [True, False, False, True, False, False]
        >>> policy.selector is None
        True

        Critic-guided subgoals: the critic scores the actor's subgoal and 8 perturbations of it.

        >>> from torchrl_dhrl.modules import GoalConditionedCritic
        >>> critic = GoalConditionedCritic(6, 2, action_low=[-4.0, -4.0], action_high=[20.0, 20.0],
        ...     goal_key="desired_goal", action_key="subgoal", relative_goal=False, num_cells=(32,))
        >>> guided = HighLevelPolicy(6, 2, [-4.0, -4.0], [20.0, 20.0], interval=3, num_cells=(32,),
        ...     critic_candidates=8, candidate_noise=1.0, critic=critic)
        >>> out = guided(td.clone())
        >>> out["subgoal_candidate"].shape, bool(((out["subgoal"] >= -4) & (out["subgoal"] <= 20)).all())
        (torch.Size([2, 1]), True)
    """

    @checked(
        _subgoal_box,
        _subgoal_box_size,
        relative_goal_needs_indices,
        subgoal_low=vector(),
        subgoal_high=vector(),
        interval=INTERVAL,
        noise_sigma=number(0.0),
        relative_goal=flag(),
        num_cells=layer_sizes(),
        critic_candidates=CANDIDATES,
        candidate_noise=number(0.0, optional=True),
        landmark_candidates=flag(),
    )
    def __init__(
        self,
        observation_dim: int,
        goal_dim: int,
        subgoal_low: torch.Tensor | Sequence[float],
        subgoal_high: torch.Tensor | Sequence[float],
        interval: int,
        *,
        noise_sigma: float | torch.Tensor = 2.0,
        goal_indices: Sequence[int] | None = None,
        relative_goal: bool = False,
        num_cells: Sequence[int] = DEFAULT_NUM_CELLS,
        activation_class: type[nn.Module] = nn.ReLU,
        observation_key: NestedKey = "observation",
        goal_key: NestedKey = "desired_goal",
        subgoal_key: NestedKey = "subgoal",
        proposal_key: NestedKey = "subgoal_proposal",
        new_subgoal_key: NestedKey = "new_subgoal",
        counter_key: NestedKey = "subgoal_step",
        step_count_key: NestedKey | None = "step_count",
        critic_candidates: int = 0,
        candidate_noise: float | torch.Tensor | None = None,
        landmark_candidates: bool = False,
        critic: TensorDictModuleBase | None = None,
        critic_params: TensorDictBase | None = None,
        landmarks: Callable[[], tuple[torch.Tensor, torch.Tensor | None] | None] | None = None,
        candidate_key: NestedKey = "subgoal_candidate",
    ) -> None:
        actor = HighLevelActor(
            observation_dim,
            goal_dim,
            subgoal_low,
            subgoal_high,
            goal_indices=goal_indices,
            relative_goal=relative_goal,
            num_cells=num_cells,
            activation_class=activation_class,
            observation_key=observation_key,
            goal_key=goal_key,
            subgoal_key=proposal_key,
        )
        exploration = GaussianUniformExplorationModule(
            low=actor.low,
            high=actor.high,
            sigma=noise_sigma,
            relative_sigma=False,
            uniform_prob=0.0,
            action_key=proposal_key,
        )
        scheduler = SubgoalScheduler(
            interval,
            goal_dim=goal_dim,
            proposal_key=proposal_key,
            subgoal_key=subgoal_key,
            new_subgoal_key=new_subgoal_key,
            counter_key=counter_key,
            step_count_key=step_count_key,
        )
        if not critic_candidates and not landmark_candidates:  # the reference's policy, module for module
            super().__init__(actor, exploration, scheduler)
            return
        selector = CriticGuidedSubgoal(
            actor.low,
            actor.high,
            num_candidates=critic_candidates,
            noise_sigma=noise_sigma if candidate_noise is None else candidate_noise,
            landmark_candidates=landmark_candidates,
            critic=critic,
            critic_params=critic_params,
            landmarks=landmarks,
            due=scheduler.due,  # eagerly, nothing scored in the steps that issue no subgoal
            observation_key=observation_key,
            goal_key=goal_key,
            proposal_key=proposal_key,
            index_key=candidate_key,
        )
        super().__init__(actor, selector, exploration, scheduler)

    @property
    def actor(self) -> HighLevelActor:
        return self.module[0]

    @property
    def selector(self) -> CriticGuidedSubgoal | None:
        """The critic-guided choice among subgoal candidates, ``None`` when off (the reference's policy)."""
        return self.module[1] if len(self.module) == 4 else None

    @property
    def exploration(self) -> GaussianUniformExplorationModule:
        return self.module[-2]

    @property
    def scheduler(self) -> SubgoalScheduler:
        return self.module[-1]

    def make_primer(self) -> TensorDictPrimer:
        """The :class:`~torchrl.envs.TensorDictPrimer` to append to the env (see :meth:`SubgoalScheduler.make_primer`)."""
        return self.scheduler.make_primer()


def make_low_level_policy(
    actor: nn.Module,
    *,
    sigma: float = 0.1,
    uniform_prob: float = 0.2,
) -> TensorDictSequential:
    """Composes a low-level actor with the reference exploration (0.1 * action_max noise, 20% uniform).

    Args:
        actor (LowLevelActor): the deterministic actor; its ``spec`` gives the action box.

    Keyword Args:
        sigma (float): Gaussian std as a fraction of the box half-width. Defaults to ``0.1``.
        uniform_prob (float): probability of a uniform random action. Defaults to ``0.2``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_dhrl.modules import LowLevelActor
        >>> actor = LowLevelActor(6, 2, action_max=30.0, action_dim=8, goal_indices=[0, 1], num_cells=(32,))
        >>> policy = make_low_level_policy(actor)
        >>> td = TensorDict({"observation": torch.randn(4, 6), "waypoint": torch.randn(4, 2)}, [4])
        >>> policy(td)["action"].shape
        torch.Size([4, 8])
    """
    action_key = actor.out_keys[0]
    exploration = GaussianUniformExplorationModule(
        actor.spec, sigma=sigma, relative_sigma=True, uniform_prob=uniform_prob, action_key=action_key
    )
    return TensorDictSequential(actor, exploration)
