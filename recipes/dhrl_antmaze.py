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
import os
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
from omegaconf.errors import OmegaConfBaseException
from torchrl.data import RandomSampler

from torchrl_dhrl.training import (
    LOW_LEVEL_KEYS,
    CheckpointError,
    ConfigError,
    ModuleTimer,
    NonFiniteLossError,
    check_known_keys,
    check_resume_config,
    checkpoint_file,
    evaluate,
    get_rng_state,
    goal_as_waypoint,
    hierarchy_diagnostics,
    load_checkpoint,
    make_agent,
    make_collector,
    make_environment,
    make_logger,
    make_replay_buffers,
    make_updaters,
    maze_epoch_diagnostics,
    plot_episode,
    plot_success_curve,
    record_video,
    resolve_device,
    save_checkpoint,
    set_rng_state,
    set_threads,
    validate_config,
)

#: The configuration directory; ``config.yaml`` there is the schema of every configuration key.
CONFIG_DIR = Path(__file__).resolve().parent / "config"
#: The entries of a checkpoint written by :func:`train`, checked before resuming from one.
CHECKPOINT_KEYS = (
    "config",
    "agent",
    "low_updater",
    "high_updater",
    "low_rb",
    "high_rb",
    "train_env",
    "eval_env",
    "collector",
    "carrier",
    "counters",
    "history",
    "rng",
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


def config_schema() -> dict:
    """The keys a configuration may hold: ``config/config.yaml`` as written (its defaults list aside).

    Read from the file on every call, so keys added there are known at once; env and preset files may
    only set keys that it defines.
    """
    schema = OmegaConf.to_container(OmegaConf.load(CONFIG_DIR / "config.yaml"), resolve=False)
    schema.pop("defaults", None)
    schema.pop("hydra", None)
    return schema


def start_up(cfg: DictConfig | dict, run_dir: str | Path | None = None):
    """Checks everything that can be checked before a run builds or writes anything, then prepares it.

    In order: the keys (only those of ``config/config.yaml``, see :func:`config_schema`), their values
    (:func:`~torchrl_dhrl.training.validate_config`), the device, the checkpoint to ``resume`` (readable,
    with every entry of :data:`CHECKPOINT_KEYS`, and trained with the same configuration up to
    :data:`~torchrl_dhrl.training.RESUME_MUTABLE_KEYS`), the run directory (not a file; no checkpoint of
    another run in it, which the run would overwrite) and, with ``plots.video=true``, MuJoCo's offscreen
    rendering. Only then it sets the thread count (``threads``, printed as one line) and creates the run
    directory.

    Args:
        cfg (DictConfig or dict): the composed configuration.
        run_dir (str or Path, optional): where the run writes; defaults to ``cfg["run_dir"]``, else the
            current directory.

    Returns:
        ``(cfg, device, run_dir, resume, state)``: the configuration as a plain dict, the
        :class:`torch.device`, the run directory, the checkpoint file to resume (or ``None``) and its
        loaded state (or ``None``).

    Raises:
        ConfigError: naming the key, the value and what is accepted; nothing has been built or written.
    """
    if isinstance(cfg, DictConfig):
        try:
            cfg = OmegaConf.to_container(cfg, resolve=True)
        except OmegaConfBaseException as err:
            raise ConfigError(f"The configuration does not resolve: {' '.join(str(err).split())}") from err
    else:
        cfg = dict(cfg)
    check_known_keys(cfg, config_schema(), source="recipes/config/config.yaml")
    validate_config(cfg)
    device = resolve_device(cfg["device"])
    run_dir = Path(run_dir or cfg["run_dir"] or ".").expanduser().resolve()
    resume = state = None
    notes: list[str] = []
    if cfg["resume"]:
        resume = checkpoint_file(Path(cfg["resume"]).expanduser()).resolve()
        what = f"`resume={cfg['resume']}`"
        try:
            state = load_checkpoint(resume, map_location=device, required_keys=CHECKPOINT_KEYS)
        except FileNotFoundError as err:
            raise ConfigError(
                f"{what}: no checkpoint at {str(resume)!r} (a checkpoint.pt or its run directory)."
            ) from err
        except CheckpointError as err:
            raise ConfigError(f"{what}: {err}") from err
        if not isinstance(state["config"], dict):
            raise ConfigError(f"{what}: {str(resume)!r} holds no configuration under 'config'.")
        notes = check_resume_config(state["config"], cfg, what=f"{what} ({resume})")
        notes = [note for note in notes if not note.startswith("resume:")]  # resume itself always changes
    _check_run_dir(run_dir, resume)
    if cfg["plots"]["video"]:
        _check_offscreen_rendering()
    print(set_threads(cfg["threads"]))
    if notes:
        print(f"Resuming {resume} with: {'; '.join(notes)}.")
    run_dir.mkdir(parents=True, exist_ok=True)
    return cfg, device, run_dir, resume, state


def _check_run_dir(run_dir: Path, resume: Path | None) -> None:
    """``run_dir`` must be (or become) a directory, and must not hold another run's checkpoint."""
    for path in (run_dir, *run_dir.parents):
        if path.exists():
            if not path.is_dir():
                raise ConfigError(f"`run_dir` {str(run_dir)!r}: {str(path)!r} is a file, not a directory.")
            if not os.access(path, os.W_OK | os.X_OK):
                raise ConfigError(f"`run_dir` {str(run_dir)!r}: {str(path)!r} is not writable.")
            break
    existing = run_dir / "checkpoint.pt"
    if existing.exists() and (resume is None or resume != existing.resolve()):
        raise ConfigError(
            f"`run_dir` {str(run_dir)!r} already holds a checkpoint.pt, which this run would overwrite: "
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


def _remove_unused_output_dir(output_dir: Path) -> None:
    """Removes Hydra's output directory of a run stopped at start-up, when it holds only what Hydra wrote
    there (``.hydra/*.yaml`` and an empty job log), and its parents that this leaves empty (within the
    current directory). A directory holding anything else is left as it is."""
    from hydra.core.hydra_config import HydraConfig

    hydra_cfg = HydraConfig.get()
    if not output_dir.is_dir():
        return
    expected = {output_dir / f"{hydra_cfg.job.name}.log"}
    if hydra_cfg.output_subdir is not None:
        expected |= {
            output_dir / hydra_cfg.output_subdir / f for f in ("config.yaml", "hydra.yaml", "overrides.yaml")
        }
    files = [p for p in output_dir.rglob("*") if not p.is_dir()]
    if any(p not in expected for p in files) or any(p.suffix == ".log" and p.stat().st_size for p in files):
        return
    for path in files:
        path.unlink()
    dirs = sorted((p for p in output_dir.rglob("*") if p.is_dir()), key=lambda p: len(p.parts), reverse=True)
    cwd = Path.cwd().resolve()
    try:
        for path in dirs:
            path.rmdir()
        output_dir.rmdir()
        parent = output_dir.resolve().parent
        while parent != cwd and cwd in parent.parents and not any(parent.iterdir()):
            parent.rmdir()
            parent = parent.parent
    except OSError:  # not empty after all (another process writing): keep the rest
        pass


def train(cfg: DictConfig | dict, run_dir: str | Path | None = None) -> dict:
    """Trains DHRL as configured; returns the last evaluation's metrics and the run directory.

    Before anything is built or written, :func:`start_up` checks the configuration, the checkpoint to
    resume and the run directory, and raises :class:`~torchrl_dhrl.training.ConfigError` on any problem.
    """
    cfg, device, run_dir, resume, state = start_up(cfg, run_dir)
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
    low_rb, high_rb = buffers
    low_updater, high_updater = make_updaters(cfg, agent, buffers)
    collector = make_collector(train_env, agent, episode_length)
    counters = {"env_steps": 0, "episodes": 0, "epochs": 0, "graph_builds": 0, "wall_s": 0.0}
    history: list[dict] = []
    if state is not None:  # loaded and checked by start_up
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
    _set_phase(cfg, agent, counters["episodes"])
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
    stop = _GracefulStop()
    try:
        for batch in collector:
            timer["collect"] += time.perf_counter() - last_time
            # ---- store: low-level [num_envs, T] batches (time-major storage); the builder cuts high-level ones
            low_rb.extend(batch.select(*LOW_LEVEL_KEYS))
            high_rb.extend(batch)
            if counters["episodes"] < warmup_end and not schedule["train_during_warmup"]:
                # the reference trains nothing on the random warm-up and does not catch up afterwards
                counters["untrained_steps"] = counters.get("untrained_steps", 0) + batch.numel()
            counters["env_steps"] += batch.numel()
            counters["episodes"] += num_envs
            # ---- learn: low_updates_per_step SQGC updates per env step, a high-level one every 10
            start = time.perf_counter()
            trained_steps = counters["env_steps"] - counters.get("untrained_steps", 0)
            n_low = math.floor(trained_steps * schedule["low_updates_per_step"]) - low_updater.num_updates
            low_out = low_updater.run(n_low)
            n_high = trained_steps // schedule["high_update_interval"] - high_updater.num_updates
            high_out = high_updater.run(n_high) if len(high_rb) else None
            timer["update"] += time.perf_counter() - start
            bar.update(batch.numel())
            # ---- phase: random warm-up, then the policies
            _set_phase(cfg, agent, counters["episodes"])
            epoch = epoch_of(counters["episodes"], warmup_end, schedule["epoch_episodes"])
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
            if stop.requested:  # a signal during this batch: stop here, every update of the batch done
                raise KeyboardInterrupt
            last_time = time.perf_counter()
    except KeyboardInterrupt:
        stop.restore()
        bar.close()
        path = checkpoint()
        _plot_curve(cfg, history, run_dir)
        print(f"\nInterrupted: checkpoint written to {path}; continue with resume={run_dir}")
        collector.shutdown()
        raise
    except NonFiniteLossError as err:
        stop.restore()
        bar.close()
        collector.shutdown()
        raise SystemExit(
            f"Stopping: {err}. The last good checkpoint is kept at {run_dir / 'checkpoint.pt'}."
        ) from err
    finally:
        stop.restore()
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


def epoch_of(episodes: int, warmup_episodes: int, epoch_episodes: int) -> int:
    """The number of epochs completed after ``episodes`` training episodes.

    As in the reference, epochs of ``epoch_episodes`` start when the warm-up ends; the warm-up itself
    is cut into epochs of the same length (evaluated too, for the curve), the last one possibly
    shorter. For example with 200 warm-up episodes and 15 per epoch, epochs end after 15, 30, ...,
    195, 200, 215, 230, ... episodes.

    Examples:
        >>> [epoch_of(e, 200, 15) for e in (194, 195, 199, 200, 214, 215)]
        [12, 13, 13, 14, 14, 15]
    """
    if episodes < warmup_episodes:
        return episodes // epoch_episodes
    return -(-warmup_episodes // epoch_episodes) + (episodes - warmup_episodes) // epoch_episodes


def _set_phase(cfg: dict, agent, episodes: int) -> None:
    """Random warm-up (uniform actions; uniform subgoals unless ``high.warmup_subgoals=policy``), then the policies."""
    warmup = episodes < cfg["schedule"]["warmup_episodes"]
    agent.exploration.uniform_prob = 1.0 if warmup else cfg["low"]["uniform_prob"]
    uniform_subgoals = warmup and cfg["high"]["warmup_subgoals"] == "uniform"
    agent.high_policy.exploration.uniform_prob = 1.0 if uniform_subgoals else 0.0


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
        before = eval_env.base_env.state_dict() if schedule["eval_flat"] else None
        result = evaluate(eval_env, agent.policy, episode_length)
        metrics["time/eval_s"] = time.perf_counter() - start
        metrics["eval/success"] = result.success
        metrics["eval/any_success"] = result.any_success
        metrics["eval/final_distance"] = result.final_distance
        metrics["eval/last10_success"] = result.last_steps_success
        metrics["eval/final_speed"] = result.final_speed
        rollout = result.rollout
        metrics["graph/mean_path_landmarks"] = rollout["planner", "path_length"].float().mean().item()
        start_state, goal = rollout[0, 0]["observation"], rollout[0, 0]["desired_goal"]
        metrics["graph/learned_distance_start_goal"] = agent.planner.distance(start_state, goal).item()
        # subgoals and graph against the maze's true geometry (diag/...; nothing for the arms)
        diag = maze_epoch_diagnostics(
            cfg["env_name"], planner, rollout, agent.high_policy.actor, margin=cfg["planner"]["oracle_margin"]
        )
        metrics.update(diag)
        # the high level's subgoals vs the goal, and the low level's delivery of them (every env)
        hierarchy = hierarchy_diagnostics(
            rollout,
            cfg["low"]["reward_threshold"],
            distance=planner.distance,
            distance_from_graph=planner.distance_from_graph,
            far_threshold=cfg["high"]["far_from_graph_factor"] * cfg["planner"]["cutoff"],
        )
        metrics.update({f"diag/{k}": v for k, v in hierarchy.items()})
        if schedule["eval_flat"]:  # the low level alone chasing the goal, on the same test goals (diagnosis)
            after = eval_env.base_env.state_dict()
            eval_env.base_env.load_state_dict(before)
            flat = evaluate(eval_env, goal_as_waypoint(agent.low_actor), episode_length)
            eval_env.base_env.load_state_dict(after)  # the next evaluation's goals as without this one
            metrics["eval/flat_success"] = flat.success
            metrics["eval/flat_any_success"] = flat.any_success
            metrics["eval/flat_final_distance"] = flat.final_distance
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


class _GracefulStop:
    """SIGINT (Ctrl-C) and SIGTERM (a job scheduler's stop) ask the loop to stop at the end of the batch.

    The first signal sets :attr:`requested`: the loop finishes the batch's updates (and its epoch end),
    then checkpoints and exits, so the checkpoint sits at a batch boundary and a resumed run continues
    exactly. An exception raised at an arbitrary point instead (Python's default for SIGINT) could land
    inside ``TensorDict.to_module``, whose exit turns it into a ``RuntimeError`` and skips the checkpoint.
    A second signal stops at once (``KeyboardInterrupt``; the last periodic checkpoint is kept if that
    one cannot be written). :meth:`restore` puts the previous handlers back.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.requested = False
        self._previous = {}
        for signum in self.SIGNALS:
            try:
                self._previous[signum] = signal.signal(signum, self._handle)
            except ValueError:  # not in the main thread: no handler, default behaviour
                pass

    def _handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        name = signal.Signals(signum).name
        print(
            f"\n{name}: stopping after this batch's updates with a checkpoint (send it again to stop now).",
            file=sys.stderr,
            flush=True,
        )

    def restore(self) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous = {}


@hydra.main(config_path="config", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    """The command line: :func:`train` in Hydra's output directory (or ``run_dir``).

    A configuration error prints one line to stderr (``<script>: configuration error: <key, value, what is
    accepted>``) and exits with status 2, without a traceback (``HYDRA_FULL_ERROR=1`` shows it) and without
    leaving Hydra's new output directory behind. Ctrl-C (or SIGTERM) checkpoints and exits with 130.
    """
    from hydra.core.hydra_config import HydraConfig

    output_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        train(cfg, run_dir=cfg.run_dir or output_dir)
    except ConfigError as err:
        _remove_unused_output_dir(output_dir)
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise
        print(f"{Path(sys.argv[0]).name}: configuration error: {' '.join(str(err).split())}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        sys.exit(130)


if __name__ == "__main__":
    main()
