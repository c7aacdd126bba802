"""Factories of the reference DHRL agent and of the TorchRL objects that train it: env, agent, replay buffers,
updaters, collector.

They know no configuration key: each takes its components' own keyword arguments, passed on as they are (the
components' defaults are the reference implementation's), and adds the wiring between them (sizes from the env's
specs, the tensordict keys of each level, the SQGC critic pairs, the planner's distance over the graph critics).
The recipe (``recipes/dhrl_antmaze.py``) maps its configuration onto the same functions.

Examples:
    >>> import torchrl_dhrl as dhrl
    >>> env = dhrl.make_environment("PointMaze", num_envs=2, max_episode_steps=20)
    >>> agent = dhrl.make_agent(env, goal_indices=dhrl.goal_indices_of(env),
    ...     high_policy={"subgoal_low": [-2.0, -2.0], "subgoal_high": [10.0, 10.0], "interval": 10})
    >>> low_rb = dhrl.make_low_level_buffer(buffer_size=10_000, batch_size=64, reward_threshold=0.5)
    >>> high_rb = dhrl.make_high_level_buffer(
    ...     buffer_size=1_000, batch_size=16, reward_threshold=0.5, planner=agent.planner)
    >>> low = dhrl.make_updater(agent.sqgc_loss, low_rb)
    >>> collector = dhrl.make_collector(dhrl.make_environment("PointMaze", num_envs=2, max_episode_steps=20,
    ...     agent=agent), agent, episode_length=20)
    >>> next(iter(collector)).batch_size
    torch.Size([2, 20])
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from tensordict.nn import CudaGraphModule, TensorDictModuleBase, TensorDictSequential
from torchrl.collectors import Collector
from torchrl.data import ReplayBuffer
from torchrl.envs import Compose, EnvBase, TransformedEnv
from torchrl.objectives import LossModule

from torchrl_dhrl.checks import ArgumentCheck, checked, flag, indices, integer, number
from torchrl_dhrl.data import (
    CompactLazyTensorStorage,
    FutureGoalRelabel,
    HighLevelTransitionBuilder,
    HindsightSubgoalRelabel,
    RelabelReplayBuffer,
    SparseGoalReward,
)
from torchrl_dhrl.envs import (
    ENVS,
    GoalEnvError,
    check_goal_env,
    get_env_factory,
    gymnasium_id,
    is_gymnasium_ant_maze,
    make_env,
)
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
    TemporalDistance,
)
from torchrl_dhrl.training import LossUpdater

__all__ = [
    "DHRLAgent",
    "LOW_LEVEL_KEYS",
    "make_agent",
    "make_collector",
    "make_environment",
    "make_eval_policy",
    "make_high_level_buffer",
    "make_low_level_buffer",
    "make_updater",
    "observation_transforms",
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


def make_agent(
    env: EnvBase,
    device: torch.device | str = "cpu",
    *,
    high_policy: Mapping[str, Any],
    goal_indices: Sequence[int] | None = None,
    low_actor: Mapping[str, Any] | None = None,
    low_critic: Mapping[str, Any] | None = None,
    exploration: Mapping[str, Any] | None = None,
    sqgc_loss: Mapping[str, Any] | None = None,
    high_critic: Mapping[str, Any] | None = None,
    high_loss: Mapping[str, Any] | None = None,
    graph: Mapping[str, Any] | None = None,
    planner: Mapping[str, Any] | None = None,
    distance: TemporalDistance | Mapping[str, Any] | None = None,
    capturable_planner: bool = False,
) -> DHRLAgent:
    """Builds both levels (actors, critics, losses), the graph planner and the acting policy on ``device``.

    Each component's hyperparameters are a mapping of its own constructor's keyword arguments, passed on as
    they are (its checks apply; see :mod:`torchrl_dhrl.checks`): a new argument of a component is reachable
    here without a change to this function. What this function supplies is the wiring: the sizes from
    ``env``'s specs (``observation``, ``achieved_goal``, the action box), ``goal_indices``, the tensordict
    keys of each level, the high-level critics' action box (the subgoal box), the SQGC critic pairs.

    Args:
        env (EnvBase): an env of the goal-env contract (e.g. :func:`make_environment` without ``agent``).
        device (torch.device or str): where the modules live. Defaults to ``"cpu"``.

    Keyword Args:
        high_policy (mapping): :class:`~torchrl_dhrl.modules.HighLevelPolicy`'s arguments: ``subgoal_low``,
            ``subgoal_high`` (the subgoal box, goal space), ``interval`` (``c_h``), ``noise_sigma``,
            ``num_cells``, ... With ``critic_candidates`` or ``landmark_candidates`` its selector scores the
            candidates with the high-level loss's critic (its current parameters) and the planner's landmarks.
        goal_indices (sequence of int, optional): where the achieved goal sits in the observation (the env's:
            :func:`~torchrl_dhrl.envs.goal_indices_of`); needed by the relative goal of the low-level actor
            (its default) and of any part given ``relative_goal=True``.
        low_actor (mapping, optional): :class:`~torchrl_dhrl.modules.LowLevelActor`'s (``relative_goal``,
            ``num_cells``, ...). Its own defaults apply: a relative goal, as in the reference (needs
            ``goal_indices``; ``relative_goal=False`` for an absolute one).
        low_critic (mapping, optional): :class:`~torchrl_dhrl.modules.GoalConditionedCritic`'s, for the policy
            and the graph critics alike (``relative_goal``, default ``False`` as in the reference;
            ``gamma``, ``distance_output``, ``num_cells``, ...).
        exploration (mapping, optional): :class:`~torchrl_dhrl.modules.GaussianUniformExplorationModule`'s
            (``sigma``, a fraction of the action box half-width; ``uniform_prob``).
        sqgc_loss (mapping, optional): :class:`~torchrl_dhrl.objectives.SQGCLoss`'s (``clip_return``,
            ``action_l2``, ``target_noise_std``, ``target_action_clamp``, ``sqgc``, ...).
        high_critic, high_loss (mapping, optional): the high level's :class:`~torchrl_dhrl.modules.GoalConditionedCritic`
            (``gamma``, ``distance_output``, ``num_cells``) and :class:`~torchrl_dhrl.objectives.HighLevelLoss`.
        graph (mapping, optional): :class:`~torchrl_dhrl.planner.LandmarkGraph`'s (``cutoff``,
            ``max_landmarks``, ``early_stop``, ``build_autocast_dtype``, ``fixed_size`` (default: as
            ``capturable_planner``), ...). A ``fixed_size`` graph is reserved at once
            (:meth:`LandmarkGraph.reserve <torchrl_dhrl.planner.LandmarkGraph.reserve>`), so that capture-safe
            queries (the high level's captured sampling, a captured policy) work from the start.
        planner (mapping, optional): :class:`~torchrl_dhrl.planner.GraphPlanner`'s (``reach_radius``, ...).
        distance (TemporalDistance or mapping, optional): the planner's distance, e.g. a
            :class:`~torchrl_dhrl.planner.LineOfSightDistance` for the oracle; or the keyword arguments of
            :meth:`GoalDistance.from_loss <torchrl_dhrl.planner.GoalDistance.from_loss>` (``twin``) over the
            graph critics (Eq. 1), the default.
        capturable_planner (bool): the :class:`~torchrl_dhrl.planner.GraphPlanner`'s ``capturable``: plans
            with static shapes, every env in the steps where some env is due for a replan (``torch.cond`` when
            compiled; ``plan_on_demand``), so that the acting policy compiles whole (:func:`make_collector`'s
            ``compile_policy``, or captured as a CUDA graph, ``cudagraph_policy``), on a ``fixed_size`` graph
            reserved at once (:meth:`LandmarkGraph.reserve <torchrl_dhrl.planner.LandmarkGraph.reserve>`: the same
            storage before the first build and after every rebuild, so no recompilation and no new capture). Same
            plans. Defaults to ``False``.

    Raises:
        ValueError: from the component whose argument is refused, naming the argument (e.g. a subgoal box
            that does not match the goal space, ``relative_goal`` without ``goal_indices``).

    Examples:
        >>> from torchrl_dhrl.factory import make_environment
        >>> env = make_environment("PointMaze")
        >>> agent = make_agent(
        ...     env,
        ...     goal_indices=[0, 1],
        ...     high_policy={"subgoal_low": [-2.0, -2.0], "subgoal_high": [10.0, 10.0], "interval": 10,
        ...                  "num_cells": (16,)},
        ...     high_critic={"num_cells": (16,)},
        ...     low_actor={"num_cells": (16,)},
        ...     low_critic={"num_cells": (16,)},
        ... )
        >>> type(agent.planner.distance).__name__, agent.low_actor.module.relative_goal  # the reference's
        ('GoalDistance', True)
    """
    device = torch.device(device)
    obs_dim = env.observation_spec["observation"].shape[-1]
    goal_dim = env.observation_spec["achieved_goal"].shape[-1]
    indices = None if goal_indices is None else tuple(int(i) for i in goal_indices)
    action_spec = env.action_spec_unbatched.to(device)
    actor = LowLevelActor(obs_dim, goal_dim, action_spec, goal_indices=indices, **(low_actor or {})).to(device)
    exploration_module = GaussianUniformExplorationModule(action_spec, **(exploration or {})).to(device)

    def critic() -> GoalConditionedCritic:
        return GoalConditionedCritic(
            obs_dim,
            goal_dim,
            action_spec,
            goal_indices=indices,
            goal_key="goal",
            **(low_critic or {}),
        ).to(device)

    sqgc = SQGCLoss(actor, critic(), critic(), **(sqgc_loss or {}))
    high = HighLevelPolicy(obs_dim, goal_dim, goal_indices=indices, **high_policy).to(device)
    high_critic_module = GoalConditionedCritic(
        obs_dim,
        goal_dim,
        action_low=high_policy["subgoal_low"],
        action_high=high_policy["subgoal_high"],
        goal_indices=indices,
        goal_key="desired_goal",
        action_key="subgoal",
        **(high_critic or {}),
    ).to(device)
    high_loss_module = HighLevelLoss(high.actor, high_critic_module, **(high_loss or {}))
    # a capturable planner plans on static storage across rebuilds: no recompilation, CUDA-graph safe
    landmark_graph = LandmarkGraph(**{"fixed_size": capturable_planner, **(graph or {})})
    if distance is None or isinstance(distance, Mapping):
        distance = GoalDistance.from_loss(sqgc, **(distance or {}))
    graph_planner = GraphPlanner(
        landmark_graph, distance, goal_dim, capturable=capturable_planner, **(planner or {})
    ).to(device)
    if landmark_graph.fixed_size:
        landmark_graph.reserve(
            obs_dim, goal_dim, dtype=env.observation_spec["observation"].dtype, device=device
        )
    if high.selector is not None:  # critic-guided subgoals: the high-level critic as trained scores them
        high.selector.critic = high_loss_module.critic_network
        high.selector.critic_params = high_loss_module.critic_network_params
        high.selector.landmarks = functools.partial(_landmark_goals, graph_planner)
    policy = TensorDictSequential(high, graph_planner, TensorDictSequential(actor, exploration_module))
    return DHRLAgent(high, actor, exploration_module, sqgc, high_loss_module, graph_planner, policy)


def _landmark_goals(planner: GraphPlanner) -> tuple[torch.Tensor, torch.Tensor | None] | None:
    """The goals of the landmarks ``planner`` plans on and which rows are landmarks (``None``: all; a fixed-size
    graph's padding rows are not), for the high level's subgoal candidates; ``None`` without a graph."""
    tensors = planner.graph.planning_tensors(planner.capturable)
    return None if tensors is None else (tensors.goals, tensors.valid)


def observation_transforms(angle_features: Sequence[int] | None = None) -> list:
    """The observation transforms to append to every env the agent acts in (training, evaluation and
    diagnosis envs alike): :class:`~torchrl_dhrl.envs.transforms.AngleFeatures` of ``angle_features``
    (observation indices of continuous joint angles), if any.

    Examples:
        >>> observation_transforms(), [type(t).__name__ for t in observation_transforms([4, 6])]
        ([], ['AngleFeatures'])
    """
    return [AngleFeatures(angle_features)] if angle_features else []


def _built_in(env_name: str):
    """The spec of a built-in env (``None`` for a registered or a Gymnasium env, whose sizes are known once built)."""
    return ENVS.get(env_name) if isinstance(env_name, str) else None


def _goal_indices_fit(env_name, goal_indices) -> None:
    spec = _built_in(env_name)
    if spec is None or goal_indices is None:
        return
    goal_dim, obs_dim = spec.goal_dim, spec.obs_dim
    if len(goal_indices) != goal_dim or any(i >= obs_dim for i in goal_indices):
        raise ValueError(
            f"`goal_indices` must be null or {goal_dim} distinct indices in [0, {obs_dim}) (where {env_name}'s "
            f"{goal_dim}-D achieved goal sits in its {obs_dim}-D observation), got {list(goal_indices)!r}."
        )


def _angle_features_fit(env_name, angle_features, goal_indices) -> None:
    if angle_features is None:
        return
    spec = _built_in(env_name)
    outside = spec is not None and any(i >= spec.obs_dim for i in angle_features)
    if outside or set(angle_features) & set(goal_indices or ()):
        where = "" if spec is None else f" in [0, {spec.obs_dim})"
        raise ValueError(
            f"`angle_features` must be distinct observation indices{where} outside `goal_indices` ({env_name}'s "
            f"continuous joint angles, e.g. [4, 6] for Reacher3D), got {list(angle_features)!r}."
        )


def _right_flipped_needs_an_ant(env_name, right_flipped_after) -> None:
    if right_flipped_after is None:
        return
    env_id = gymnasium_id(env_name)
    if env_id is not None:
        try:
            if is_gymnasium_ant_maze(env_id):
                return
        except GoalEnvError:  # not registered: the env's construction says so
            return
    elif hasattr(getattr(_built_in(env_name), "agent", None), "upright_qpos"):
        return
    raise ValueError(
        f"`right_flipped_after` rights a flipped ant: it applies to the ant mazes only (the built-in ones and "
        f"gymnasium-robotics' AntMaze_*), not to {env_name}; leave it None (null)."
    )


def _reference_engine_needs_an_ant_maze(env_name, reference_engine) -> None:
    if reference_engine is not True:
        return
    if _built_in(env_name) is None:
        raise ValueError(
            f"`reference_engine` is an option of the built-in ant mazes, not of {env_name}; leave it False."
        )
    from torchrl_dhrl.envs.simulation import reference_engine_spec

    try:
        reference_engine_spec(env_name)
    except ValueError as err:
        raise ValueError(f"`reference_engine`: {err}") from err


def _step_threads_of_built_in_envs(env_name, step_threads) -> None:
    if step_threads != 1 and _built_in(env_name) is None:
        raise ValueError(f"`step_threads` is an option of the built-in envs, not of {env_name}; leave it at 1.")


@checked(
    _goal_indices_fit,
    _angle_features_fit,
    _right_flipped_needs_an_ant,
    _reference_engine_needs_an_ant_maze,
    _step_threads_of_built_in_envs,
    num_envs=integer(1),
    max_episode_steps=integer(1, optional=True),
    goal_indices=indices(optional=True),
    angle_features=indices(optional=True, non_empty=True),
    right_flipped_after=integer(1, optional=True, what="env steps upside down before the ant is righted"),
    reference_engine=flag(),
    step_threads=ArgumentCheck(
        lambda value: isinstance(value, int) and not isinstance(value, bool) and value >= 1,
        ">= 1 (an integer: the threads stepping the envs)",
    ),
)
def make_environment(
    env_name: str,
    device: torch.device | str = "cpu",
    *,
    num_envs: int = 1,
    seed: int = 0,
    eval: bool = False,  # noqa: A002
    max_episode_steps: int | None = None,
    goal_indices: Sequence[int] | None = None,
    angle_features: Sequence[int] | None = None,
    agent: DHRLAgent | None = None,
    goal_shifting: Mapping[str, Any] | None = None,
    right_flipped_after: int | None = None,
    reference_engine: bool = False,
    step_threads: int = 1,
    env_kwargs: Mapping[str, Any] | None = None,
) -> EnvBase:
    """A batched env of :func:`~torchrl_dhrl.envs.make_env` (``eval``: on the test goals), with the agent's primers.

    Without ``agent`` the env meets the goal-env contract or this raises: it is checked with
    :func:`~torchrl_dhrl.envs.check_goal_env` (with ``goal_indices``; a short rollout that draws no random
    numbers), so any env registered with :func:`~torchrl_dhrl.envs.register_env` that passes can be trained;
    the env is returned with the :func:`observation_transforms` only (to read the specs before the agent
    exists). With ``agent``, the subgoal scheduler's and the planner's primers are appended, and
    ``goal_shifting`` (the keyword arguments of :class:`~torchrl_dhrl.planner.FrontierGoalShifting`:
    ``noise``, ``weighting``, ``trigger``) adds frontier-based goal shifting at every reset.
    ``right_flipped_after``, ``reference_engine`` (ant mazes), ``step_threads`` (built-in envs) and ``env_kwargs``
    (``gymnasium:<id>``) are passed to :func:`~torchrl_dhrl.envs.make_env`.

    The arguments are checked before anything is built (:func:`~torchrl_dhrl.checks.checked`; the recipe runs
    the same checks on its configuration with :func:`~torchrl_dhrl.checks.check_arguments`): sizes and types, and,
    for a built-in env, ``goal_indices`` and ``angle_features`` within its observation, ``right_flipped_after``
    and ``reference_engine`` for the ant mazes only, ``step_threads`` for the built-in envs only.

    Raises:
        ValueError: naming the argument, for a value it does not accept.
        GoalEnvError: when the env does not meet the contract.

    Examples:
        >>> env = make_environment("PointMaze", num_envs=2, seed=1, max_episode_steps=50)
        >>> env.batch_size, env.observation_spec["observation"].shape
        (torch.Size([2]), torch.Size([2, 6]))
    """
    env = make_env(
        env_name,
        num_envs=num_envs,
        seed=seed,
        device=device,
        eval=eval,
        max_episode_steps=max_episode_steps,
        right_flipped_after=right_flipped_after,
        reference_engine=reference_engine,
        step_threads=step_threads,
        env_kwargs=env_kwargs,
    )
    features = observation_transforms(angle_features)
    steps = env.max_episode_steps  # the env's own attribute, which a TransformedEnv it is wrapped in would hide
    if agent is None:  # the whole contract once, with a rollout that draws no random numbers
        built_in = get_env_factory(env_name) is None and gymnasium_id(env_name) is None
        check_goal_env(
            env,
            goal_indices=None if goal_indices is None else tuple(goal_indices),
            # an env of its own: a whole episode and one step more, so that its truncation step is checked too
            steps=2 if built_in else steps + 1,
        )
        if not features:
            return env
        out = TransformedEnv(env, Compose(*features))
    else:
        transforms = [*features, agent.high_policy.make_primer(), agent.planner.make_primer()]
        if goal_shifting is not None:
            transforms.append(GoalShiftOnReset(FrontierGoalShifting(agent.planner, **goal_shifting)))
        out = TransformedEnv(env, Compose(*transforms))
    out.max_episode_steps = steps
    return out


def _check_policy_capture(agent: DHRLAgent, device: torch.device | None, what: str) -> None:
    """Refuses ``cudagraph_policy`` where the captured graph could not replay the policy: a planner that is not
    capturable, ``what`` off CUDA, or planning tensors that a rebuild would reallocate."""
    if not agent.planner.capturable:
        raise ValueError(
            "`cudagraph_policy` needs a capturable planner (make_agent(..., capturable_planner=True), or "
            "agent.planner.capturable = True): the planner's replanning branch cannot be captured."
        )
    tensors = agent.planner.graph.planning_tensors(capturable=True)
    if tensors is None or tensors.valid is None:
        raise ValueError(
            "`cudagraph_policy` needs the planner's graph to plan on fixed-size tensors that exist before the "
            "capture (LandmarkGraph(fixed_size=True) and .reserve(obs_dim, goal_dim), as make_agent(..., "
            "capturable_planner=True) does): a graph captured on the graph's own buffers would keep reading the "
            "landmarks of the capture."
        )
    if device is None or torch.device(device).type != "cuda":
        raise ValueError(
            f"`cudagraph_policy` captures the acting policy as a CUDA graph: it needs {what} on a CUDA device, "
            f"got {device}."
        )


def make_collector(
    env: EnvBase,
    agent: DHRLAgent,
    episode_length: int,
    *,
    compile_policy: bool | Mapping[str, Any] = False,
    cudagraph_policy: bool | Mapping[str, Any] = False,
) -> Collector:
    """A :class:`~torchrl.collectors.Collector` yielding one whole episode per env and batch.

    Episodes only truncate, so every env ends its episode at the last step of a batch and the
    collector's automatic reset starts the next one: batches are ``[num_envs, episode_length]``.
    Batches are stored on the env's device, trajectory ids included, so that they can be written into
    replay buffers on that device (also into a storage restored from a checkpoint, which has no device).
    The policy runs on that device too (``device=env.device``): the collector's step tensordict then
    keeps a device and the env does not cast it, key by key, on every step (a collector that infers the
    policy's device leaves it ``None``; 0.2 ms of a 1.46 ms warm-up env step on PointMaze, same data).

    ``compile_policy`` (``True`` or the keyword arguments of :func:`torchrl._utils.compile_with_warmup`)
    is the collector's own: the acting policy (high level, planner, low level) is compiled with
    ``torch.compile`` after a warm-up call. It needs a capturable planner (``make_agent(...,
    capturable_planner=True)``), whose policy compiles as one graph; the same actions up to float
    round-off (and, in a compiled graph, other random draws for the exploration noise).

    ``cudagraph_policy`` (``True`` or the keyword arguments of :class:`tensordict.nn.CudaGraphModule`, e.g.
    ``{"warmup": 3}``) is the collector's too: after its warm-up calls the acting policy is captured whole as one
    CUDA graph and replayed at every step (the step's inputs copied in, its outputs copied out: no Python or
    kernel launches of the policy's own). It needs the env on a CUDA device and a capturable planner on a
    reserved ``fixed_size`` graph (what ``make_agent(..., capturable_planner=True)`` builds): the graph is
    captured before the first landmarks exist and reads every later rebuild in place, and in a captured call
    the planner plans every env (static control flow). The same plans and actions up to float round-off; the
    exploration noise is drawn inside the graph (other draws than eager). Combined with ``compile_policy``,
    the compiled policy is captured.

    Raises:
        ValueError: ``compile_policy`` or ``cudagraph_policy`` with a planner that is not ``capturable``;
            ``cudagraph_policy`` with the env off CUDA or a graph without reserved fixed-size planning tensors.
    """
    if compile_policy not in (False, None) and not agent.planner.capturable:
        raise ValueError(
            "`compile_policy` needs a capturable planner (make_agent(..., capturable_planner=True), or "
            "agent.planner.capturable = True): the planner's replanning branch would split the compiled "
            "policy into pieces at every step."
        )
    if cudagraph_policy not in (False, None):
        _check_policy_capture(agent, env.device, "the env (and the policy)")
    num_envs = env.batch_size.numel()
    # The planner and the subgoal scheduler carry their state with TensorDictPrimers (already on the env);
    # they do not need the InitTracker the collector would add for recurrent-looking modules.
    return Collector(
        env,
        agent.policy,
        frames_per_batch=num_envs * episode_length,
        total_frames=-1,
        device=env.device,
        auto_register_policy_transforms=False,
        compile_policy=None if compile_policy is False else compile_policy,
        cudagraph_policy=None if cudagraph_policy is False else cudagraph_policy,
    )


def make_eval_policy(
    agent: DHRLAgent, *, cudagraph_policy: bool | Mapping[str, Any] = False
) -> TensorDictModuleBase:
    """The policy of the test episodes: ``agent.policy``, or with ``cudagraph_policy`` (``True`` or the keyword
    arguments of :class:`tensordict.nn.CudaGraphModule`) that policy captured whole as a CUDA graph of its own.

    Evaluation acts with exploration off, which the policy's modules read when they run: a graph captured in the
    collector (exploration on) cannot serve it, so the test episodes get their own, captured in the first
    evaluation (its second step, after one eager warm-up call by default) and replayed in every later one. Build it
    once per run and pass it to :func:`evaluate_epoch` (``policy=``); it needs what ``make_collector``'s
    ``cudagraph_policy`` needs (a capturable planner on a reserved fixed-size graph, the policy on CUDA), so that
    the graph rebuilds between evaluations are read in place.

    Raises:
        ValueError: ``cudagraph_policy`` with a planner that is not capturable, parameters off CUDA or a graph
            without reserved fixed-size planning tensors.

    Examples:
        >>> from torchrl_dhrl.factory import make_agent, make_environment
        >>> env = make_environment("PointMaze", max_episode_steps=20)
        >>> agent = make_agent(env, goal_indices=[0, 1], high_policy={"subgoal_low": [-2.0, -2.0],
        ...     "subgoal_high": [10.0, 10.0], "interval": 5, "num_cells": (16,)})
        >>> make_eval_policy(agent) is agent.policy
        True
    """
    if cudagraph_policy in (False, None):
        return agent.policy
    device = next(agent.low_actor.parameters()).device
    _check_policy_capture(agent, device, "the policy")
    kwargs = {} if cudagraph_policy is True else dict(cudagraph_policy)
    return CudaGraphModule(agent.policy, **{"device": device, **kwargs})


def _batch_within_buffer(batch_size, buffer_size) -> None:
    if batch_size > buffer_size:
        raise ValueError(
            f"`batch_size` ({batch_size}) must be <= `buffer_size` ({buffer_size}), the transitions it samples from."
        )


#: The checks of both levels' buffer arguments (:func:`~torchrl_dhrl.checks.checked`).
_BUFFER_CHECKS = {
    "buffer_size": integer(1),
    "batch_size": integer(1),
    "reward_threshold": number(0.0, low_open=True),
    "her_ratio": number(0.0, 1.0),
    "her_window": integer(1, optional=True),
}


@checked(_batch_within_buffer, **_BUFFER_CHECKS)
def make_low_level_buffer(
    *,
    buffer_size: int,
    batch_size: int,
    reward_threshold: float,
    her_ratio: float = 0.8,
    her_window: int | None = 150,
    device: torch.device | str = "cpu",
) -> RelabelReplayBuffer:
    """The low-level buffer: a time-major ``[T, num_envs]`` :class:`~torchrl_dhrl.data.CompactLazyTensorStorage`
    (extended with collector batches ``[num_envs, T]``) of ``buffer_size`` transitions, whatever ``num_envs``,
    whose :meth:`~torchrl_dhrl.data.RelabelReplayBuffer.sample` relabels future goals
    (:class:`~torchrl_dhrl.data.FutureGoalRelabel`: the waypoint is replaced for ``her_ratio`` of the policy
    critics' batch and all of the graph critics', within ``her_window`` steps; sparse rewards within
    ``reward_threshold``).

    Examples:
        >>> rb = make_low_level_buffer(buffer_size=1000, batch_size=32, reward_threshold=0.5)
        >>> rb.storage.ndim, rb.batch_size
        (2, 32)
    """
    reward = SparseGoalReward(reward_threshold)
    # ``max_size`` counts transitions (elements of the ``[T, num_envs]`` storage), not time steps
    return RelabelReplayBuffer(
        storage=CompactLazyTensorStorage(buffer_size, ndim=2, device=device),
        relabel=[
            FutureGoalRelabel(reward, her_ratio=(her_ratio, 1.0), window=her_window, goal_key="waypoint")
        ],
        batch_size=batch_size,
    )


@checked(
    _batch_within_buffer,
    **_BUFFER_CHECKS,
    subgoal_test_ratio=number(0.0, 1.0),
    subgoal_test_threshold=number(0.0, low_open=True),
    subgoal_miss_penalty=number(0.0),
    gradual_penalty=number(0.0, optional=True),
    far_from_graph_threshold=number(0.0, low_open=True),
)
def make_high_level_buffer(
    *,
    buffer_size: int,
    batch_size: int,
    reward_threshold: float,
    her_ratio: float = 1.0,
    her_window: int | None = 15,
    subgoal_test_ratio: float = 0.2,
    subgoal_test_threshold: float = 1.0,
    subgoal_miss_penalty: float = 1.3,
    gradual_penalty: float | None = 5.0,
    planner: GraphPlanner | None = None,
    far_from_graph_threshold: float = 90.0,
    device: torch.device | str = "cpu",
) -> RelabelReplayBuffer:
    """The high-level buffer: a :class:`~torchrl_dhrl.data.HighLevelTransitionBuilder` turns low-level batches
    into one transition per subgoal at ``extend``; :meth:`~torchrl_dhrl.data.RelabelReplayBuffer.sample`
    relabels future goals (``her_ratio``, ``her_window`` high-level steps) and runs
    :class:`~torchrl_dhrl.data.HindsightSubgoalRelabel` (HAC action relabelling, subgoal testing and, with
    ``gradual_penalty`` and a ``planner``, the gradual penalty of subgoals farther than
    ``far_from_graph_threshold`` from the planner's graph; without a ``planner`` no subgoal is penalised
    as far from the graph).

    Examples:
        >>> rb = make_high_level_buffer(buffer_size=1000, batch_size=32, reward_threshold=0.5)
        >>> type(rb.transform[0]).__name__, rb.batch_size
        ('HighLevelTransitionBuilder', 32)
    """
    reward = SparseGoalReward(reward_threshold)
    distance_from_graph = (
        # exact relative to the threshold, the only thing the penalty reads, at a fraction of the cost
        functools.partial(planner.distance_from_graph, at_most=far_from_graph_threshold)
        if gradual_penalty is not None and planner is not None
        else None
    )
    relabel = [
        FutureGoalRelabel(
            reward,
            her_ratio=her_ratio,
            window=her_window,
            out_keys=["desired_goal"],
            reward_keys=None,
            traj_key="episode_id",
            step_count_key="segment_index",
        ),
        HindsightSubgoalRelabel(
            distance_from_graph,
            reward,
            subgoal_test_ratio=subgoal_test_ratio,
            subgoal_test_threshold=subgoal_test_threshold,
            subgoal_miss_penalty=subgoal_miss_penalty,
            gradual_penalty=gradual_penalty,
            far_from_graph_threshold=far_from_graph_threshold,
        ),
    ]
    return RelabelReplayBuffer(
        storage=CompactLazyTensorStorage(buffer_size, device=device),
        transform=HighLevelTransitionBuilder(reward_fn=reward),
        relabel=relabel,
        batch_size=batch_size,
    )


def make_updater(
    loss: LossModule,
    replay_buffer: ReplayBuffer,
    *,
    optimizers: Mapping[str, Any] | None = None,
    **kwargs,
) -> LossUpdater:
    """A :class:`~torchrl_dhrl.training.LossUpdater` of ``loss`` on ``replay_buffer``'s samples, with the two Adam
    optimisers of :func:`~torchrl_dhrl.objectives.make_optimizers`.

    Keyword Args:
        optimizers (mapping, optional): :func:`~torchrl_dhrl.objectives.make_optimizers`'s arguments (``actor_lr``,
            ``critic_lr``, ``fused``); its defaults are the reference's learning rates (1e-4 and 1e-3).
        **kwargs: those of :class:`~torchrl_dhrl.training.LossUpdater` (``polyak``, ``actor_update_interval``,
            ``cudagraphs``, ``autocast_dtype``, ...); its defaults are the reference's.

    Examples:
        >>> import torchrl_dhrl as dhrl
        >>> env = dhrl.make_environment("PointMaze", max_episode_steps=20)
        >>> agent = dhrl.make_agent(env, goal_indices=[0, 1], high_policy={"subgoal_low": [-2.0, -2.0],
        ...     "subgoal_high": [10.0, 10.0], "interval": 5, "num_cells": (16,)})
        >>> rb = dhrl.make_low_level_buffer(buffer_size=1000, batch_size=32, reward_threshold=0.5)
        >>> updater = make_updater(agent.sqgc_loss, rb, optimizers={"critic_lr": 3e-4})
        >>> updater.optimizers["critic"].param_groups[0]["lr"]
        0.0003
    """
    return LossUpdater(loss, replay_buffer, make_optimizers(loss, **(optimizers or {})), **kwargs)
