"""HAC hindsight action relabelling with subgoal testing and DHRL's gradual penalty (high level)."""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch
from tensordict import TensorDictBase, is_tensor_collection
from tensordict.utils import NestedKey
from torchrl.data import TensorStorage
from torchrl.envs.transforms import Transform

from torchrl_dhrl._unregistered import UnregisteredAttributes
from torchrl_dhrl.data.future_goals import _SampleTransform, _unravel_key
from torchrl_dhrl.data.rewards import SparseGoalReward

__all__ = ["HindsightSubgoalRelabel"]

DistanceFromGraph = Callable[[torch.Tensor], torch.Tensor]


class HindsightSubgoalRelabel(UnregisteredAttributes, _SampleTransform, Transform):
    """Relabels high-level samples: hindsight subgoals (HAC) or subgoal testing with penalties.

    Applied to high-level transitions ``(s_t, g, sg_t, s_{t+c})`` after their goals were relabelled (see
    :class:`~torchrl_dhrl.data.FutureGoalRelabel`), typically as the step after it in
    :class:`~torchrl_dhrl.data.RelabelReplayBuffer`'s ``relabel`` list. It only reads the sample, so it
    also works on its own, in a :class:`~torchrl.envs.Compose` or appended to any replay buffer. Each
    sample independently becomes one of:

    * **hindsight action** (probability ``1 - subgoal_test_ratio``, 0.8): the action ``sg_t`` is replaced
      by the achieved goal at the end of the segment ``ag_{t+c}`` (HAC), as if the low level had been
      asked for what it reached; reward ``r(ag_{t+c}, g)``.
    * **subgoal test** (probability ``subgoal_test_ratio``, 0.2): the issued subgoal is kept and penalised
      when the low level (and graph) could not deliver it.

    Rewards, with ``r(ag, g)`` = ``reward_fn`` (sparse ``-1`` / ``0`` at 0.5), ``missed`` =
    ``||ag_{t+c} - sg_t|| > subgoal_test_threshold`` and ``far`` = ``distance_from_graph(sg_t) >
    far_from_graph_threshold`` (evaluated only for subgoal tests, only when both ``gradual_penalty`` and
    ``distance_from_graph`` are set, and never for a non-finite distance: ``+inf`` means there is no
    graph yet):

    ======================  ===========================  =====================================
    case                    reference code (default)     ``far_penalty_requires_miss=True``
    ======================  ===========================  =====================================
    hindsight action        ``r(ag_{t+c}, g)``           ``r(ag_{t+c}, g)``
    test, far               ``-gradual_penalty``         missed: ``-gradual_penalty``,
                                                         reached: ``r(ag_{t+c}, g)``
    test, not far, missed   ``-subgoal_miss_penalty``    ``-subgoal_miss_penalty``
    test, not far, reached  ``r(ag_{t+c}, g)``           ``r(ag_{t+c}, g)``
    ======================  ===========================  =====================================

    The default follows the reference implementation, which overwrites the miss penalty with the
    gradual penalty for every tested subgoal far from the graph, reached or not. With
    ``far_penalty_requires_miss=True`` it follows the paper's Algorithms 1 and 4 literally: a reached
    subgoal (``L1``) keeps its reward, and the gradual penalty only grades missed ones (``L2``: near the
    graph, ``-p1``; ``L3``: far, ``-p2``). Without ``distance_from_graph`` (or with
    ``gradual_penalty=None``) tested subgoals get ``-subgoal_miss_penalty`` when missed (plain HAC subgoal
    testing).

    Args:
        distance_from_graph (callable, optional): ``distance_from_graph(goals: Tensor[B, goal_dim]) ->
            Tensor[B]``, the minimum over landmarks of the learned distance landmark -> goal (``+inf``
            when there is no graph), e.g. ``GraphPlanner.distance_from_graph`` or, exact for the ``far``
            test and much cheaper, ``functools.partial(planner.distance_from_graph,
            at_most=far_from_graph_threshold)``. Called without gradients
            on the tested subgoals only. Can be set later through the attribute of the same name.
            Any callable, an ``nn.Module`` included: it is kept as a plain attribute, not a
            submodule (not in ``state_dict()``, not moved by ``.to()``). Defaults to ``None`` (no
            gradual penalty).
        reward_fn (callable, optional): ``reward_fn(achieved_goal, goal) -> [B, 1]``. Defaults to
            :class:`~torchrl_dhrl.data.SparseGoalReward` with threshold ``0.5``. An ``nn.Module`` is
            kept as a plain attribute too.

    Keyword Args:
        subgoal_test_ratio (float, optional): probability that a sample is a subgoal test. Defaults to
            ``0.2``.
        subgoal_test_threshold (float, optional): distance beyond which a tested subgoal counts as
            missed (1 for the mazes, 0.1 for Reacher3D). Defaults to ``1.0``.
        subgoal_miss_penalty (float, optional): ``p1 >= 0``; a missed subgoal gets reward ``-p1``.
            Defaults to ``1.3``.
        gradual_penalty (float, optional): ``p2 >= 0``; a subgoal far from the graph gets reward ``-p2``
            (5.0 for the small mazes and Reacher3D, 1.5 for Bottleneck / Complex); ``None`` disables it.
            Defaults to ``5.0``.
        far_from_graph_threshold (float, optional): distance (env steps) beyond which a subgoal is far
            from the graph: 3 x the edge cutoff, i.e. ``90`` for the 30-step mazes, ``30`` for
            Reacher3D. Defaults to ``90.0``.
        far_penalty_requires_miss (bool, optional): see the table above. Defaults to ``False``
            (reference behaviour).
        action_key (NestedKey, optional): the high-level action (subgoal). Defaults to ``"subgoal"``.
        goal_key (NestedKey, optional): the (relabelled) goal. Defaults to ``"desired_goal"``.
        achieved_goal_key (NestedKey, optional): the achieved goal at the end of the segment. Defaults
            to ``("next", "achieved_goal")``.
        reward_key (NestedKey, optional): where the reward is written. Defaults to ``("next", "reward")``.
        subgoal_test_key (NestedKey, optional): where a bool ``[*batch, 1]`` marks subgoal tests, or
            ``None`` to write nothing. Defaults to ``"subgoal_test"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> _ = torch.manual_seed(0)
        >>> sample = TensorDict(
        ...     {
        ...         "subgoal": torch.tensor([[8.0, 0.0]]).expand(1000, 2),
        ...         "desired_goal": torch.zeros(1000, 2),
        ...         ("next", "achieved_goal"): torch.zeros(1000, 2),
        ...     },
        ...     batch_size=[1000],
        ... )
        >>> relabel = HindsightSubgoalRelabel(distance_from_graph=lambda goals: goals.norm(dim=-1) * 10)
        >>> out = relabel(sample.clone())  # relabels in place
        >>> tested = out["subgoal_test"].squeeze(-1)
        >>> bool((out["subgoal"][~tested] == 0).all())  # hindsight: action := achieved goal
        True
        >>> out["next", "reward"][tested].unique()  # subgoal 80 steps from the graph, missed by 8
        tensor([-1.3000])
        >>> relabel.distance_from_graph = lambda goals: goals.norm(dim=-1) * 100  # 800 > 90: far
        >>> out = relabel(sample.clone())
        >>> out["next", "reward"][out["subgoal_test"].squeeze(-1)].unique()
        tensor([-5.])
    """

    #: callables (possibly ``nn.Module`` s) kept as plain attributes, never registered as submodules
    _unregistered = ("distance_from_graph", "reward_fn")
    _usage = (
        "it relabels replay-buffer samples; pass it to RelabelReplayBuffer(relabel=[...]) or apply it to "
        "rb.sample()'s output"
    )

    def __init__(
        self,
        distance_from_graph: DistanceFromGraph | None = None,
        reward_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
        *,
        subgoal_test_ratio: float = 0.2,
        subgoal_test_threshold: float = 1.0,
        subgoal_miss_penalty: float = 1.3,
        gradual_penalty: float | None = 5.0,
        far_from_graph_threshold: float = 90.0,
        far_penalty_requires_miss: bool = False,
        action_key: NestedKey = "subgoal",
        goal_key: NestedKey = "desired_goal",
        achieved_goal_key: NestedKey = ("next", "achieved_goal"),
        reward_key: NestedKey = ("next", "reward"),
        subgoal_test_key: NestedKey | None = "subgoal_test",
    ) -> None:
        if not 0.0 <= subgoal_test_ratio <= 1.0:
            raise ValueError(f"subgoal_test_ratio must be in [0, 1], got {subgoal_test_ratio}.")
        if not subgoal_test_threshold >= 0:
            raise ValueError(f"subgoal_test_threshold must be >= 0, got {subgoal_test_threshold}.")
        if not subgoal_miss_penalty >= 0:
            raise ValueError(
                "subgoal_miss_penalty is a penalty (reward -p1) and must be >= 0, got "
                f"{subgoal_miss_penalty}."
            )
        if gradual_penalty is not None and not gradual_penalty >= 0:
            raise ValueError(
                f"gradual_penalty is a penalty (reward -p2) and must be >= 0, got {gradual_penalty}."
            )
        if not far_from_graph_threshold >= 0:
            raise ValueError(f"far_from_graph_threshold must be >= 0, got {far_from_graph_threshold}.")
        if reward_fn is None:
            reward_fn = SparseGoalReward(0.5)
        elif not callable(reward_fn):
            raise TypeError(f"reward_fn must be callable, got {type(reward_fn).__name__}.")
        action_key, goal_key = _unravel_key(action_key), _unravel_key(goal_key)
        achieved_goal_key, reward_key = _unravel_key(achieved_goal_key), _unravel_key(reward_key)
        subgoal_test_key = None if subgoal_test_key is None else _unravel_key(subgoal_test_key)
        super().__init__(
            in_keys=[action_key, goal_key, achieved_goal_key],
            out_keys=[action_key, reward_key] + ([subgoal_test_key] if subgoal_test_key is not None else []),
        )
        self.distance_from_graph = distance_from_graph
        self.reward_fn = reward_fn
        self.subgoal_test_ratio = float(subgoal_test_ratio)
        self.subgoal_test_threshold = float(subgoal_test_threshold)
        self.subgoal_miss_penalty = float(subgoal_miss_penalty)
        self.gradual_penalty = None if gradual_penalty is None else float(gradual_penalty)
        self.far_from_graph_threshold = float(far_from_graph_threshold)
        self.far_penalty_requires_miss = bool(far_penalty_requires_miss)
        self.action_key = action_key
        self.goal_key = goal_key
        self.achieved_goal_key = achieved_goal_key
        self.reward_key = reward_key
        self.subgoal_test_key = subgoal_test_key

    @property
    def distance_from_graph(self) -> DistanceFromGraph | None:
        """The graph query used by the gradual penalty (``None``: no gradual penalty)."""
        return self._distance_from_graph

    @distance_from_graph.setter
    def distance_from_graph(self, value: DistanceFromGraph | None) -> None:
        if value is not None and not callable(value):
            raise TypeError(f"distance_from_graph must be callable or None, got {type(value).__name__}.")
        self.__dict__["_distance_from_graph"] = value

    def _far_from_graph(self, subgoals: torch.Tensor, query: DistanceFromGraph | None = None) -> torch.Tensor:
        with torch.no_grad():
            distance = (self.distance_from_graph if query is None else query)(subgoals)
        if not isinstance(distance, torch.Tensor) or distance.shape not in (
            subgoals.shape[:1],
            subgoals.shape[:1] + (1,),
        ):
            shape = tuple(distance.shape) if isinstance(distance, torch.Tensor) else type(distance).__name__
            raise ValueError(
                f"distance_from_graph must return a tensor of shape [{subgoals.shape[0]}] for "
                f"{subgoals.shape[0]} subgoals, got {shape}."
            )
        distance = distance.reshape(-1).to(subgoals.device)
        return torch.isfinite(distance) & (distance > self.far_from_graph_threshold)

    def capturable_relabel(
        self, storage: TensorStorage
    ) -> Callable[[TensorDictBase, torch.Tensor, torch.Tensor], TensorDictBase]:
        """The relabelling of :meth:`forward` as a capture-safe function of tensors.

        Returns ``relabel(tensordict, coords, newest_index)`` (the signature of
        :meth:`FutureGoalRelabel.capturable_relabel <torchrl_dhrl.data.FutureGoalRelabel.capturable_relabel>`;
        this step reads neither): the same draws and rewards as :meth:`forward`, with static shapes and no host
        synchronisation, for :meth:`RelabelReplayBuffer.capturable_sampler
        <torchrl_dhrl.data.RelabelReplayBuffer.capturable_sampler>`. The gradual penalty's graph query then runs
        for every row (kept where the subgoal is tested) through ``distance_from_graph(subgoals, capturable=True)``,
        e.g. :meth:`GraphPlanner.distance_from_graph <torchrl_dhrl.planner.GraphPlanner.distance_from_graph>` on a
        ``fixed_size`` graph (its exact minimum: the same penalties as the eager query to float round-off).

        Raises:
            RuntimeError: with a gradual penalty, a ``distance_from_graph`` without a ``capturable`` keyword, or one
                that refuses it (e.g. a graph that is not ``fixed_size``); the message says which.
        """
        query = None
        if self.gradual_penalty is not None and self.distance_from_graph is not None:
            query = functools.partial(self.distance_from_graph, capturable=True)
            subgoals = storage._storage.get(self.action_key)
            probe = subgoals.new_zeros((0, subgoals.shape[-1]))
            try:
                query(probe)
            except (TypeError, RuntimeError) as err:
                raise RuntimeError(
                    "HindsightSubgoalRelabel: the gradual penalty's distance_from_graph has no capture-safe form "
                    f"here (called with capturable=True: {err})"
                ) from err

        def relabel(tensordict: TensorDictBase, coords: torch.Tensor, newest_index: torch.Tensor) -> TensorDictBase:
            return self._relabel(tensordict, query, capturable=True)

        return relabel

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self._relabel(tensordict, None, capturable=False)

    def _relabel(
        self, tensordict: TensorDictBase, query: DistanceFromGraph | None, capturable: bool
    ) -> TensorDictBase:
        if not is_tensor_collection(tensordict):
            raise TypeError(f"HindsightSubgoalRelabel expects a TensorDict, got {type(tensordict).__name__}.")
        values = {}
        for key in (self.action_key, self.goal_key, self.achieved_goal_key):
            value = tensordict.get(key, None)
            if value is None:
                raise KeyError(f"HindsightSubgoalRelabel: {key!r} is missing from the sample.")
            values[key] = value
        batch_size = tensordict.batch_size
        numel = batch_size.numel()
        subgoal = values[self.action_key].reshape(numel, -1)
        goal = values[self.goal_key].reshape(numel, -1)
        achieved = values[self.achieved_goal_key].reshape(numel, -1)
        if not subgoal.shape[-1] == goal.shape[-1] == achieved.shape[-1]:
            raise ValueError(
                f"{self.action_key!r}, {self.goal_key!r} and {self.achieved_goal_key!r} must all be goals "
                f"of the same dimension, got {subgoal.shape[-1]}, {goal.shape[-1]} and {achieved.shape[-1]}."
            )
        device = subgoal.device
        tested = torch.rand(numel, device=device) < self.subgoal_test_ratio
        action = torch.where(tested.unsqueeze(-1), subgoal, achieved.to(subgoal.dtype))

        reward = self.reward_fn(achieved, goal)
        if reward.shape == (numel,):
            reward = reward.unsqueeze(-1)
        if reward.shape != (numel, 1):
            raise ValueError(f"reward_fn must return [B, 1] or [B], got {tuple(reward.shape)} for B={numel}.")
        missed = tested & (
            torch.linalg.vector_norm(achieved.to(subgoal.dtype) - subgoal, dim=-1)
            > self.subgoal_test_threshold
        )
        far = torch.zeros_like(tested)
        if capturable:  # every row queried (static shapes), kept where the subgoal is tested
            if query is not None:
                far = tested & self._far_from_graph(subgoal, query)
        elif self.gradual_penalty is not None and self.distance_from_graph is not None and bool(tested.any()):
            far[tested] = self._far_from_graph(subgoal[tested])
        if self.far_penalty_requires_miss:
            far = far & missed
        penalty = torch.where(far, -(self.gradual_penalty or 0.0), -self.subgoal_miss_penalty)
        reward = torch.where((far | missed).unsqueeze(-1), penalty.unsqueeze(-1).to(reward.dtype), reward)

        tensordict.set(self.action_key, action.reshape(values[self.action_key].shape))
        tensordict.set(self.reward_key, reward.reshape(*batch_size, 1))
        if self.subgoal_test_key is not None:
            tensordict.set(self.subgoal_test_key, tested.reshape(*batch_size, 1))
        return tensordict

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        return tensordict

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(subgoal_test_ratio={self.subgoal_test_ratio}, "
            f"subgoal_test_threshold={self.subgoal_test_threshold}, "
            f"subgoal_miss_penalty={self.subgoal_miss_penalty}, gradual_penalty={self.gradual_penalty}, "
            f"far_from_graph_threshold={self.far_from_graph_threshold}, "
            f"far_penalty_requires_miss={self.far_penalty_requires_miss})"
        )
