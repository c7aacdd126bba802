"""Hindsight relabelling with future achieved goals of the same episode (DHRL's "future" strategy)."""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDictBase, is_tensor_collection
from tensordict.utils import NestedKey
from torchrl.data.replay_buffers import ReplayBuffer
from torchrl.data.replay_buffers.storages import Storage, TensorStorage
from torchrl.envs import EnvBase
from torchrl.envs.transforms import Compose, Transform

from torchrl_dhrl._unregistered import UnregisteredAttributes
from torchrl_dhrl.data.rewards import SparseGoalReward

__all__ = ["FutureGoalRelabel"]

_DEFAULT_REWARD_KEYS = (("next", "reward"), ("next", "graph_reward"))

RewardFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def _next(key: NestedKey) -> tuple:
    return ("next", *key) if isinstance(key, tuple) else ("next", key)


def _unravel_key(key: NestedKey) -> NestedKey:
    if isinstance(key, (list, tuple)):
        key = tuple(key)
        return key[0] if len(key) == 1 else key
    if isinstance(key, str):
        return key
    raise TypeError(f"Expected a NestedKey (str or tuple of str), got {key!r}.")


class _SampleTransform:
    """Mixin of the replay-buffer transforms of :mod:`torchrl_dhrl.data`: refuses to go in an environment.

    TorchRL calls ``set_container`` as soon as a transform is put in a
    :class:`~torchrl.envs.TransformedEnv` (directly, through ``append_transform`` or inside a
    :class:`~torchrl.envs.Compose` attached to one), before any spec or data goes through it; the
    clear error is raised there instead of a spec ``KeyError`` or a missing-entry error at the
    first reset or step. ``_usage`` completes the message with how the transform is meant to be used.
    """

    _usage = "apply it to replay-buffer samples"

    def _not_an_env_transform(self) -> RuntimeError:
        return RuntimeError(
            f"{type(self).__name__} is not an environment transform: {self._usage}, not inside an "
            "environment (TransformedEnv, env.append_transform)."
        )

    def set_container(self, container) -> None:
        super().set_container(container)
        env = container
        while isinstance(env, Compose):  # a Compose not (yet) attached to an env ends the walk with None
            ref = env.__dict__.get("_container")
            env = ref() if ref is not None else None
        if isinstance(env, EnvBase):
            self.reset_parent()
            raise self._not_an_env_transform()

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        raise self._not_an_env_transform()


class FutureGoalRelabel(UnregisteredAttributes, _SampleTransform, Transform):
    """Relabels the goals of sampled transitions with future achieved goals of the same episode.

    This is the hindsight step of DHRL (and of its reference implementation) for both levels. For each
    sampled transition ``t`` and each output ``i``, with probability ``her_ratio[i]`` the goal is replaced by
    the achieved goal reached at the end of transition ``t + k`` of the same episode,

    .. math::

        \\hat g_t = ag_{t + 1 + k}, \\qquad k = \\lfloor U \\cdot \\min(T_t, W) \\rfloor,
        \\quad U \\sim \\mathcal{U}[0, 1),

    where ``T_t`` is the number of stored transitions of the episode from ``t`` on (``t`` included) and ``W``
    is ``window`` (150 low-level steps, or the high-level window in high-level steps). The goal is
    therefore at least one step ahead (``k = 0`` is the transition's own next achieved goal, reward ``0``),
    never more than ``W`` steps ahead, and never taken from another episode. The reward is then
    recomputed from the goals with ``reward_fn(achieved_goal[t], goal)`` for every sample (relabelled or
    not), where ``achieved_goal`` is ``achieved_goal_key`` (the next achieved goal).

    Several outputs can be written from one sample: DHRL's SQGC trains the policy critics with 80 %
    relabelled goals and the graph critics with 100 %, so the defaults write two goal / reward pairs,
    ``"goal"`` / ``("next", "reward")`` (ratio 0.8, policy critics) and ``"graph_goal"`` /
    ``("next", "graph_reward")`` (ratio 1.0, graph critics), the default keys of
    :class:`~torchrl_dhrl.objectives.SQGCLoss`, drawn independently for the same transitions (the
    reference draws two independent batches; sharing the transitions halves the sampling cost and each
    critic still sees its own relabelling distribution). With
    ``write_next_goal=True`` each goal is also written under ``("next", out_key)`` so a target policy run
    on ``td["next"]`` sees the same goal.

    **A relabel step of the replay buffer.** The future records of the same episode are read from the
    storage at the sample's storage coordinates, which a transform appended with ``rb.append_transform``
    never sees (it runs on the sampled records alone). Pass this relabeller to
    :class:`~torchrl_dhrl.data.RelabelReplayBuffer` (``relabel=[FutureGoalRelabel(...), ...]``): the
    buffer hands it the sampled indices, its storage and its newest write position, and ``rb.sample()``
    returns relabelled data, like torchrl's :class:`~torchrl.data.HERReplayBuffer` (which needs a 1-D
    storage, includes the current step, has no window cap and supports a single ratio). On data read from
    a storage by other means, call :meth:`relabel_sample` with the coordinates. Any sampler works, with
    1-D storages and multi-dimensional ones (time first, then lanes, as ``LazyTensorStorage(..., ndim=2)``
    stores collector batches of shape ``[num_envs, T]``). Called as a plain transform (``relabel(td)``,
    in a :class:`~torchrl.envs.Compose` or appended to a buffer), it raises an error saying so.

    **Episode boundaries.** For each sample, the window of the next ``W`` records along the storage's
    time dimension (modulo its length, so a circular buffer's wrap-around is followed) is read once and a
    record ``t + j`` is accepted only if every available marker agrees: same trajectory id
    (``traj_key``, e.g. the collector's ``("collector", "traj_ids")``), consecutive step counter
    (``step_count[t + j] == step_count[t] + j``), no done flag at ``t .. t + j - 1`` (``done_key``), and
    ``t + j`` not past the newest written record (the write seam of a full circular buffer: the
    ``newest_index`` that :class:`~torchrl_dhrl.data.RelabelReplayBuffer` tracks; a storage that has not
    wrapped around yet needs none). The first rejected record ends the window. Markers that are ``None``
    or absent from the storage are skipped; at least one of the three must be present. Storing ``[num_envs, T]`` batches in a 1-D storage with
    ``rb.extend(batch.reshape(-1))`` interleaves partial episodes of different envs: with trajectory ids
    no goal crosses an episode, but windows stop at the end of each chunk. Store such batches with
    ``LazyTensorStorage(capacity, ndim=2)`` instead, which keeps each env's time line contiguous.

    The storage (a :class:`~torchrl.data.replay_buffers.TensorStorage`, e.g. ``LazyTensorStorage``) must
    hold ``achieved_goal_key`` and the markers.

    Args:
        reward_fn (callable, optional): ``reward_fn(achieved_goal, goal) -> reward`` on tensors of shape
            ``[B, goal_dim]``, returning ``[B, 1]`` or ``[B]``. Defaults to
            :class:`~torchrl_dhrl.data.SparseGoalReward` with threshold ``0.5`` (``-1`` / ``0``). An
            ``nn.Module`` is kept as a plain attribute, not a submodule (not in ``state_dict()``).

    Keyword Args:
        her_ratio (float or sequence of float, optional): relabelling probability of each output, in
            ``[0, 1]``, drawn independently per sample (Bernoulli, as the reference). Defaults to
            ``(0.8, 1.0)``.
        window (int, optional): the maximum look-ahead ``W`` in stored records. Defaults to ``150``.
        goal_key (NestedKey, optional): the goal the agent actually chased (for the low level: the
            waypoint). Defaults to ``"desired_goal"``.
        achieved_goal_key (NestedKey, optional): the achieved goal after the transition, used both as
            the relabelling source (read from the storage at ``t + k``) and for the reward (read from the
            sample). Defaults to ``("next", "achieved_goal")``.
        out_keys (sequence of NestedKey, optional): where each output's goal is written, one per ratio.
            Passing ``[goal_key]`` relabels in place. Defaults to ``("goal", "graph_goal")``.
        reward_keys (sequence of NestedKey, optional): where each output's reward is written, one per
            ratio, or ``None`` to write no reward. Defaults to ``"default"``, meaning
            ``(("next", "reward"), ("next", "graph_reward"))`` for two outputs and
            ``[("next", "reward")]`` for one.
        traj_key (NestedKey, optional): trajectory / episode id marker. Defaults to
            ``("collector", "traj_ids")``.
        done_key (NestedKey, optional): end-of-episode marker of each transition. Defaults to
            ``("next", "done")``.
        step_count_key (NestedKey, optional): per-episode step counter marker. Defaults to
            ``"step_count"``.
        write_next_goal (bool, optional): also write each goal under ``("next", out_key)``. Defaults to
            ``True``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage
        >>> from torchrl_dhrl.data import RelabelReplayBuffer
        >>> num_envs, T = 2, 8
        >>> step = torch.arange(T).expand(num_envs, T)
        >>> achieved = torch.stack([torch.arange(num_envs)[:, None].expand(num_envs, T), step], -1).float()
        >>> batch = TensorDict(
        ...     {
        ...         "observation": achieved,
        ...         "desired_goal": torch.full((num_envs, T, 2), -1.0),
        ...         "step_count": step.unsqueeze(-1),
        ...         ("next", "achieved_goal"): achieved + torch.tensor([0.0, 1.0]),
        ...         ("next", "done"): (step == T - 1).unsqueeze(-1),
        ...     },
        ...     batch_size=[num_envs, T],
        ... )
        >>> relabel = FutureGoalRelabel(window=3)
        >>> rb = RelabelReplayBuffer(storage=LazyTensorStorage(64, ndim=2), relabel=[relabel], batch_size=16)
        >>> _ = rb.extend(batch)
        >>> sample = rb.sample()  # relabelled by the buffer
        >>> goal, achieved = sample["graph_goal"], sample["next", "achieved_goal"]
        >>> bool((goal[:, 0] == achieved[:, 0]).all())  # same env and episode
        True
        >>> offset = goal[:, 1] - achieved[:, 1]  # steps ahead of the next achieved goal
        >>> bool(((offset >= 0) & (offset < 3)).all())
        True
        >>> sample["next", "graph_reward"].shape
        torch.Size([16, 1])
        >>> index = sample["index"]  # the same relabelling, called directly on records read from the storage
        >>> records = rb.storage[index.unbind(-1)]
        >>> again = relabel.relabel_sample(records, index, rb.storage, newest_index=rb.newest_index)
        >>> bool(((again["goal"] - again["next", "achieved_goal"])[:, 1] < 3).all())
        True
    """

    #: ``reward_fn`` may be an ``nn.Module``: a plain attribute, not a submodule (not in ``state_dict()``)
    _unregistered = ("reward_fn",)
    _usage = "it relabels replay-buffer samples; pass it to RelabelReplayBuffer(relabel=[...])"

    def __init__(
        self,
        reward_fn: RewardFn | None = None,
        *,
        her_ratio: float | Sequence[float] = (0.8, 1.0),
        window: int = 150,
        goal_key: NestedKey = "desired_goal",
        achieved_goal_key: NestedKey = ("next", "achieved_goal"),
        out_keys: Sequence[NestedKey] = ("goal", "graph_goal"),
        reward_keys: Sequence[NestedKey] | None | str = "default",
        traj_key: NestedKey | None = ("collector", "traj_ids"),
        done_key: NestedKey | None = ("next", "done"),
        step_count_key: NestedKey | None = "step_count",
        write_next_goal: bool = True,
    ) -> None:
        if isinstance(reward_fn, (ReplayBuffer, Storage)):
            raise TypeError(
                "FutureGoalRelabel does not take the replay buffer or its storage: pass it to "
                "RelabelReplayBuffer(storage=..., relabel=[FutureGoalRelabel(...)]), which hands it the "
                "sampled indices and the storage, or call relabel_sample(data, index, storage)."
            )
        if isinstance(her_ratio, (int, float)) and not isinstance(her_ratio, bool):
            her_ratio = (her_ratio,)
        her_ratio = tuple(float(r) for r in her_ratio)
        if not her_ratio or any(not 0.0 <= r <= 1.0 for r in her_ratio):
            raise ValueError(f"her_ratio must be one or more probabilities in [0, 1], got {her_ratio}.")
        out_keys = [_unravel_key(k) for k in ([out_keys] if isinstance(out_keys, str) else out_keys)]
        if len(out_keys) != len(her_ratio):
            raise ValueError(
                f"Expected one out_key per her_ratio, got {len(out_keys)} out_keys for "
                f"{len(her_ratio)} ratios."
            )
        if isinstance(reward_keys, str) and reward_keys == "default":
            if len(her_ratio) > 2:
                raise ValueError(
                    f"Pass one reward key per her_ratio ({len(her_ratio)}), or reward_keys=None."
                )
            reward_keys = [("next", "reward")] if len(her_ratio) == 1 else list(_DEFAULT_REWARD_KEYS)
        if reward_keys is not None:
            reward_keys = [
                _unravel_key(k) for k in ([reward_keys] if isinstance(reward_keys, str) else reward_keys)
            ]
            if len(reward_keys) != len(her_ratio):
                raise ValueError(
                    f"Expected one reward key per her_ratio, got {len(reward_keys)} reward_keys for "
                    f"{len(her_ratio)} ratios (pass reward_keys=None to write no reward)."
                )
        if isinstance(window, bool) or not isinstance(window, int) or window < 1:
            raise ValueError(f"window must be a positive integer, got {window!r}.")
        if reward_fn is None:
            reward_fn = SparseGoalReward(0.5)
        elif not callable(reward_fn):
            raise TypeError(f"reward_fn must be callable, got {type(reward_fn).__name__}.")
        if traj_key is None and done_key is None and step_count_key is None:
            raise ValueError("At least one of traj_key, done_key and step_count_key must be given.")
        goal_key = _unravel_key(goal_key)
        super().__init__(
            in_keys=[goal_key, _unravel_key(achieved_goal_key)],
            out_keys=out_keys
            + ([_next(k) for k in out_keys] if write_next_goal else [])
            + (reward_keys or []),
        )
        self.reward_fn = reward_fn
        self.her_ratio = her_ratio
        self.window = window
        self.goal_key = goal_key
        self.achieved_goal_key = _unravel_key(achieved_goal_key)
        self.goal_out_keys = out_keys
        self.reward_keys = reward_keys
        self.traj_key = None if traj_key is None else _unravel_key(traj_key)
        self.done_key = None if done_key is None else _unravel_key(done_key)
        self.step_count_key = None if step_count_key is None else _unravel_key(step_count_key)
        self.write_next_goal = write_next_goal
        self._warned_seam = False

    # ------------------------------------------------------------------ storage access
    @staticmethod
    def _check_storage(storage: Storage) -> TensorStorage:
        if not isinstance(storage, TensorStorage):
            raise TypeError(
                "FutureGoalRelabel needs the TensorStorage the samples come from (e.g. LazyTensorStorage), "
                f"got {type(storage).__name__}."
            )
        return storage

    @staticmethod
    def _field(
        storage: TensorStorage, key: NestedKey, required: bool = False, whole: bool = False
    ) -> torch.Tensor | None:
        """The written part of one storage entry, shape ``[T_len, *lanes, *feature]`` (a view).

        Reads the one entry and slices it: ``storage.get(key)`` would first slice every entry of the
        storage's TensorDict (about a sixth of a sample's time at the quick preset). With ``whole=True``
        the whole preallocated entry (``[T_max, *lanes, *feature]``, static shape) is returned.
        """
        data = storage._storage
        if not is_tensor_collection(data):
            if whole:
                raise TypeError(
                    "FutureGoalRelabel: a capture-safe relabelling needs a TensorDict storage (e.g. "
                    f"LazyTensorStorage), got entries of type {type(data).__name__}."
                )
            data = storage.get(slice(None))  # the rows written so far
        value = data.get(key, None)
        if value is None:
            if required:
                raise KeyError(
                    f"FutureGoalRelabel: {key!r} is not in the storage; the replay buffer must store it."
                )
            return None
        if whole:
            return value
        lanes = value.shape[1 : storage.ndim].numel()
        return value[: -(-len(storage) // lanes)]  # the rows written so far (all of a full storage)

    def _storage_fields(self, storage: TensorStorage, whole: bool = False) -> dict[str, torch.Tensor | None]:
        """The storage entries the relabelling reads: achieved goals and the episode markers found."""
        fields = {"achieved": self._field(storage, self.achieved_goal_key, required=True, whole=whole)}
        for name, key in (("traj", self.traj_key), ("count", self.step_count_key), ("done", self.done_key)):
            fields[name] = None if key is None else self._field(storage, key, whole=whole)
        if fields["traj"] is None and fields["count"] is None and fields["done"] is None:
            raise KeyError(
                "FutureGoalRelabel: none of the episode markers "
                f"{[k for k in (self.traj_key, self.step_count_key, self.done_key) if k is not None]} is in "
                "the storage, so episode boundaries cannot be told apart."
            )
        return fields

    @staticmethod
    def _newest_time_index(
        storage: TensorStorage, length: int, newest_index: int | torch.Tensor | None
    ) -> int | torch.Tensor | None:
        """Time coordinate of the most recently written record, or ``None`` if unknown (a tensor stays one)."""
        if isinstance(newest_index, torch.Tensor):
            return torch.remainder(newest_index, length)
        if newest_index is not None:
            return int(newest_index) % length
        if len(storage) < storage.max_size:  # not wrapped around yet: the last written row is the newest
            return length - 1
        return None

    @staticmethod
    def _marker(field: torch.Tensor, storage_ndim: int, flat: torch.Tensor) -> torch.Tensor:
        """Gathers one scalar marker per record (stored as ``[T, *lanes]`` or ``[T, *lanes, 1]``)."""
        records = field.shape[:storage_ndim].numel()
        if field.numel() != records:
            raise ValueError(
                f"Episode markers must hold one value per record, got shape {tuple(field.shape)}."
            )
        return field.reshape(records)[flat]

    @staticmethod
    def _coordinates(index: torch.Tensor | tuple, batch_size: torch.Size, ndim: int) -> torch.Tensor:
        if isinstance(index, tuple):  # per-dimension coordinates, as a sampler's info["index"]
            index = torch.stack([torch.as_tensor(i) for i in index], -1)
        elif not isinstance(index, torch.Tensor):
            index = torch.as_tensor(index)
        if index.dtype in (torch.float16, torch.bfloat16, torch.float32, torch.float64, torch.bool):
            raise TypeError(f"index must hold integer storage coordinates, got {index.dtype}.")
        numel = batch_size.numel()
        if ndim == 1 and index.shape in (batch_size, batch_size + (1,)):
            return index.reshape(numel, 1).long()
        if ndim > 1 and index.shape == batch_size + (ndim,):
            return index.reshape(numel, ndim).long()
        expected = tuple(batch_size) if ndim == 1 else (*batch_size, ndim)
        raise ValueError(
            f"index has shape {tuple(index.shape)}; expected {expected} storage coordinates for a batch of "
            f"shape {tuple(batch_size)} sampled from a {ndim}-dimensional storage (the sampler's "
            "info['index'], as RelabelReplayBuffer passes it)."
        )

    # ------------------------------------------------------------------ relabelling
    def window_lengths(
        self, coords: torch.Tensor, storage: Storage, newest_index: int | torch.Tensor | None = None
    ) -> torch.Tensor:
        """Number of usable future records ``min(T_t, W)`` for storage coordinates ``coords``.

        ``coords`` is ``[B, ndim]`` (``[B]`` is accepted for 1-D storages), as in the ``"index"`` entry of
        a sample. ``T_t`` counts the records of the same episode from ``t`` on (``t`` included) stored
        contiguously along the time dimension of ``storage``, the newest written record (time coordinate
        ``newest_index``, see :meth:`relabel_sample`) included. The result, ``[B]`` int64, is ``>= 1``
        (the record itself).
        """
        storage = self._check_storage(storage)
        ndim = storage.ndim
        if coords.ndim == 1 and ndim == 1:
            coords = coords.unsqueeze(-1)
        if coords.ndim != 2 or coords.shape[-1] != ndim:
            raise ValueError(f"coords must have shape [B, {ndim}], got {tuple(coords.shape)}.")
        fields = self._storage_fields(storage, whole=isinstance(newest_index, torch.Tensor))
        newest = self._resolve_newest(storage, fields, newest_index)
        return self._window_lengths(coords.to(fields["achieved"].device), fields, ndim, newest)

    def _resolve_newest(
        self, storage: TensorStorage, fields: dict, newest_index: int | torch.Tensor | None
    ) -> int | torch.Tensor | None:
        """The newest record's time coordinate on the fields' time line; warns once when it is unknown."""
        newest = self._newest_time_index(storage, fields["achieved"].shape[0], newest_index)
        if newest is None and not self._warned_seam:
            warnings.warn(
                "FutureGoalRelabel: the storage is full and its newest write position is unknown "
                "(newest_index=None); episode markers alone guard the wrap-around seam.",
                stacklevel=3,
            )
            self._warned_seam = True
        return newest

    def _window_lengths(
        self,
        coords: torch.Tensor,
        fields: dict[str, torch.Tensor | None],
        ndim: int,
        newest: int | torch.Tensor | None,
    ) -> torch.Tensor:
        """:meth:`window_lengths` on the storage's entries: tensor operations only, static shapes."""
        achieved = fields["achieved"]
        length = achieved.shape[0]
        device = achieved.device
        time = coords[:, 0]
        steps = torch.arange(self.window, device=device)
        positions = torch.remainder(time.unsqueeze(1) + steps, length)  # [B, W] on the circular time line
        # one flat index into the [T, *lanes] record grid, shared by all markers
        flat = positions
        for d, size in enumerate(achieved.shape[1:ndim], start=1):
            flat = flat * size + coords[:, d : d + 1]
        if newest is None:
            valid = torch.ones(positions.shape, dtype=torch.bool, device=device)
        else:
            valid = steps <= torch.remainder(newest - time, length).unsqueeze(1)
        if fields["traj"] is not None:
            traj = self._marker(fields["traj"], ndim, flat)
            valid &= traj == traj[:, :1]
        if fields["count"] is not None:
            count = self._marker(fields["count"], ndim, flat)
            valid &= (count - count[:, :1]) == steps
        if fields["done"] is not None:
            done = self._marker(fields["done"], ndim, flat).bool()
            valid[:, 1:] &= ~done[:, :-1]  # record t + j needs no episode end at t + j - 1
        # the window ends at the first rejected record (record t itself is always accepted): its length is
        # the number of leading accepted records (a running product; argmax over ties is not order-safe
        # in every compiled backend)
        valid[:, 0] = True
        return valid.long().cumprod(1).sum(1)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError(
            "FutureGoalRelabel reads the future of each sampled transition from the storage, which a "
            "transform called on the sample alone cannot see: pass it to RelabelReplayBuffer(storage=..., "
            "relabel=[...]) (rb.sample() then returns relabelled data), or call "
            "relabel_sample(data, index, storage)."
        )

    def relabel_sample(
        self,
        tensordict: TensorDictBase,
        index: torch.Tensor | tuple,
        storage: Storage,
        *,
        newest_index: int | torch.Tensor | None = None,
    ) -> TensorDictBase:
        """Relabels ``tensordict``, the records of ``storage`` at ``index``, in place and returns it.

        This is the call :class:`~torchrl_dhrl.data.RelabelReplayBuffer` makes on every sample.

        Args:
            tensordict (TensorDictBase): the sampled records, batch shape ``[*batch]``.
            index (Tensor or tuple of Tensor): their storage coordinates, ``[*batch]`` for a 1-D storage
                and ``[*batch, ndim]`` otherwise (or a tuple of ``ndim`` tensors ``[*batch]``, as a
                sampler's ``info["index"]``).
            storage (TensorStorage): the storage they were read from.

        Keyword Args:
            newest_index (int, optional): the time coordinate (first storage dimension) of the most
                recently written record, where the write seam of a full circular storage lies (see
                :attr:`RelabelReplayBuffer.newest_index <torchrl_dhrl.data.RelabelReplayBuffer.newest_index>`).
                ``None`` for a storage that has not wrapped around (the last written row is the newest);
                for a full storage it leaves the seam to the episode markers, with a warning. A 0-d tensor
                (on the storage's device) is used as it is, without reading it on the host, and the whole
                preallocated storage is read (static shapes, the same result).
        """
        if not is_tensor_collection(tensordict):
            raise TypeError(f"FutureGoalRelabel expects a TensorDict, got {type(tensordict).__name__}.")
        storage = self._check_storage(storage)
        if len(storage) == 0:
            raise RuntimeError("FutureGoalRelabel: the storage is empty; nothing to relabel from.")
        goal = tensordict.get(self.goal_key, None)
        achieved_next = tensordict.get(self.achieved_goal_key, None)
        for key, value in ((self.goal_key, goal), (self.achieved_goal_key, achieved_next)):
            if value is None:
                raise KeyError(f"FutureGoalRelabel: {key!r} is missing from the sample.")
        batch_size = tensordict.batch_size
        goal_shape = goal.shape[len(batch_size) :]
        if achieved_next.shape[len(batch_size) :] != goal_shape:
            raise ValueError(
                f"{self.goal_key!r} and {self.achieved_goal_key!r} must have the same goal shape, got "
                f"{tuple(goal_shape)} and {tuple(achieved_next.shape[len(batch_size) :])}."
            )
        coords = self._coordinates(index, batch_size, storage.ndim)
        whole = isinstance(newest_index, torch.Tensor)
        fields = self._storage_fields(storage, whole=whole)
        achieved_store = fields["achieved"]
        if achieved_store.shape[storage.ndim :] != goal_shape:
            raise ValueError(
                f"Stored {self.achieved_goal_key!r} has goal shape "
                f"{tuple(achieved_store.shape[storage.ndim :])}, the sampled {self.goal_key!r} has "
                f"{tuple(goal_shape)}."
            )
        coords = coords.to(achieved_store.device)
        newest = self._resolve_newest(storage, fields, newest_index)
        n_valid = self._window_lengths(coords, fields, storage.ndim, newest)
        return self._write_goals(tensordict, coords, n_valid, fields, storage.ndim)

    def capturable_relabel(
        self, storage: Storage
    ) -> Callable[[TensorDictBase, torch.Tensor, torch.Tensor], TensorDictBase]:
        """The relabelling of :meth:`relabel_sample` as a capture-safe function of tensors.

        Returns ``relabel(tensordict, coords, newest_index)``: ``coords`` the ``[B, ndim]`` storage
        coordinates of the records in ``tensordict`` (batch ``[B]``), ``newest_index`` a 0-d integer
        tensor on the storage's device (the time coordinate of the newest written record; for a storage
        that has not wrapped around, the last written row). It reads the storage's whole preallocated
        entries, so its shapes never change as the storage fills, and it makes no host synchronisation:
        it can be captured in a CUDA graph or compiled with ``torch.compile(fullgraph=True)``, and writes
        made between calls are seen. Given the same coordinates and random state it writes exactly what
        :meth:`relabel_sample` writes (rows past the newest one are never used). The function holds the
        storage's tensors: build it again after the storage is reallocated (``load_state_dict``).
        :meth:`RelabelReplayBuffer.capturable_sampler
        <torchrl_dhrl.data.RelabelReplayBuffer.capturable_sampler>` builds it.
        """
        storage = self._check_storage(storage)
        if len(storage) == 0:
            raise RuntimeError("FutureGoalRelabel: the storage is empty; write to it before capturing.")
        fields = self._storage_fields(storage, whole=True)
        ndim = storage.ndim
        length = fields["achieved"].shape[0]

        def relabel(tensordict: TensorDictBase, coords: torch.Tensor, newest_index: torch.Tensor):
            n_valid = self._window_lengths(coords, fields, ndim, torch.remainder(newest_index, length))
            return self._write_goals(tensordict, coords, n_valid, fields, ndim)

        return relabel

    def _write_goals(
        self,
        tensordict: TensorDictBase,
        coords: torch.Tensor,
        n_valid: torch.Tensor,
        fields: dict[str, torch.Tensor | None],
        ndim: int,
    ) -> TensorDictBase:
        """Draws the future offsets and writes each output's goal and reward (tensor operations only)."""
        achieved_store = fields["achieved"]
        store_device = achieved_store.device
        goal = tensordict.get(self.goal_key)
        achieved_next = tensordict.get(self.achieved_goal_key)
        batch_size = tensordict.batch_size
        numel = batch_size.numel()
        goal_shape = goal.shape[len(batch_size) :]
        time = coords[:, 0]
        lanes = tuple(coords[:, d] for d in range(1, ndim))
        length = achieved_store.shape[0]

        goal_flat = goal.reshape(numel, *goal_shape)
        achieved_flat = achieved_next.reshape(numel, *goal_shape)
        out_device = goal.device
        for i, ratio in enumerate(self.her_ratio):
            offset = (torch.rand(numel, device=store_device) * n_valid).long()
            offset = torch.minimum(offset, n_valid - 1)
            future_goal = achieved_store[((time + offset) % length, *lanes)].to(out_device, goal.dtype)
            relabel = torch.rand(numel, device=out_device) < ratio
            relabel = relabel.reshape(numel, *([1] * len(goal_shape)))
            new_goal = torch.where(relabel, future_goal, goal_flat)
            new_goal_b = new_goal.reshape(*batch_size, *goal_shape)
            out_key = self.goal_out_keys[i]
            tensordict.set(out_key, new_goal_b)
            if self.write_next_goal:
                tensordict.set(_next(out_key), new_goal_b.clone())
            if self.reward_keys is not None:
                reward = self.reward_fn(achieved_flat, new_goal)
                if reward.shape == (numel,):
                    reward = reward.unsqueeze(-1)
                if reward.shape != (numel, 1):
                    raise ValueError(
                        "reward_fn must return a tensor of shape [B, 1] or [B], got "
                        f"{tuple(reward.shape)} for B={numel}."
                    )
                tensordict.set(self.reward_keys[i], reward.reshape(*batch_size, 1))
        return tensordict

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        return tensordict

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(her_ratio={self.her_ratio}, window={self.window}, "
            f"goal_key={self.goal_key!r}, out_keys={self.goal_out_keys!r}, reward_keys={self.reward_keys!r})"
        )
