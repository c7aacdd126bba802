"""DHRL training on the paper's environments (Lee et al., NeurIPS 2022), TorchRL sota-recipe style.

Usage::

    python recipes/dhrl_antmaze.py env=PointMaze preset=quick       # ~20-30 min on a 2-core CPU
    python recipes/dhrl_antmaze.py env=AntMaze seed=3 total_steps=1000000
    python recipes/dhrl_antmaze.py env=AntMaze resume=outputs/<date>/<time>   # continue exactly
    python recipes/dhrl_antmaze.py env=AntMaze low.sqgc=false                 # ablations, see README

The loop follows Appendix A, "Overview of DHRL": random-walk warm-up episodes (uniform actions),
then hierarchical acting without a graph (the planner passes subgoals through), then graph planning
with a graph rebuilt from scratch every epoch (15 episodes). The collector yields one whole episode
per env; after each, one low-level (SQGC) update per env step and one high-level update every 10
env steps are run (both ratios configurable). After every epoch the agent is evaluated on the test
goals: 10 deterministic episodes, final-state success (any-time success is logged too), logged
against env steps counted from the start, warm-up included, as the reference does.

Everything is built by the factories of :mod:`torchrl_dhrl.training` from ``config/``; the run
directory receives ``logs/`` (CSV by default), ``checkpoint.pt``, ``metrics.csv``,
``success_curve.png`` and ``episodes/epoch_*.png``.
"""

from __future__ import annotations

import csv
import math
import random
import signal
import sys
import time
from pathlib import Path

import hydra
import numpy as np
import torch
import tqdm
from omegaconf import DictConfig, OmegaConf
from torchrl.data import RandomSampler

from torchrl_dhrl.training import (
    LOW_LEVEL_KEYS,
    ModuleTimer,
    NonFiniteLossError,
    checkpoint_file,
    evaluate,
    get_rng_state,
    load_checkpoint,
    make_agent,
    make_collector,
    make_environment,
    make_logger,
    make_replay_buffers,
    make_updaters,
    plot_episode,
    plot_success_curve,
    record_video,
    resolve_device,
    save_checkpoint,
    set_rng_state,
    validate_config,
)

#: The paper's DHRL success rates (Table 2): env -> {env steps: success}.
PAPER_SUCCESS = {
    "PointMaze": {250_000: 0.969, 500_000: 0.998},
    "AntMazeSmall": {500_000: 0.898, 1_000_000: 0.951},
    "AntMaze": {500_000: 0.715, 1_000_000: 0.911},
    "AntMazeBottleneck": {500_000: 0.165, 1_000_000: 0.387},
    "AntMazeComplex": {2_500_000: 0.204, 4_000_000: 0.401},
    "Reacher3D": {250_000: 0.951, 500_000: 0.906},
}


def train(cfg: DictConfig | dict, run_dir: str | Path | None = None) -> dict:
    """Trains DHRL as configured; returns the last evaluation's metrics and the run directory."""
    cfg = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)
    validate_config(cfg)
    device = resolve_device(cfg["device"])
    run_dir = Path(run_dir or cfg["run_dir"] or ".").resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    resume = checkpoint_file(cfg["resume"]) if cfg["resume"] else None
    torch.manual_seed(cfg["seed"])
    np.random.seed(cfg["seed"])
    random.seed(cfg["seed"])
    schedule = cfg["schedule"]

    # ---- build: env specs -> agent -> envs with the agent's primers -> buffers, updaters, collector
    agent = make_agent(cfg, make_environment(cfg, device), device)
    train_env = make_environment(cfg, device, agent=agent)
    eval_env = make_environment(cfg, device, eval=True, agent=agent)
    episode_length = train_env.base_env.max_episode_steps
    num_envs = cfg["num_envs"]
    buffers = make_replay_buffers(cfg, agent, device)
    low_rb, _, high_rb, _ = buffers
    low_updater, high_updater = make_updaters(cfg, agent, buffers)
    collector = make_collector(train_env, agent, episode_length)
    counters = {"env_steps": 0, "episodes": 0, "epochs": 0, "graph_builds": 0, "wall_s": 0.0}
    history: list[dict] = []
    if resume is not None:
        state = load_checkpoint(resume, map_location=device)
        agent.load_state_dict(state["agent"])
        low_updater.load_state_dict(state["low_updater"])
        high_updater.load_state_dict(state["high_updater"])
        low_rb.load_state_dict(state["low_rb"])
        high_rb.load_state_dict(state["high_rb"])
        train_env.base_env.load_state_dict(state["train_env"])
        eval_env.base_env.load_state_dict(state["eval_env"])
        collector.load_state_dict(state["collector"])
        # the post-reset state of the live episodes, copied into the carrier's own tensors: the collector keeps
        # some of them (trajectory ids) on its storing device, not on the training device
        collector._carrier.update_(state["carrier"])
        counters, history = state["counters"], state["history"]
        set_rng_state(state["rng"])
        print(f"Resumed from {resume} at {counters['env_steps']} env steps.")

    def checkpoint() -> Path:
        return save_checkpoint(
            {
                "config": cfg,
                "agent": agent.state_dict(),
                "low_updater": low_updater.state_dict(),
                "high_updater": high_updater.state_dict(),
                "low_rb": low_rb.state_dict(),
                "high_rb": high_rb.state_dict(),
                "train_env": train_env.base_env.state_dict(),
                "eval_env": eval_env.base_env.state_dict(),
                "collector": collector.state_dict(),
                "carrier": collector._carrier.clone(),
                "counters": counters,
                "history": history,
                "rng": get_rng_state(),
            },
            run_dir / "checkpoint.pt",
        )

    logger = make_logger(cfg, run_dir)
    warmup_end = schedule["warmup_episodes"]
    graph_start = warmup_end + schedule["graph_start_epoch"] * schedule["epoch_episodes"]
    uniform_prob = cfg["low"]["uniform_prob"]
    agent.exploration.uniform_prob = 1.0 if counters["episodes"] < warmup_end else uniform_prob
    bar = tqdm.tqdm(
        total=cfg["total_steps"], initial=counters["env_steps"], unit="step", disable=not cfg["progress"]
    )
    # timers cover this process only (a resumed run starts them again), hence the steps at the start
    timer = {
        "collect": 0.0,
        "update": 0.0,
        "planner": ModuleTimer(agent.planner),
        "steps": counters["env_steps"],
    }
    wall_start, wall_before = time.perf_counter(), counters["wall_s"]
    last_time = time.perf_counter()
    metrics: dict = {}
    _raise_keyboard_interrupt_on_sigterm()
    try:
        for batch in collector:
            timer["collect"] += time.perf_counter() - last_time
            # ---- store: low-level [num_envs, T] batches (time-major storage); the builder cuts high-level ones
            low_rb.extend(batch.select(*LOW_LEVEL_KEYS))
            high_rb.extend(batch)
            counters["env_steps"] += batch.numel()
            counters["episodes"] += num_envs
            # ---- learn: low_updates_per_step SQGC updates per env step, a high-level one every 10
            start = time.perf_counter()
            n_low = (
                math.floor(counters["env_steps"] * schedule["low_updates_per_step"]) - low_updater.num_updates
            )
            low_out = low_updater.run(n_low)
            n_high = counters["env_steps"] // schedule["high_update_interval"] - high_updater.num_updates
            high_out = high_updater.run(n_high) if len(high_rb) else None
            timer["update"] += time.perf_counter() - start
            bar.update(batch.numel())
            # ---- phase: random warm-up, then the policies
            agent.exploration.uniform_prob = 1.0 if counters["episodes"] < warmup_end else uniform_prob
            epoch = counters["episodes"] // schedule["epoch_episodes"]
            counters["wall_s"] = wall_before + time.perf_counter() - wall_start
            if epoch > counters["epochs"]:
                counters["epochs"] = epoch
                metrics = _end_of_epoch(
                    cfg, agent, low_rb, eval_env, episode_length, counters, graph_start, timer, run_dir
                )
                for prefix, out in (("low", low_out), ("high", high_out)):
                    if out is not None:
                        metrics.update({f"{prefix}/{k}": v.item() for k, v in out.items()})
                history.append(metrics)
                _log(logger, metrics, counters["env_steps"])
                _write_metrics_csv(history, run_dir / "metrics.csv")
                bar.set_postfix(success=f"{metrics.get('eval/success', float('nan')):.2f}", epoch=epoch)
                if epoch % cfg["checkpoint"]["every_epochs"] == 0:
                    checkpoint()
            if counters["env_steps"] >= cfg["total_steps"]:
                break
            last_time = time.perf_counter()
    except KeyboardInterrupt:
        bar.close()
        path = checkpoint()
        _plot_curve(cfg, history, run_dir)
        print(f"\nInterrupted: checkpoint written to {path}; continue with resume={run_dir}")
        collector.shutdown()
        raise
    except NonFiniteLossError as err:
        bar.close()
        collector.shutdown()
        raise SystemExit(
            f"Stopping: {err}. The last good checkpoint is kept at {run_dir / 'checkpoint.pt'}."
        ) from err
    bar.close()
    path = checkpoint()
    collector.shutdown()
    _plot_curve(cfg, history, run_dir)
    if cfg["plots"]["video"]:
        video = record_video(eval_env, agent.policy, episode_length, run_dir / "test_episode.gif")
        print(f"Video of a test episode: {video}")
    summary = {"run_dir": str(run_dir), "checkpoint": str(path), **(history[-1] if history else {})}
    print(
        f"Done: {counters['env_steps']} env steps, last success {summary.get('eval/success', float('nan')):.2f}. "
        + (
            f"Curve: {run_dir / 'success_curve.png'}, metrics: {run_dir / 'metrics.csv'}, "
            f"pictures: {run_dir / 'episodes'}, checkpoint: {path}"
            if history
            else f"No epoch finished (no curve or metrics yet); checkpoint: {path}"
        )
    )
    return summary


def _end_of_epoch(
    cfg, agent, low_rb, eval_env, episode_length, counters, graph_start, timer, run_dir
) -> dict:
    """Graph rebuild (when due), evaluation on the test goals, pictures; returns the epoch's metrics."""
    schedule, planner = cfg["schedule"], agent.planner
    epoch = counters["epochs"]
    metrics = {"epoch": epoch, "env_steps": counters["env_steps"], "episodes": counters["episodes"]}
    metrics["time/wall_s"] = counters["wall_s"]  # since the start of the run, resumes included
    graph_due = (
        cfg["planner"]["enabled"]
        and counters["episodes"] >= graph_start
        and (epoch - 1) % schedule["graph_rebuild_epochs"] == 0
    )
    if graph_due:
        start = time.perf_counter()
        index, _ = RandomSampler().sample(low_rb.storage, cfg["planner"]["candidates"])
        candidates = low_rb.storage[index]
        planner.build(candidates["observation"], candidates["achieved_goal"])
        counters["graph_builds"] += 1
        metrics["graph/build_s"] = time.perf_counter() - start
    metrics["graph/landmarks"] = planner.num_landmarks
    metrics["graph/edges"] = int(planner.edges.shape[0]) if planner.has_graph else 0
    if epoch % schedule["eval_every_epochs"] == 0:
        start = time.perf_counter()
        result = evaluate(eval_env, agent.policy, episode_length)
        metrics["time/eval_s"] = time.perf_counter() - start
        metrics["eval/success"] = result.success
        metrics["eval/any_success"] = result.any_success
        metrics["eval/final_distance"] = result.final_distance
        rollout = result.rollout
        metrics["graph/mean_path_landmarks"] = rollout["planner", "path_length"].float().mean().item()
        start_state, goal = rollout[0, 0]["observation"], rollout[0, 0]["desired_goal"]
        metrics["graph/learned_distance_start_goal"] = agent.planner.distance(start_state, goal).item()
        every = cfg["plots"]["every_epochs"]
        if every and (epoch // schedule["eval_every_epochs"]) % every == 0:
            plot_episode(
                cfg["env_name"],
                planner,
                rollout,
                run_dir / "episodes" / f"epoch_{epoch:04d}.png",
                title=f"{cfg['env_name']} epoch {epoch}, {counters['env_steps']} steps: success {result.success:.0%}",
            )
    planner_s, planner_calls = timer["planner"].pop()
    metrics["time/planner_ms_per_call"] = 1e3 * planner_s / max(planner_calls, 1)
    metrics["time/collect_s"] = timer["collect"]
    metrics["time/update_s"] = timer["update"]
    steps = counters["env_steps"] - timer["steps"]
    metrics["env_steps_per_s"] = steps / max(timer["collect"] + timer["update"], 1e-9)
    return metrics


def _plot_curve(cfg: dict, history: list[dict], run_dir: Path) -> None:
    """``success_curve.png`` with the paper's points (at the end, and on Ctrl-C)."""
    if history:
        plot_success_curve(
            history,
            run_dir / "success_curve.png",
            title=f"DHRL {cfg['env_name']} (seed {cfg['seed']})",
            reference=PAPER_SUCCESS.get(cfg["env_name"]),
        )


def _log(logger, metrics: dict, step: int) -> None:
    if logger is None:
        return
    for key, value in metrics.items():
        logger.log_scalar(key, float(value), step=step)


def _write_metrics_csv(history: list[dict], path: Path) -> None:
    keys = sorted({k for h in history for k in h}, key=lambda k: (k not in ("epoch", "env_steps"), k))
    tmp = path.with_suffix(".tmp")
    with tmp.open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=keys)
        writer.writeheader()
        writer.writerows(history)
    tmp.replace(path)


def _raise_keyboard_interrupt_on_sigterm() -> None:
    """Treat SIGTERM (e.g. a job scheduler's stop) like Ctrl-C: checkpoint, then exit."""

    def handler(signum, frame):
        raise KeyboardInterrupt

    try:
        signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not in the main thread
        pass


@hydra.main(config_path="config", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    try:
        train(cfg, run_dir=cfg.run_dir or HydraConfig.get().runtime.output_dir)
    except KeyboardInterrupt:
        sys.exit(130)


if __name__ == "__main__":
    main()
