"""The training loop's own machinery: its counters, graceful stops, timer, metrics files and logger.

:class:`RunCounters` is where a run stands (checkpointed); :class:`GracefulStop` turns SIGINT and SIGTERM into a
stop at the end of the current batch; :class:`LoopTimer` times collection and updates; :func:`log_metrics`,
:func:`write_metrics_csv` and :func:`make_logger` record an epoch's metrics; :func:`frozen_gc` keeps the garbage
collector off the run's long-lived objects.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import gc
import os
import signal
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from torchrl_dhrl.training import ModuleTimer

from .run import write_csv

__all__ = [
    "GracefulStop",
    "LoopTimer",
    "RunCounters",
    "frozen_gc",
    "log_metrics",
    "make_logger",
    "write_metrics_csv",
]


@dataclasses.dataclass
class RunCounters:
    """Where a run stands: what the training loop counts, checkpointed as JSON (``state_dict``).

    Attributes:
        env_steps (int): env steps collected, the random warm-up included (the x axis of every curve).
        episodes (int): training episodes finished.
        epochs (int): epochs finished (the first epochs of the warm-up included).
        graph_builds (int): graph rebuilds.
        wall_s (float): seconds of training, resumes included.
        untrained_steps (int): env steps of the warm-up without updates (the update-to-data ratios count the
            steps after them).
        train_episodes (dict, optional): the :class:`~torchrl_dhrl.diagnostics.TrainingEpisodeLog` state of the
            running epoch.
        forks (list of dict): the checkpoints this run was forked from, with the env steps and seed.

    Examples:
        >>> from torchrl_dhrl.recipe import RunCounters
        >>> counters = RunCounters(env_steps=600, episodes=1)
        >>> restored = RunCounters()
        >>> restored.load_state_dict(counters.state_dict())
        >>> restored == counters
        True
    """

    env_steps: int = 0
    episodes: int = 0
    epochs: int = 0
    graph_builds: int = 0
    wall_s: float = 0.0
    untrained_steps: int = 0
    train_episodes: dict | None = None
    forks: list = dataclasses.field(default_factory=list)

    def state_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restores the counters; keys a checkpoint does not hold (older versions) keep their defaults."""
        fields = {field.name for field in dataclasses.fields(self)}
        unknown = set(state) - fields
        if unknown:
            raise KeyError(f"Unknown run counters {sorted(unknown)}; known: {sorted(fields)}.")
        defaults = RunCounters()
        for name in fields:
            setattr(self, name, copy.deepcopy(state.get(name, getattr(defaults, name))))


@contextlib.contextmanager
def frozen_gc():
    """Moves every object alive now (torch, Hydra, the agent, buffers, envs: about 0.5M objects in a run) out of the
    cyclic garbage collector's reach for the ``with`` block, so that its full collections stop walking them (they
    took 6% of a PointMaze quick run's first 12k steps, 2.7% with the freeze). Reference counting still frees them.

    Examples:
        >>> import gc
        >>> from torchrl_dhrl.recipe import frozen_gc
        >>> with frozen_gc():
        ...     gc.get_freeze_count() > 0
        True
        >>> gc.get_freeze_count()
        0
    """
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


class GracefulStop:
    """SIGINT (Ctrl-C) and SIGTERM (a job scheduler's stop) ask a training loop to stop at the end of its batch.

    The first signal sets :attr:`requested`: the loop finishes the batch's updates (and its epoch end),
    then checkpoints and exits, so the checkpoint sits at a batch boundary and a resumed run continues
    exactly. An exception raised at an arbitrary point instead (Python's default for SIGINT) could land
    inside ``TensorDict.to_module``, whose exit turns it into a ``RuntimeError`` and skips the checkpoint.
    A second signal stops at once (``KeyboardInterrupt``). :meth:`restore` (or leaving the ``with`` block)
    puts the previous handlers back. Outside the main thread no handler is installed.

    Examples:
        >>> import signal
        >>> before = signal.getsignal(signal.SIGTERM)
        >>> with GracefulStop() as stop:
        ...     signal.getsignal(signal.SIGTERM) == stop._handle, stop.requested
        (True, False)
        >>> signal.getsignal(signal.SIGTERM) is before
        True
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.requested = False
        self._previous = {}
        for signum in self.SIGNALS:
            try:
                self._previous[signum] = signal.signal(signum, self._handle)
            except ValueError:  # not in the main thread: no handler, default behaviour
                pass

    def _handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        name = signal.Signals(signum).name
        print(
            f"\n{name}: stopping after this batch's updates with a checkpoint (send it again to stop now).",
            file=sys.stderr,
            flush=True,
        )

    def restore(self) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous = {}

    def __enter__(self) -> GracefulStop:
        return self

    def __exit__(self, *exc) -> None:
        self.restore()


class LoopTimer:
    """The wall-clock time a training loop spends collecting and updating in this process, with the share of
    ``module``'s calls (the planner's, while acting).

    :meth:`lap` adds the time since the previous lap to a phase (``"collect"``, ``"update"``; none: untimed);
    :meth:`metrics` reports them, with the env steps per second of this process since ``env_steps`` (a
    resumed run counts from its checkpoint).

    Examples:
        >>> timer = LoopTimer(env_steps=80)
        >>> timer.lap("collect"); timer.lap("update")
        >>> sorted(timer.metrics(env_steps=160))
        ['env_steps_per_s', 'time/collect_s', 'time/update_s']
    """

    def __init__(self, module: torch.nn.Module | None = None, *, env_steps: int = 0) -> None:
        self.seconds = {"collect": 0.0, "update": 0.0}
        self.module_timer = ModuleTimer(module) if module is not None else None
        self.start_steps = env_steps
        self._last = time.perf_counter()

    def lap(self, phase: str | None = None) -> None:
        now = time.perf_counter()
        if phase is not None:
            self.seconds[phase] += now - self._last
        self._last = now

    def metrics(self, env_steps: int) -> dict[str, float]:
        """``time/planner_ms_per_call`` (since the last call; with a module), ``time/collect_s``,
        ``time/update_s`` and ``env_steps_per_s`` (collection and updates only)."""
        metrics = {}
        if self.module_timer is not None:
            seconds, calls = self.module_timer.pop()
            metrics["time/planner_ms_per_call"] = 1e3 * seconds / max(calls, 1)
        metrics["time/collect_s"] = self.seconds["collect"]
        metrics["time/update_s"] = self.seconds["update"]
        busy = self.seconds["collect"] + self.seconds["update"]
        metrics["env_steps_per_s"] = (env_steps - self.start_steps) / max(busy, 1e-9)
        return metrics


def log_metrics(logger, metrics: Mapping[str, float], step: int) -> None:
    """Logs every metric as a scalar at ``step`` (nothing when ``logger`` is ``None``).

    Examples:
        >>> log_metrics(None, {"eval/success": 1.0}, step=80)
    """
    if logger is None:
        return
    for key, value in metrics.items():
        logger.log_scalar(key, float(value), step=step)


def write_metrics_csv(history: Sequence[Mapping[str, Any]], path: str | os.PathLike) -> Path:
    """Writes one row per epoch (the union of the keys, sorted, ``env_steps`` and ``epoch`` first),
    atomically (a temporary file, then renamed).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> path = write_metrics_csv([{"env_steps": 80, "epoch": 1, "eval/success": 0.5}], Path(tempfile.mkdtemp()) / "m.csv")
        >>> path.read_text().splitlines()[0]
        'env_steps,epoch,eval/success'
    """
    keys = sorted({k for h in history for k in h}, key=lambda k: (k not in ("epoch", "env_steps"), k))
    return write_csv(history, keys, path)


def make_logger(
    backend: str,
    exp_name: str,
    run_dir: str | Path,
    *,
    project: str | None = None,
    wandb_mode: str = "offline",
    group: str | None = None,
):
    """A TorchRL logger: ``"csv"`` (files under ``run_dir/logs``), ``"wandb"`` (offline unless
    ``wandb_mode="online"``; the runs of one sweep share ``group``) or ``"tensorboard"``; ``None`` for ``"none"``.

    Examples:
        >>> import tempfile
        >>> type(make_logger("csv", "dhrl", tempfile.mkdtemp())).__name__, make_logger("none", "dhrl", ".")
        ('CSVLogger', None)
    """
    from torchrl.record.loggers import CSVLogger, TensorboardLogger, WandbLogger

    log_dir = str(Path(run_dir) / "logs")
    if backend == "csv":
        return CSVLogger(exp_name, log_dir=log_dir)
    if backend == "tensorboard":
        return TensorboardLogger(exp_name, log_dir=log_dir)
    if backend == "wandb":
        extra = {"group": group} if group else {}
        return WandbLogger(
            exp_name, offline=wandb_mode != "online", save_dir=log_dir, project=project, **extra
        )
    if backend == "none":
        return None
    raise ValueError(f"Unknown logger backend {backend!r}: csv, wandb, tensorboard or none.")
