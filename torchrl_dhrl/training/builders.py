"""Factories that turn a DHRL configuration into TorchRL objects: env, agent, buffers, collector, logger.

The recipes (``recipes/dhrl_antmaze.py``) are short loops over what these return; every knob
comes from the configuration validated by :func:`~torchrl_dhrl.training.validate_config` (see
``recipes/config/`` for the keys and the reference values).
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict.nn import TensorDictSequential
from torchrl.collectors import Collector
from torchrl.envs import Compose, EnvBase, TransformedEnv

from torchrl_dhrl.data import (
    CompactLazyTensorStorage,
    FutureGoalRelabel,
    HighLevelTransitionBuilder,
    HindsightSubgoalRelabel,
    RelabelReplayBuffer,
    SparseGoalReward,
)
from torchrl_dhrl.envs import GoalEnvError, check_goal_env, make_env
from torchrl_dhrl.envs.transforms import AngleFeatures
from torchrl_dhrl.modules import (
    GaussianUniformExplorationModule,
    GoalConditionedCritic,
    HighLevelPolicy,
    LowLevelActor,
)
from torchrl_dhrl.objectives import HighLevelLoss, SQGCLoss, make_optimizers
from torchrl_dhrl.planner import (
    FrontierGoalShifting,
    GoalDistance,
    GoalShiftOnReset,
    GraphPlanner,
    LandmarkGraph,
    LineOfSightDistance,
)

from .config import BUILD_DTYPES, UPDATE_DTYPES, ConfigError
from .updates import LossUpdater

__all__ = [
    "DHRLAgent",
    "LOW_LEVEL_KEYS",
    "make_agent",
    "make_collector",
    "make_environment",
    "make_graph_distance",
    "make_logger",
    "make_replay_buffers",
    "make_updaters",
]

#: Entries of a collector batch the low-level buffer keeps (relabelling, losses, graph candidates).
LOW_LEVEL_KEYS = (
    "observation",
    "achieved_goal",
    "waypoint",
    "action",
    "step_count",
    ("collector", "traj_ids"),
    ("next", "observation"),
    ("next", "achieved_goal"),
    ("next", "done"),
)


@dataclass
class DHRLAgent:
    """The modules of one DHRL agent, as built by :func:`make_agent`.

    The acting policy is ``TensorDictSequential(high_policy, planner, low_policy)``: the high
    level issues a subgoal every ``c_h`` steps, the planner turns it into the current waypoint and
    the low level acts towards it. All trainable parameters (with target copies) live in the two
    losses; the graph lives in the planner. :meth:`state_dict` gathers them for checkpoints.
    """

    high_policy: HighLevelPolicy
    low_actor: LowLevelActor
    exploration: GaussianUniformExplorationModule
    sqgc_loss: SQGCLoss
    high_loss: HighLevelLoss
    planner: GraphPlanner
    policy: TensorDictSequential

    def state_dict(self) -> dict[str, Any]:
        return {
            "sqgc_loss": self.sqgc_loss.state_dict(),
            "high_loss": self.high_loss.state_dict(),
            "planner": self.planner.state_dict(),
        }

    def load_state_dict(self, state_dict: Mapping[str, Any]) -> None:
        self.sqgc_loss.load_state_dict(state_dict["sqgc_loss"])
        self.high_loss.load_state_dict(state_dict["high_loss"])
        self.planner.load_state_dict(state_dict["planner"])


def _goal_indices(cfg: Mapping) -> tuple[int, ...] | None:
    indices = cfg["goal_indices"]
    return None if indices is None else tuple(int(i) for i in indices)


def make_graph_distance(cfg: Mapping, sqgc_loss: SQGCLoss):
    """The planner's distance: the learned graph critics (Eq. 1) or the line-of-sight oracle."""
    if cfg["planner"]["distance"] == "learned":
        return GoalDistance.from_loss(sqgc_loss, twin=cfg["planner"]["twin"])
    indices = _goal_indices(cfg)
    if indices is None:
        raise ConfigError(
            f"planner.distance=oracle needs the achieved goal inside the observation (goal_indices), "
            f"which {cfg['env_name']} does not provide."
        )
    return LineOfSightDistance(
        cfg["planner"]["oracle_speed"],
        boxes=_obstacle_boxes(cfg["env_name"]),
        margin=cfg["planner"]["oracle_margin"],
        goal_indices=indices,
    )


def _obstacle_boxes(name: str) -> torch.Tensor | None:
    """``[W, 2, goal_dim]`` obstacle boxes in goal space: maze wall footprints or the UR3's boards."""
    from torchrl_dhrl.envs import ARM_NAMES, MAZE_NAMES, get_arm_spec, get_maze_spec

    if name in MAZE_NAMES:
        boxes = [wall.xy_bounds for wall in get_maze_spec(name).layout.wall_boxes]
        return torch.tensor([[[x0, y0], [x1, y1]] for x0, x1, y0, y1 in boxes], dtype=torch.float32)
    if name in ARM_NAMES and get_arm_spec(name).boards:
        boards = get_arm_spec(name).boards
        centre = torch.tensor([b.center for b in boards], dtype=torch.float32)
        half = torch.tensor([b.half_size for b in boards], dtype=torch.float32)
        return torch.stack([centre - half, centre + half], 1)
    return None


def make_agent(cfg: Mapping, env: EnvBase, device: torch.device) -> DHRLAgent:
    """Builds actors, critics, both losses, the graph planner and the acting policy on ``device``."""
    obs_dim = env.observation_spec["observation"].shape[-1]
    goal_dim = env.observation_spec["achieved_goal"].shape[-1]
    if len(cfg["high"]["subgoal_low"]) != goal_dim:
        raise ConfigError(
            f"high.subgoal_low has {len(cfg['high']['subgoal_low'])} entries; the goal space has {goal_dim}."
        )
    action_spec = env.action_spec_unbatched.to(device)
    indices = _goal_indices(cfg)
    low, high = cfg["low"], cfg["high"]
    relative = bool(low["relative_goal"])
    if relative and indices is None:
        raise ConfigError(
            f"low.relative_goal=true needs goal_indices, which {cfg['env_name']} does not provide."
        )
    common = {"goal_indices": indices, "num_cells": tuple(low["hidden"])}
    actor = LowLevelActor(obs_dim, goal_dim, action_spec, relative_goal=relative, **common).to(device)
    exploration = GaussianUniformExplorationModule(
        action_spec, sigma=low["action_noise"], uniform_prob=low["uniform_prob"]
    ).to(device)

    # the reference's low-level critics see the absolute goal even where the actor sees the relative one
    relative_critic = low["critic_goal"] == "relative"

    def critic() -> GoalConditionedCritic:
        return GoalConditionedCritic(
            obs_dim,
            goal_dim,
            action_spec,
            relative_goal=relative_critic,
            gamma=low["gamma"],
            goal_key="goal",
            **common,
        ).to(device)

    sqgc_loss = SQGCLoss(
        actor,
        critic(),
        critic(),
        clip_return=low["clip_return"],
        action_l2=low["action_l2"],
        target_noise_std=low["target_noise"],
        target_action_clamp=low["target_action_clamp"],
        actor_update_interval=low["actor_update_interval"],
        sqgc=low["sqgc"],
    )
    high_policy = HighLevelPolicy(
        obs_dim,
        goal_dim,
        high["subgoal_low"],
        high["subgoal_high"],
        interval=high["c_h"],
        noise_sigma=high["subgoal_noise"],
        goal_indices=indices,
        num_cells=tuple(high["hidden"]),
    ).to(device)
    high_critic = GoalConditionedCritic(
        obs_dim,
        goal_dim,
        action_low=high["subgoal_low"],
        action_high=high["subgoal_high"],
        goal_indices=indices,
        relative_goal=False,
        gamma=high["gamma"],
        num_cells=tuple(high["hidden"]),
        goal_key="desired_goal",
        action_key="subgoal",
    ).to(device)
    high_loss = HighLevelLoss(
        high_policy.actor,
        high_critic,
        clip_return=high["clip_return"],
        action_l2=high["action_l2"],
        target_noise_std=high["target_noise"],
        target_action_clamp=high["target_action_clamp"],
        actor_update_interval=high["actor_update_interval"],
    )
    planner_cfg = cfg["planner"]
    graph = LandmarkGraph(
        cutoff=planner_cfg["cutoff"],
        max_landmarks=planner_cfg["max_landmarks"],
        early_stop=planner_cfg["early_stop"],
        build_autocast_dtype=BUILD_DTYPES[planner_cfg["build_dtype"]],
    )
    planner = GraphPlanner(
        graph, make_graph_distance(cfg, sqgc_loss), goal_dim, reach_radius=planner_cfg["reach_radius"]
    ).to(device)
    policy = TensorDictSequential(high_policy, planner, TensorDictSequential(actor, exploration))
    return DHRLAgent(high_policy, actor, exploration, sqgc_loss, high_loss, planner, policy)


def observation_transforms(cfg: Mapping) -> list:
    """The observation transforms of the configuration (``angle_features``: :class:`AngleFeatures`), to append to
    every env the agent acts in (training, evaluation and diagnosis envs alike)."""
    indices = cfg.get("angle_features")
    return [AngleFeatures(indices)] if indices else []


def make_environment(
    cfg: Mapping,
    device: torch.device,
    *,
    eval: bool = False,
    agent: DHRLAgent | None = None,  # noqa: A002
) -> EnvBase:
    """The batched env (``eval``: ``eval_episodes`` envs on the test goals), with the agent's primers.

    Without ``agent`` the bare env (with the :func:`observation_transforms` only) is returned (used to read the
    specs before the agent exists), after
    :func:`~torchrl_dhrl.envs.check_goal_env` (with ``goal_indices``) has checked that it meets the goal-env
    contract: any env registered with :func:`~torchrl_dhrl.envs.register_env` that does can be trained.
    Training envs get frontier-based goal shifting when ``fgs.enabled``.

    Raises:
        ConfigError: when the env does not meet the contract (the message names the key).
    """
    num_envs = cfg["schedule"]["eval_episodes"] if eval else cfg["num_envs"]
    seed = cfg["seed"] + (10_000 if eval else 0)
    try:
        env = make_env(
            cfg["env_name"],
            num_envs=num_envs,
            seed=seed,
            device=device,
            eval=eval,
            max_episode_steps=cfg["episode_length"],
        )
        if agent is None:  # the whole contract once, with a short rollout that draws no random numbers
            check_goal_env(env, goal_indices=_goal_indices(cfg))
    except GoalEnvError as err:
        raise ConfigError(f"env_name={cfg['env_name']}: {err}") from err
    if agent is None:
        features = observation_transforms(cfg)
        return TransformedEnv(env, Compose(*features)) if features else env
    transforms = [*observation_transforms(cfg), agent.high_policy.make_primer(), agent.planner.make_primer()]
    if cfg["fgs"]["enabled"] and not eval:
        fgs = FrontierGoalShifting(
            agent.planner,
            noise=cfg["fgs"]["noise"],
            weighting=cfg["fgs"]["weighting"],
            trigger=cfg["fgs"]["trigger"],
        )
        transforms.append(GoalShiftOnReset(fgs))
    return TransformedEnv(env, Compose(*transforms))


def make_collector(env: EnvBase, agent: DHRLAgent, episode_length: int) -> Collector:
    """A :class:`~torchrl.collectors.Collector` yielding one whole episode per env and batch.

    Episodes only truncate, so every env ends its episode at the last step of a batch and the
    collector's automatic reset starts the next one: batches are ``[num_envs, episode_length]``.
    Batches are stored on the env's device, trajectory ids included, so that they can be written into
    replay buffers on that device (also into a storage restored from a checkpoint, which has no device).
    """
    num_envs = env.batch_size.numel()
    # The planner and the subgoal scheduler carry their state with TensorDictPrimers (already on the env);
    # they do not need the InitTracker the collector would add for recurrent-looking modules.
    return Collector(
        env,
        agent.policy,
        frames_per_batch=num_envs * episode_length,
        total_frames=-1,
        storing_device=env.device,
        auto_register_policy_transforms=False,
    )


def make_replay_buffers(cfg: Mapping, agent: DHRLAgent, device: torch.device):
    """The low-level buffer (time-major ``[T, num_envs]`` storage, extended with ``[num_envs, T]`` batches) and
    the high-level one (a transition builder turns low-level batches into one transition per subgoal), both
    :class:`~torchrl_dhrl.data.RelabelReplayBuffer` s whose ``sample()`` returns relabelled batches.
    ``low.buffer_size`` and ``high.buffer_size`` count transitions, whatever ``num_envs``.

    Returns:
        ``(low_rb, high_rb)``.
    """
    low, high = cfg["low"], cfg["high"]
    reward = SparseGoalReward(low["reward_threshold"])
    # ``max_size`` counts transitions (elements of the ``[T, num_envs]`` storage), not time steps
    low_rb = RelabelReplayBuffer(
        storage=CompactLazyTensorStorage(low["buffer_size"], ndim=2, device=device),
        relabel=[
            FutureGoalRelabel(
                reward, her_ratio=(low["her_ratio"], 1.0), window=low["her_window"], goal_key="waypoint"
            )
        ],
        batch_size=low["batch_size"],
    )
    far_threshold = high["far_from_graph_factor"] * cfg["planner"]["cutoff"]
    distance_from_graph = (
        # exact relative to the threshold, the only thing the penalty reads, at a fraction of the cost
        functools.partial(agent.planner.distance_from_graph, at_most=far_threshold)
        if high["gradual_penalty"] is not None and cfg["planner"]["enabled"]
        else None
    )
    high_relabel = [
        FutureGoalRelabel(
            reward,
            her_ratio=high["her_ratio"],
            window=high["her_window"],
            out_keys=["desired_goal"],
            reward_keys=None,
            traj_key="episode_id",
            step_count_key="segment_index",
        ),
        HindsightSubgoalRelabel(
            distance_from_graph,
            reward,
            subgoal_test_ratio=high["subgoal_test_ratio"],
            subgoal_test_threshold=high["subgoal_test_threshold"],
            subgoal_miss_penalty=high["subgoal_miss_penalty"],
            gradual_penalty=high["gradual_penalty"],
            far_from_graph_threshold=far_threshold,
        ),
    ]
    high_rb = RelabelReplayBuffer(
        storage=CompactLazyTensorStorage(high["buffer_size"], device=device),
        transform=HighLevelTransitionBuilder(reward_fn=reward),
        relabel=high_relabel,
        batch_size=high["batch_size"],
    )
    return low_rb, high_rb


def make_updaters(cfg: Mapping, agent: DHRLAgent, buffers) -> tuple[LossUpdater, LossUpdater]:
    """The low-level (SQGC) and high-level updaters with their Adam optimisers, sampling ``buffers``
    (``(low_rb, high_rb)`` from :func:`make_replay_buffers`)."""
    low_rb, high_rb = buffers
    updaters = []
    for level, loss, rb in (("low", agent.sqgc_loss, low_rb), ("high", agent.high_loss, high_rb)):
        c = cfg[level]
        optimizers = make_optimizers(loss, actor_lr=c["actor_lr"], critic_lr=c["critic_lr"])
        updaters.append(
            LossUpdater(
                loss,
                rb,
                optimizers,
                polyak=c["polyak"],
                target_update_interval=c["target_update_interval"],
                cudagraphs=cfg.get("cudagraphs", False),
                autocast_dtype=UPDATE_DTYPES[cfg.get("update_dtype", "float32")],
                actor_after_critic_step=c["actor_after_critic_step"],
            )
        )
    return updaters[0], updaters[1]


def make_logger(cfg: Mapping, run_dir: Path):
    """A TorchRL logger: CSV (default, files under ``run_dir/logs``), W&B (offline unless
    ``logger.wandb_mode=online``) or TensorBoard; ``None`` for ``logger.backend=none``."""
    from torchrl.record.loggers import CSVLogger, TensorboardLogger, WandbLogger

    log_cfg = cfg["logger"]
    backend = log_cfg["backend"]
    exp_name = log_cfg["exp_name"] or f"dhrl_{cfg['env_name']}_seed{cfg['seed']}"
    log_dir = str(run_dir / "logs")
    if backend == "csv":
        return CSVLogger(exp_name, log_dir=log_dir)
    if backend == "tensorboard":
        return TensorboardLogger(exp_name, log_dir=log_dir)
    if backend == "wandb":
        return WandbLogger(
            exp_name,
            offline=log_cfg["wandb_mode"] != "online",
            save_dir=log_dir,
            project=log_cfg["project"],
        )
    return None
