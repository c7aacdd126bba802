"""Where one env step's milliseconds go in the recipe: every phase of collection, updates and the epoch end.

Builds the recipe's agent, envs, buffers and updaters exactly as ``recipes/dhrl_antmaze.py`` does (same
configuration, same factories), fills the buffers with ``--episodes`` episodes (random warm-up, then the
policies), builds the graph, and then times each phase alone on that state, interleaved over
``--repeats`` rounds (the minimum of each is reported: the least-disturbed figure on a shared machine):

* collection, per env step: the env (``base_env`` step), the high level, the planner and the low level
  (forward hooks), and the rest (transforms, the collector's own work);
* one low-level update: sampling (storage gather), relabelling, loss forward, backward and Adam of the
  critics, then of the delayed actor (every ``actor_update_interval``-th update), the target update
  (every ``target_update_interval``-th), and the whole ``LossUpdater.step()`` (its own overhead is the
  difference);
* one high-level update: sampling, relabelling (HAC relabel, subgoal tests, the gradual penalty's
  distance-from-graph query), the rest of the step;
* per epoch: the graph rebuild and the evaluation.

The "per env step" column weighs each update by the schedule (``low_updates_per_step`` low-level updates
and ``1 / high_update_interval`` high-level ones per env step) and each epoch-end phase by the env steps of
an epoch. Run::

    python benchmarks/profile_train.py                                   # PointMaze, preset=quick, 1 thread
    python benchmarks/profile_train.py env=AntMaze preset=paper --episodes 6
    python benchmarks/profile_train.py env=AntMaze preset=paper update_dtype=bfloat16 --threads 2
    python benchmarks/profile_train.py compile=true             # the compiled updates

Arguments after the options are recipe overrides (``key=value``), as on the recipe's command line. On CUDA
every timed part ends with a device synchronisation, so a figure is the part's device time, not its launch time.

``--kernels`` also counts what one update runs, over ``--kernel-updates`` updates of each level under
:mod:`torch.profiler`: operator calls (``aten::`` ops, nested ones included; on a CPU the closest thing to a
kernel count) and, on CUDA, the kernels the device ran, the kernel launches the host issued and the CUDA-graph
replays. A captured update (``cudagraphs=true``) shows one graph replay and no kernel launch of its own::

    python benchmarks/profile_train.py --kernels env=AntMaze preset=paper device=cuda cudagraphs=true
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
import warnings
from pathlib import Path

import torch

RECIPES = Path(__file__).resolve().parents[1] / "recipes"
sys.path.insert(0, str(RECIPES))


def recipe_config(overrides: list[str]) -> dict:
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=str(RECIPES / "config"), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    return OmegaConf.to_container(cfg, resolve=True)


def _no_sync() -> None:
    pass


#: waits for the device's queued work before a clock is read (``torch.cuda.synchronize`` on CUDA, see main)
_sync = _no_sync


def _now() -> float:
    _sync()
    return time.perf_counter()


class _Clock:
    """Seconds accumulated per phase by forward hooks (pre/post) and by explicit wrappers."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._start: dict[str, float] = {}

    def hook(self, module: torch.nn.Module, name: str) -> None:
        def before(*_):
            self._start[name] = _now()

        def after(*_):
            self.add(name, _now() - self._start[name])

        module.register_forward_pre_hook(before)
        module.register_forward_hook(after)

    def wrap(self, owner, attr: str, name: str) -> None:
        fn = getattr(owner, attr)

        def timed(*args, **kwargs):
            start = _now()
            try:
                return fn(*args, **kwargs)
            finally:
                self.add(name, _now() - start)

        setattr(owner, attr, timed)

    def add(self, name: str, seconds: float) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds

    def pop(self) -> dict[str, float]:
        out, self.seconds = self.seconds, {}
        return out


@contextlib.contextmanager
def _no_relabel(rb):
    steps = rb._relabel
    rb._relabel = ()
    try:
        yield
    finally:
        rb._relabel = steps


def _timed(fn, repeats: int = 1) -> float:
    start = _now()
    for _ in range(repeats):
        fn()
    return (_now() - start) / repeats


def count_kernels(fn, calls: int, cuda: bool) -> dict[str, float]:
    """Per call of ``fn`` under :mod:`torch.profiler`: ``aten::`` operator calls (nested included) and, on CUDA,
    kernels run on the device, kernel launches from the host and CUDA-graph replays."""
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    _sync()
    with profile(activities=activities) as prof:
        for _ in range(calls):
            fn()
        _sync()
    events = prof.events()
    counts = {"aten ops": sum(event.name.startswith("aten::") for event in events)}
    if cuda:
        counts["device kernels"] = sum(event.device_type == DeviceType.CUDA for event in events)
        counts["kernel launches"] = sum(event.name in _LAUNCHES for event in events)
        counts["graph replays"] = sum(event.name == "cudaGraphLaunch" for event in events)
    return {name: count / calls for name, count in counts.items()}


#: the CUDA runtime and driver calls that launch one kernel
_LAUNCHES = frozenset({"cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx"})


def profile_low_update(updater) -> dict[str, float]:
    """Seconds of each part of one low-level update, each part run alone on a fresh sample."""
    rb, opt = updater.replay_buffer, updater.optimizers
    out = {}
    with _no_relabel(rb):
        out["low: sample (gather)"] = _timed(rb.sample)
    out["low: sample + relabel"] = _timed(rb.sample)
    sample = rb.sample()
    autocast = updater._autocast
    t0 = _now()
    with autocast():
        terms = updater._loss_terms(sample, False)  # compiled with compile=true
    total = torch.stack([v for k, v in terms.items() if k.startswith("loss_")]).sum()
    t1 = _now()
    for o in opt.values():
        o.zero_grad(set_to_none=True)
    total.backward()
    t2 = _now()
    opt["critic"].step()
    t3 = _now()
    with autocast():
        actor = updater._actor_fn(sample)[0]
    t4 = _now()
    opt["actor"].zero_grad(set_to_none=True)
    actor.backward()
    t5 = _now()
    opt["actor"].step()
    t6 = _now()
    updater.target_updater.step()
    t7 = _now()
    interval = updater.actor_update_interval
    out |= {
        "low: critic forward": t1 - t0,
        "low: critic backward": t2 - t1,
        "low: critic Adam": t3 - t2,
        "low: actor forward (per update)": (t4 - t3) / interval,
        "low: actor backward (per update)": (t5 - t4) / interval,
        "low: actor Adam (per update)": (t6 - t5) / interval,
        "low: target update (per update)": (t7 - t6) / updater.target_update_interval,
    }
    out["low: LossUpdater.step() (whole)"] = _timed(updater.step, 2 * interval) if interval else 0.0
    return out


def profile_high_update(updater) -> dict[str, float]:
    rb = updater.replay_buffer
    out = {}
    with _no_relabel(rb):
        out["high: sample (gather)"] = _timed(rb.sample)
    out["high: sample + relabel"] = _timed(rb.sample)
    out["high: LossUpdater.step() (whole)"] = _timed(updater.step, 2)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--episodes", type=int, default=40, help="episodes collected before timing")
    parser.add_argument("--repeats", type=int, default=5, help="interleaved timing rounds (minimum reported)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--kernels", action="store_true", help="also count operators and kernels per update")
    parser.add_argument(
        "--kernel-updates", type=int, default=20, help="updates of each level counted (--kernels)"
    )
    parser.add_argument("overrides", nargs="*", help="recipe overrides, e.g. env=AntMaze preset=paper")
    args = parser.parse_args()
    warnings.filterwarnings("ignore")
    torch.set_num_threads(args.threads)
    overrides = ["env=PointMaze", "preset=quick", *args.overrides, "logger.backend=none", "progress=false"]
    from dhrl_utils import build_run, evaluation_kwargs

    from torchrl_dhrl.factory import LOW_LEVEL_KEYS
    from torchrl_dhrl.recipe import evaluate_epoch, rebuild_graph, resolve_device

    cfg = recipe_config(overrides)
    device = resolve_device(cfg["device"])
    if device.type == "cuda":
        global _sync
        _sync = torch.cuda.synchronize
    torch.manual_seed(cfg["seed"])
    agent, train_env, eval_env, low_rb, high_rb, low_updater, high_updater, collector, eval_policy = build_run(
        cfg, device
    )
    episode_length = train_env.base_env.max_episode_steps
    schedule = cfg["schedule"]

    clock = _Clock()
    clock.hook(agent.high_policy, "collect: high level")
    clock.hook(agent.planner, "collect: planner")
    clock.hook(agent.policy[-1], "collect: low level")
    clock.wrap(train_env.base_env, "_step", "collect: env step")

    # fill the buffers: warm-up episodes (uniform actions), then the policies; no updates (timing only)
    warmup = min(schedule["warmup_episodes"], args.episodes // 2)
    agent.exploration.uniform_prob = 1.0
    episodes = 0
    iterator = iter(collector)
    while episodes < args.episodes:
        if episodes == warmup:
            agent.exploration.uniform_prob = cfg["low"]["uniform_prob"]
            agent.high_policy.exploration.uniform_prob = 0.0
        batch = next(iterator)
        low_rb.extend(batch.select(*LOW_LEVEL_KEYS))
        high_rb.extend(batch)
        episodes += cfg["num_envs"]
    for _ in range(4):  # Adam state, lazy initialisation and compilation (compile=true), as in a running loop
        low_updater.step()
        high_updater.step()
    profile_low_update(low_updater)  # the profiler's own calls compile too
    build_s = rebuild_graph(agent.planner, low_rb, cfg["planner"]["candidates"])["graph/build_s"]
    clock.pop()

    rounds: list[dict[str, float]] = []
    for _ in range(args.repeats):
        r: dict[str, float] = {}
        start = _now()
        batch = next(iterator)
        collect = _now() - start
        steps = batch.numel()
        parts = clock.pop()
        r["collect: whole (per env step)"] = collect / steps
        for name, seconds in parts.items():
            r[name] = seconds / steps
        r["collect: rest (per env step)"] = (collect - sum(parts.values())) / steps
        r |= profile_low_update(low_updater)
        r |= profile_high_update(high_updater)
        r["epoch: graph rebuild"] = rebuild_graph(agent.planner, low_rb, cfg["planner"]["candidates"])[
            "graph/build_s"
        ]
        start = _now()
        evaluate_epoch(agent, eval_env, episode_length, policy=eval_policy, **evaluation_kwargs(cfg))
        r["epoch: evaluation"] = _now() - start
        clock.pop()
        rounds.append(r)
    kernels = (
        {
            level: count_kernels(updater.step, args.kernel_updates, device.type == "cuda")
            for level, updater in (("low", low_updater), ("high", high_updater))
        }
        if args.kernels
        else {}
    )
    collector.shutdown()
    best = {k: min(r[k] for r in rounds) for k in rounds[0]}

    epoch_steps = schedule["epoch_episodes"] * episode_length
    per_step = {}
    for name, seconds in best.items():
        if name.startswith("collect"):
            per_step[name] = seconds
        elif name.startswith("low"):
            per_step[name] = seconds * schedule["low_updates_per_step"]
        elif name.startswith("high"):
            per_step[name] = seconds / schedule["high_update_interval"]
        else:
            per_step[name] = seconds / epoch_steps
    whole = [
        "collect: whole (per env step)",
        "low: LossUpdater.step() (whole)",
        "high: LossUpdater.step() (whole)",
        "epoch: graph rebuild",
        "epoch: evaluation",
    ]
    total = sum(per_step[k] for k in whole)
    label = " ".join([f"env={cfg['env_name']}", *(o for o in args.overrides if not o.startswith("env="))])
    print(
        f"profile of {label}: torch {torch.__version__}, {device}, {args.threads} thread(s), "
        f"low batch {cfg['low']['batch_size']} nets {cfg['low']['hidden']}, {agent.planner.num_landmarks} landmarks "
        f"(first build {build_s:.2f} s), minimum of {args.repeats} rounds"
    )
    print(f"{'phase':<36} {'ms per call':>12} {'ms per env step':>16} {'share':>7}")
    for name, seconds in best.items():
        share = per_step[name] / total if name in whole else float("nan")
        share_text = f"{100 * share:6.1f}%" if name in whole else ""
        print(f"{name:<36} {1e3 * seconds:>12.3f} {1e3 * per_step[name]:>16.3f} {share_text:>7}")
    print(
        f"{'total (whole phases)':<36} {'':>12} {1e3 * total:>16.3f} {'100.0%':>7}  -> {1 / total:.1f} env steps/s"
    )
    if kernels:
        names = list(kernels["low"])
        print(
            f"\nper LossUpdater.step() (mean of {args.kernel_updates} updates of each level, torch.profiler)"
        )
        print(f"{'level':<8}" + "".join(f"{name:>18}" for name in names))
        for level, counts in kernels.items():
            print(f"{level:<8}" + "".join(f"{counts[name]:>18.1f}" for name in names))


if __name__ == "__main__":
    main()
