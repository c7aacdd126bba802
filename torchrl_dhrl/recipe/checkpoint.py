"""Checkpoints of a training run: one :class:`torchrl.checkpoint.Checkpoint` registry of its components.

:func:`make_checkpoint` registers every stateful component of a run once, by name; the same registry writes
(:func:`save_checkpoint`) and restores (:func:`restore_checkpoint`) them, and :func:`load_checkpoint` reads a
checkpoint's states without building anything (diagnostics, tests). A checkpoint is a
``torchrl.checkpoint`` directory (``manifest.json`` and one payload directory per component), written
atomically: the components are staged in a hidden sibling directory, which then replaces the previous
checkpoint, so a crash (or Ctrl-C) while writing leaves the previous one complete.

The components, named in :data:`CHECKPOINT_COMPONENTS`:

* ``config`` (JSON), ``counters`` (JSON), ``history`` (JSON, the per-epoch metrics);
* ``agent``: the networks with their target copies (in the two losses) and the graph (in the planner); the
  acting policy is made of these modules and is saved with them, once;
* ``low_updater``, ``high_updater``: the update counts and the optimisers;
* ``low_rb``, ``high_rb``: the replay buffers through their ``state_dict`` (a
  :class:`~torchrl_dhrl.data.CompactLazyTensorStorage` holds only its written rows there), not through the
  default ``dump`` adapter of replay buffers, which writes the whole preallocated capacity;
* ``train_env``, ``eval_env``: the envs' exact simulation states (physics, goals, RNG streams);
* ``collector``: the collector's counters, trajectory ids and live episodes (its carrier), without its
  policy's weights (:class:`CollectorCheckpointAdapter`);
* ``rng``: the global random states (:class:`~torchrl.checkpoint.GlobalRNGState`), restored last.

**0.2.0 checkpoints.** torchrl-dhrl 0.2.0 and earlier wrote one :func:`torch.save` file, ``checkpoint.pt``,
holding a dictionary with the same entries (and ``carrier`` apart from ``collector``). They are still read:
:func:`load_checkpoint` returns their entries under the component names above and
:func:`restore_checkpoint` resumes them (the collector's copy of the policy is ignored); new checkpoints are
always written in the directory layout.

**The saved agent.** :func:`save_agent` writes ``<run dir>/agent``, a checkpoint of ``config``, ``agent``,
``counters`` and ``history`` only (:data:`AGENT_COMPONENTS`): what re-evaluates and diagnoses a run, without
the replay buffers, envs, optimisers or random states (megabytes where a long run's checkpoint takes
hundreds, for committing with a run's results). The recipe writes it each time it writes its checkpoint; :func:`load_checkpoint` reads it as any
checkpoint, and :func:`agent_checkpoint_file` falls back on it for a run directory without ``checkpoint``.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Collection, Mapping, MutableMapping
from pathlib import Path
from typing import Any

import torch
from torchrl.checkpoint import (
    Checkpoint,
    CheckpointAdapter,
    GlobalRNGState,
    JSONCheckpointAdapter,
    StateDictCheckpointAdapter,
)
from torchrl.checkpoint import CheckpointError as _TorchRLCheckpointError

__all__ = [
    "AGENT_COMPONENTS",
    "AGENT_NAME",
    "agent_checkpoint_file",
    "recover_checkpoint",
    "holds_state",
    "CHECKPOINT_COMPONENTS",
    "CHECKPOINT_NAME",
    "CheckpointError",
    "CollectorCheckpointAdapter",
    "checkpoint_file",
    "load_checkpoint",
    "make_checkpoint",
    "restore_checkpoint",
    "save_agent",
    "save_checkpoint",
]

#: The name of a run directory's checkpoint (a ``torchrl.checkpoint`` directory).
CHECKPOINT_NAME = "checkpoint"
#: The single-file checkpoint of torchrl-dhrl 0.2.0 and earlier.
LEGACY_CHECKPOINT_NAME = "checkpoint.pt"
#: The components :func:`make_checkpoint` registers, hence those every training checkpoint holds.
CHECKPOINT_COMPONENTS = (
    "config",
    "agent",
    "low_updater",
    "high_updater",
    "low_rb",
    "high_rb",
    "train_env",
    "eval_env",
    "collector",
    "counters",
    "history",
    "rng",
)
#: The name of a run directory's saved agent (:func:`save_agent`), a ``torchrl.checkpoint`` directory too.
AGENT_NAME = "agent"
#: The components of a saved agent: the networks, their targets and the graph, with what describes them.
AGENT_COMPONENTS = ("config", "agent", "counters", "history")
#: Components that describe the run rather than its state: saved, not restored (checked before resuming).
_NOT_RESTORED = ("config",)
#: Restored after every other component, so that no restoring step can draw from the restored streams.
_RESTORED_LAST = ("rng",)


class CheckpointError(ValueError):
    """A file or directory that cannot be read as a checkpoint, or lacks components a checkpoint must hold;
    the message names the path."""


class _GlobalRNGState(GlobalRNGState):
    """:class:`~torchrl.checkpoint.GlobalRNGState` that skips accelerator states where that accelerator is
    absent (a CUDA run resumed on a CPU machine), as torchrl-dhrl always did."""

    def load_state_dict(self, state_dict: Mapping[str, Any]) -> None:
        absent = {
            "torch_cuda": not torch.cuda.is_available(),
            "torch_xpu": not (hasattr(torch, "xpu") and torch.xpu.is_available()),
            "torch_mps": not torch.backends.mps.is_available(),
        }
        super().load_state_dict({k: v for k, v in state_dict.items() if not absent.get(k, False)})


class _StateCapture:
    """A stand-in component that keeps the state an adapter loads into it (reading without live objects)."""

    state: Any = None

    def load_state_dict(self, state_dict: Any) -> None:
        self.state = state_dict


class CollectorCheckpointAdapter(CheckpointAdapter):
    """Checkpoints a :class:`~torchrl.collectors.Collector` without its policy's weights, with its live episodes.

    A collector's ``state_dict`` holds its policy's (the agent's networks and graph, which the checkpoint
    saves once, elsewhere) and not the tensordict its envs continue from (the carrier: each env's last
    observation, the planner's and the subgoal scheduler's state of the running episode). This adapter saves
    the collector's ``state_dict`` less ``policy_state_dict``, plus the carrier under ``"carrier"``, as a
    :class:`~torchrl.checkpoint.StateDictCheckpointAdapter` payload; loading restores the counters and the
    trajectory ids, then copies the carrier into the collector's own tensors (some of which live on its
    storing device).

    Examples:
        >>> import tempfile, torch
        >>> from torchrl.checkpoint import Checkpoint
        >>> from torchrl.collectors import Collector
        >>> from torchrl_dhrl.envs import make_env
        >>> from torchrl_dhrl.recipe import CollectorCheckpointAdapter
        >>> def collector():
        ...     env = make_env("PointMaze", num_envs=2, seed=0, max_episode_steps=5)
        ...     return Collector(env, None, frames_per_batch=10, total_frames=-1)
        >>> source, target = collector(), collector()
        >>> _ = next(iter(source))
        >>> path = tempfile.mkdtemp() + "/ckpt"
        >>> _ = Checkpoint().register("collector", source, adapter=CollectorCheckpointAdapter()).save(path)
        >>> _ = Checkpoint().register("collector", target, adapter=CollectorCheckpointAdapter()).load(path)
        >>> torch.equal(target._carrier["observation"], source._carrier["observation"])
        True
    """

    adapter_id = "torchrl_dhrl.collector"
    format_version = 1

    def __init__(self) -> None:
        self._payload = StateDictCheckpointAdapter()

    @staticmethod
    def collector_state(collector) -> dict[str, Any]:
        """What is saved: the collector's ``state_dict`` without ``policy_state_dict``, with ``"carrier"``."""
        state = dict(collector.state_dict())
        state.pop("policy_state_dict", None)
        state["carrier"] = collector._carrier.to_dict()
        return state

    @staticmethod
    def load_collector_state(collector, state: Mapping[str, Any]) -> None:
        """Restores :meth:`collector_state` (a ``policy_state_dict`` in it, as 0.2.0 saved, is ignored)."""
        state = dict(state)
        state.pop("policy_state_dict", None)
        carrier = state.pop("carrier")
        # strict=False: the policy's state is absent (the agent restores it); the envs' transforms' is loaded
        collector.load_state_dict(state, strict=False)
        collector._carrier.update_(carrier)

    def save(self, component, path: Path, *, args, kwargs):
        holder = _StateHolder(self.collector_state(component))
        return self._payload.save(holder, path, args=args, kwargs=kwargs)

    def load(self, component, path: Path, *, map_location, tensor_load_kwargs, args, kwargs):
        capture = _StateCapture()
        self._payload.load(
            capture,
            path,
            map_location=map_location,
            tensor_load_kwargs=tensor_load_kwargs,
            args=args,
            kwargs=kwargs,
        )
        self.load_collector_state(component, capture.state)
        return None


class _JSONStateAdapter(JSONCheckpointAdapter):
    """:class:`~torchrl.checkpoint.JSONCheckpointAdapter` for an object with ``state_dict``/``load_state_dict``
    (the run's counters): the same file as a dict's, so either loads the other's."""

    def save(self, component, path: Path, *, args, kwargs):
        super().save(component.state_dict(), path, args=args, kwargs=kwargs)
        return component

    def load(self, component, path: Path, *, map_location, tensor_load_kwargs, args, kwargs):
        value = super().load(
            None, path, map_location=map_location, tensor_load_kwargs=tensor_load_kwargs, args=args, kwargs=kwargs
        )
        component.load_state_dict(value)
        return component


class _StateHolder:
    """A saved state as a component (``state_dict`` returns it)."""

    def __init__(self, state: Any) -> None:
        self._state = state

    def state_dict(self) -> Any:
        return self._state


def make_checkpoint(
    *,
    config: Mapping[str, Any],
    agent,
    low_updater,
    high_updater,
    low_rb,
    high_rb,
    train_env,
    eval_env,
    collector,
    counters: Any,
    history: list,
) -> Checkpoint:
    """The registry of every stateful component of a DHRL run: one :class:`~torchrl.checkpoint.Checkpoint`
    for :func:`save_checkpoint` and :func:`restore_checkpoint` alike.

    The components are registered by reference: saving reads their state at that time, restoring loads into
    them (``counters`` and ``history`` are updated in place). See the module's documentation for what each
    one holds, and :data:`CHECKPOINT_COMPONENTS` for the names.

    Keyword Args:
        config (Mapping): the run's configuration (JSON; saved, checked before resuming, not restored).
        agent: a :class:`~torchrl_dhrl.factory.DHRLAgent` (or anything with ``state_dict`` /
            ``load_state_dict`` holding the networks, their targets and the graph).
        low_updater, high_updater: the :class:`~torchrl_dhrl.training.LossUpdater` of each level.
        low_rb, high_rb: the replay buffers (saved through their ``state_dict``: the written rows of a
            :class:`~torchrl_dhrl.data.CompactLazyTensorStorage`).
        train_env, eval_env: the envs whose ``state_dict`` is their exact state (the base envs of
            :func:`~torchrl_dhrl.envs.make_env`, without the agent's transforms).
        collector: the training :class:`~torchrl.collectors.Collector` (:class:`CollectorCheckpointAdapter`).
        counters (RunCounters or dict): env steps, episodes, epochs, ... (restored in place); ``history`` (list): the per-epoch metrics.

    Examples:
        >>> import tempfile, torch
        >>> from torchrl_dhrl.recipe import load_checkpoint, make_checkpoint, restore_checkpoint, save_checkpoint
        >>> from torchrl_dhrl.recipe.checkpoint import CHECKPOINT_COMPONENTS
        >>> net, counters, history = torch.nn.Linear(2, 1), {"env_steps": 80}, [{"eval/success": 0.5}]
        >>> parts = dict.fromkeys(("agent", "low_updater", "high_updater", "low_rb", "high_rb"), net)
        >>> from torchrl_dhrl.envs import make_env
        >>> from torchrl.collectors import Collector
        >>> env = make_env("PointMaze", num_envs=1, seed=0, max_episode_steps=4)
        >>> collector = Collector(env, None, frames_per_batch=4, total_frames=-1)
        >>> ckpt = make_checkpoint(config={"seed": 0}, train_env=env, eval_env=env, collector=collector,
        ...                        counters=counters, history=history, **parts)
        >>> path = save_checkpoint(ckpt, tempfile.mkdtemp() + "/checkpoint")
        >>> counters["env_steps"] = 160
        >>> restore_checkpoint(ckpt, path)
        >>> counters, sorted(load_checkpoint(path)) == sorted(CHECKPOINT_COMPONENTS)
        ({'env_steps': 80}, True)
    """
    state_dict = StateDictCheckpointAdapter()
    json = JSONCheckpointAdapter()
    checkpoint = Checkpoint()
    checkpoint.register("config", dict(config), adapter=json)
    checkpoint.register("agent", agent, adapter=state_dict)
    checkpoint.register("low_updater", low_updater, adapter=state_dict)
    checkpoint.register("high_updater", high_updater, adapter=state_dict)
    # through state_dict: the default adapter of a replay buffer (dump) writes the whole allocated storage
    checkpoint.register("low_rb", low_rb, adapter=state_dict)
    checkpoint.register("high_rb", high_rb, adapter=state_dict)
    checkpoint.register("train_env", train_env, adapter=state_dict)
    checkpoint.register("eval_env", eval_env, adapter=state_dict)
    checkpoint.register("collector", collector, adapter=CollectorCheckpointAdapter())
    checkpoint.register(
        "counters", counters, adapter=_JSONStateAdapter() if hasattr(counters, "state_dict") else json
    )
    checkpoint.register("history", history, adapter=json)
    checkpoint.register("rng", _GlobalRNGState(), adapter=state_dict)
    return checkpoint


def save_checkpoint(checkpoint: Checkpoint, path: str | os.PathLike) -> Path:
    """Writes every component of ``checkpoint`` at ``path`` (a directory) atomically and returns ``path``.

    :meth:`torchrl.checkpoint.Checkpoint.save` stages the components in a hidden sibling directory and
    swaps it in when all are written: a crash (or Ctrl-C) while writing leaves the previous checkpoint at
    ``path`` complete, and the staging directory is removed on failure. The manifest's metadata records the
    torchrl-dhrl version that wrote it.
    """
    from torchrl_dhrl import __version__

    return checkpoint.save(Path(path), metadata={"torchrl_dhrl": __version__})


def save_agent(source: Checkpoint | str | os.PathLike, out: str | os.PathLike | None = None) -> Path:
    """Writes a run's saved agent: a ``torchrl.checkpoint`` directory of :data:`AGENT_COMPONENTS` only, and
    returns its path.

    It holds ``config``, ``agent`` (the networks, their target copies and the graph: landmarks, distances,
    shortest paths), ``counters`` and ``history``, without the replay buffers, envs, collector, optimisers or
    random states: what :func:`~dhrl_utils.agent_from_checkpoint`, ``recipes/evaluate.py`` and the
    diagnostics need, small enough to commit (the agent's tensors in one consolidated TensorDict file). It
    is written atomically, as :func:`save_checkpoint` writes: a crash while writing leaves the previous one
    (and :func:`recover_checkpoint` completes an interrupted swap). It cannot be resumed.

    Args:
        source (Checkpoint, str or os.PathLike): the live registry of :func:`make_checkpoint` (the recipe's
            way, right after :func:`save_checkpoint`: the states are read from the objects, the buffers are
            not touched), or a checkpoint or the run directory holding it (see :func:`checkpoint_file`; only
            the four components are read).
        out (str or os.PathLike, optional): where to write it. Defaults to :data:`AGENT_NAME` beside the
            checkpoint of a path ``source`` (``<run dir>/agent``); required with a registry.

    Raises:
        ValueError: a registry without ``out``, or without a ``config`` or an ``agent`` component.
        FileNotFoundError, CheckpointError: as :func:`load_checkpoint`, for a path ``source``.

    Examples:
        >>> import tempfile, torch
        >>> from pathlib import Path
        >>> from torchrl.checkpoint import Checkpoint, JSONCheckpointAdapter, StateDictCheckpointAdapter
        >>> from torchrl_dhrl.recipe import AGENT_NAME, load_checkpoint, save_agent, save_checkpoint
        >>> run = Path(tempfile.mkdtemp())
        >>> ckpt = Checkpoint()
        >>> for name, value in (("config", {"seed": 0}), ("counters", {"env_steps": 80}), ("history", [])):
        ...     _ = ckpt.register(name, value, adapter=JSONCheckpointAdapter())
        >>> _ = ckpt.register("agent", torch.nn.Linear(2, 1), adapter=StateDictCheckpointAdapter())
        >>> _ = ckpt.register("low_rb", torch.nn.Linear(64, 64), adapter=StateDictCheckpointAdapter())
        >>> _ = save_checkpoint(ckpt, run / "checkpoint")
        >>> path = save_agent(ckpt, run / AGENT_NAME)  # from the live objects, as the recipe does
        >>> sorted(load_checkpoint(path)), load_checkpoint(path)["counters"]
        (['agent', 'config', 'counters', 'history'], {'env_steps': 80})
        >>> save_agent(run) == path  # or from a run directory's checkpoint
        True
    """
    from torchrl_dhrl import __version__

    if isinstance(source, Checkpoint):
        if out is None:
            raise ValueError("save_agent: `out` is required with a registry (it knows no run directory).")
        held = source.components
        missing = [name for name in ("config", "agent") if name not in held]
        if missing:
            raise ValueError(f"save_agent: the registry has no {' or '.join(map(repr, missing))} component.")
        values = {name: held[name] for name in AGENT_COMPONENTS if name in held}
    else:
        path = checkpoint_file(source)
        values = load_checkpoint(path, components=AGENT_COMPONENTS, required_keys=("config", "agent"))
        values["agent"] = _StateHolder(values["agent"])
        out = path.parent / AGENT_NAME if out is None else out
    saved = Checkpoint()
    for name, value in values.items():
        if name == "agent":  # one file for the tensors, not one per tensor: a few files to commit
            adapter = StateDictCheckpointAdapter(payload_format="consolidated")
        else:
            adapter = _JSONStateAdapter() if hasattr(value, "state_dict") else JSONCheckpointAdapter()
        saved.register(name, value, adapter=adapter)
    return saved.save(Path(out), metadata={"torchrl_dhrl": __version__})


def restore_checkpoint(
    checkpoint: Checkpoint, path: str | os.PathLike, map_location: str | torch.device | None = None
) -> None:
    """Loads the checkpoint at ``path`` (see :func:`checkpoint_file`) into the components of ``checkpoint``.

    Every registered component is restored but ``config`` (check it first, e.g. with
    :func:`~torchrl_dhrl.recipe.check_resume_config`), the global random states last. A 0.2.0
    ``checkpoint.pt`` is restored from its entries (see the module's documentation).

    Raises:
        FileNotFoundError: when there is no checkpoint at ``path``.
        CheckpointError: when a component is missing or does not load; the message names the path.
    """
    path = checkpoint_file(path)
    names = [name for name in checkpoint.components if name not in _NOT_RESTORED]
    first = [name for name in names if name not in _RESTORED_LAST]
    last = [name for name in names if name in _RESTORED_LAST]
    if _is_legacy(path):
        states = load_checkpoint(path, map_location, required_keys=tuple(names))
        for group in (first, last):
            for name in group:
                _load_state(checkpoint, name, states[name])
        return
    if not path.exists():
        raise FileNotFoundError(f"No checkpoint at {str(path)!r}.")
    try:
        for group in (first, last):
            checkpoint.load(path, components=group, map_location=map_location)
    except (_TorchRLCheckpointError, OSError, ValueError, KeyError, TypeError) as err:
        raise CheckpointError(f"{str(path)!r} does not restore this run: {_short(err)}") from err


def _load_state(checkpoint: Checkpoint, name: str, state: Any) -> None:
    """Loads one component from a state read by :func:`load_checkpoint` (the 0.2.0 path)."""
    component = checkpoint.components[name]
    if name == "collector":
        CollectorCheckpointAdapter.load_collector_state(component, state)
    elif isinstance(component, MutableMapping):
        component.clear()
        component.update(state)
    elif isinstance(component, list):
        component[:] = state
    else:
        component.load_state_dict(state)


def recover_checkpoint(run_dir: str | os.PathLike) -> str | None:
    """Completes a checkpoint swap that a crash interrupted, and removes what interrupted saves left behind.

    :func:`save_checkpoint` stages the new checkpoint in ``.checkpoint.stage-*`` (its ``manifest.json`` written
    last), renames the current one to ``.checkpoint.backup-*``, the staged one into place, and removes the
    backup. A process killed between the two renames leaves no ``checkpoint``: the staged one is moved into
    place when it is complete, else the backup is moved back. Complete means a manifest that parses and
    validates (:meth:`torchrl.checkpoint.Checkpoint.is_checkpoint`): a process killed while writing the
    manifest leaves an empty or truncated one. Incomplete stages and stale backups are removed. The saved
    agent (``agent``, :func:`save_agent`) is recovered in the same way.
    Call it only while no save is running in ``run_dir`` (the recipe does at start-up).

    Returns:
        a one-line note when a checkpoint was moved into place, else ``None``.

    Examples:
        >>> import tempfile
        >>> run = Path(tempfile.mkdtemp())
        >>> checkpoint = Checkpoint()
        >>> _ = checkpoint.register("counters", {"k": 1}, adapter=JSONCheckpointAdapter())
        >>> _ = save_checkpoint(checkpoint, run / ".checkpoint.backup-1")  # renamed away, then killed
        >>> (run / ".checkpoint.stage-2").mkdir()  # the next save, killed while writing its manifest
        >>> (run / ".checkpoint.stage-2" / "manifest.json").write_text("")
        0
        >>> recover_checkpoint(run)
        'Recovered the checkpoint of an interrupted save in ... (the previous one).'
        >>> sorted(p.name for p in run.iterdir())
        ['checkpoint']
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        return None
    pairs = ((CHECKPOINT_NAME, "checkpoint"), (AGENT_NAME, "saved agent"))
    notes = [_recover(run_dir, name, what) for name, what in pairs]
    return " ".join(note for note in notes if note) or None


def _recover(run_dir: Path, name: str, what: str) -> str | None:
    """:func:`recover_checkpoint` of the checkpoint directory ``run_dir/name``."""
    target = run_dir / name
    stages = sorted(run_dir.glob(f".{name}.stage-*"), key=lambda p: p.stat().st_mtime, reverse=True)
    backups = sorted(run_dir.glob(f".{name}.backup-*"), key=lambda p: p.stat().st_mtime, reverse=True)
    note = None
    if not target.exists():
        complete = [p for p in (*stages, *backups) if Checkpoint.is_checkpoint(p)]
        if complete:
            os.replace(complete[0], target)
            which = "new" if complete[0] in stages else "previous"
            note = f"Recovered the {what} of an interrupted save in {run_dir} (the {which} one)."
    for leftover in (*stages, *backups, *run_dir.glob(f".{name}.archive-*")):
        if leftover.is_dir():
            shutil.rmtree(leftover, ignore_errors=True)
        elif leftover.exists():
            leftover.unlink()
    return note


def holds_state(state: Any) -> bool:
    """Whether a ``state_dict`` holds anything (a value other than an empty container, at any depth): an env
    whose ``state_dict`` holds nothing (e.g. ``{"worker0": {}, "worker1": {}}``) resumes from a fresh
    simulation, not where it stopped.

    Examples:
        >>> holds_state({"worker0": {}, "worker1": {}}), holds_state({"qpos": [0.0]})
        (False, True)
    """
    if isinstance(state, Mapping):
        return any(holds_state(value) for value in state.values())
    if isinstance(state, (list, tuple)):
        return any(holds_state(value) for value in state)
    return state is not None


def checkpoint_file(path: str | os.PathLike) -> Path:
    """The checkpoint ``path`` designates: ``path`` itself when it is a checkpoint, else the checkpoint of the
    run directory ``path``.

    A checkpoint is a ``torchrl.checkpoint`` directory (holding ``manifest.json``; a saved agent,
    ``path/agent``, is one too) or a 0.2.0 file; a run directory's is ``path/checkpoint``, or ``path/checkpoint.pt`` when only that 0.2.0 file is there. (In
    0.2.0 this returned ``path/checkpoint.pt`` for every directory.) The path is returned whether it exists
    or not.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> run = Path(tempfile.mkdtemp())
        >>> checkpoint_file(run) == run / "checkpoint"
        True
        >>> (run / "checkpoint.pt").touch()  # a 0.2.0 run
        >>> checkpoint_file(run).name
        'checkpoint.pt'
    """
    path = Path(path)
    if not path.is_dir() or (path / "manifest.json").exists():
        return path
    current, legacy = path / CHECKPOINT_NAME, path / LEGACY_CHECKPOINT_NAME
    return legacy if legacy.exists() and not current.exists() else current


def agent_checkpoint_file(path: str | os.PathLike) -> Path:
    """The checkpoint to read a run's agent from: :func:`checkpoint_file`'s, or, for a run directory that holds
    none, its saved agent (:data:`AGENT_NAME`, :func:`save_agent`): a run's results kept without the full
    checkpoint still re-evaluate. A checkpoint (or a saved agent) given itself is returned as it is.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> run = Path(tempfile.mkdtemp())
        >>> agent_checkpoint_file(run) == run / "checkpoint"  # nothing there: where the checkpoint goes
        True
        >>> (run / "agent").mkdir()  # only the saved agent kept
        >>> agent_checkpoint_file(run) == run / "agent"
        True
    """
    path = Path(path)
    found = checkpoint_file(path)
    saved = path / AGENT_NAME
    return saved if found != path and not found.exists() and saved.exists() else found


def load_checkpoint(
    path: str | os.PathLike,
    map_location: str | torch.device | None = "cpu",
    *,
    required_keys: Collection[str] = (),
    components: Collection[str] | None = None,
) -> dict[str, Any]:
    """Reads the states of a checkpoint, ``{component name: state}``, without building anything.

    The states are those the components' ``state_dict`` returned when saved (``config``, ``counters`` and
    ``history`` as they were); the ``collector``'s holds the carrier under ``"carrier"``.

    Args:
        path (str or os.PathLike): a checkpoint or the run directory holding it (see :func:`checkpoint_file`).
        map_location (str, torch.device or None): where tensors are loaded. Defaults to ``"cpu"``.

    Keyword Args:
        required_keys (collection of str): components the checkpoint must hold (e.g.
            :data:`CHECKPOINT_COMPONENTS`). Defaults to none.
        components (collection of str, optional): the components to read (e.g. ``("config", "agent")``
            without the replay buffers); those the checkpoint lacks are left out. Defaults to all.

    Raises:
        FileNotFoundError: when there is no such checkpoint.
        CheckpointError: when it cannot be read (corrupt, truncated, not a checkpoint) or lacks one of
            ``required_keys``; the message names the path.

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
    if not path.exists():
        raise FileNotFoundError(f"No checkpoint at {str(path)!r}.")
    if _is_legacy(path):
        states = _read_legacy(path, map_location)
        _check_keys(path, list(states), required_keys)
        return {k: v for k, v in states.items() if components is None or k in components}
    try:
        manifest = Checkpoint.manifest(path)
    except (_TorchRLCheckpointError, OSError, ValueError) as err:
        raise CheckpointError(f"{str(path)!r} is not a readable checkpoint ({_short(err)}).") from err
    records = manifest["components"]
    _check_keys(path, list(records), required_keys)
    names = [name for name in records if components is None or name in components]
    reader = Checkpoint()
    for name in names:
        adapter = _READERS.get(records[name]["adapter"])
        if adapter is None:
            raise CheckpointError(
                f"{str(path)!r}: component {name!r} was written by adapter {records[name]['adapter']!r}, "
                "which this version does not read."
            )
        reader.register(
            name, None if isinstance(adapter, JSONCheckpointAdapter) else _StateCapture(), adapter=adapter
        )
    try:
        result = reader.load(path, map_location=map_location)
    except (_TorchRLCheckpointError, OSError, ValueError, KeyError, TypeError) as err:
        raise CheckpointError(f"{str(path)!r} is not a readable checkpoint ({_short(err)}).") from err
    return {
        name: result.values[name] if name in result.values else reader.components[name].state
        for name in names
    }


class _CollectorStateReader(StateDictCheckpointAdapter):
    """Reads a :class:`CollectorCheckpointAdapter` payload as a state (it is a state-dict payload)."""

    adapter_id = CollectorCheckpointAdapter.adapter_id
    format_version = CollectorCheckpointAdapter.format_version


#: How :func:`load_checkpoint` reads each adapter's payload (into a :class:`_StateCapture`, or as JSON).
_READERS: dict[str, CheckpointAdapter] = {
    StateDictCheckpointAdapter.adapter_id: StateDictCheckpointAdapter(),
    JSONCheckpointAdapter.adapter_id: JSONCheckpointAdapter(),
    CollectorCheckpointAdapter.adapter_id: _CollectorStateReader(),
}


def _short(err: BaseException) -> str:
    return f"{type(err).__name__}: {' '.join(str(err).split())[:160]}"


def _check_keys(path: Path, held: list[str], required: Collection[str]) -> None:
    missing = [key for key in required if key not in held]
    if missing:
        lacks = ", ".join(map(repr, missing[:4])) + (
            f" and {len(missing) - 4} more" if len(missing) > 4 else ""
        )
        shown = ", ".join(repr(k) for k in held[:4]) + (", ..." if len(held) > 4 else "")
        raise CheckpointError(
            f"{str(path)!r} is not a training checkpoint: it lacks {lacks} (it holds {shown})."
        )


def _is_legacy(path: Path) -> bool:
    """A file that is not a ``torchrl.checkpoint`` archive: a 0.2.0 :func:`torch.save` checkpoint, or garbage."""
    return path.is_file() and not Checkpoint.is_checkpoint(path)


def _read_legacy(path: Path, map_location) -> dict[str, Any]:
    """The entries of a 0.2.0 ``checkpoint.pt`` under the component names of :func:`make_checkpoint`."""
    try:
        state = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as err:  # pickle, zip and torch errors alike: the file is not a readable checkpoint
        raise CheckpointError(f"{str(path)!r} is not a readable checkpoint ({_short(err)}).") from err
    if not isinstance(state, dict):
        raise CheckpointError(
            f"{str(path)!r} is not a training checkpoint: it holds a {type(state).__name__}."
        )
    state = dict(state)
    if "collector" in state and "carrier" in state:
        state["collector"] = {**state["collector"], "carrier": state.pop("carrier")}
        state["collector"].pop("policy_state_dict", None)
    rng = state.get("rng")
    if isinstance(rng, Mapping) and "torch" in rng:  # get_rng_state() of 0.2.0 -> GlobalRNGState's keys
        names = {"python": "python", "numpy": "numpy", "torch": "torch_cpu", "cuda": "torch_cuda"}
        state["rng"] = {names[k]: v for k, v in rng.items() if k in names}
    return state
