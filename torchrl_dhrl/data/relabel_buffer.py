"""A replay buffer whose samples come out relabelled (hindsight goals, rewards, subgoal tests)."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data import TensorDictReplayBuffer
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

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        state = super().state_dict()
        state[_STATE_KEY] = self._newest_index
        return state

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        super().load_state_dict(state_dict)
        with self._replay_lock:
            self._newest_index = state_dict.get(_STATE_KEY)

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

    def __repr__(self) -> str:
        text = super().__repr__()
        return f"{text[:-1]}, \n    relabel={list(self._relabel)!r})"
