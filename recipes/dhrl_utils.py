"""The recipe's objects from its configuration: env, agent, buffers, updaters, collector, logger.

``dhrl_antmaze.py`` (training) and ``diagnose_*.py`` (a run's checkpoint) build their objects through these
functions, each a call of the library's key-free factory (:mod:`torchrl_dhrl.factory`: ``make_agent``,
``make_environment``, the buffers, ``make_updater``, ``make_collector``) with the configuration's values. The
components take the keys of their group as their own arguments, routed by name
(:mod:`torchrl_dhrl.recipe.routing`; ``config/config.yaml`` is the schema); what is left here is the wiring the
recipe adds (the env's sizes, the run's device and precision, the oracle distance, the graph for the penalty). A
configuration that a component refuses is reported as a :class:`~torchrl_dhrl.recipe.ConfigError` naming the key.
"""

from __future__ import annotations

import copy
import inspect
import random
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException
from torchrl_dhrl.envs import ENVS, GoalEnvError, gymnasium_id, is_gymnasium_ant_maze
from torchrl_dhrl.envs.geometry import obstacle_boxes

from torchrl_dhrl.diagnostics import TrainingEpisodeLog
from torchrl_dhrl.factory import (
    DHRLAgent,
    make_agent,
    make_collector,
    make_environment,
    make_eval_policy,
    make_high_level_buffer,
    make_low_level_buffer,
    make_updater,
)
from torchrl_dhrl.planner import LineOfSightDistance, make_edge_rule
from torchrl_dhrl.recipe import (
    GOAL_UNIT_KEYS,
    ConfigError,
    RunStart,
    agent_checkpoint_file,
    check_known_keys,
    checkpoint_file,
    derive_goal_units,
    load_checkpoint,
    make_logger,
    policy_captured,
    resolve_speed,
    run_precisions,
    start_run,
    upside_down_steps,
    validate_config,
    validate_env_name,
    with_changes,
    with_implied_keys,
)
from torchrl_dhrl.recipe.routing import TARGETS, check_components, component_arguments
from torchrl_dhrl.training import LossUpdater, available_cpus, evaluate

#: The configuration directory; ``config.yaml`` there is the schema of every configuration key.
CONFIG_DIR = Path(__file__).resolve().parent / "config"

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


def to_dict(cfg: DictConfig | dict) -> dict:
    """The composed configuration as a plain dict (interpolations resolved)."""
    if not isinstance(cfg, DictConfig):
        return dict(cfg)
    try:
        return OmegaConf.to_container(cfg, resolve=True)
    except OmegaConfBaseException as err:
        raise ConfigError(f"The configuration does not resolve: {' '.join(str(err).split())}") from err


def start_up(cfg: DictConfig | dict, run_dir: str | Path | None = None, *, write: bool = True) -> RunStart:
    """:func:`~torchrl_dhrl.recipe.start_run` of the composed configuration, with ``config/config.yaml`` as
    the schema: every check before anything is built or written, then the run directory.

    Returns:
        ``(cfg, device, run_dir, resume, state, threads)``, a :class:`~torchrl_dhrl.recipe.RunStart`.

    Raises:
        ConfigError: naming the key, the value and what is accepted.
    """
    cfg = to_dict(cfg)
    check_known_keys(cfg, config_schema(), source="recipes/config/config.yaml", complete=True)
    cfg = resolve_goal_units(cfg)
    return start_run(cfg, run_dir, schema=config_schema(), schema_source="recipes/config/config.yaml", write=write)


def resolve_goal_units(cfg: dict) -> dict:
    """The configuration with its keys in goal units derived from the env where they are ``null``, and
    ``goal_indices=auto`` read from it (:func:`~torchrl_dhrl.recipe.derive_goal_units`; ``env=gymnasium`` and
    ``env=custom`` leave them so), printed as one line; the configuration as it is when nothing is to derive. A
    ``gymnasium:<id>`` env is built here in any case, so that what it refuses (``continuing_task=False``) stops the
    run before anything else is built, and a line says when the adapter puts the achieved goal into the observation.

    Raises:
        ConfigError: for an env of its own (registered, ``gymnasium:<id>``) run with the default env file's
            (AntMaze's) values in goal units, which are sized for a 24-unit maze; or when the env cannot be built.
    """
    name = cfg["env_name"]
    derive = cfg.get("goal_indices") == "auto" or any(_get_path(cfg, path) is None for path in GOAL_UNIT_KEYS)
    if name not in ENVS and not derive and isinstance(name, str):
        default = default_goal_units()
        if all(_get_path(cfg, path) == value for path, value in default.items()):
            listed = ", ".join(f"{path}={value}" for path, value in default.items())
            raise ConfigError(
                f"env_name={name} runs with the default env file's values in goal units ({listed}), sized for "
                f"AntMaze's 24-unit maze: choose env=custom (a registered env) or env=gymnasium (gymnasium:<id>), "
                "which derive them from the env, or set them for your env."
            )
    gymnasium = gymnasium_id(name) is not None
    if not derive and not gymnasium:
        return cfg
    validate_env_name(cfg)
    cfg = copy.deepcopy(cfg)
    try:
        env = make_environment(
            name, num_envs=1, seed=cfg["seed"], max_episode_steps=cfg["episode_length"],
            env_kwargs=gymnasium_kwargs(cfg),
        )
    except (GoalEnvError, ValueError) as err:  # the adapter's arguments named as the `gymnasium` keys
        message = str(err).replace("`make_kwargs`", "`gymnasium.make_kwargs`") if gymnasium else err
        raise ConfigError(f"env_name={name}: {message}") from err
    base = getattr(env, "base_env", env)
    if getattr(base, "achieved_goal_in_observation", False):
        size, goal = base.observation_spec["observation"].shape[-1], base.observation_spec["achieved_goal"].shape[-1]
        print(
            f"{name}: its observation leaves out the achieved goal, so GymnasiumGoalEnv puts it first: "
            f"observation[0:{goal}] = achieved_goal ({size} entries, the env's {size - goal} after it)."
        )
    if gymnasium and cfg.get("right_flipped_after") is None and is_gymnasium_ant_maze(gymnasium_id(name)):
        print(
            f"{name}: its ant can flip over and nothing in the env rights it (the episode goes on with the ant on its "
            "back; train/upside_down logs how often): right_flipped_after=10 puts it back on its feet "
            "(docs/goal_env.md)."
        )
    if not derive:
        env.close()
        return cfg
    notes = derive_goal_units(cfg, env)
    of_env = getattr(getattr(env, "base_env", env), "maze_geometry", None)
    maze = of_env() if callable(of_env) else None
    env.close()
    print(f"Derived from {name}: {'; '.join(notes)}.")
    print(step_keys_in_goal_units(cfg, maze))
    return cfg


def step_keys_in_goal_units(cfg: dict, maze=None) -> str:
    """One start-up line: the keys in env steps (``high.c_h``, ``planner.cutoff``) as lengths at the agent's top
    speed (``planner.oracle_speed``), and in the maze's cells where it has them.

    Examples:
        >>> step_keys_in_goal_units({"high": {"c_h": 40}, "planner": {"cutoff": 30.0, "oracle_speed": 0.052}})
        'In goal units at the top speed 0.052 per step: high.c_h=40 steps reach 2.08, planner.cutoff=30 steps 1.56.'
    """
    speed = cfg["planner"]["oracle_speed"]
    c_h, cutoff = cfg["high"]["c_h"] * speed, cfg["planner"]["cutoff"] * speed
    line = (
        f"In goal units at the top speed {speed:g} per step: high.c_h={cfg['high']['c_h']:g} steps reach {c_h:.3g}, "
        f"planner.cutoff={cfg['planner']['cutoff']:g} steps {cutoff:.3g}"
    )
    if maze is not None and maze.scale:
        line += f" ({c_h / maze.scale:.2g} and {cutoff / maze.scale:.2g} of its {maze.scale:g}-unit cells)"
    return line + "."


def default_goal_units() -> dict[str, Any]:
    """The values in goal units of the default configuration (``config.yaml`` with its default env file)."""
    base = OmegaConf.load(CONFIG_DIR / "config.yaml")
    env = next(entry["env"] for entry in base.defaults if isinstance(entry, DictConfig) and "env" in entry)
    merged = OmegaConf.to_container(OmegaConf.merge(base, OmegaConf.load(CONFIG_DIR / "env" / f"{env}.yaml")))
    return {path: _get_path(merged, path) for path in GOAL_UNIT_KEYS}


def _get_path(cfg: dict, path: str) -> Any:
    node = cfg
    for part in path.split("."):
        node = node.get(part) if isinstance(node, dict) else None
    return node


def print_table(text: str, out: str | Path | None = None) -> None:
    """Prints an analysis script's table (markdown) and, with ``out``, writes the same text there (``--out``)."""
    print(text, end="")
    if out:
        Path(out).write_text(text)


def seed_everything(seed: int, *envs) -> None:
    """Seeds the global random streams (torch on every device, NumPy, Python's ``random``) and ``envs``' own
    (their simulations' per-env streams, through ``set_seed``)."""
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)
    for env in envs:
        env.set_seed(seed)


def episode_outcomes(
    env, policy, batches: int, seed: int, upside_down=None
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Final-state success of each of ``batches`` batches of deterministic episodes (bool, batch after batch),
    batch k seeded with ``seed + k``, and, with an ``upside_down`` test (:func:`upside_down_test`), whether each
    ended with the agent upside down (else ``None``)."""
    successes, flipped = [], []
    for k in range(batches):
        seed_everything(seed + k, env)
        rollout = evaluate(env, policy, env.max_episode_steps).rollout
        successes.append(rollout["next", "is_success"].reshape(*rollout.shape, -1).any(-1)[..., -1].reshape(-1).cpu())
        if upside_down is not None:
            flipped.append(upside_down_steps(rollout, upside_down)[..., -1].reshape(-1).cpu())
    return torch.cat(successes), torch.cat(flipped) if flipped else None


def resumed_run_dir(cfg: DictConfig | dict) -> Path | None:
    """The directory of the run that ``resume=<run dir or checkpoint>`` continues (``None`` for ``resume=auto``,
    no ``resume``, a ``fork``, or a path that holds no checkpoint): a resumed run goes on writing where it wrote."""
    resume, fork = cfg.get("resume"), cfg.get("fork")
    if not resume or resume == "auto" or fork:
        return None
    checkpoint = checkpoint_file(Path(str(resume)).expanduser())
    return checkpoint.resolve().parent if checkpoint.exists() else None


def adopt_output_dir(output_dir: Path, run_dir: Path) -> None:
    """Moves Hydra's record of a job (``.hydra/``, the job log) from its output directory into the run directory
    when they differ, and removes the output directory and the parents this leaves empty (within the current
    directory), so that ``run_dir=...`` or a resume leaves no stray ``outputs/<date>/<time>``. An output
    directory that holds anything else is left as it is."""
    output_dir, run_dir = Path(output_dir).resolve(), Path(run_dir).resolve()
    if output_dir == run_dir or not output_dir.is_dir() or not run_dir.is_dir():
        return
    from hydra.core.hydra_config import HydraConfig

    hydra_cfg = HydraConfig.get()
    record = {output_dir / f"{hydra_cfg.job.name}.log"}
    if hydra_cfg.output_subdir is not None:
        record.add(output_dir / hydra_cfg.output_subdir)
    if any(path not in record for path in output_dir.iterdir()):
        return
    for path in record:
        if path.exists():
            target = run_dir / path.name
            if target.is_dir():
                shutil.rmtree(target)
            shutil.move(str(path), str(target))
    remove_unused_output_dir(output_dir)
    if output_dir.is_dir() and not any(output_dir.iterdir()):
        output_dir.rmdir()
        parent, cwd = output_dir.parent, Path.cwd().resolve()
        while parent != cwd and cwd in parent.parents and not any(parent.iterdir()):
            parent.rmdir()
            parent = parent.parent


def remove_unused_output_dir(output_dir: Path) -> None:
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


def goal_indices(cfg: dict) -> tuple[int, ...] | None:
    indices = cfg["goal_indices"]
    return None if indices is None else tuple(int(i) for i in indices)


def far_from_graph_threshold(cfg: dict) -> float:
    """ "Far from the graph" for the gradual penalty and the diagnostics: ``far_from_graph_factor x cutoff``."""
    return cfg["high"]["far_from_graph_factor"] * cfg["planner"]["cutoff"]


def build_environment(cfg: dict, device: torch.device, *, eval: bool = False, agent: DHRLAgent | None = None):  # noqa: A002
    """:func:`~torchrl_dhrl.factory.make_environment` of the configuration: ``num_envs`` training envs (seed
    ``seed``, goal shifting with ``fgs.enabled``) or ``schedule.eval_episodes`` envs on the test goals (seed
    ``seed + 10000``); without ``agent``, the bare env after the goal-env contract check."""
    args = component_arguments(cfg)
    env_args = {**args["environment"], "goal_indices": goal_indices(cfg)}
    if eval:  # the test episodes: one env each, on their own seeds
        env_args |= {"num_envs": cfg["schedule"]["eval_episodes"], "seed": cfg["seed"] + 10_000}
    try:
        return make_environment(
            device=device,
            eval=eval,
            agent=agent,
            goal_shifting=args["goal_shifting"] if cfg["fgs"]["enabled"] and not eval else None,
            env_kwargs=gymnasium_kwargs(cfg, eval=eval),
            **env_args,
        )
    except GoalEnvError as err:  # the adapter's arguments named as the `gymnasium` keys
        message = str(err).replace("`make_kwargs`", "`gymnasium.make_kwargs`")
        raise ConfigError(f"env_name={cfg['env_name']}: {message}") from err


def gymnasium_kwargs(cfg: dict, *, eval: bool = False) -> dict[str, Any] | None:  # noqa: A002
    """The :class:`~torchrl_dhrl.envs.GymnasiumGoalEnv` arguments of ``env_name=gymnasium:<id>`` (``gymnasium.*``;
    the test envs reset with ``eval_reset_options`` and take ``eval_goals``), ``None`` for any other env."""
    if gymnasium_id(cfg["env_name"]) is None:
        return None
    args = dict(component_arguments(cfg)["gymnasium_env"])
    if eval:
        args["reset_options"] = cfg["gymnasium"]["eval_reset_options"]
        args["goals"] = cfg["gymnasium"].get("eval_goals")
    return args


def high_sampling_captured(cfg: dict, device: torch.device) -> bool:
    """Whether the high level samples with the capture-safe sampler (``high.capture_sampling``: true, or null
    with ``cudagraphs``), which needs the planner's graph fixed-size and reserved."""
    switch = cfg["high"].get("capture_sampling", False)
    return bool(switch) or (switch is None and bool(resolve_speed(cfg, device)[0]["cudagraphs"]))


def build_agent(cfg: dict, device: torch.device) -> DHRLAgent:
    """:func:`~torchrl_dhrl.factory.make_agent` of the configuration: each component takes the keys of its
    group that are its arguments (:mod:`torchrl_dhrl.recipe.routing`); sizes from the env's specs."""
    env = build_environment(cfg, device)
    # a registered env's goal size is known only now: the subgoal box is checked against it, naming the keys
    check_components(cfg, goal_dim=env.observation_spec["achieved_goal"].shape[-1], device=device, error=ConfigError)
    args = component_arguments(cfg)
    return make_agent(
        env,
        device,
        goal_indices=goal_indices(cfg),
        **{part: args[part] for part in AGENT_PARTS},
        graph={
            **args["graph"],
            # planner.edge_rule (absent from older checkpoints' configurations: the reference's cutoff rule)
            "edge_rule": make_edge_rule(**args["edge_rule"]),
            "build_autocast_dtype": run_precisions(cfg, device)[1],
            # fixed-size planning tensors, reserved: for a captured or compiled policy, and for the high level's
            # capture-safe sampling (the gradual penalty's graph query)
            "fixed_size": policy_captured(cfg) or high_sampling_captured(cfg, device),
        },
        distance=oracle_distance(cfg) if cfg["planner"]["distance"] == "oracle" else args["distance"],
        capturable_planner=policy_captured(cfg),
    )


#: The parts of :func:`~torchrl_dhrl.factory.make_agent` that take their arguments from the configuration as
#: routed: its keywords that are routing targets (:data:`~torchrl_dhrl.recipe.TARGETS`), read from its signature;
#: the graph and the distance get more from the recipe.
AGENT_PARTS = tuple(
    name
    for name in inspect.signature(make_agent).parameters
    if any(name in targets for targets in TARGETS.values()) and name not in ("graph", "distance")
)


def oracle_distance(cfg: dict, env=None) -> LineOfSightDistance:
    """``planner.distance=oracle``: straight-line steps at ``oracle_speed``, blocked by walls and boards (the
    configuration's check makes sure that the env has ``goal_indices``): a built-in env's, or the walls of a
    gymnasium-robotics maze (:func:`run_maze` of ``env``, or of an env built from ``cfg`` when it is ``None``)."""
    boxes = obstacle_boxes(cfg["env_name"])
    if boxes is None and gymnasium_id(cfg["env_name"]) is not None:
        maze = run_maze(cfg, env if env is not None else build_environment(cfg, torch.device("cpu")))
        boxes = None if maze is None else maze.boxes
    return LineOfSightDistance(**component_arguments(cfg)["oracle"], boxes=boxes, goal_indices=goal_indices(cfg))


def build_replay_buffers(cfg: dict, agent: DHRLAgent, device: torch.device):
    """The low- and high-level buffers of the configuration: ``(low_rb, high_rb)``."""
    args = component_arguments(cfg)
    low_rb = make_low_level_buffer(**args["low_buffer"], device=device)
    high_rb = make_high_level_buffer(
        **args["high_buffer"],
        reward_threshold=cfg["low"]["reward_threshold"],  # one sparse-reward radius for both levels
        planner=agent.planner if cfg["planner"]["enabled"] else None,
        far_from_graph_threshold=far_from_graph_threshold(cfg),
        device=device,
    )
    return low_rb, high_rb


def build_updaters(cfg: dict, agent: DHRLAgent, low_rb, high_rb) -> tuple[LossUpdater, LossUpdater]:
    """The low-level (SQGC) and high-level updaters of the configuration; the speed switches left at null take
    their value for the networks' device (``resolve_speed``; :func:`start_up` has resolved them already)."""
    cfg = resolve_speed(cfg, next(agent.sqgc_loss.parameters()).device)[0]
    args = component_arguments(cfg)
    out = []
    for level, loss, rb in (("low", agent.sqgc_loss, low_rb), ("high", agent.high_loss, high_rb)):
        out.append(
            make_updater(
                loss,
                rb,
                optimizers=args[f"{level}_optimizers"],
                **args[f"{level}_updater"],  # the level's keys and the top-level speed switches, resolved
                autocast_dtype=run_precisions(cfg, next(loss.parameters()).device)[0],
            )
        )
    return out[0], out[1]


class RunParts(NamedTuple):
    """What a run is made of, as :func:`build_run` builds it."""

    agent: DHRLAgent
    train_env: Any
    eval_env: Any
    low_rb: Any
    high_rb: Any
    low_updater: LossUpdater
    high_updater: LossUpdater
    collector: Any
    eval_policy: Any  # the policy of the test episodes: agent.policy, or captured (cudagraph_policy)


def build_run(cfg: dict, device: torch.device) -> RunParts:
    """Everything a run trains with, in dependency order: env specs -> agent -> envs with the agent's
    primers -> replay buffers -> updaters -> the collector (one whole episode per env and batch)."""
    agent = build_agent(cfg, device)
    train_env = build_environment(cfg, device, agent=agent)
    eval_env = build_environment(cfg, device, eval=True, agent=agent)
    low_rb, high_rb = build_replay_buffers(cfg, agent, device)
    low_updater, high_updater = build_updaters(cfg, agent, low_rb, high_rb)
    args = component_arguments(cfg)
    collector = make_collector(train_env, agent, train_env.max_episode_steps, **args["collector"])
    eval_policy = make_eval_policy(agent, **args["eval_policy"])
    return RunParts(agent, train_env, eval_env, low_rb, high_rb, low_updater, high_updater, collector, eval_policy)


def build_logger(cfg: dict, run_dir: Path):
    """The configuration's TorchRL logger (``None`` for ``logger.backend=none``)."""
    log = cfg["logger"]
    name = log["exp_name"] or f"dhrl_{cfg['env_name']}_seed{cfg['seed']}"
    return make_logger(
        log["backend"],
        name,
        run_dir,
        project=log["project"],
        wandb_mode=log["wandb_mode"],
        group=log.get("group"),
    )


def sweep_defaults(cfg: DictConfig, hydra_cfg: DictConfig) -> None:
    """Fills two keys of a job of a Hydra sweep (``-m``) when they are null, in place (one run: nothing).

    - ``threads``: the cores divided among the jobs the launcher runs at once (joblib's ``n_jobs``, -1 for one
      per core), or the cores each job is given (submitit's ``cpus_per_task``, Ray's
      ``ray.remote.num_cpus``; unset, both reserve one core per job, so one thread); one job at a time
      (Hydra's basic launcher) keeps them all. Two jobs each using both cores of a 2-core machine ran 10x
      slower than with one thread each.
    - ``logger.group``: the sweep directory's name, so W&B groups the sweep's runs.
    """
    from hydra.types import RunMode

    if hydra_cfg.mode != RunMode.MULTIRUN:
        return
    if cfg.threads is None:
        launcher = hydra_cfg.launcher
        target = str(OmegaConf.select(launcher, "_target_", default="") or "")
        n_jobs = OmegaConf.select(launcher, "n_jobs", default=None)
        per_job = OmegaConf.select(launcher, "cpus_per_task", default=None) or OmegaConf.select(
            launcher, "ray.remote.num_cpus", default=None
        )
        if per_job is None and ("hydra_submitit_launcher" in target or "hydra_ray_launcher" in target):
            per_job = 1  # a Slurm task or a Ray task reserves one CPU unless told otherwise
        if per_job:
            cfg.threads = int(per_job)
        elif n_jobs is not None:
            cpus = available_cpus()
            jobs = cpus if int(n_jobs) < 0 else min(int(n_jobs), cpus)
            cfg.threads = max(1, cpus // max(jobs, 1))
    if cfg.logger.group is None:
        cfg.logger.group = Path(hydra_cfg.sweep.dir).name


def evaluation_kwargs(cfg: dict) -> dict[str, Any]:
    """The keyword arguments of :func:`~torchrl_dhrl.recipe.evaluate_epoch` of the configuration."""
    return {
        "env_name": cfg["env_name"],
        "reward_threshold": cfg["low"]["reward_threshold"],
        "far_from_graph_threshold": far_from_graph_threshold(cfg),
        "oracle_margin": cfg["planner"]["oracle_margin"],
        "flat": cfg["schedule"]["eval_flat"],
        "upside_down": upside_down_test(cfg),
    }


def upside_down_test(cfg: dict):
    """The ant mazes' :meth:`~torchrl_dhrl.envs.AntAgent.is_upside_down` (the ant can flip over, and only
    ``right_flipped_after`` rights it: the recipe logs how much of the training and test episodes it spends so),
    ``None`` for any other env. gymnasium-robotics' ``AntMaze_*`` count: their observation, as the adapter hands
    it on (the achieved goal first), starts with the torso's x, y, z and quaternion, as the built-in ant's."""
    from torchrl_dhrl.envs import MAZE_NAMES, AntAgent, get_maze_spec

    env_id = gymnasium_id(cfg["env_name"])
    if env_id is not None:
        return AntAgent.is_upside_down if is_gymnasium_ant_maze(env_id) else None
    if cfg["env_name"] not in MAZE_NAMES:
        return None
    return getattr(get_maze_spec(cfg["env_name"]).agent, "is_upside_down", None)


def add_oracle_options(parser) -> None:
    """``--oracle-margin`` and ``--oracle-speed`` of the checkpoint diagnostics: the maze geometry's agent radius
    and the oracle's goal units per step, in place of the run's recorded ``planner.oracle_margin`` and
    ``planner.oracle_speed`` (runs of 0.4.0 and earlier recorded the configuration's values for gymnasium mazes,
    e.g. 0.5 and 0.15 on PointMaze_Large-v3, whose derived values are 0.125 and 0.0523)."""
    parser.add_argument(
        "--oracle-margin", type=float, default=None, help="the agent's radius in the maze geometry (goal units)"
    )
    parser.add_argument("--oracle-speed", type=float, default=None, help="the oracle's goal units per env step")


def oracle_overrides(parser, args) -> dict[str, float]:
    """The ``planner`` keys given by :func:`add_oracle_options`' options (``parser.error`` on a bad value)."""
    if args.oracle_margin is not None and not args.oracle_margin >= 0:
        parser.error(f"--oracle-margin must be >= 0, got {args.oracle_margin}")
    if args.oracle_speed is not None and not args.oracle_speed > 0:
        parser.error(f"--oracle-speed must be > 0, got {args.oracle_speed}")
    given = {"oracle_margin": args.oracle_margin, "oracle_speed": args.oracle_speed}
    return {key: value for key, value in given.items() if value is not None}


def run_maze(cfg: dict, env=None):
    """The true geometry of the run's maze (:class:`~torchrl_dhrl.envs.geometry.MazeGeometry`, walls inflated by
    ``planner.oracle_margin``): a built-in maze's, the maze of a gymnasium-robotics env (``env``'s
    :meth:`~torchrl_dhrl.envs.GymnasiumGoalEnv.maze_geometry`, with the start of its fixed ``reset_cell``), or
    ``None`` (the arms, other envs)."""
    from torchrl_dhrl.diagnostics import maze_geometry

    margin = float(cfg["planner"]["oracle_margin"])
    of_env = getattr(getattr(env, "base_env", env), "maze_geometry", None)
    try:
        return of_env(margin=margin) if callable(of_env) else maze_geometry(cfg["env_name"], margin)
    except ValueError as err:  # a margin that closes the maze
        raise ConfigError(f"planner.oracle_margin={margin:g} on env_name={cfg['env_name']}: {err}") from err


def build_episode_log(cfg: dict, state: dict | None = None, maze=None) -> TrainingEpisodeLog:
    """The run's per-epoch statistics of its training episodes (progress along the maze for the mazes).

    ``state``: a :meth:`TrainingEpisodeLog.state_dict` to continue from (the recipe keeps it in its
    checkpointed counters, so a run stopped in the middle of an epoch resumes its counts). ``maze``: the run's
    :func:`run_maze` (defaults to a built-in maze's); progress is logged where it has a start.
    """
    maze = run_maze(cfg) if maze is None else maze
    geometry = maze if maze is not None and maze.start is not None else None
    log = TrainingEpisodeLog(geometry, upside_down=upside_down_test(cfg))
    if state:
        log.load_state_dict(state)
    return log


def agent_from_checkpoint(
    path, device: str | torch.device = "cpu", changes: Mapping[str, Any] | None = None
) -> tuple[dict, DHRLAgent]:
    """The configuration of a run's checkpoint and its agent, rebuilt and loaded (the graph with it).

    Args:
        path (str or Path): a checkpoint, a saved agent (``<run dir>/agent``) or the run directory holding
            them (its checkpoint, else its saved agent: :func:`~torchrl_dhrl.recipe.agent_checkpoint_file`).
        device (str or torch.device): where the agent is built. Defaults to ``"cpu"``.
        changes (Mapping, optional): dotted keys no checkpointed state holds (role ``unsaved``), set before the
            agent is built (:func:`~torchrl_dhrl.recipe.with_changes`) and checked like the recipe's: the same
            trained agent acting otherwise. A change of a ``planner`` key redoes the loaded graph's edges with it
            (the same landmarks and learned distances). Defaults to none.
    """
    device = torch.device(device)
    state = load_checkpoint(agent_checkpoint_file(path), map_location=device, components=("config", "agent"))
    cfg = with_implied_keys(state["config"])  # an older checkpoint rebuilt with its own behaviour
    if changes:
        cfg = with_changes(cfg, changes)
        validate_config(cfg)
    agent = build_agent(cfg, device)
    agent.load_state_dict(state["agent"])
    if changes and any(key.startswith("planner.") for key in changes):
        agent.planner.graph.redo_edges()  # the loaded edges were the saved rule's
    return cfg, agent
