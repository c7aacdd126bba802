"""Cost of DHRL's replay relabelling: low-level sample + FutureGoalRelabel, high-level building and relabel.

The relabellers run inside ``RelabelReplayBuffer.sample()``; each is also timed alone, on a sample drawn once.
The capture-safe sampler (``rb.capturable_sampler()``: the same draw and relabelling with tensor operations only)
is timed eagerly, compiled whole (``torch.compile(fullgraph=True)``, ``--compile``) and, on CUDA, replayed as a
CUDA graph, with its ratio to ``rb.sample()`` in the same run.

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_relabel.py`` (add ``--device cuda`` on a GPU machine).
Figures are medians over repeats, in milliseconds per call.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage

from torchrl_dhrl.data import (
    FutureGoalRelabel,
    HighLevelTransitionBuilder,
    HindsightSubgoalRelabel,
    RelabelReplayBuffer,
)


def median_ms(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times)


def low_level_batch(
    num_envs: int, horizon: int, obs_dim: int, episode: int, start: int, device
) -> TensorDict:
    step = (torch.arange(start, start + horizon, device=device) % episode).expand(num_envs, horizon)
    position = torch.randn(num_envs, horizon, 2, device=device)
    return TensorDict(
        {
            "observation": torch.randn(num_envs, horizon, obs_dim, device=device),
            "achieved_goal": position,
            "desired_goal": torch.randn(num_envs, horizon, 2, device=device),
            "action": torch.randn(num_envs, horizon, 8, device=device),
            "step_count": step.unsqueeze(-1),
            "subgoal": torch.randn(num_envs, horizon, 2, device=device),
            "new_subgoal": (step % 40 == 0).unsqueeze(-1),
            ("collector", "traj_ids"): torch.arange(num_envs, device=device)[:, None]
            + num_envs * (torch.arange(start, start + horizon, device=device) // episode),
            ("next", "observation"): torch.randn(num_envs, horizon, obs_dim, device=device),
            ("next", "achieved_goal"): position,
            ("next", "done"): (step == episode - 1).unsqueeze(-1),
        },
        batch_size=[num_envs, horizon],
        device=device,
    )


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--capacity", type=int, default=200_000)
    parser.add_argument("--batch-size", type=int, default=1024)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--compile", action="store_true", help="also time the compiled capture-safe sampler")
    args = parser.parse_args()
    device = torch.device(args.device)
    num_envs, horizon, episode = 4, 600, 600

    relabel = FutureGoalRelabel(window=150)
    rb = RelabelReplayBuffer(
        storage=LazyTensorStorage(args.capacity, ndim=2, device=device),
        relabel=[relabel],
        batch_size=args.batch_size,
    )
    for i in range(args.capacity // (num_envs * horizon) + 2):  # full and wrapped
        rb.extend(low_level_batch(num_envs, horizon, 29, episode, i * horizon, device))
    sample, info = rb.sample(return_info=True)
    print(
        f"device={device}, low-level storage {tuple(rb.storage.shape)}, batch {args.batch_size}, window 150"
    )
    sample_ms = median_ms(rb.sample, args.repeats)
    print(f"  rb.sample() (relabelled):             {sample_ms:7.3f} ms")
    capturable = rb.capturable_sampler()
    variants = {"capture-safe sampler, eager": capturable}
    if args.compile:
        compiled = torch.compile(capturable, fullgraph=True, options={"fallback_random": True})
        start = time.perf_counter()
        compiled()
        print(f"  (compiling the capture-safe sampler: {time.perf_counter() - start:.1f} s)")
        variants["capture-safe sampler, compiled"] = compiled
    if device.type == "cuda":
        for _ in range(3):
            capturable()
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            capturable()
        variants["capture-safe sampler, CUDA graph"] = graph.replay
    for name, fn in variants.items():
        ms = median_ms(fn, args.repeats)
        print(f"  {name + ':':<37}{ms:7.3f} ms  ({sample_ms / ms:.2f}x rb.sample())")
    relabel_ms = median_ms(
        lambda: relabel.relabel_sample(
            sample.clone(), info["index"], rb.storage, newest_index=rb.newest_index
        ),
        args.repeats,
    )
    print(f"  FutureGoalRelabel (2 outputs):        {relabel_ms:7.3f} ms")

    builder = HighLevelTransitionBuilder()
    batches = [low_level_batch(num_envs, 40, 29, episode, i * 40, device) for i in range(15)]
    state = iter(range(10**9))

    def build():
        builder.build(batches[next(state) % len(batches)])

    print(f"  HighLevelTransitionBuilder [4, 40]:   {median_ms(build, args.repeats):7.3f} ms")

    high_relabel = [
        FutureGoalRelabel(
            her_ratio=1.0,
            window=15,
            out_keys=["desired_goal"],
            reward_keys=None,
            traj_key="episode_id",
            step_count_key="segment_index",
        ),
        HindsightSubgoalRelabel(lambda goals: goals.norm(dim=-1)),
    ]
    hi = RelabelReplayBuffer(
        storage=LazyTensorStorage(60_000, device=device), relabel=high_relabel, batch_size=args.batch_size
    )
    hi_builder = HighLevelTransitionBuilder()
    for i in range(300):
        records = hi_builder.build(low_level_batch(num_envs, 600, 29, episode, i * 600, device))
        if records.shape[0]:
            hi.extend(records)
    high_sample, high_info = hi.sample(return_info=True)

    def relabel_high():
        out = high_relabel[0].relabel_sample(
            high_sample.clone(), high_info["index"], hi.storage, newest_index=hi.newest_index
        )
        return high_relabel[1](out)

    print(f"  high-level relabel (HER + HAC + GP):  {median_ms(relabel_high, args.repeats):7.3f} ms")
    print(f"  high-level rb.sample() (relabelled):  {median_ms(hi.sample, args.repeats):7.3f} ms")


if __name__ == "__main__":
    main()
