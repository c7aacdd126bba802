"""How many CPU threads PyTorch uses in a training run: chosen by the run, not left to the default.

PyTorch sizes its OpenMP pool once, from the machine; when the process may use fewer cores, or shares
them with another CPU-bound process, every parallel region waits for threads that are not running and
small updates (the DHRL networks are a few 256-wide layers) slow down many times over (on 2 cores next
to one busy process, 2 threads ran 3-5x slower than alone, 1 thread about as fast as alone:
``benchmarks/bench_threads.py``). The recipe therefore sets the thread count itself from its ``threads``
key, and by default (:class:`AdaptiveThreads`) keeps it at the number of cores other processes leave free.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterable

import torch

__all__ = [
    "AdaptiveThreads",
    "available_cpus",
    "cpu_busy_seconds",
    "resolve_threads",
    "set_threads",
    "start_threads",
]


def available_cpus() -> int:
    """The number of CPU cores this process may run on (its affinity mask, not the machine's core count).

    Examples:
        >>> available_cpus() >= 1
        True
    """
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity masks (macOS, Windows)
        return os.cpu_count() or 1


def resolve_threads(threads: int | None) -> tuple[int, str]:
    """The intra-op thread count for a ``threads`` configuration value, and why.

    Args:
        threads (int or None): a positive count, or ``None`` for: ``OMP_NUM_THREADS`` when that
            environment variable holds a positive integer (an explicit request, e.g. from a job
            script), else :func:`available_cpus`.

    Returns:
        ``(count, reason)``, the reason as a short phrase for the start-up line.

    Examples:
        >>> resolve_threads(3)
        (3, 'threads=3 in the configuration')
    """
    if threads is not None:
        return int(threads), f"threads={threads} in the configuration"
    if (env := _omp_num_threads()) is not None:
        return env, f"threads=null and OMP_NUM_THREADS={env}"
    count = available_cpus()
    return count, f"threads=null: the {count} CPU core(s) this process may run on"


def _omp_num_threads() -> int | None:
    env = os.environ.get("OMP_NUM_THREADS", "").strip()
    return int(env) if env.isdigit() and int(env) >= 1 else None


def start_threads(threads: int | None) -> tuple[str, AdaptiveThreads | None]:
    """The recipe's thread policy: a fixed count (:func:`set_threads`), or by default one that follows the load.

    ``threads=None`` without ``OMP_NUM_THREADS`` starts an :class:`AdaptiveThreads` over the cores this
    process may use, which the training loop polls; any explicit count (the argument or the environment
    variable) is set once and kept.

    Returns:
        ``(line, adaptive)``: the start-up line and the :class:`AdaptiveThreads` to poll (``None`` when fixed).

    Examples:
        >>> import torch
        >>> before = torch.get_num_threads()
        >>> line, adaptive = start_threads(1)
        >>> adaptive is None, line.startswith("Threads: 1 intra-op")
        (True, True)
        >>> torch.set_num_threads(before)
    """
    line = set_threads(threads)
    if threads is not None or _omp_num_threads() is not None:
        return line, None
    adaptive = AdaptiveThreads()
    return f"{line[:-2]}, {adaptive.describe()}).", adaptive


def set_threads(threads: int | None) -> str:
    """Sets PyTorch's intra-op (and, where still allowed, inter-op) thread counts; returns a line saying so.

    :func:`torch.set_num_interop_threads` only works before the process has run any inter-op parallel
    work; later calls keep the current inter-op count (the line reports the counts in effect).

    Args:
        threads (int or None): see :func:`resolve_threads`.

    Returns:
        one line for the start-up output, e.g. ``"Threads: 2 intra-op, 2 inter-op (threads=null: the 2
        CPU core(s) this process may run on)."``

    Examples:
        >>> import torch
        >>> before = torch.get_num_threads()
        >>> set_threads(1).startswith("Threads: 1 intra-op")
        True
        >>> torch.get_num_threads()
        1
        >>> _ = set_threads(before)
    """
    count, reason = resolve_threads(threads)
    torch.set_num_threads(count)
    if torch.get_num_interop_threads() != count:
        try:
            torch.set_num_interop_threads(count)
        except RuntimeError:  # inter-op work already started in this process
            pass
    return (
        f"Threads: {torch.get_num_threads()} intra-op, {torch.get_num_interop_threads()} inter-op ({reason})."
    )


def _clock_ticks() -> int:
    try:
        return int(os.sysconf("SC_CLK_TCK"))
    except (AttributeError, ValueError, OSError):
        return 100


def cpu_busy_seconds(
    cpus: Iterable[int], *, count_niced: bool = True, path: str = "/proc/stat"
) -> float | None:
    """Seconds the given CPUs have spent running anything since boot (Linux ``/proc/stat``), or ``None``.

    Busy time is ``user + nice + system + irq + softirq + steal`` of each listed CPU (idle and iowait are
    not); a virtual machine's ``steal`` counts as busy (a hypervisor neighbour had the core). With
    ``count_niced=False`` the ``nice`` column (user time of processes with a positive nice value) is left
    out: such processes yield their core to a normal-priority one, so they do not compete with it.

    Args:
        cpus (iterable of int): CPU numbers (as in :func:`os.sched_getaffinity`).

    Keyword Args:
        count_niced (bool): count the time of niced processes. Defaults to ``True``.
        path (str): the file to read. Defaults to ``"/proc/stat"``.

    Returns:
        the summed busy seconds, or ``None`` where the file is missing or lists none of ``cpus``
        (not Linux): :class:`AdaptiveThreads` then keeps its count.

    Examples:
        >>> busy = cpu_busy_seconds([0])
        >>> busy is None or busy >= 0.0
        True
    """
    wanted = {f"cpu{cpu}" for cpu in cpus}
    try:
        with open(path) as stat:
            lines = stat.read().splitlines()
    except OSError:
        return None
    ticks, found = 0, False
    for line in lines:
        fields = line.split()
        if not fields or fields[0] not in wanted:
            continue
        found = True
        # user nice system idle iowait irq softirq steal [guest guest_nice: already inside user and nice]
        user, nice, system, _idle, _iowait, irq, softirq, steal = (
            int(v) for v in (fields[1:9] + ["0"] * 8)[:8]
        )
        ticks += user + (nice if count_niced else 0) + system + irq + softirq + steal
    return ticks / _clock_ticks() if found else None


class AdaptiveThreads:
    """Keeps PyTorch's intra-op thread count at the number of this process's cores that others leave free.

    Every :meth:`poll` after ``interval_s`` seconds since the last decision compares the busy time of the
    cores this process may run on (:func:`cpu_busy_seconds`) with this process's own CPU time
    (:func:`time.process_time`): the difference, divided by the wall-clock time, is how many cores other
    processes used. A core counts as taken once others used more than ``busy_threshold`` of it, and the
    thread count becomes ``max(1, cores - taken)`` (:func:`torch.set_num_threads`). Alone, a process keeps
    every core; next to one busy process on 2 cores it drops to 1 thread within one interval, and returns
    to 2 once the other process has stopped. Processes with a positive nice value are not counted when this
    one is not niced (they yield their core to it).

    Why: an OpenMP parallel region waits for its slowest thread, so with more threads than free cores every
    region of a small update waits for a descheduled thread (``benchmarks/bench_threads.py``: 2 threads
    next to a busy process ran 3.3x slower than alone, 1 thread as fast as alone). The thread count does
    not change an update's results on the CPUs measured (the same parameters after 30 SQGC updates with 1
    and 2 threads), but that is up to the BLAS library: fix ``threads`` for bit-level comparisons across
    machines.

    Where ``/proc/stat`` is missing (not Linux), :meth:`poll` keeps the count it started with
    (:attr:`adaptive` is ``False``).

    Args:
        cores (int, optional): the most threads to use. Defaults to :func:`available_cpus`.

    Keyword Args:
        interval_s (float): the shortest window a decision is measured over. Defaults to ``2.0``.
        busy_threshold (float): the fraction of a core others must use for it to count as taken.
            Defaults to ``0.25``.
        cpus (iterable of int, optional): the CPUs whose load is read. Defaults to this process's affinity.
        busy_seconds (callable, optional): returns the cumulative busy seconds of those CPUs (``None`` when
            unknown). Defaults to :func:`cpu_busy_seconds` (niced processes left out when this one is not
            niced).
        own_seconds (callable): this process's cumulative CPU seconds. Defaults to :func:`time.process_time`.
        clock (callable): wall-clock seconds. Defaults to :func:`time.monotonic`.
        set_num_threads (callable): applies a count. Defaults to :func:`torch.set_num_threads`.

    Examples:
        >>> import torch
        >>> before = torch.get_num_threads()
        >>> busy, own, now = [0.0], [0.0], [0.0]
        >>> threads = AdaptiveThreads(2, interval_s=1.0, busy_seconds=lambda: busy[0],
        ...     own_seconds=lambda: own[0], clock=lambda: now[0], set_num_threads=lambda n: None)
        >>> threads.threads
        2
        >>> now[0], own[0], busy[0] = 2.0, 2.0, 4.0  # 2 s: we used 2 core-seconds, another process 2
        >>> threads.poll()
        1
        >>> now[0], own[0], busy[0] = 4.0, 4.0, 6.0  # the other process has stopped
        >>> threads.poll(), threads.changes
        (2, 2)
    """

    def __init__(
        self,
        cores: int | None = None,
        *,
        interval_s: float = 2.0,
        busy_threshold: float = 0.25,
        cpus: Iterable[int] | None = None,
        busy_seconds: Callable[[], float | None] | None = None,
        own_seconds: Callable[[], float] = time.process_time,
        clock: Callable[[], float] = time.monotonic,
        set_num_threads: Callable[[int], None] = torch.set_num_threads,
    ) -> None:
        if cores is not None and (isinstance(cores, bool) or not isinstance(cores, int) or cores < 1):
            raise ValueError(f"`cores` must be None or an integer >= 1, got {cores!r}.")
        if not (isinstance(interval_s, (int, float)) and interval_s > 0):
            raise ValueError(f"`interval_s` must be a number > 0, got {interval_s!r}.")
        if not (isinstance(busy_threshold, (int, float)) and 0.0 <= busy_threshold < 1.0):
            raise ValueError(f"`busy_threshold` must be in [0, 1), got {busy_threshold!r}.")
        self.cores = available_cpus() if cores is None else int(cores)
        self.interval_s = float(interval_s)
        self.busy_threshold = float(busy_threshold)
        if busy_seconds is None:
            if cpus is None:
                cpus = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else range(self.cores)
            cpus = sorted(cpus)
            niced = _niceness() > 0

            def busy_seconds() -> float | None:
                return cpu_busy_seconds(cpus, count_niced=niced)

        self._busy, self._own, self._clock, self._set = busy_seconds, own_seconds, clock, set_num_threads
        #: the current thread count
        self.threads = self.cores
        #: how many times the count changed
        self.changes = 0
        #: cores other processes used over the last decision's window (``nan`` before the first)
        self.others = math.nan
        self._set(self.threads)
        self._mark = self._read()
        self.adaptive = self._mark[1] is not None

    def _read(self) -> tuple[float, float | None, float]:
        return self._clock(), self._busy(), self._own()

    def poll(self) -> int:
        """Re-decides the count when ``interval_s`` has passed since the last decision; returns the count.

        Cheap between decisions (one clock read), so a loop may call it as often as it likes."""
        if not self.adaptive or self._clock() - self._mark[0] < self.interval_s:
            return self.threads
        now, busy, own = self._read()
        if busy is None:
            return self.threads
        wall = now - self._mark[0]
        self.others = max(0.0, (busy - self._mark[1]) - (own - self._mark[2])) / wall
        self._mark = (now, busy, own)
        taken = max(0, math.ceil(self.others - self.busy_threshold - 1e-9))  # a tie is not taken
        threads = min(self.cores, max(1, self.cores - taken))
        if threads != self.threads:
            self._set(threads)
            self.threads = threads
            self.changes += 1
        return self.threads

    def describe(self) -> str:
        """A phrase for the start-up line."""
        if not self.adaptive:
            return "kept: the load of other processes cannot be read here"
        return f"fewer while other processes keep some of them busy, re-checked every {self.interval_s:g} s"


def _niceness() -> int:
    try:
        return os.nice(0)
    except (AttributeError, OSError):
        return 0
