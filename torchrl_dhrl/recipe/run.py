"""Starting a training run: start-up checks, resume and fork, the run directory and its provenance.

:func:`start_run` checks everything that can be checked before a run builds or writes anything (the
configuration, the device, the checkpoint to resume, the run directory, offscreen rendering) and prepares
the run; :func:`write_run_dir` writes its configuration and appends what the start runs on and with to its
provenance (:func:`describe_start`). The loop's own machinery (counters, stops, timer, metrics) is in
:mod:`torchrl_dhrl.recipe.loop`.
"""

from __future__ import annotations

import contextlib
import csv
import datetime
import importlib.metadata
import os
import platform
import shlex
import subprocess
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import torch
import yaml

from torchrl_dhrl.training import AdaptiveThreads, native_bfloat16, start_threads

from .checkpoint import (
    CHECKPOINT_COMPONENTS,
    CheckpointError,
    checkpoint_file,
    load_checkpoint,
    recover_checkpoint,
)
from .config import validate_config
from .resolve import _dtype_name, describe_precisions, resolve_device, resolve_speed, run_precisions
from .resume import check_resume_config
from .schema import FORK_MUTABLE_KEYS, ConfigError, check_known_keys

__all__ = [
    "CONFIG_NAME",
    "PROVENANCE_NAME",
    "RESUME_AUTO",
    "RunStart",
    "code_and_machine",
    "describe_start",
    "read_provenance",
    "start_run",
    "write_run_dir",
    "write_csv",
    "write_yaml",
]

#: The run's configuration, as :func:`start_run` writes it into the run directory (YAML).
CONFIG_NAME = "config.yaml"
#: What each start of the run ran on and with (YAML, a list: one entry per start, a resume's appended).
PROVENANCE_NAME = "provenance.yaml"
#: The distributions whose versions a start records.
PROVENANCE_PACKAGES = ("torchrl-dhrl", "torch", "torchrl", "tensordict", "mujoco", "numpy")
#: ``resume=auto``: continue the run directory's own checkpoint when there is one, else start afresh (sweeps).
RESUME_AUTO = "auto"


class RunStart(NamedTuple):
    """What :func:`start_run` prepared.

    Attributes:
        config (dict): the validated configuration (``fork``, when set, as the resolved checkpoint path).
        device (torch.device): where the networks, the planner and the buffers live.
        run_dir (Path): the run directory (created).
        resume (Path or None): the checkpoint to restore, checked: the run's own (``resume``) or the one it
            is forked from (``fork``, see :attr:`forking`).
        state (dict or None): its ``config`` and ``counters`` (:func:`~torchrl_dhrl.recipe.load_checkpoint`).
        threads (AdaptiveThreads or None): the thread count to poll in the loop (``threads=null``), ``None``
            when the count is fixed.
    """

    config: dict
    device: torch.device
    run_dir: Path
    resume: Path | None
    state: dict | None
    threads: AdaptiveThreads | None = None

    @property
    def forking(self) -> bool:
        """Whether the run starts as a fork: from another run's checkpoint (``fork``), into its own directory.
        A forked run resumed later restores its own checkpoint and is not forking."""
        fork = self.config.get("fork")
        return self.resume is not None and fork is not None and self.resume == Path(fork)


def start_run(
    cfg: Mapping[str, Any],
    run_dir: str | os.PathLike | None = None,
    *,
    schema: Mapping[str, Any] | None = None,
    schema_source: str = "config.yaml",
    write: bool = True,
) -> RunStart:
    """Checks everything that can be checked before a run builds or writes anything, then prepares it.

    In order: the keys (only those of ``schema``, see :func:`~torchrl_dhrl.recipe.check_known_keys`), their
    values (:func:`~torchrl_dhrl.recipe.validate_config`), the device, the checkpoint to ``resume``
    (readable, with every component of :data:`~torchrl_dhrl.recipe.CHECKPOINT_COMPONENTS`, and trained with
    the same configuration up to :data:`~torchrl_dhrl.recipe.RESUME_MUTABLE_KEYS`), the run directory (not
    a file, writable; no checkpoint of another run in it, which the run would overwrite) and, with
    ``plots.video=true``, MuJoCo's offscreen rendering. Only then it sets the thread count (``threads``,
    printed as one line), creates the run directory and writes the configuration there
    (:data:`CONFIG_NAME`, YAML; rewritten by a resume, whose keys differ only in run bookkeeping); with
    ``write=False`` it leaves that to :func:`write_run_dir`, for a caller that builds the run's objects first
    (whose own checks may still refuse it: an env's sizes are known only once it is built).

    ``resume="auto"`` (:data:`RESUME_AUTO`) resumes the run directory's own checkpoint when it holds one and
    starts afresh otherwise, so re-launching a sweep continues its interrupted runs (the returned
    configuration holds the path, or ``None``).

    ``fork=<run directory or checkpoint>`` starts a *new* run in ``run_dir`` from another run's checkpoint
    (every state: networks, optimisers, buffers, graph, envs, counters, metrics so far) with a configuration
    that may differ from that run's in :data:`~torchrl_dhrl.recipe.FORK_MUTABLE_KEYS` as well (the seed and
    the hyperparameters no state holds), e.g. an A/B of the gradual penalty from one state of a long run. The
    forked run's directory must not hold a checkpoint, and ``total_steps`` must go past the checkpoint's. A
    forked run is continued like any other, with ``resume=<its run_dir>`` (``fork`` may then be left out; if
    given it must name the same checkpoint). What happens to the states is the training loop's business (see
    :attr:`RunStart.forking`).

    Args:
        cfg (Mapping): the configuration, a plain nested dict (e.g. the recipe's composed Hydra config).
        run_dir (str or os.PathLike, optional): where the run writes; defaults to ``cfg["run_dir"]``, else
            the current directory.

    Keyword Args:
        schema (Mapping, optional): the keys a configuration may hold (the recipe's ``config.yaml``); not
            checked when ``None``.
        schema_source (str): how error messages name the schema.
        write (bool): create the run directory and write the configuration. Defaults to ``True``.

    Returns:
        a :class:`RunStart`.

    Raises:
        ConfigError: naming the key, the value and what is accepted; nothing has been built or written.
    """
    cfg = dict(cfg)
    if schema is not None:
        check_known_keys(cfg, schema, source=schema_source, complete=True)
    validate_config(cfg)
    device = resolve_device(cfg["device"])
    cfg, speed_line = resolve_speed(cfg, device)  # the speed switches left at null, for this device
    run_dir = Path(run_dir or cfg["run_dir"] or ".").expanduser().resolve()
    # a save killed between its two renames leaves the checkpoint under another name: put it back first
    directories = {run_dir}
    if cfg["resume"] and cfg["resume"] != RESUME_AUTO:
        resumed = Path(cfg["resume"]).expanduser().resolve()
        directories.add(resumed if resumed.is_dir() and not (resumed / "manifest.json").exists() else resumed.parent)
    for directory in sorted(directories):
        note = recover_checkpoint(directory)
        if note:
            print(note)
    if cfg["resume"] == RESUME_AUTO:  # a sweep's job: continue its own run if it has one, else start it
        cfg["resume"] = str(run_dir) if checkpoint_file(run_dir).exists() else None
    resume = state = None
    notes: list[str] = []
    forking = False  # starting from another run's checkpoint (`fork` without `resume`)
    fork = cfg.get("fork")
    if fork is not None:
        cfg["fork"] = fork = str(checkpoint_file(Path(fork).expanduser()).resolve())
    if cfg["resume"]:
        resume = checkpoint_file(Path(cfg["resume"]).expanduser()).resolve()
        what = f"`resume={cfg['resume']}`"
        state = _read_checkpoint(resume, what)
        forked_from = state["config"].get("fork")
        if fork is not None and fork != forked_from:
            raise ConfigError(
                f"{what} with `fork={fork}`: that run "
                + (f"was forked from {forked_from}" if forked_from else "was not forked")
                + "; leave `fork` out to continue it, or start the fork in another run_dir."
            )
        if "fork" in cfg:
            cfg["fork"] = forked_from  # where a resumed run came from stays in its configuration
        notes = check_resume_config(state["config"], cfg, what=f"{what} ({resume})")
        notes = [note for note in notes if not note.startswith("resume:")]  # resume itself always changes
    elif fork is not None:
        forking, resume = True, Path(fork)
        what = f"`fork={fork}`"
        state = _read_checkpoint(resume, what)
        if resume == checkpoint_file(run_dir).resolve():
            raise ConfigError(
                f"{what}: a fork is a new run; choose a run_dir other than the forked run's ({run_dir})."
            )
        steps = state["counters"]["env_steps"]
        if cfg["total_steps"] <= steps:
            raise ConfigError(
                f"`total_steps` {cfg['total_steps']} with {what}: the checkpoint is at {steps} env steps, so the "
                "fork would not train; set total_steps above it."
            )
        notes = check_resume_config(
            state["config"], cfg, mutable=FORK_MUTABLE_KEYS, what=f"{what} ({resume})", action="fork"
        )
        notes = [note for note in notes if not note.startswith(("resume:", "fork:", "run_dir:"))]
    _check_run_dir(run_dir, None if forking else resume)
    if cfg["plots"]["video"]:
        _check_offscreen_rendering()
    threads_line, adaptive_threads = start_threads(cfg["threads"])
    print(threads_line)
    print(speed_line)
    print(describe_precisions(cfg, device))
    if cfg.get("cudagraph_policy", False):
        print(
            "Acting: the policy captured as CUDA graphs (one in the collector, one for the test episodes), its "
            "planner capturable on a reserved fixed-size graph (every env planned in a replay; the same plans; "
            "the planner's time per call is not logged)."
            + (" The collector's graph captures the compiled policy." if cfg.get("compile_policy", False) else "")
        )
    elif cfg.get("compile_policy", False):
        print(
            "Acting: the policy compiled in the collector (torch.compile), its planner capturable (every env "
            "planned inside a torch.cond in the steps where a replan is due; the same plans; the planner's time "
            "per call is not logged)."
        )
    if forking:
        print(
            f"Forking {resume} at {state['counters']['env_steps']} env steps into {run_dir}"
            + (f" with: {'; '.join(notes)}." if notes else " (nothing changed: a copy that goes on).")
        )
    elif notes:
        print(f"Resuming {resume} with: {'; '.join(notes)}.")
    start = RunStart(cfg, device, run_dir, resume, state, adaptive_threads)
    if write:
        write_run_dir(start)
    return start


def write_run_dir(start: RunStart) -> None:
    """Creates the run directory of a :func:`start_run`, writes its configuration (:data:`CONFIG_NAME`) and
    appends this start to its provenance (:data:`PROVENANCE_NAME`, :func:`describe_start`)."""
    start.run_dir.mkdir(parents=True, exist_ok=True)
    _write_config(start.config, start.run_dir / CONFIG_NAME)
    # a resume goes on with the starts of the run it continues (its checkpoint's directory); a fork is a new run
    starts = read_provenance(start.resume.parent) if start.resume is not None and not start.forking else []
    write_yaml([*starts, describe_start(start)], start.run_dir / PROVENANCE_NAME)


def describe_start(start: RunStart) -> dict[str, Any]:
    """What a start of a run runs on and with, for its run directory's :data:`PROVENANCE_NAME`.

    ``config.yaml`` holds the keys as given, ``auto`` included; this record holds what they resolved to on
    this machine, and what the keys cannot say: ``started`` (UTC), ``env_steps`` (where the start
    continues: 0, a resumed or forked checkpoint's count; ``forked_from`` for a fork), ``command`` (the
    interpreter's name and the process's arguments, as a shell would take them), ``code`` (the git
    commit of the checkout ``torchrl_dhrl`` is imported from and whether its tracked files were modified,
    ``None`` outside a git checkout, and the imported package's ``__version__``), ``versions``
    (:data:`PROVENANCE_PACKAGES` and Python), ``machine`` (architecture, CPU model, cores, whether the
    device has native bfloat16), ``device``, ``threads`` and ``precision`` (``update_dtype`` and
    ``planner.build_dtype`` as resolved, :func:`~torchrl_dhrl.recipe.run_precisions`). ``recipes/aggregate.py``
    reads ``precision`` to tell an ``auto`` run's variant.
    """
    update, build = run_precisions(start.config, start.device)
    record: dict[str, Any] = {
        "started": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "env_steps": int(start.state["counters"]["env_steps"]) if start.state is not None else 0,
    }
    if start.forking:
        record["forked_from"] = str(start.resume)
    record |= {
        "command": shlex.join([Path(sys.executable).name, *sys.argv]),
        **code_and_machine(start.device),
        "threads": torch.get_num_threads(),
        "precision": {"update_dtype": _dtype_name(update), "planner.build_dtype": _dtype_name(build)},
    }
    return record


def code_and_machine(device: str | torch.device) -> dict[str, Any]:
    """What a result was computed with, for a provenance record: ``code`` (the git commit of the checkout
    ``torchrl_dhrl`` is imported from and whether its tracked files were modified, ``None`` outside a git checkout,
    and the imported package's ``__version__``), ``versions`` (:data:`PROVENANCE_PACKAGES` and Python), ``machine``
    (architecture, CPU model, cores, whether ``device`` has native bfloat16) and ``device``.

    Examples:
        >>> record = code_and_machine("cpu")
        >>> sorted(record), record["device"], sorted(record["machine"])
        (['code', 'device', 'machine', 'versions'], 'cpu', ['architecture', 'cores', 'cpu', 'native_bfloat16'])
    """
    device = torch.device(device)
    return {
        "code": {**_git_commit(Path(__file__).resolve().parents[2]), "version": _package_version()},
        "versions": {"python": platform.python_version(), **{p: _version(p) for p in PROVENANCE_PACKAGES[1:]}},
        "machine": {
            "architecture": platform.machine(),
            "cpu": _cpu_model(),
            "cores": os.cpu_count(),
            "native_bfloat16": bool(native_bfloat16(device)),
        },
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else str(device),
    }


def read_provenance(run_dir: str | os.PathLike) -> list[dict[str, Any]]:
    """The starts recorded in ``run_dir``'s :data:`PROVENANCE_NAME` (oldest first); ``[]`` when it has none
    (a run older than the record, or none written yet).

    Examples:
        >>> import tempfile
        >>> read_provenance(tempfile.mkdtemp())  # nothing started there yet
        []
    """
    path = Path(run_dir) / PROVENANCE_NAME
    if not path.is_file():
        return []
    try:
        starts = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise ValueError(f"{path}: not readable as YAML; move it aside to start a new record.") from err
    return [s for s in starts if isinstance(s, dict)] if isinstance(starts, list) else []


def _version(distribution: str) -> str | None:
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        return None


def _package_version() -> str:
    """The version of the ``torchrl_dhrl`` package this code is (``torchrl_dhrl.__version__``), not the installed
    distribution's metadata, which an editable install leaves stale and a ``PYTHONPATH`` snapshot bypasses."""
    from torchrl_dhrl import __version__  # here: the package imports this module

    return __version__


def _cpu_model() -> str:
    """The CPU's model name (Linux: ``/proc/cpuinfo``), else what :func:`platform.processor` says."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def _git_commit(root: Path) -> dict[str, Any]:
    """``{"commit": sha, "modified": bool}`` of the git checkout at ``root``; ``None`` for both elsewhere."""
    if not (root / ".git").exists():
        return {"commit": None, "modified": None}

    def git(*args: str) -> str:
        command = ["git", "-C", str(root), *args]
        return subprocess.run(command, capture_output=True, text=True, timeout=10, check=True).stdout.strip()

    try:
        commit, status = git("rev-parse", "HEAD"), git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "modified": None}
    return {"commit": commit, "modified": bool(status)}


def _read_checkpoint(path: Path, what: str) -> dict:
    """The ``config`` and ``counters`` of the checkpoint at ``path``, checked complete, or a ConfigError."""
    try:
        state = load_checkpoint(path, required_keys=CHECKPOINT_COMPONENTS, components=("config", "counters"))
    except FileNotFoundError as err:
        raise ConfigError(
            f"{what}: no checkpoint at {str(path)!r} (a checkpoint or its run directory)."
        ) from err
    except CheckpointError as err:
        raise ConfigError(f"{what}: {err}") from err
    if not isinstance(state["config"], dict):
        raise ConfigError(f"{what}: {str(path)!r} holds no configuration under 'config'.")
    return state


def _write_config(cfg: Mapping[str, Any], path: Path) -> None:
    """The run's configuration as YAML (atomically), for tools that read run directories (``recipes/aggregate.py``)."""
    write_yaml(cfg, path)


def write_yaml(value: Any, path: str | os.PathLike) -> None:
    """Writes ``value`` (tuples and paths as plain YAML) to ``path`` atomically (a temporary file, then renamed).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> path = Path(tempfile.mkdtemp()) / "record.yaml"
        >>> write_yaml({"successes": 9, "sizes": (2, 3)}, path)
        >>> print(path.read_text(), end="")
        successes: 9
        sizes:
        - 2
        - 3
    """
    path = Path(path)
    tmp = path.with_suffix(".yaml.tmp")
    tmp.write_text(yaml.safe_dump(_plain(value), sort_keys=False))
    tmp.replace(path)


def write_csv(rows: Sequence[Mapping[str, Any]], columns: Sequence[str], path: str | os.PathLike) -> Path:
    """Writes ``rows`` under ``columns`` (a header line, then one line per row; a key a row lacks is left empty)
    to ``path`` atomically (a temporary file, then renamed): a crash leaves the previous file whole.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> path = write_csv([{"a": 1}, {"a": 2, "b": 3}], ["a", "b"], Path(tempfile.mkdtemp()) / "t.csv")
        >>> path.read_text().splitlines()
        ['a,b', '1,', '2,3']
    """
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with tmp.open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=list(columns))
        writer.writeheader()
        writer.writerows(rows)
    tmp.replace(path)
    return path


def _plain(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def _check_run_dir(run_dir: Path, resume: Path | None) -> None:
    """``run_dir`` must be (or become) a writable directory, and must not hold another run's checkpoint."""
    for path in (run_dir, *run_dir.parents):
        if path.exists():
            if not path.is_dir():
                raise ConfigError(f"`run_dir` {str(run_dir)!r}: {str(path)!r} is a file, not a directory.")
            if not os.access(path, os.W_OK | os.X_OK):
                raise ConfigError(f"`run_dir` {str(run_dir)!r}: {str(path)!r} is not writable.")
            break
    existing = checkpoint_file(run_dir)
    if existing.exists() and (resume is None or resume != existing.resolve()):
        raise ConfigError(
            f"`run_dir` {str(run_dir)!r} already holds a checkpoint, which this run would overwrite: "
            f"continue that run with resume={run_dir}, or choose another run_dir."
        )


def _check_offscreen_rendering() -> None:
    """``plots.video=true`` renders at the very end: fail now if MuJoCo cannot render offscreen."""
    import mujoco

    try:
        mujoco.Renderer(mujoco.MjModel.from_xml_string("<mujoco/>"), 16, 16).close()
    except Exception as err:  # mujoco.FatalError, EGL/OSMesa errors
        raise ConfigError(
            f"`plots.video=true` needs MuJoCo offscreen rendering, which fails here ({type(err).__name__}: "
            f"{' '.join(str(err).split())[:120]}); set MUJOCO_GL=egl or osmesa, or plots.video=false."
        ) from err


