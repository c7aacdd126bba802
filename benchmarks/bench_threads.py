"""Low-level (SQGC) update rate with 2 vs 1 torch threads, each alone and next to a CPU-bound competitor.

The quick preset slowed from about 60 to 6-9 env steps/s when another CPU-bound process shared the
2-core machine: PyTorch's OpenMP pool had as many threads as cores, and every parallel region of a
small update waited for a thread the competitor had descheduled. This script shows that effect in one
run, at the quick preset's low-level shape (PointMaze: obs 6, goal 2, action 2; 2 x 256 networks,
batch 256; one update = forward + backward + Adam steps of the four critics and, every second call,
the actor, as :class:`~torchrl_dhrl.training.LossUpdater` runs them).

Every cell runs in a fresh process with ``torch.set_num_threads(n)`` (and the inter-op count), or with
``default`` the recipe's default (``threads=null``: every core, then as many as other processes leave
free, :class:`~torchrl_dhrl.training.AdaptiveThreads` polled at every update and re-deciding every
second), for ``--seconds`` after a short warm-up; a competitor is a Python busy loop (one per ``--competitors``),
started before the cell and stopped after it. The table gives updates/s, how much the competitor
costs each thread count, and 2 threads vs 1 in each setting. Cores available to this process, the
thread counts and the load average before the run are printed too: figures from a machine that is
busy with other work besides the competitor (e.g. a training run) are noisier. Run::

    python benchmarks/bench_threads.py                 # about 1.5 minutes
    python benchmarks/bench_threads.py --threads default 4 2 1 --seconds 10 --competitors 2

The recipe sets the count from its ``threads`` key (default ``null``: adaptive, as the ``default`` row).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

OBS, GOAL, ACT, AMAX, GAMMA = 6, 2, 2, 1.0, 0.99
CELLS = (256, 256)
BATCH = 256
DEFAULT = "default"  # the recipe's threads=null: adaptive


def _update_fn(batch: int):
    """One SQGC update of the quick preset's low level (actor every second call), and its batch."""
    import torch
    from torchrl.objectives import SoftUpdate

    from torchrl_dhrl.objectives import SQGCLoss, make_optimizers

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from bench_losses import low_level_networks, sqgc_batch

    torch.manual_seed(0)
    actor, critic = low_level_networks(OBS, GOAL, ACT, AMAX, CELLS, GAMMA)
    loss = SQGCLoss(actor, critic(), critic())
    optims = make_optimizers(loss)
    target = SoftUpdate(loss, eps=0.995)
    data = sqgc_batch(batch, OBS, GOAL, ACT, AMAX)
    calls = [0]

    def update():
        calls[0] += 1
        value, _ = loss.value_loss(data)
        optims["critic"].zero_grad(set_to_none=True)
        value.backward()
        optims["critic"].step()
        if calls[0] % 2 == 0:  # the actor on the stepped critic, then the target networks
            actor_loss, _ = loss.actor_loss(data)
            optims["actor"].zero_grad(set_to_none=True)
            actor_loss.backward()
            optims["actor"].step()
            target.step()

    return update


def _worker(threads: str, seconds: float, batch: int) -> None:
    """Runs updates for ``seconds`` with ``threads`` threads (``default``: adaptive, polled at every update);
    prints ``{"rate": updates/s, ...}`` as JSON."""
    import torch

    from torchrl_dhrl.training import start_threads

    _, adaptive = start_threads(None if threads == DEFAULT else int(threads))
    if adaptive is not None:
        adaptive.interval_s = 1.0
    update = _update_fn(batch)
    for _ in range(10):  # warm-up: allocator, Adam state
        update()
    count, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        update()
        if adaptive is not None:
            adaptive.poll()
        count += 1
    elapsed = time.perf_counter() - start
    print(json.dumps({"rate": count / elapsed, "threads": torch.get_num_threads(), "updates": count}))


def _cell(threads: str, competitors: int, seconds: float, batch: int) -> tuple[float, int]:
    """Updates/s of a fresh worker process, with ``competitors`` busy loops running next to it, and its
    thread count at the end."""
    burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(competitors)]
    try:
        time.sleep(0.2 if competitors else 0.0)  # let them reach full speed
        env = {**os.environ, "OMP_NUM_THREADS": threads}
        if threads == DEFAULT:
            env.pop("OMP_NUM_THREADS")
        out = subprocess.run(
            [
                sys.executable,
                __file__,
                "--worker",
                threads,
                "--seconds",
                str(seconds),
                "--batch",
                str(batch),
            ],
            capture_output=True,
            text=True,
            env=env,
            check=True,
        ).stdout
    finally:
        for burner in burners:
            burner.terminate()
        for burner in burners:
            burner.wait()
    result = json.loads(out.strip().splitlines()[-1])
    return result["rate"], result["threads"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--threads",
        nargs="+",
        default=[DEFAULT, "2", "1"],
        help=f"thread counts, '{DEFAULT}' for the recipe's default (default: {DEFAULT} 2 1)",
    )
    parser.add_argument("--seconds", type=float, default=6.0, help="timed seconds per cell (default: 6)")
    parser.add_argument("--competitors", type=int, default=1, help="CPU-burning processes (default: 1)")
    parser.add_argument("--batch", type=int, default=BATCH, help=f"batch size (default: {BATCH})")
    parser.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker is not None:
        _worker(args.worker, args.seconds, args.batch)
        return
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = os.cpu_count()
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(
        f"SQGC low-level update, {len(CELLS)}x{CELLS[0]} networks, batch {args.batch}; {cores} cores available, "
        f"load average {load:.2f} before the run; competitor: {args.competitors} busy-loop process(es); "
        f"{args.seconds:g} s per cell."
    )
    for threads in args.threads:
        if threads != DEFAULT and not (threads.isdigit() and int(threads) >= 1):
            parser.error(f"--threads takes positive integers or {DEFAULT!r}, got {threads!r}")
    rates, counts = {}, {}
    for threads in args.threads:
        for competitors in (0, args.competitors):
            rates[threads, competitors], counts[threads, competitors] = _cell(
                threads, competitors, args.seconds, args.batch
            )
    base = args.threads[-1]
    print()
    print(
        "| threads | alone (updates/s) | with competitor (updates/s) | alone / with competitor "
        f"| vs {base} alone | vs {base} with competitor |"
    )
    print("|---|---:|---:|---:|---:|---:|")
    for threads in args.threads:
        alone, busy = rates[threads, 0], rates[threads, args.competitors]
        label = threads
        if threads == DEFAULT:  # the counts the adaptive default ended with
            label = (
                f"{DEFAULT} ({counts[threads, 0]} alone, {counts[threads, args.competitors]} with competitor)"
            )
        print(
            f"| {label} | {alone:.1f} | {busy:.1f} | {alone / busy:.2f}x "
            f"| {alone / rates[base, 0]:.2f}x | {busy / rates[base, args.competitors]:.2f}x |"
        )


if __name__ == "__main__":
    main()
