"""High-level transitions ``(s_t, g, sg_t, s_{t+c_h})`` built from collected low-level trajectories."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Literal

import torch
from tensordict import TensorDict, TensorDictBase, is_tensor_collection
from tensordict.utils import NestedKey
from torchrl.envs.transforms import Transform

from torchrl_dhrl._unregistered import UnregisteredAttributes
from torchrl_dhrl.data.future_goals import _next, _SampleTransform, _unravel_key
from torchrl_dhrl.data.rewards import SparseGoalReward

__all__ = ["HighLevelTransitionBuilder"]

_NO_END = torch.iinfo(torch.int64).max


def _flag(td: TensorDictBase, key: NestedKey, shape: torch.Size) -> torch.Tensor:
    value = td.get(key)
    if value.shape == shape + (1,):
        value = value.squeeze(-1)
    if value.shape != shape:
        raise ValueError(
            f"{key!r} must have shape {tuple(shape)} or {(*shape, 1)}, got {tuple(value.shape)}."
        )
    return value


def _stable_sort_by(
    records: TensorDictBase, primary: torch.Tensor, secondary: torch.Tensor
) -> TensorDictBase:
    order = torch.sort(secondary, stable=True).indices
    order = order[torch.sort(primary[order], stable=True).indices]
    return records[order]


class HighLevelTransitionBuilder(UnregisteredAttributes, _SampleTransform, Transform):
    """Cuts collected low-level trajectories into high-level transitions, one per subgoal.

    The high-level actor issues a subgoal every ``c_h`` steps and flags that step with ``new_subgoal``.
    Each run of steps from one flag to the step before the next flag (or to the episode's last step) is a
    *segment*, and gives one high-level transition

    ``(s_t, ag_t, g, sg_t)  ->  (s_{t+c}, ag_{t+c}, g, r, done)``

    with ``s_t`` the observation at the flagged step, ``g`` the environment's goal, ``sg_t`` the issued
    subgoal (the high-level action, under ``action_key``), ``s_{t+c}`` / ``ag_{t+c}`` the next observation and
    achieved goal of the segment's last step (the state at the next flag, or the final state of the
    episode), ``c <= c_h`` the segment's length and ``r = reward_fn(ag_{t+c}, g)`` (sparse ``-1`` / ``0`` at
    ``0.5`` by default). ``("next", goal_key)`` repeats ``g`` and the done flags are those of the
    segment's last step. Each record also carries its ``episode_id`` (unique, assigned by the builder),
    ``segment_index`` (0, 1, ... within the episode) and ``segment_length`` ``c`` (int64, shape ``[1]``),
    which :class:`~torchrl_dhrl.data.FutureGoalRelabel` uses as episode markers for hindsight goals within
    the high-level window (pass ``traj_key="episode_id", step_count_key="segment_index"``). The segment's
    final achieved goal ``("next", "achieved_goal")`` is what HAC hindsight action relabelling
    (:class:`~torchrl_dhrl.data.HindsightSubgoalRelabel`) substitutes for the subgoal.

    **Batches.** The input is a collector batch with time as its last batch dimension: ``[T]`` for one
    env, ``[num_envs, T]`` for a batched env (more leading dimensions are flattened into lanes). Batches do
    not need to be aligned with episodes or segments: a segment that spans several batches is kept open in
    the builder's state (the record at its flagged step, its length so far and the next state of its last
    step, per lane) and emitted once its end is seen; a segment is closed by the next ``new_subgoal``
    flag, by ``("next", "done")`` or by a reset that was not flagged done (``step_count == 0``, marked
    done and truncated). Steps of an episode before its first flag belong to no segment and are dropped
    (the high-level actor should flag the first step of every episode). The state consists of tensors
    (``TensorDict`` s), follows the input's device and is saved by ``state_dict()`` through
    ``get_extra_state`` (so a replay buffer holding the builder checkpoints it too); the number of lanes
    must stay the same between calls (:meth:`reset` starts over).

    **Emission.** With ``emit="episode"`` (default) the segments of an episode are held back until the
    episode ends and then emitted together, in order: a 1-D replay storage then holds every episode
    contiguously, the layout :class:`~torchrl_dhrl.data.FutureGoalRelabel` needs to find future segments
    of the same episode (the reference stores whole episodes too). With ``emit="segment"`` every segment
    is emitted as soon as it ends. Within one call, the output is sorted by episode id, then segment index.

    Use it offline with :meth:`build` (or ``builder.inv(batch)``), or as a replay-buffer transform:
    ``TensorDictReplayBuffer(storage=LazyTensorStorage(n), transform=builder)`` turns every
    ``rb.extend(low_level_batch)`` into writes of high-level transitions (``forward`` is the identity, so
    sampling is unaffected), like :class:`~torchrl.envs.transforms.MultiStepTransform`.

    Keyword Args:
        observation_keys (sequence of NestedKey, optional): state entries copied from the flagged step,
            and their ``("next", key)`` from the segment's last step. Must contain ``achieved_goal_key``.
            Defaults to ``("observation", "achieved_goal")``.
        goal_key (NestedKey, optional): the environment goal ``g``. Defaults to ``"desired_goal"``.
        subgoal_key (NestedKey, optional): the subgoal in force. Defaults to ``"subgoal"``.
        new_subgoal_key (NestedKey, optional): bool flag of the steps where a subgoal was issued.
            Defaults to ``"new_subgoal"``.
        action_key (NestedKey, optional): where the issued subgoal (the high-level action) is written.
            Defaults to ``"subgoal"`` (the action key of :class:`~torchrl_dhrl.objectives.HighLevelLoss`).
        achieved_goal_key (NestedKey, optional): achieved goal entry (the reward compares
            ``("next", achieved_goal_key)`` with ``g``). Defaults to ``"achieved_goal"``.
        done_keys (sequence of NestedKey, optional): end-of-episode flags read under ``"next"``; the first
            is required and ends episodes, the others are copied when present. Defaults to
            ``("done", "terminated", "truncated")``.
        step_count_key (NestedKey, optional): per-episode low-level step counter (``0`` at reset), used
            to detect resets when present (it is not copied: the high-level counter is
            ``segment_index``); ``None`` to ignore. Defaults to ``"step_count"``.
        reward_fn (callable, optional): ``reward_fn(achieved_goal, goal) -> [M, 1]``. Defaults to
            :class:`~torchrl_dhrl.data.SparseGoalReward` with threshold ``0.5``. An ``nn.Module`` is
            kept as a plain attribute, not a submodule (not in ``state_dict()``).
        reward_key (NestedKey, optional): where the reward is written. Defaults to ``("next", "reward")``.
        episode_id_key, segment_index_key, segment_length_key (NestedKey, optional): where the episode id,
            segment index and segment length are written. Default to ``"episode_id"``,
            ``"segment_index"`` and ``"segment_length"``.
        emit (str, optional): ``"episode"`` or ``"segment"`` (see above). Defaults to ``"episode"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> T = 10
        >>> step = torch.arange(T)
        >>> position = torch.stack([step, -step], -1).float()
        >>> batch = TensorDict(
        ...     {
        ...         "observation": position,
        ...         "achieved_goal": position,
        ...         "desired_goal": torch.full((T, 2), 9.0),
        ...         "subgoal": (step // 4 * 4 + 4).float().unsqueeze(-1).expand(T, 2),
        ...         "new_subgoal": (step % 4 == 0).unsqueeze(-1),
        ...         "step_count": step.unsqueeze(-1),
        ...         ("next", "observation"): position + torch.tensor([1.0, -1.0]),
        ...         ("next", "achieved_goal"): position + torch.tensor([1.0, -1.0]),
        ...         ("next", "done"): (step == T - 1).unsqueeze(-1),
        ...     },
        ...     batch_size=[T],
        ... )
        >>> builder = HighLevelTransitionBuilder()
        >>> transitions = builder.build(batch)  # segments [0, 4), [4, 8), [8, 10)
        >>> transitions["observation"][:, 0]
        tensor([0., 4., 8.])
        >>> transitions["next", "observation"][:, 0]
        tensor([ 4.,  8., 10.])
        >>> transitions["segment_length"].squeeze(-1)
        tensor([4, 4, 2])
        >>> transitions["next", "done"].squeeze(-1)
        tensor([False, False,  True])
    """

    #: ``reward_fn`` may be an ``nn.Module``: a plain attribute, not a submodule
    _unregistered = ("reward_fn",)
    _usage = (
        "it cuts collected trajectories; call build(batch) or pass it as a replay buffer's transform "
        "(rb.extend)"
    )

    def __init__(
        self,
        *,
        observation_keys: Sequence[NestedKey] = ("observation", "achieved_goal"),
        goal_key: NestedKey = "desired_goal",
        subgoal_key: NestedKey = "subgoal",
        new_subgoal_key: NestedKey = "new_subgoal",
        action_key: NestedKey = "subgoal",
        achieved_goal_key: NestedKey = "achieved_goal",
        done_keys: Sequence[NestedKey] = ("done", "terminated", "truncated"),
        step_count_key: NestedKey | None = "step_count",
        reward_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
        reward_key: NestedKey = ("next", "reward"),
        episode_id_key: NestedKey = "episode_id",
        segment_index_key: NestedKey = "segment_index",
        segment_length_key: NestedKey = "segment_length",
        emit: Literal["episode", "segment"] = "episode",
    ) -> None:
        observation_keys = [_unravel_key(k) for k in observation_keys]
        achieved_goal_key = _unravel_key(achieved_goal_key)
        if achieved_goal_key not in observation_keys:
            raise ValueError(
                f"observation_keys {observation_keys} must contain achieved_goal_key {achieved_goal_key!r}."
            )
        done_keys = [_unravel_key(k) for k in done_keys]
        if not done_keys:
            raise ValueError("done_keys must name at least the end-of-episode flag (e.g. 'done').")
        if emit not in ("episode", "segment"):
            raise ValueError(f"emit must be 'episode' or 'segment', got {emit!r}.")
        if reward_fn is None:
            reward_fn = SparseGoalReward(0.5)
        elif not callable(reward_fn):
            raise TypeError(f"reward_fn must be callable, got {type(reward_fn).__name__}.")
        goal_key, subgoal_key = _unravel_key(goal_key), _unravel_key(subgoal_key)
        new_subgoal_key, action_key = _unravel_key(new_subgoal_key), _unravel_key(action_key)
        super().__init__(
            in_keys=[*observation_keys, goal_key, subgoal_key, new_subgoal_key],
            out_keys=[*observation_keys, goal_key, action_key],
        )
        self.observation_keys = observation_keys
        self.goal_key = goal_key
        self.subgoal_key = subgoal_key
        self.new_subgoal_key = new_subgoal_key
        self.action_key = action_key
        self.achieved_goal_key = achieved_goal_key
        self.done_keys = done_keys
        self.step_count_key = None if step_count_key is None else _unravel_key(step_count_key)
        self.reward_fn = reward_fn
        self.reward_key = _unravel_key(reward_key)
        self.episode_id_key = _unravel_key(episode_id_key)
        self.segment_index_key = _unravel_key(segment_index_key)
        self.segment_length_key = _unravel_key(segment_length_key)
        self.emit = emit
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forgets open segments, held-back episodes and the episode counter."""
        self._state: TensorDictBase | None = None
        self._pending: TensorDictBase | None = None
        self._next_episode_id = 0

    @property
    def num_pending(self) -> int:
        """Number of completed segments held back until their episode ends (``emit="episode"``)."""
        return 0 if self._pending is None else self._pending.batch_size[0]

    def get_extra_state(self) -> dict[str, Any]:
        def dump(td):
            return None if td is None else {"data": td.to_dict(), "batch_size": list(td.batch_size)}

        return {
            "state": dump(self._state),
            "pending": dump(self._pending),
            "next_episode_id": self._next_episode_id,
        }

    def set_extra_state(self, state: dict[str, Any]) -> None:
        def load(entry):
            if entry is None:
                return None
            return TensorDict(entry["data"], batch_size=entry["batch_size"])

        self._state = load(state["state"])
        self._pending = load(state["pending"])
        self._next_episode_id = int(state["next_episode_id"])

    # ------------------------------------------------------------------ building

    def _rows(self, td: TensorDictBase) -> tuple[TensorDictBase, list[NestedKey], list[NestedKey]]:
        """The per-step entries a record is made of: start fields and end (``"next"``) fields."""
        present = set(td.keys(True, True))
        missing = [
            key
            for key in [
                *self.observation_keys,
                *(_next(k) for k in self.observation_keys),
                self.goal_key,
                self.subgoal_key,
                self.new_subgoal_key,
                _next(self.done_keys[0]),
            ]
            if key not in present
        ]
        if missing:
            raise KeyError(f"HighLevelTransitionBuilder: the batch is missing {missing}.")
        rows = TensorDict(batch_size=td.batch_size, device=td.device)
        for key in self.observation_keys:
            rows.set(key, td.get(key))
            rows.set(_next(key), td.get(_next(key)))
        rows.set(self.goal_key, td.get(self.goal_key))
        rows.set(self.action_key, td.get(self.subgoal_key))
        if self.step_count_key is not None and self.step_count_key in present:
            rows.set(self.step_count_key, td.get(self.step_count_key))
        for key in self.done_keys:
            if _next(key) in present:
                rows.set(_next(key), _flag(td, _next(key), td.batch_size).bool().unsqueeze(-1))
        start_keys = [*self.observation_keys, self.goal_key, self.action_key]
        end_keys = [_next(k) for k in self.observation_keys] + [
            _next(k) for k in self.done_keys if _next(k) in present
        ]
        return rows, start_keys, end_keys

    def build(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Returns the high-level transitions completed by ``tensordict`` (a flat TensorDict ``[M]``)."""
        if not is_tensor_collection(tensordict):
            raise TypeError(
                f"HighLevelTransitionBuilder expects a TensorDict, got {type(tensordict).__name__}."
            )
        if tensordict.batch_dims < 1 or tensordict.batch_size[-1] == 0:
            raise ValueError(
                "HighLevelTransitionBuilder expects a trajectory batch with time as the last batch dimension "
                f"([T] or [num_envs, T], T >= 1), got batch_size={tuple(tensordict.batch_size)}."
            )
        td = tensordict.reshape(-1, tensordict.batch_size[-1])
        num_lanes, horizon = td.batch_size
        real, start_keys, end_keys = self._rows(td)
        device = real.device if real.device is not None else td.get(self.goal_key).device
        starts = _flag(td, self.new_subgoal_key, td.batch_size).bool()
        dones = real.get(_next(self.done_keys[0])).squeeze(-1)
        state = self._prepare_state(real, device)
        lane = torch.arange(num_lanes, device=device)
        col = torch.arange(horizon + 1, device=device).expand(num_lanes, horizon + 1)

        # columns: 0 is the open segment carried over from the previous batch, 1..T this batch's steps
        rows = torch.cat([state.get("record").unsqueeze(1), real], dim=1)
        start = torch.cat([state.get("open").unsqueeze(1), starts], dim=1)
        done = torch.cat([torch.zeros_like(dones[:, :1]), dones], dim=1)
        new_episode = torch.zeros_like(start)
        new_episode[:, 1] = ~state.get("episode_active")
        new_episode[:, 2:] = done[:, 1:-1]
        if self.step_count_key is not None and self.step_count_key in real.keys(True, True):
            new_episode[:, 1:] |= _flag(td, self.step_count_key, td.batch_size) == 0
        # a segment ends where the episode ends or where the next segment / episode starts
        end = done.clone()
        end[:, :-1] |= start[:, 1:] | new_episode[:, 1:]
        next_end = torch.where(end, col, torch.full_like(col, _NO_END))
        next_end = next_end.flip(1).cummin(1).values.flip(1)

        # episode ids: fresh ids in lane-major order, carried along time
        fresh = (
            new_episode.flatten().long().cumsum(0).reshape(num_lanes, horizon + 1) - 1 + self._next_episode_id
        )
        episode = torch.where(new_episode, fresh, torch.full_like(fresh, -1))
        episode[:, 0] = state.get("episode_id")
        episode = episode.cummax(1).values
        self._next_episode_id += int(new_episode.sum())

        # segment index within the episode (column 0: the carried segment's own index)
        episode_start = torch.where(new_episode, col, torch.zeros_like(col)).cummax(1).values
        count = start.long()
        count[:, 0] = 0
        count = count.cumsum(1)
        before = count.gather(1, (episode_start - 1).clamp_min(0))
        base = torch.where(
            episode_start == 0, state.get("num_segments").unsqueeze(1), torch.zeros_like(count)
        )
        segment_index = base + count - 1 - before
        segment_index[:, 0] = state.get("num_segments") - 1
        length = torch.ones_like(count)
        length[:, 0] = state.get("length")

        # completed segments
        start_lane, start_col = start.nonzero(as_tuple=True)
        end_col = next_end[start_lane, start_col]
        complete = end_col != _NO_END
        s_lane, s_col, e_col = start_lane[complete], start_col[complete], end_col[complete]
        records = self._records(rows, start_keys, end_keys, s_lane, s_col, e_col)
        cut = ~done[s_lane, e_col] & new_episode[s_lane, (e_col + 1).clamp_max(horizon)] & (e_col < horizon)
        for key in self.done_keys[:1] + [k for k in self.done_keys[1:] if k == "truncated"]:
            if _next(key) in records.keys(True, True):
                records.set(_next(key), records.get(_next(key)) | cut.unsqueeze(-1))
        records.set(self.episode_id_key, episode[s_lane, s_col].unsqueeze(-1))
        records.set(self.segment_index_key, segment_index[s_lane, s_col].unsqueeze(-1))
        records.set(self.segment_length_key, (length[s_lane, s_col] + e_col - s_col).unsqueeze(-1))

        # the segment still open at the end of the batch becomes the carried state
        last_start = torch.where(start, col, torch.full_like(col, -1)).cummax(1).values[:, -1]
        is_open = (last_start >= 0) & (next_end[lane, last_start.clamp_min(0)] == _NO_END)
        keep_col = torch.where(is_open, last_start, torch.full_like(last_start, horizon))
        record = rows[lane, keep_col].clone()
        record.update(rows[:, -1].select(*end_keys))
        base_last = torch.where(
            episode_start[:, -1] == 0, state.get("num_segments"), torch.zeros_like(count[:, -1])
        )
        self._state = TensorDict(
            {
                "record": record,
                "open": is_open,
                "length": torch.where(is_open, length[lane, keep_col] + horizon - keep_col, 0),
                "episode_id": episode[:, -1],
                "episode_active": ~done[:, -1],
                "num_segments": base_last + count[:, -1] - before[:, -1],
            },
            batch_size=[num_lanes],
        )
        return self._emit(records)

    def _records(self, rows, start_keys, end_keys, lane, s_col, e_col) -> TensorDictBase:
        records = rows[lane, s_col].select(*start_keys)
        records.update(rows[lane, e_col].select(*end_keys))
        goal = records.get(self.goal_key)
        records.set(_next(self.goal_key), goal.clone())
        reward = self.reward_fn(records.get(_next(self.achieved_goal_key)), goal)
        if reward.shape == records.batch_size:
            reward = reward.unsqueeze(-1)
        records.set(self.reward_key, reward)
        return records

    def _prepare_state(self, real: TensorDictBase, device: torch.device) -> TensorDictBase:
        num_lanes = real.batch_size[0]
        if self._state is None:
            zeros = torch.zeros(num_lanes, dtype=torch.long, device=device)
            self._state = TensorDict(
                {
                    "record": real[:, 0].clone().zero_(),
                    "open": zeros.bool(),
                    "length": zeros,
                    "episode_id": zeros - 1,
                    "episode_active": zeros.bool(),
                    "num_segments": zeros,
                },
                batch_size=[num_lanes],
            )
        if self._state.batch_size[0] != num_lanes:
            raise ValueError(
                f"HighLevelTransitionBuilder was fed {self._state.batch_size[0]} lanes (envs) before and "
                f"{num_lanes} now; call reset() before changing the number of envs."
            )
        record_keys = set(self._state.get("record").keys(True, True))
        if record_keys != set(real.keys(True, True)):
            raise KeyError(
                "HighLevelTransitionBuilder: the batch entries changed between calls: "
                f"{sorted(map(str, record_keys ^ set(real.keys(True, True))))}."
            )
        self._state = self._state.to(device)
        if self._pending is not None:
            self._pending = self._pending.to(device)
        return self._state

    def _emit(self, records: TensorDictBase) -> TensorDictBase:
        if self.emit == "episode":
            if self._pending is not None:
                records = torch.cat([self._pending, records], 0)
            episode = records.get(self.episode_id_key).squeeze(-1)
            ended = episode[records.get(_next(self.done_keys[0])).squeeze(-1)]
            finished = torch.isin(episode, ended)
            self._pending = records[~finished]
            records = records[finished]
        return _stable_sort_by(
            records,
            records.get(self.episode_id_key).squeeze(-1),
            records.get(self.segment_index_key).squeeze(-1),
        )

    #: it acts on writes only (``inv``); a sample goes through unchanged, so a capture-safe sampler may skip it
    sample_identity = True

    # ------------------------------------------------------------------ transform API
    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase | None:
        records = self.build(tensordict)
        return records if records.batch_size[0] else None

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return tensordict

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(emit={self.emit!r}, goal_key={self.goal_key!r}, "
            f"subgoal_key={self.subgoal_key!r}, action_key={self.action_key!r})"
        )
