"""Atomic checkpoints and the process-wide random states a training run must carry."""

from __future__ import annotations

import os
import random
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["CheckpointError", "get_rng_state", "load_checkpoint", "save_checkpoint", "set_rng_state"]


class CheckpointError(ValueError):
    """A file that cannot be read as a checkpoint, or lacks entries a checkpoint must hold; the message
    names the file."""


def save_checkpoint(state: dict[str, Any], path: str | os.PathLike) -> Path:
    """Writes ``state`` with :func:`torch.save` atomically: to a temporary file, then renamed.

    A crash (or Ctrl-C) while writing leaves the previous checkpoint intact: the rename is
    atomic on POSIX and Windows file systems, and the temporary file is removed on failure.

    Examples:
        >>> import tempfile, torch
        >>> from pathlib import Path
        >>> path = Path(tempfile.mkdtemp()) / "ckpt.pt"
        >>> _ = save_checkpoint({"step": 3, "w": torch.ones(2)}, path)
        >>> load_checkpoint(path)["step"]
        3
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as file:
            torch.save(state, file)
            file.flush()
            os.fsync(file.fileno())
        os.chmod(tmp, 0o644)  # mkstemp creates 0600 files
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def checkpoint_file(path: str | os.PathLike) -> Path:
    """``path`` itself, or ``path/checkpoint.pt`` when ``path`` is a run directory."""
    path = Path(path)
    return path / "checkpoint.pt" if path.is_dir() else path


def load_checkpoint(
    path: str | os.PathLike,
    map_location: str | torch.device | None = "cpu",
    *,
    required_keys: tuple[str, ...] = (),
) -> dict[str, Any]:
    """Loads a checkpoint written by :func:`save_checkpoint`.

    Args:
        path (str or os.PathLike): the file, or the run directory holding ``checkpoint.pt``.
        map_location (str, torch.device or None): where tensors are loaded. Defaults to ``"cpu"``.

    Keyword Args:
        required_keys (tuple of str): top-level entries the checkpoint must hold (e.g. the recipe's
            ``CHECKPOINT_KEYS``). Defaults to none.

    Raises:
        FileNotFoundError: when there is no such file (or no ``checkpoint.pt`` in the directory).
        CheckpointError: when the file cannot be unpickled (corrupt, truncated, not a torch file), is not a
            dictionary, or lacks one of ``required_keys``; the message names the file.

    Examples:
        >>> import tempfile, torch
        >>> from pathlib import Path
        >>> path = Path(tempfile.mkdtemp()) / "weights.pt"
        >>> torch.save({"weights": torch.ones(2)}, path)
        >>> try:
        ...     load_checkpoint(path, required_keys=("agent", "counters"))
        ... except CheckpointError as err:
        ...     print(str(err).replace(str(path), "weights.pt"))
        'weights.pt' is not a training checkpoint: it lacks 'agent', 'counters' (it holds 'weights').
    """
    path = checkpoint_file(path)
    if not path.is_file():
        raise FileNotFoundError(f"No checkpoint at {str(path)!r}.")
    try:
        state = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as err:  # pickle, zip and torch errors alike: the file is not a readable checkpoint
        detail = " ".join(str(err).split())[:160]
        raise CheckpointError(
            f"{str(path)!r} is not a readable checkpoint ({type(err).__name__}: {detail})."
        ) from err
    if not isinstance(state, dict):
        raise CheckpointError(
            f"{str(path)!r} is not a training checkpoint: it holds a {type(state).__name__}."
        )
    missing = [key for key in required_keys if key not in state]
    if missing:
        lacks = ", ".join(map(repr, missing[:4])) + (
            f" and {len(missing) - 4} more" if len(missing) > 4 else ""
        )
        held = ", ".join(repr(k) for k in list(state)[:4]) + (", ..." if len(state) > 4 else "")
        raise CheckpointError(
            f"{str(path)!r} is not a training checkpoint: it lacks {lacks} (it holds {held})."
        )
    return state


def get_rng_state() -> dict[str, Any]:
    """The global random states of Python, NumPy, torch (CPU) and every CUDA device."""
    state = {
        "python": random.getstate(),
        "numpy": np.random.get_state(),
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    """Restores the states of :func:`get_rng_state` (CUDA states only where CUDA is available)."""
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"].cpu())
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])
