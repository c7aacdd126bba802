"""A replay buffer whose samples come out relabelled (hindsight goals, rewards, subgoal tests)."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase, is_tensor_collection
from torchrl.data import RandomSampler, TensorDictReplayBuffer
from torchrl.data.replay_buffers.storages import TensorStorage
from torchrl.data.replay_buffers.utils import pin_memory_output
from torchrl.envs.transforms import Compose

__all__ = ["RelabelReplayBuffer"]

RelabelStep = Callable[[TensorDictBase], TensorDictBase]

_STATE_KEY = "_newest_index"
_DUMP_FILE = "relabel_buffer.json"


class RelabelReplayBuffer(TensorDictReplayBuffer):
    """A :class:`~torchrl.data.TensorDictReplayBuffer` whose :meth:`sample` returns relabelled data.

    Hindsight relabelling needs more than the sampled records: the future of each sampled transition
    lives elsewhere in the storage. Like :class:`~torchrl.data.HERReplayBuffer`, this buffer relabels in
    ``_sample``, with the storage coordinates the sampler has just drawn, so that ``rb.sample()`` (and
    ``for batch in rb``) gives training-ready batches to any TorchRL loss, trainer or updater. The
    ``relabel`` steps run in order on every sample, after the forward pass of the buffer's ``transform``:

    * a step with a ``relabel_sample(data, index, storage, *, newest_index)`` method, such as
      :class:`~torchrl_dhrl.data.FutureGoalRelabel`, is called with the sample's storage coordinates
      (``[*batch]`` for a 1-D storage, ``[*batch, ndim]`` otherwise), the buffer's storage and
      :attr:`newest_index`;
    * any other step is a callable ``step(data) -> data``: a TorchRL transform such as
      :class:`~torchrl_dhrl.data.HindsightSubgoalRelabel` or :class:`~torchrl.envs.RenameTransform`.

    A :class:`~torchrl.envs.Compose` passed as ``relabel`` is unpacked into its steps. Writing is
    unchanged (``transform``'s inverse runs at ``extend``, e.g. a
    :class:`~torchrl_dhrl.data.HighLevelTransitionBuilder`), and the steps receive the sample before
    ``"index"`` and the other sampling info are written into it.

    **The write seam.** A full circular storage holds, right after its newest record, the oldest one,
    which may look like the continuation of the newest episode. The buffer records the time coordinate
    (the first storage dimension) of its newest record from the indices ``extend`` and ``add`` return:
    :attr:`newest_index`, handed to the relabel steps. It is part of :meth:`state_dict` (and of
    :meth:`dumps`), so a restored buffer relabels exactly as the saved one (checkpoint it while no other
    thread writes); ``state_dict`` of a plain :class:`~torchrl.data.TensorDictReplayBuffer` loads too,
    with an unknown newest position (``None``) until the next write.

    **Prefetching** (``prefetch=n``) is supported: sampling threads draw and relabel each batch while
    holding the buffer's lock, which ``extend`` and ``add`` take for the whole write (newest position
    included), so a batch is always relabelled against the storage it was drawn from, even when the
    buffer is extended before it is consumed. A prefetched batch is relabelled when it is drawn, up to
    ``n`` batches before it is used: steps that call models (e.g. the gradual penalty's
    ``distance_from_graph``) see them as they were then, from the sampling thread. ``shared=True``
    (writes from other processes, which this process's newest position would miss) is refused.

    Keyword Args:
        relabel (callable or sequence of callables, optional): the relabel steps (see above). Defaults
            to ``None`` (no relabelling: a :class:`~torchrl.data.TensorDictReplayBuffer` that tracks
            :attr:`newest_index`).
        **kwargs: the keyword arguments of :class:`~torchrl.data.TensorDictReplayBuffer` (``storage``,
            ``sampler``, ``writer``, ``transform``, ``batch_size``, ``prefetch``, ...).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage
        >>> from torchrl_dhrl.data import FutureGoalRelabel, HindsightSubgoalRelabel
        >>> T = 10  # one env, one episode; achieved goals (step, 0)
        >>> achieved = torch.stack([torch.arange(T), torch.zeros(T, dtype=torch.long)], -1).float()
        >>> episode = TensorDict(
        ...     {
        ...         "desired_goal": torch.full((T, 2), 100.0),
        ...         "subgoal": torch.full((T, 2), 50.0),
        ...         "step_count": torch.arange(T).unsqueeze(-1),
        ...         ("next", "achieved_goal"): achieved + torch.tensor([1.0, 0.0]),
        ...         ("next", "done"): (torch.arange(T) == T - 1).unsqueeze(-1),
        ...     },
        ...     batch_size=[T],
        ... )
        >>> rb = RelabelReplayBuffer(
        ...     storage=LazyTensorStorage(100),
        ...     relabel=[
        ...         FutureGoalRelabel(her_ratio=1.0, window=4, out_keys=["desired_goal"], reward_keys=None),
        ...         HindsightSubgoalRelabel(subgoal_test_ratio=0.0),  # hindsight actions only
        ...     ],
        ...     batch_size=32,
        ... )
        >>> _ = rb.extend(episode)
        >>> rb.newest_index
        9
        >>> batch = rb.sample()  # training-ready
        >>> ahead = batch["desired_goal"][:, 0] - batch["next", "achieved_goal"][:, 0]
        >>> bool(((ahead >= 0) & (ahead < 4)).all())  # a future goal of the episode, within the window
        True
        >>> bool((batch["subgoal"] == batch["next", "achieved_goal"]).all())  # HAC hindsight action
        True
        >>> torch.equal(batch["next", "reward"], torch.where(ahead == 0, 0.0, -1.0).unsqueeze(-1))
        True
        >>> restored = RelabelReplayBuffer(storage=LazyTensorStorage(100), relabel=rb.relabel, batch_size=32)
        >>> restored.load_state_dict(rb.state_dict())
        >>> restored.newest_index
        9
    """

    def __init__(self, *, relabel: RelabelStep | Sequence[RelabelStep] | None = None, **kwargs: Any) -> None:
        if relabel is None:
            steps = ()
        elif isinstance(relabel, Compose):
            steps = tuple(relabel.transforms)
        elif callable(relabel) or hasattr(relabel, "relabel_sample"):
            steps = (relabel,)
        else:
            steps = tuple(relabel)
        for step in steps:
            if not (callable(getattr(step, "relabel_sample", None)) or callable(step)):
                raise TypeError(
                    "relabel steps must be callables step(data) -> data or have a "
                    f"relabel_sample(data, index, storage, *, newest_index) method, got {type(step).__name__}."
                )
        self._relabel = steps
        self._newest_index: int | None = None
        # (rows written, newest row) as 0-d tensors on the storage's device, made by capturable_sampler()
        # and kept up to date in place by every write, so captured samplers see them change
        self._device_counters: tuple[torch.Tensor, torch.Tensor] | None = None
        super().__init__(**kwargs)

    def share(self, shared: bool = True):
        if shared:  # also reached from the constructor's shared=True
            raise ValueError(
                "RelabelReplayBuffer does not support shared=True: it tracks its newest write position in "
                "this process, so writes from other processes would not move it."
            )
        return super().share(shared)

    # ------------------------------------------------------------------ public attributes
    @property
    def relabel(self) -> tuple[RelabelStep, ...]:
        """The relabel steps, in the order they run on every sample."""
        return self._relabel

    @property
    def newest_index(self) -> int | None:
        """Time coordinate (first storage dimension) of the most recently written record.

        ``None`` before the first write, after :meth:`empty`, and after loading the state of a buffer that
        did not track it.
        """
        return self._newest_index

    # ------------------------------------------------------------------ writing
    def _record_write(self, index: int | torch.Tensor | tuple) -> None:
        """Keeps the time coordinate of the last record of a write (a round-robin writer's write order)."""
        if isinstance(index, tuple):
            index = index[0]
        index = torch.as_tensor(index)
        if not index.numel():  # nothing written (e.g. the transform kept the data back)
            return
        ndim = self.storage.ndim
        if ndim > 1 and index.ndim > 1 and index.shape[-1] == ndim:
            index = index[..., 0]
        self._newest_index = int(index.reshape(-1)[-1])
        self._sync_device_counters()

    def _sync_device_counters(self) -> None:
        """Copies the rows written and the newest row into the capture-safe counters, in place (no sync)."""
        if self._device_counters is None:
            return
        rows, newest = self._device_counters
        rows.fill_(self._storage.shape[0] if len(self._storage) else 0)
        newest.fill_(-1 if self._newest_index is None else self._newest_index)

    def extend(self, tensordicts: TensorDictBase, *, update_priority: bool | None = None) -> torch.Tensor:
        with self._replay_lock:  # no sample is drawn between the write and the newest position
            index = super().extend(tensordicts, update_priority=update_priority)
            self._record_write(index)
        return index

    def add(self, data: TensorDictBase) -> int | torch.Tensor:
        with self._replay_lock:
            index = super().add(data)
            self._record_write(index)
        return index

    def empty(self, empty_write_count: bool = True) -> None:
        with self._replay_lock:
            super().empty(empty_write_count=empty_write_count)
            self._newest_index = None
            self._sync_device_counters()

    # ------------------------------------------------------------------ sampling
    @pin_memory_output
    def _sample(self, batch_size: int) -> tuple[Any, dict]:
        # the lock (re-entrant, also taken by the parent's sampling and by every write) covers drawing the
        # indices, reading the records and relabelling: a prefetching thread relabels against the
        # storage it sampled from
        with self._replay_lock:
            data, info = super()._sample(batch_size)
            if not self._relabel:
                return data, info
            index = info["index"]
            if isinstance(index, tuple):
                index = torch.stack([torch.as_tensor(i) for i in index], -1)
            with data.unlock_():
                for step in self._relabel:
                    relabel_sample = getattr(step, "relabel_sample", None)
                    if relabel_sample is not None:
                        data = relabel_sample(data, index, self._storage, newest_index=self._newest_index)
                    else:
                        data = step(data)
        return data, info

    def capturable_sampler(self, batch_size: int | None = None) -> Callable[[], TensorDictBase]:
        """A function drawing relabelled batches with tensor operations only: capture-safe sampling.

        ``sample = rb.capturable_sampler()`` returns a function of no argument whose every call draws
        ``batch_size`` records uniformly, with replacement, from the records written so far (the
        distribution of :class:`~torchrl.data.RandomSampler`), reads them from the storage, runs the
        relabel steps' capture-safe forms (``step.capturable_relabel(storage)``, e.g.
        :meth:`FutureGoalRelabel.capturable_relabel
        <torchrl_dhrl.data.FutureGoalRelabel.capturable_relabel>`) and writes the storage coordinates under
        ``"index"``, as :meth:`sample` does. It makes no host synchronisation, its shapes are static
        (the whole preallocated storage is read) and the number of rows written and the newest row are
        0-d tensors on the storage's device that every ``extend`` / ``add`` updates in place: the
        function can be captured in a CUDA graph together with the update that consumes its batch
        (:class:`~torchrl_dhrl.training.LossUpdater` with ``cudagraphs=True`` does) or compiled with
        ``torch.compile(fullgraph=True)``, and sees every later write without being captured again.

        Its random draws come from the storage device's default generator (``torch.rand`` /
        ``torch.randint``; on CUDA the graph-safe Philox stream), not from the sampler's, so it draws
        other batches than :meth:`sample` does from the same seed. Build it after the first write and
        again after anything that reallocates the storage (``load_state_dict``, ``loads``); ``empty``
        keeps the allocation, and a sampler called on an emptied buffer draws from the stale rows.

        Args:
            batch_size (int, optional): records per batch. Defaults to the buffer's ``batch_size``.

        Raises:
            RuntimeError: on an empty buffer, a full storage whose newest row is unknown (a state loaded
                from a buffer that did not track it: write once more), a sampler other than
                :class:`~torchrl.data.RandomSampler`, a sample-side ``transform`` (one that acts on samples: a
                transform with ``sample_identity = True`` acts on writes only), ``prefetch``, or a
                relabel step without a ``capturable_relabel`` form (the error names it).

        Examples:
            >>> import torch
            >>> from tensordict import TensorDict
            >>> from torchrl.data import LazyTensorStorage
            >>> from torchrl_dhrl.data import FutureGoalRelabel
            >>> T = 10  # one env, one episode; achieved goals (step + 1, 0)
            >>> episode = TensorDict(
            ...     {
            ...         "desired_goal": torch.full((T, 2), 100.0),
            ...         "step_count": torch.arange(T).unsqueeze(-1),
            ...         ("next", "achieved_goal"): torch.stack([torch.arange(1, T + 1), torch.zeros(T)], -1),
            ...         ("next", "done"): (torch.arange(T) == T - 1).unsqueeze(-1),
            ...     },
            ...     batch_size=[T],
            ... )
            >>> rb = RelabelReplayBuffer(storage=LazyTensorStorage(100), relabel=[FutureGoalRelabel(window=4)],
            ...     batch_size=32)
            >>> _ = rb.extend(episode)
            >>> sample = rb.capturable_sampler()
            >>> batch = sample()
            >>> bool((batch["index"] < T).all())  # only written rows are drawn
            True
            >>> ahead = batch["graph_goal"][:, 0] - batch["next", "achieved_goal"][:, 0]
            >>> bool(((ahead >= 0) & (ahead < 4)).all())
            True
            >>> _ = rb.extend(episode)  # the same function sees the new rows
            >>> bool((torch.cat([sample()["index"] for _ in range(20)]) >= T).any())
            True
        """
        storage = self._storage
        batch_size = self._batch_size if batch_size is None else batch_size
        if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
            raise ValueError(f"capturable_sampler: batch_size must be a positive int, got {batch_size!r}.")
        if type(self._sampler) is not RandomSampler:
            raise RuntimeError(
                "capturable_sampler draws uniformly like RandomSampler; this buffer's sampler is "
                f"{type(self._sampler).__name__}, whose draws it would not reproduce."
            )
        for step in self._relabel:
            if not callable(getattr(step, "capturable_relabel", None)):
                raise RuntimeError(
                    f"capturable_sampler: the relabel step {type(step).__name__} has no capture-safe form "
                    "(a `capturable_relabel(storage)` method); sample with rb.sample() instead."
                )
        sample_side = [t for t in self._transform if not getattr(t, "sample_identity", False)]
        if sample_side:
            raise RuntimeError(
                "capturable_sampler does not run the buffer's sample-side `transform` "
                f"({sample_side}); put capture-safe steps in `relabel` instead (transforms that act on writes only, "
                "with `sample_identity = True`, such as HighLevelTransitionBuilder, are fine)."
            )
        if self._prefetch:
            raise RuntimeError(
                "capturable_sampler cannot be used with prefetch: it samples on the caller's thread."
            )
        if not isinstance(storage, TensorStorage) or len(storage) == 0:
            raise RuntimeError(
                "capturable_sampler needs a TensorStorage (e.g. LazyTensorStorage) that has been written to; "
                f"got {type(storage).__name__} with {len(storage)} records."
            )
        if not is_tensor_collection(storage._storage):
            raise RuntimeError("capturable_sampler needs a storage of TensorDicts, not of plain tensors.")
        if self._newest_index is None:
            raise RuntimeError(
                "capturable_sampler: the newest written row is unknown (a state loaded from a buffer that "
                "did not track it); write to the buffer once before building the sampler."
            )
        relabels = [step.capturable_relabel(storage) for step in self._relabel]
        data = storage._storage  # the whole preallocated storage: [T_max, *lanes]
        device = data.device if data.device is not None else data.get(next(iter(data.keys()))).device
        if self._device_counters is None or self._device_counters[0].device != device:
            self._device_counters = (
                torch.zeros((), dtype=torch.long, device=device),
                torch.zeros((), dtype=torch.long, device=device),
            )
        self._sync_device_counters()
        rows, newest = self._device_counters
        lanes = tuple(data.shape[1 : storage.ndim])
        ndim = storage.ndim

        def sample() -> TensorDictBase:
            time = (torch.rand(batch_size, device=device) * rows).long()
            time = torch.minimum(time, rows - 1)  # float round-off at the top of the range
            coords = torch.stack(
                [time, *(torch.randint(size, (batch_size,), device=device) for size in lanes)], -1
            )
            batch = data[tuple(coords.unbind(-1))]
            for relabel in relabels:
                batch = relabel(batch, coords, newest)
            batch.set("index", coords if ndim > 1 else time)
            return batch

        return sample

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        state = super().state_dict()
        state[_STATE_KEY] = self._newest_index
        return state

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        super().load_state_dict(state_dict)
        with self._replay_lock:
            self._newest_index = state_dict.get(_STATE_KEY)
            self._sync_device_counters()

    def dumps(self, path) -> None:
        super().dumps(path)
        with open(Path(path).absolute() / _DUMP_FILE, "w") as file:
            json.dump({"newest_index": self._newest_index}, file)

    def loads(self, path) -> None:
        super().loads(path)
        file = Path(path).absolute() / _DUMP_FILE
        newest = json.loads(file.read_text())["newest_index"] if file.exists() else None
        with self._replay_lock:
            self._newest_index = newest
            self._sync_device_counters()

    def __repr__(self) -> str:
        text = super().__repr__()
        return f"{text[:-1]}, \n    relabel={list(self._relabel)!r})"
