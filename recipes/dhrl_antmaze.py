"""DHRL training on the paper's environments (Lee et al., NeurIPS 2022), TorchRL sota-recipe style.

Usage::

    python recipes/dhrl_antmaze.py env=PointMaze preset=quick       # ~20-30 min on a 2-core CPU
    python recipes/dhrl_antmaze.py env=AntMaze seed=3 total_steps=1000000
    python recipes/dhrl_antmaze.py env=AntMaze resume=outputs/<date>/<time>   # continue exactly
    python recipes/dhrl_antmaze.py env=AntMaze fork=<run dir> run_dir=<new dir> high.far_from_graph_factor=1.0
                                                  # branch a run from its checkpoint (an A/B from one state)
    python recipes/dhrl_antmaze.py env=AntMaze low.sqgc=false                 # ablations, see docs/faithfulness.md

The loop is Appendix A's Algorithm 6, "Overview of DHRL", with the collector yielding one whole episode per env
and the updates of its env steps run after it (as many as the paper's interleaved ones: one low-level update per
env step, one high-level update every 10; ``schedule.*``). Each line of the algorithm, and what carries it:

====== =================================== ===============================================================
Alg. 6 the paper                           here: the component (where)
====== =================================== ===============================================================
2      ``Dist(s, g)`` from ``Q_graph``      ``GoalDistance`` (planner/distances.py) on ``SQGCLoss``'s graph
                                           critics; ``planner.distance=oracle``: ``LineOfSightDistance``
3      for tau = 1 .. tau_total            ``for batch in run.collector`` in :func:`train` (whole episodes)
4-5    Env.reset when done                 the ``Collector``; truncation by the env (envs/torchrl_env.py)
6-7    g <- FGS(G, g, Q_graph)             ``GoalShiftOnReset`` + ``FrontierGoalShifting`` (planner/fgs.py)
                                           in the training env, with ``fgs.enabled``
10-11  random actions (warm-up)            ``GaussianUniformExplorationModule.uniform_prob = 1``
                                           (modules/exploration.py), set by :func:`set_phase`
12-13  vanilla HRL before the graph        ``GraphPlanner`` (planner/graph_planner.py) passes the subgoal
                                           through while its graph is empty
15-16  create the graph with FPS           ``rebuild_graph`` (recipe/epoch.py) -> ``LandmarkGraph.build``
                                           (planner/graph.py: ``farthest_point_sampling``, edges < cutoff)
18-19  sg <- pi_hi(s, g) every c_h steps   ``HighLevelPolicy`` + ``SubgoalScheduler`` (modules/); the cadence
                                           lives in the tensordict
20     waypoints <- Dijkstra(s, sg)        ``GraphPlanner`` -> ``LandmarkGraph.plan`` (all-pairs shortest
                                           paths once per rebuild, ``floyd_warshall``; secondary path)
23-24  next waypoint: reached or timed out ``GraphPlanner``'s waypoint tracking (``planner.reach_radius``)
26     a <- pi_lo(s, wp)                   ``LowLevelActor`` (modules/actors.py) + the exploration noise
28     Env.step(a)                         the ``Collector``; ``low_rb.extend`` / ``high_rb.extend``
29     train both levels                   ``LossUpdater.run`` (training/updates.py): ``SQGCLoss`` on a
                                           ``RelabelReplayBuffer`` with ``FutureGoalRelabel`` (low level);
                                           ``HighLevelLoss`` on ``HighLevelTransitionBuilder`` +
                                           ``HindsightSubgoalRelabel`` (subgoal testing, gradual penalty)
30-31  update the graph every N            :func:`end_epoch`: ``rebuild_graph`` every
                                           ``schedule.graph_rebuild_epochs`` epochs (15 episodes each)
====== =================================== ===============================================================

After every epoch the agent is evaluated on the test goals: 10 deterministic episodes, final-state success
(any-time success is logged too), logged against env steps counted from the start, warm-up included, as the
reference does. Everything is built by ``dhrl_utils.py`` from ``config/``; the run directory receives ``logs/``
(CSV by default), ``checkpoint/`` (a ``torchrl.checkpoint`` directory), ``agent/`` (the saved agent: the networks
and the graph without the buffers, written with each checkpoint; ``recipes/evaluate.py`` re-evaluates it),
``metrics.csv``, ``success_curve.png`` and ``episodes/epoch_*.png``.
"""

from __future__ import annotations

import math
import os
import sys
import time
import warnings
from pathlib import Path

import cloudpickle
import hydra
import torch
import tqdm
from omegaconf import DictConfig

from torchrl_dhrl.diagnostics import TrainingEpisodeLog
from torchrl_dhrl.factory import LOW_LEVEL_KEYS
from torchrl_dhrl.recipe import (
    AGENT_NAME,
    CHECKPOINT_NAME,
    CheckpointError,
    ConfigError,
    GracefulStop,
    LoopTimer,
    RunCounters,
    RunStart,
    epoch_of,
    evaluate_epoch,
    frozen_gc,
    graph_metrics,
    holds_state,
    log_metrics,
    make_checkpoint,
    plot_epoch,
    plot_success_curve,
    policy_captured,
    rebuild_graph,
    restore_checkpoint,
    save_agent,
    save_checkpoint,
    write_metrics_csv,
    write_run_dir,
)
from torchrl_dhrl.training import NonFiniteLossError, record_video

# The helpers beside the script, also when it is started from elsewhere (runpy.run_path, a user's launcher)
if str(Path(__file__).resolve().parent) not in sys.path:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
import dhrl_utils  # noqa: E402
from dhrl_utils import (  # noqa: E402
    PAPER_SUCCESS,
    RunParts,
    adopt_output_dir,
    build_episode_log,
    build_logger,
    build_run,
    evaluation_kwargs,
    remove_unused_output_dir,
    resumed_run_dir,
    run_maze,
    seed_everything,
    start_up,
    sweep_defaults,
)

# Launchers that pickle the task for another process (submitit's local and Slurm executors) import its
# modules there by name, and this folder is not on that process's path: ship the helpers by value.
cloudpickle.register_pickle_by_value(dhrl_utils)


def train(cfg: DictConfig | dict, run_dir: str | Path | None = None) -> dict:
    """Trains DHRL as configured; returns the last evaluation's metrics and the run directory.

    Before anything is built or written, :func:`~dhrl_utils.start_up` checks the configuration, the
    checkpoint to resume and the run directory, and raises :class:`~torchrl_dhrl.recipe.ConfigError` on any
    problem; the run directory is written once the run's objects are built (their own checks passed too).
    """
    start = start_up(cfg, run_dir, write=False)
    cfg, device, run_dir = start.config, start.device, start.run_dir
    seed_everything(cfg["seed"])
    schedule = cfg["schedule"]
    # ---- build: env specs -> agent -> envs with the agent's primers -> buffers, updaters, collector
    run = build_run(cfg, device)
    maze = run_maze(cfg, run.train_env)  # the maze's true geometry (diag/..., pictures), or None; checks oracle_margin
    write_run_dir(start)
    agent, low_rb, high_rb = run.agent, run.low_rb, run.high_rb
    low_updater, high_updater = run.low_updater, run.high_updater
    counters, history = RunCounters(), []
    # one registry of everything the run carries, for saving and restoring alike
    checkpoint = make_checkpoint(
        config=cfg,
        agent=agent,
        low_updater=low_updater,
        high_updater=high_updater,
        low_rb=low_rb,
        high_rb=high_rb,
        train_env=run.train_env.base_env,
        eval_env=run.eval_env.base_env,
        collector=run.collector,
        counters=counters,
        history=history,
    )
    checkpoint_path = run_dir / CHECKPOINT_NAME

    def write_checkpoint():
        """The checkpoint, then the saved agent from the same live objects (no buffer read again)."""
        path = save_checkpoint(checkpoint, checkpoint_path)
        save_agent(checkpoint, run_dir / AGENT_NAME)
        return path

    try:  # the collector's workers stop however the run ends
        if start.resume is not None:
            restore_or_fork(start, checkpoint, counters, run)
            if not start.forking and start.resume.parent == run_dir:  # a kill may have come between the two
                save_agent(checkpoint, run_dir / AGENT_NAME)  # the saved agent of the checkpoint resumed
            if counters.env_steps >= cfg["total_steps"]:  # e.g. a finished job of a re-run sweep
                print(
                    f"Already finished: {counters.env_steps} env steps (total_steps={cfg['total_steps']}); "
                    "nothing to do."
                )
                return {
                    "run_dir": str(run_dir),
                    "checkpoint": str(checkpoint_path),
                    **(history[-1] if history else {}),
                }
        logger = build_logger(cfg, run_dir)
        # the training episodes' success, FGS shifts and maze progress per epoch; its counts travel in the counters
        episode_log = build_episode_log(cfg, counters.train_episodes, maze)
        warmup_end = schedule["warmup_episodes"]
        set_phase(cfg, agent, counters.episodes)
        bar = tqdm.tqdm(
            total=cfg["total_steps"], initial=counters.env_steps, unit="step", disable=not cfg["progress"]
        )
        # timers cover this process only (a resumed run starts them again), hence the steps at the start (the
        # planner's share of acting is timed with forward hooks: not in a compiled policy, whose graph they would
        # break at the planner; time/planner_ms_per_call is then left out)
        timer = LoopTimer(None if policy_captured(cfg) else agent.planner, env_steps=counters.env_steps)
        wall_start, wall_before = time.perf_counter(), counters.wall_s
        capture_reported: set[str] = set()
        with GracefulStop() as stop, frozen_gc():
            try:
                for batch in run.collector:  # Alg. 6 l.3-28: one whole episode per env, acted by the policy
                    timer.lap("collect")
                    # an env that ended an episode itself (GymnasiumGoalEnv.refusal): stop at this batch boundary,
                    # the batch unused, with a checkpoint that resumes once the env is fixed
                    refusal = next(
                        (r for env in (run.train_env, run.eval_env) if (r := getattr(env.base_env, "refusal", None))),
                        None,
                    )
                    if refusal is not None:
                        bar.close()
                        write_checkpoint()
                        plot_curve(cfg, history, run_dir, counters)
                        raise SystemExit(
                            f"Stopping: {refusal} Checkpoint written to {checkpoint_path}: once the env is fixed, "
                            f"continue with resume={run_dir}"
                        )
                    # ---- store (l.28): low-level [num_envs, T] batches; the builder cuts high-level ones
                    low_rb.extend(batch.select(*LOW_LEVEL_KEYS))
                    high_rb.extend(batch)
                    episode_log.update(batch)
                    counters.train_episodes = episode_log.state_dict()
                    if counters.episodes < warmup_end and not schedule["train_during_warmup"]:
                        # the reference trains nothing on the random warm-up and does not catch up afterwards
                        counters.untrained_steps += batch.numel()
                    counters.env_steps += batch.numel()
                    counters.episodes += cfg["num_envs"]
                    timer.lap()
                    # ---- learn (l.29): low_updates_per_step SQGC updates per env step, a high-level one every 10
                    trained_steps = counters.env_steps - counters.untrained_steps
                    low_out = low_updater.run(
                        math.floor(trained_steps * schedule["low_updates_per_step"]) - low_updater.num_updates
                    )
                    n_high = trained_steps // schedule["high_update_interval"] - high_updater.num_updates
                    high_out = high_updater.run(n_high) if len(high_rb) else None
                    timer.lap("update")
                    if start.threads is not None:  # threads=null: as many as the other processes leave free
                        start.threads.poll()
                    report_capture(run, capture_reported)
                    bar.update(batch.numel())
                    # ---- phase (l.10-13): random warm-up, then the policies
                    set_phase(cfg, agent, counters.episodes)
                    counters.wall_s = wall_before + time.perf_counter() - wall_start
                    epoch = epoch_of(counters.episodes, warmup_end, schedule["epoch_episodes"])
                    # ---- epoch end (l.30-31): graph, evaluation, logs, checkpoint
                    if epoch > counters.epochs:
                        metrics = end_epoch(
                            cfg, run, run_dir, counters, epoch, episode_log, timer, low_out, high_out, maze
                        )
                        history.append(metrics)
                        log_metrics(logger, metrics, counters.env_steps)
                        write_metrics_csv(history, run_dir / "metrics.csv")
                        bar.set_postfix(
                            success=f"{metrics.get('eval/success', float('nan')):.2f}", epoch=epoch
                        )
                        if epoch % cfg["checkpoint"]["every_epochs"] == 0:
                            write_checkpoint()
                    if counters.env_steps >= cfg["total_steps"]:
                        break
                    # a signal during this batch: stop here, every update of the batch done
                    if stop.requested:
                        raise KeyboardInterrupt
                    timer.lap()
            except KeyboardInterrupt:
                bar.close()
                write_checkpoint()
                plot_curve(cfg, history, run_dir, counters)
                print(
                    f"\nInterrupted: checkpoint written to {checkpoint_path}; continue with resume={run_dir}"
                )
                raise
            except NonFiniteLossError as err:
                bar.close()
                raise SystemExit(
                    f"Stopping: {err}. The last good checkpoint is kept at {checkpoint_path}."
                ) from err
        bar.close()
        path = write_checkpoint()
    finally:
        run.collector.shutdown()
    plot_curve(cfg, history, run_dir, counters)
    episode_length = run.train_env.max_episode_steps
    if cfg["plots"]["video"]:
        video = record_video(run.eval_env, agent.policy, episode_length, run_dir / "test_episode.gif")
        print(f"Video of a test episode: {video}")
    summary = {"run_dir": str(run_dir), "checkpoint": str(path), **(history[-1] if history else {})}
    print(
        f"Done: {counters.env_steps} env steps, last success {summary.get('eval/success', float('nan')):.2f}. "
        + (
            f"Curve: {run_dir / 'success_curve.png'}, metrics: {run_dir / 'metrics.csv'}, "
            f"pictures: {run_dir / 'episodes'}, checkpoint: {path}, saved agent: {run_dir / AGENT_NAME}"
            if history
            else f"No epoch finished (no curve or metrics yet); checkpoint: {path}"
        )
    )
    return summary


def restore_or_fork(start: RunStart, checkpoint, counters: RunCounters, run: RunParts) -> None:
    """Restores the checkpoint ``start`` names into the run: ``resume`` continues it exactly, ``fork`` starts a new
    run from its state (re-seeding the training streams when the seed differs)."""
    cfg = start.config
    key = "fork" if start.forking else "resume"
    try:
        restore_checkpoint(checkpoint, start.resume, map_location=start.device)
    except CheckpointError as err:
        raise ConfigError(f"`{key}={cfg[key]}`: {err}") from err
    for name, env in (("training", run.train_env.base_env), ("test", run.eval_env.base_env)):
        if not holds_state(env.state_dict()):
            warnings.warn(
                f"The {name} env ({type(env).__name__}) keeps no state in its state_dict: it goes on from a fresh "
                "simulation, so this run does not continue exactly where it stopped (docs/goal_env.md).",
                stacklevel=2,
            )
    if not start.forking:
        print(f"Resumed from {start.resume} at {counters.env_steps} env steps.")
        return
    counters.forks.append(
        {"checkpoint": str(start.resume), "env_steps": counters.env_steps, "seed": cfg["seed"]}
    )
    reseeded = cfg["seed"] != start.state["config"]["seed"]
    if reseeded:  # the test episodes keep their stream: both arms of an A/B see the same ones
        seed_everything(cfg["seed"], run.train_env)
    print(
        f"Forked from {start.resume} at {counters.env_steps} env steps"
        + (f", re-seeded with seed {cfg['seed']}." if reseeded else ", its random streams continued.")
    )


def end_epoch(
    cfg: dict,
    run: RunParts,
    run_dir: Path,
    counters: RunCounters,
    epoch: int,
    episode_log: TrainingEpisodeLog,
    timer: LoopTimer,
    low_out,
    high_out,
    maze=None,
) -> dict:
    """The epoch end (Alg. 6 l.30-31, and the evaluation): rebuilds the graph when due, evaluates the agent on the
    test goals (the ``diag/...`` metrics against ``maze``, the run's :func:`run_maze`), draws the graph and a test
    episode; returns the epoch's metrics row."""
    schedule = cfg["schedule"]
    counters.epochs = epoch
    metrics = {"epoch": epoch, "env_steps": counters.env_steps, "episodes": counters.episodes}
    metrics["time/wall_s"] = counters.wall_s  # since the start of the run, resumes included
    metrics["time/threads"] = torch.get_num_threads()  # intra-op, at the epoch's end
    graph_start = schedule["warmup_episodes"] + schedule["graph_start_epoch"] * schedule["epoch_episodes"]
    graph_due = counters.episodes >= graph_start and (epoch - 1) % schedule["graph_rebuild_epochs"] == 0
    if cfg["planner"]["enabled"] and graph_due:
        metrics.update(rebuild_graph(run.agent.planner, run.low_rb, cfg["planner"]["candidates"]))
        counters.graph_builds += 1
    metrics.update(graph_metrics(run.agent.planner))
    metrics.update(episode_log.pop_metrics())
    counters.train_episodes = episode_log.state_dict()
    if epoch % schedule["eval_every_epochs"] == 0:
        episode_length = run.train_env.max_episode_steps
        evaluation, result = evaluate_epoch(
            run.agent, run.eval_env, episode_length, policy=run.eval_policy, maze=maze, **evaluation_kwargs(cfg)
        )
        metrics.update(evaluation)
        every = cfg["plots"]["every_epochs"]
        if every and (epoch // schedule["eval_every_epochs"]) % every == 0:
            plot_epoch(
                cfg["env_name"],
                run.agent.planner,
                result,
                run_dir / "episodes",
                epoch=epoch,
                env_steps=counters.env_steps,
                maze=maze,
            )
    metrics.update(timer.metrics(counters.env_steps))
    for prefix, out in (("low", low_out), ("high", high_out)):
        if out is not None:
            metrics.update({f"{prefix}/{k}": v.item() for k, v in out.items()})
    return metrics


def report_capture(run: RunParts, reported: set[str]) -> None:
    """Says once per level how its updates sample (``cudagraphs=true`` or ``capture_sampling=true``)."""
    for level, updater in (("low", run.low_updater), ("high", run.high_updater)):
        if updater.sampling_captured is not None and level not in reported:
            reported.add(level)
            print(f"Sampling, {level} level: {updater.sampling_note}.")


def set_phase(cfg: dict, agent, episodes: int) -> None:
    """Random warm-up (uniform actions; uniform subgoals unless ``high.warmup_subgoals=policy``), then the policies."""
    warmup = episodes < cfg["schedule"]["warmup_episodes"]
    agent.exploration.uniform_prob = 1.0 if warmup else cfg["low"]["uniform_prob"]
    uniform_subgoals = warmup and cfg["high"]["warmup_subgoals"] == "uniform"
    agent.high_policy.exploration.uniform_prob = 1.0 if uniform_subgoals else 0.0


def plot_curve(cfg: dict, history: list[dict], run_dir: Path, counters: RunCounters) -> None:
    """``success_curve.png`` with the paper's points and where the run was forked (at the end, and on Ctrl-C)."""
    if history:
        plot_success_curve(
            history,
            run_dir / "success_curve.png",
            title=f"DHRL {cfg['env_name']} (seed {cfg['seed']})",
            reference=PAPER_SUCCESS.get(cfg["env_name"]),
            forks=[fork["env_steps"] for fork in counters.forks],
        )


@hydra.main(config_path="config", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    """The command line: :func:`train` in Hydra's output directory, or in ``run_dir``, or (``resume=<run dir>``
    without ``run_dir``) in the resumed run's directory; Hydra's record of the job (``.hydra/``, its log) then
    moves there too, and its output directory is removed.

    A configuration error prints one line to stderr (``<script>: configuration error: <key, value, what is
    accepted>``) and exits with status 2, without a traceback (``HYDRA_FULL_ERROR=1`` shows it) and without
    leaving Hydra's new output directory behind. Ctrl-C (or SIGTERM) checkpoints and exits with 130. In a
    sweep (``-m``) :func:`~dhrl_utils.sweep_defaults` fills ``threads`` and ``logger.group`` when they are null.
    """
    from hydra.core.hydra_config import HydraConfig

    hydra_cfg = HydraConfig.get()
    output_dir = Path(hydra_cfg.runtime.output_dir)
    sweep_defaults(cfg, hydra_cfg)
    run_dir = Path(cfg.run_dir or resumed_run_dir(cfg) or output_dir)
    try:
        train(cfg, run_dir=run_dir)
        adopt_output_dir(output_dir, run_dir)
    except ConfigError as err:
        remove_unused_output_dir(output_dir)
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise
        print(f"{Path(sys.argv[0]).name}: configuration error: {' '.join(str(err).split())}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        adopt_output_dir(output_dir, run_dir)
        sys.exit(130)


if __name__ == "__main__":
    main()
