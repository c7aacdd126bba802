"""The high-level cadence: issue a new subgoal every ``c_h`` env steps (and at reset), hold it in between."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import TensorDictPrimer

from torchrl_dhrl.checks import checked, integer

#: The accepted high-level intervals ``c_h`` (env steps per subgoal).
INTERVAL = integer(1, what="the high-level interval")

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

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        proposal = tensordict.get(self.proposal_key)
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
