"""How many CPU threads PyTorch uses in a training run: chosen at start-up, not left to the default.

PyTorch sizes its OpenMP pool once, from the machine; when the process may use fewer cores, or shares
them with another CPU-bound process, every parallel region waits for threads that are not running and
small updates (the DHRL networks are a few 256-wide layers) slow down many times over. The recipe
therefore sets the thread count itself from its ``threads`` key (see ``benchmarks/bench_threads.py``).
"""

from __future__ import annotations

import os

import torch

__all__ = ["available_cpus", "resolve_threads", "set_threads"]


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
    env = os.environ.get("OMP_NUM_THREADS", "").strip()
    if env.isdigit() and int(env) >= 1:
        return int(env), f"threads=null and OMP_NUM_THREADS={env}"
    count = available_cpus()
    return count, f"threads=null: the {count} CPU core(s) this process may run on"


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
