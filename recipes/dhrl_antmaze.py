"""DHRL training on the paper's environments (Lee et al., NeurIPS 2022), TorchRL sota-recipe style.

Usage::

    python recipes/dhrl_antmaze.py env=PointMaze preset=quick       # ~20-30 min on a 2-core CPU
    python recipes/dhrl_antmaze.py env=AntMaze seed=3 total_steps=1000000
    python recipes/dhrl_antmaze.py env=AntMaze resume=outputs/<date>/<time>   # continue exactly
    python recipes/dhrl_antmaze.py env=AntMaze fork=<run dir> run_dir=<new dir> high.far_from_graph_factor=1.0
                                                  # branch a run from its checkpoint (an A/B from one state)
    python recipes/dhrl_antmaze.py env=AntMaze low.sqgc=false                 # ablations, see README

The loop follows Appendix A, "Overview of DHRL": random-walk warm-up episodes (uniform actions),
then hierarchical acting without a graph (the planner passes subgoals through), then graph planning
with a graph rebuilt from scratch every epoch (15 episodes). The collector yields one whole episode
per env; after each, one low-level (SQGC) update per env step and one high-level update every 10
env steps are run (both ratios configurable). After every epoch the agent is evaluated on the test
goals: 10 deterministic episodes, final-state success (any-time success is logged too), logged
against env steps counted from the start, warm-up included, as the reference does.

Everything is built by the factories of :mod:`torchrl_dhrl.training`, with the arguments
``dhrl_utils.py`` maps from ``config/``; the run directory receives ``logs/`` (CSV by default),
``checkpoint/`` (a ``torchrl.checkpoint`` directory), ``metrics.csv``, ``success_curve.png`` and
``episodes/epoch_*.png``.
"""

from __future__ import annotations

import gc
import math
import os
import sys
import time
from pathlib import Path

import cloudpickle
import dhrl_utils
import hydra
import tqdm
from dhrl_utils import (
    PAPER_SUCCESS,
    build_episode_log,
    build_logger,
    build_run,
    evaluation_kwargs,
    remove_unused_output_dir,
    seed_everything,
    start_up,
    sweep_defaults,
)
from omegaconf import DictConfig

from torchrl_dhrl.training import (
    CHECKPOINT_NAME,
    LOW_LEVEL_KEYS,
    CheckpointError,
    ConfigError,
    GracefulStop,
    LoopTimer,
    NonFiniteLossError,
    epoch_of,
    evaluate_epoch,
    graph_metrics,
    log_metrics,
    make_checkpoint,
    plot_epoch,
    plot_success_curve,
    rebuild_graph,
    record_video,
    restore_checkpoint,
    save_checkpoint,
    write_metrics_csv,
)

# Launchers that pickle the task for another process (submitit's local and Slurm executors) import its
# modules there by name, and this folder is not on that process's path: ship the helpers by value.
cloudpickle.register_pickle_by_value(dhrl_utils)


def train(cfg: DictConfig | dict, run_dir: str | Path | None = None) -> dict:
    """Trains DHRL as configured; returns the last evaluation's metrics and the run directory.

    Before anything is built or written, :func:`~dhrl_utils.start_up` checks the configuration, the
    checkpoint to resume and the run directory, and raises :class:`~torchrl_dhrl.training.ConfigError` on any
    problem.
    """
    start = start_up(cfg, run_dir)
    cfg, device, run_dir, resume, state = start
    seed_everything(cfg["seed"])
    schedule = cfg["schedule"]

    # ---- build: env specs -> agent -> envs with the agent's primers -> buffers, updaters, collector
    agent, train_env, eval_env, low_rb, high_rb, low_updater, high_updater, collector = build_run(cfg, device)
    episode_length = train_env.base_env.max_episode_steps
    counters = {"env_steps": 0, "episodes": 0, "epochs": 0, "graph_builds": 0, "wall_s": 0.0}
    history: list[dict] = []
    # one registry of everything the run carries, for saving and restoring alike
    checkpoint = make_checkpoint(
        config=cfg,
        agent=agent,
        low_updater=low_updater,
        high_updater=high_updater,
        low_rb=low_rb,
        high_rb=high_rb,
        train_env=train_env.base_env,
        eval_env=eval_env.base_env,
        collector=collector,
        counters=counters,
        history=history,
    )
    if resume is not None:  # checked by start_up; restored before anything is written
        try:
            restore_checkpoint(checkpoint, resume, map_location=device)
        except CheckpointError as err:
            key = "fork" if start.forking else "resume"
            raise ConfigError(f"`{key}={cfg[key]}`: {err}") from err
        if start.forking:  # a new run from another's state: its own seed's training streams
            counters.setdefault("forks", []).append(
                {"checkpoint": str(resume), "env_steps": counters["env_steps"], "seed": cfg["seed"]}
            )
            reseeded = cfg["seed"] != state["config"]["seed"]
            if reseeded:  # the test episodes keep their stream: both arms of an A/B see the same ones
                seed_everything(cfg["seed"], train_env)
            print(
                f"Forked from {resume} at {counters['env_steps']} env steps"
                + (f", re-seeded with seed {cfg['seed']}." if reseeded else ", its random streams continued.")
            )
        else:
            print(f"Resumed from {resume} at {counters['env_steps']} env steps.")
    checkpoint_path = run_dir / CHECKPOINT_NAME
    if (
        resume is not None and counters["env_steps"] >= cfg["total_steps"]
    ):  # e.g. a finished job of a re-run sweep
        collector.shutdown()
        print(
            f"Already finished: {counters['env_steps']} env steps (total_steps={cfg['total_steps']}); nothing to do."
        )
        return {
            "run_dir": str(run_dir),
            "checkpoint": str(checkpoint_path),
            **(history[-1] if history else {}),
        }

    logger = build_logger(cfg, run_dir)
    # the training episodes' success, FGS shifts and maze progress per epoch; its counts travel in the counters
    episode_log = build_episode_log(cfg, counters.get("train_episodes"))
    warmup_end = schedule["warmup_episodes"]
    graph_start = warmup_end + schedule["graph_start_epoch"] * schedule["epoch_episodes"]
    _set_phase(cfg, agent, counters["episodes"])
    bar = tqdm.tqdm(
        total=cfg["total_steps"], initial=counters["env_steps"], unit="step", disable=not cfg["progress"]
    )
    # timers cover this process only (a resumed run starts them again), hence the steps at the start
    # (the planner's share of acting is timed with forward hooks: not in a compiled policy, whose graph they would
    # break at the planner; time/planner_ms_per_call is then left out)
    timer = LoopTimer(
        None if cfg.get("compile_policy", False) else agent.planner, env_steps=counters["env_steps"]
    )
    wall_start, wall_before = time.perf_counter(), counters["wall_s"]
    stop = GracefulStop()
    capture_reported: set[str] = set()
    # What exists now (torch, Hydra, the agent, buffers, envs: about 0.5M objects) lives for the whole run: out of
    # the cyclic garbage collector's reach, its full collections stop walking it (they took 6% of a PointMaze quick
    # run's first 12k steps, 2.7% with the freeze). Reference counting still frees these objects; unfrozen at the end.
    gc.collect()
    gc.freeze()
    try:
        for batch in collector:
            timer.lap("collect")
            # ---- store: low-level [num_envs, T] batches (time-major storage); the builder cuts high-level ones
            low_rb.extend(batch.select(*LOW_LEVEL_KEYS))
            high_rb.extend(batch)
            episode_log.update(batch)
            counters["train_episodes"] = episode_log.state_dict()
            if counters["episodes"] < warmup_end and not schedule["train_during_warmup"]:
                # the reference trains nothing on the random warm-up and does not catch up afterwards
                counters["untrained_steps"] = counters.get("untrained_steps", 0) + batch.numel()
            counters["env_steps"] += batch.numel()
            counters["episodes"] += cfg["num_envs"]
            timer.lap()
            # ---- learn: low_updates_per_step SQGC updates per env step, a high-level one every 10
            trained_steps = counters["env_steps"] - counters.get("untrained_steps", 0)
            n_low = math.floor(trained_steps * schedule["low_updates_per_step"]) - low_updater.num_updates
            low_out = low_updater.run(n_low)
            n_high = trained_steps // schedule["high_update_interval"] - high_updater.num_updates
            high_out = high_updater.run(n_high) if len(high_rb) else None
            timer.lap("update")
            for level, updater in (("low", low_updater), ("high", high_updater)):
                if updater.sampling_captured is not None and level not in capture_reported:
                    capture_reported.add(level)  # cudagraphs=true or capture_sampling=true
                    print(f"Sampling, {level} level: {updater.sampling_note}.")
            bar.update(batch.numel())
            # ---- phase: random warm-up, then the policies
            _set_phase(cfg, agent, counters["episodes"])
            epoch = epoch_of(counters["episodes"], warmup_end, schedule["epoch_episodes"])
            counters["wall_s"] = wall_before + time.perf_counter() - wall_start
            if epoch > counters["epochs"]:
                # ---- epoch end: rebuild the graph (when due), evaluate on the test goals, draw
                counters["epochs"] = epoch
                metrics = {
                    "epoch": epoch,
                    "env_steps": counters["env_steps"],
                    "episodes": counters["episodes"],
                }
                metrics["time/wall_s"] = counters["wall_s"]  # since the start of the run, resumes included
                graph_due = (
                    counters["episodes"] >= graph_start
                    and (epoch - 1) % schedule["graph_rebuild_epochs"] == 0
                )
                if cfg["planner"]["enabled"] and graph_due:
                    metrics.update(rebuild_graph(agent.planner, low_rb, cfg["planner"]["candidates"]))
                    counters["graph_builds"] += 1
                metrics.update(graph_metrics(agent.planner))
                metrics.update(episode_log.pop_metrics())
                counters["train_episodes"] = episode_log.state_dict()
                if epoch % schedule["eval_every_epochs"] == 0:
                    evaluation, result = evaluate_epoch(
                        agent, eval_env, episode_length, **evaluation_kwargs(cfg)
                    )
                    metrics.update(evaluation)
                    every = cfg["plots"]["every_epochs"]
                    if every and (epoch // schedule["eval_every_epochs"]) % every == 0:
                        plot_epoch(
                            cfg["env_name"],
                            agent.planner,
                            result,
                            run_dir / "episodes",
                            epoch=epoch,
                            env_steps=counters["env_steps"],
                        )
                metrics.update(timer.metrics(counters["env_steps"]))
                for prefix, out in (("low", low_out), ("high", high_out)):
                    if out is not None:
                        metrics.update({f"{prefix}/{k}": v.item() for k, v in out.items()})
                history.append(metrics)
                log_metrics(logger, metrics, counters["env_steps"])
                write_metrics_csv(history, run_dir / "metrics.csv")
                bar.set_postfix(success=f"{metrics.get('eval/success', float('nan')):.2f}", epoch=epoch)
                if epoch % cfg["checkpoint"]["every_epochs"] == 0:
                    save_checkpoint(checkpoint, checkpoint_path)
            if counters["env_steps"] >= cfg["total_steps"]:
                break
            if stop.requested:  # a signal during this batch: stop here, every update of the batch done
                raise KeyboardInterrupt
            timer.lap()
    except KeyboardInterrupt:
        stop.restore()
        bar.close()
        save_checkpoint(checkpoint, checkpoint_path)
        _plot_curve(cfg, history, run_dir, counters)
        print(f"\nInterrupted: checkpoint written to {checkpoint_path}; continue with resume={run_dir}")
        collector.shutdown()
        raise
    except NonFiniteLossError as err:
        stop.restore()
        bar.close()
        collector.shutdown()
        raise SystemExit(f"Stopping: {err}. The last good checkpoint is kept at {checkpoint_path}.") from err
    finally:
        stop.restore()
        gc.unfreeze()
    bar.close()
    path = save_checkpoint(checkpoint, checkpoint_path)
    collector.shutdown()
    _plot_curve(cfg, history, run_dir, counters)
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


def _set_phase(cfg: dict, agent, episodes: int) -> None:
    """Random warm-up (uniform actions; uniform subgoals unless ``high.warmup_subgoals=policy``), then the policies."""
    warmup = episodes < cfg["schedule"]["warmup_episodes"]
    agent.exploration.uniform_prob = 1.0 if warmup else cfg["low"]["uniform_prob"]
    uniform_subgoals = warmup and cfg["high"]["warmup_subgoals"] == "uniform"
    agent.high_policy.exploration.uniform_prob = 1.0 if uniform_subgoals else 0.0


def _plot_curve(cfg: dict, history: list[dict], run_dir: Path, counters: dict) -> None:
    """``success_curve.png`` with the paper's points and where the run was forked (at the end, and on Ctrl-C)."""
    if history:
        plot_success_curve(
            history,
            run_dir / "success_curve.png",
            title=f"DHRL {cfg['env_name']} (seed {cfg['seed']})",
            reference=PAPER_SUCCESS.get(cfg["env_name"]),
            forks=[fork["env_steps"] for fork in counters.get("forks", ())],
        )


@hydra.main(config_path="config", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    """The command line: :func:`train` in Hydra's output directory (or ``run_dir``).

    A configuration error prints one line to stderr (``<script>: configuration error: <key, value, what is
    accepted>``) and exits with status 2, without a traceback (``HYDRA_FULL_ERROR=1`` shows it) and without
    leaving Hydra's new output directory behind. Ctrl-C (or SIGTERM) checkpoints and exits with 130. In a
    sweep (``-m``) :func:`~dhrl_utils.sweep_defaults` fills ``threads`` and ``logger.group`` when they are null.
    """
    from hydra.core.hydra_config import HydraConfig

    hydra_cfg = HydraConfig.get()
    output_dir = Path(hydra_cfg.runtime.output_dir)
    sweep_defaults(cfg, hydra_cfg)
    try:
        train(cfg, run_dir=cfg.run_dir or output_dir)
    except ConfigError as err:
        remove_unused_output_dir(output_dir)
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise
        print(f"{Path(sys.argv[0]).name}: configuration error: {' '.join(str(err).split())}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        sys.exit(130)


if __name__ == "__main__":
    main()
