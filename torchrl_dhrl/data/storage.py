"""A lazily allocated tensor storage whose checkpoints hold only what was written."""

from __future__ import annotations

import math
from typing import Any

from tensordict import TensorDict, is_tensor_collection
from torchrl.data import LazyTensorStorage

__all__ = ["CompactLazyTensorStorage"]


class CompactLazyTensorStorage(LazyTensorStorage):
    """A :class:`~torchrl.data.LazyTensorStorage` whose ``state_dict`` holds only the rows written so far.

    :class:`~torchrl.data.LazyTensorStorage` allocates its whole capacity at the first write and its
    ``state_dict`` holds all of it, so a checkpoint of DHRL's 2.5M-transition low-level buffer weighs
    hundreds of MB from the first episode on. This storage saves the written rows (the leading
    ``ceil(len / prod(shape[1:]))`` rows along the storage's first dimension; a round-robin writer fills
    them in order) plus the allocated row count, and ``load_state_dict`` pads them back to the full
    capacity, so writing and sampling continue exactly as before the round trip. Once the buffer has
    wrapped around, the state is the same as the parent's. ``state_dict``\\ s of a plain
    :class:`~torchrl.data.LazyTensorStorage` (and of earlier checkpoints) load unchanged.

    Args:
        max_size (int): the capacity in elements (transitions), whatever ``ndim``.

    Keyword Args:
        Those of :class:`~torchrl.data.LazyTensorStorage` (``device``, ``ndim``, ...).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import TensorDictReplayBuffer
        >>> from torchrl_dhrl.data import CompactLazyTensorStorage
        >>> rb = TensorDictReplayBuffer(storage=CompactLazyTensorStorage(1000, ndim=2), batch_size=8)
        >>> _ = rb.extend(TensorDict(obs=torch.randn(4, 10, 3), batch_size=[4, 10]))  # [num_envs, T]
        >>> rb.state_dict()["_storage"]["_storage"]["obs"].shape  # 10 written time steps of 4 envs
        torch.Size([10, 4, 3])
        >>> restored = TensorDictReplayBuffer(storage=CompactLazyTensorStorage(1000, ndim=2), batch_size=8)
        >>> restored.load_state_dict(rb.state_dict())
        >>> restored.storage._storage.shape, len(restored)
        (torch.Size([250, 4]), 40)
    """

    def state_dict(self) -> dict[str, Any]:
        state = super().state_dict()
        storage = self._storage
        if not self.initialized or storage is None:
            return state
        allocated = storage.shape[0]
        written = min(math.ceil(self._len / math.prod(storage.shape[1:])), allocated)
        if written < allocated:
            # clone: saving a view would serialise the whole underlying allocation
            trimmed = storage[:written].clone()
            state["_storage"] = trimmed.state_dict() if is_tensor_collection(trimmed) else trimmed
            state["_allocated_rows"] = allocated
        return state

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        if "_allocated_rows" not in state_dict:
            return super().load_state_dict(state_dict)
        state_dict = dict(state_dict)
        allocated = state_dict.pop("_allocated_rows")
        data = state_dict["_storage"]
        if isinstance(data, dict):
            data = TensorDict().load_state_dict(data, strict=False)
        full = data.new_zeros((allocated, *data.shape[1:]))
        full[: data.shape[0]] = data
        state_dict["_storage"] = full.state_dict() if is_tensor_collection(full) else full
        super().load_state_dict(state_dict)
