"""Diagnostics for runs that do not learn: can the low level reach nearby goals on its own?"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torch import Tensor
from torchrl.envs import Compose, EnvBase, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_dhrl.envs import gymnasium_id, make_env
from torchrl_dhrl.envs.geometry import obstacle_boxes
from torchrl_dhrl.envs.transforms import AngleFeatures
from torchrl_dhrl.planner import LineOfSightDistance
from torchrl_dhrl.training import goal_as_waypoint

__all__ = [
    "ReachResult",
    "low_level_reach_test",
    "reach_offsets",
    "reach_test",
    "summarize_reach",
    "visible_offsets",
]


class ReachResult(NamedTuple):
    """Outcome of :func:`low_level_reach_test`, one entry per env (goal).

    Attributes:
        radius (Tensor): the offset radius each goal was drawn at (goal units).
        start_distance (Tensor): distance between the achieved goal after the reset and the goal.
        reached (Tensor): bool, within ``reach_radius`` at some step.
        steps_to_reach (Tensor): first step within ``reach_radius`` (1-based); ``max_steps + 1`` if never.
        min_distance (Tensor): closest approach over the episode.
        final_distance (Tensor): distance after the last step.
        offset (Tensor): ``[N, goal_dim]``, each goal's offset from its start.
    """

    radius: Tensor
    start_distance: Tensor
    reached: Tensor
    steps_to_reach: Tensor
    min_distance: Tensor
    final_distance: Tensor
    offset: Tensor


def reach_offsets(goal_dim: int, radii: Sequence[float], num_directions: int, *, seed: int = 0) -> Tensor:
    """``[len(radii) * num_directions, goal_dim]`` offsets: ``num_directions`` unit directions per radius.

    In 2-D the directions are evenly spaced angles; in other dimensions they are seeded random unit
    vectors (the same for every radius).

    Examples:
        >>> reach_offsets(2, [1.0, 2.0], 4).round(decimals=3).tolist()[:4]
        [[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [-0.0, -1.0]]
    """
    if num_directions < 1 or not radii or min(radii) <= 0:
        raise ValueError(f"Need num_directions >= 1 and positive radii, got {num_directions}, {list(radii)}.")
    if goal_dim == 2:
        angle = torch.arange(num_directions, dtype=torch.float64) * (2 * math.pi / num_directions)
        directions = torch.stack([angle.cos(), angle.sin()], -1)
    else:
        generator = torch.Generator().manual_seed(seed)
        directions = torch.randn(num_directions, goal_dim, generator=generator, dtype=torch.float64)
        directions = directions / directions.norm(dim=-1, keepdim=True)
    radius = torch.as_tensor(list(radii), dtype=torch.float64)
    return (radius[:, None, None] * directions).reshape(-1, goal_dim).float()


def visible_offsets(start: Tensor, offsets: Tensor, obstacles: LineOfSightDistance) -> Tensor:
    """The ``offsets`` whose straight segment ``start -> start + offset`` no obstacle of ``obstacles`` blocks.

    Examples:
        >>> import torch
        >>> wall = LineOfSightDistance(1.0, boxes=[[[1.0, -5.0], [2.0, 5.0]]], goal_indices=[0, 1])
        >>> visible_offsets(torch.zeros(2), reach_offsets(2, [3.0], 4), wall).round().tolist()
        [[0.0, 3.0], [-3.0, 0.0], [-0.0, -3.0]]
    """
    start = start.to(offsets.dtype).expand_as(offsets)
    return offsets[~obstacles.crosses_obstacle(start, start + offsets)]


@torch.no_grad()
def low_level_reach_test(
    env: EnvBase,
    actor: TensorDictModuleBase,
    offsets: Tensor,
    *,
    max_steps: int,
    reach_radius: float,
    start: Tensor | None = None,
) -> ReachResult:
    """Runs the low-level actor alone (no high level, no graph) towards ``start + offset`` goals.

    Separates "the low level cannot move yet" from "the graph or the high level is wrong" when a run
    does not learn: env ``i`` of ``env`` (a bare goal env, e.g. ``make_env(name, num_envs=N)``) is
    reset, given the goal ``achieved goal + offsets[i]`` as its waypoint for the whole episode, and
    stepped ``max_steps`` times with exploration off. Use :func:`visible_offsets` first to keep only
    goals reachable in a straight line.

    Args:
        env (EnvBase): a goal env of batch size ``[N]`` honouring ``"desired_goal"`` at reset.
        actor (TensorDictModuleBase): reads ``(observation, waypoint)`` in the order of its ``in_keys``
            and writes the action (e.g. :class:`~torchrl_dhrl.modules.LowLevelActor`).
        offsets (Tensor): ``[N, goal_dim]`` goal offsets from the reset's achieved goal.

    Keyword Args:
        max_steps (int): steps per episode.
        reach_radius (float): the low level's success radius (the planner's waypoint radius).
        start (Tensor, optional): ``[goal_dim]``, where every agent starts (the env's ``"start"`` reset entry,
            mazes only); the goals are ``start + offsets``. By default the env's own start, and the goals are
            the offsets from the achieved goal after a first reset.

    Examples:
        >>> import torch
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl_dhrl.envs import gymnasium_id, make_env
        >>> offsets = reach_offsets(2, [1.0], 4)
        >>> env = make_env("PointMaze", num_envs=4, seed=0)
        >>> still = TensorDictModule(lambda o, w: torch.zeros(*o.shape[:-1], 2),
        ...                          in_keys=["observation", "waypoint"], out_keys=["action"])
        >>> low_level_reach_test(env, still, offsets, max_steps=5, reach_radius=0.5).reached.tolist()
        [False, False, False, False]
    """
    if tuple(env.batch_size) != (offsets.shape[0],):
        raise ValueError(
            f"The env must have batch size [{offsets.shape[0]}] (one env per offset), got {tuple(env.batch_size)}."
        )
    if max_steps < 1 or not reach_radius > 0:
        raise ValueError(f"Need max_steps >= 1 and reach_radius > 0, got {max_steps}, {reach_radius}.")
    if start is None:
        td = env.reset()
        origin = td["achieved_goal"]
    else:
        origin = start.to(env.device, torch.float32).expand(*env.batch_size, -1)
        td = TensorDict(start=origin, batch_size=env.batch_size, device=env.device)
    offsets = offsets.to(origin.device, origin.dtype)
    td = env.reset(td.set("desired_goal", origin + offsets))
    goal = td["desired_goal"]
    policy = goal_as_waypoint(actor)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = env.rollout(max_steps, policy, tensordict=td, auto_reset=False, break_when_any_done=False)
    distance = (rollout["next", "achieved_goal"] - goal.unsqueeze(-2)).norm(dim=-1)  # [N, T]
    within = distance <= reach_radius
    reached = within.any(-1)
    never = torch.full_like(reached, max_steps + 1, dtype=torch.long)
    first = torch.where(reached, within.float().argmax(-1) + 1, never)
    return ReachResult(
        radius=offsets.norm(dim=-1).cpu(),
        start_distance=(td["achieved_goal"] - goal).norm(dim=-1).cpu(),
        reached=reached.cpu(),
        steps_to_reach=first.cpu(),
        min_distance=distance.amin(-1).cpu(),
        final_distance=distance[..., -1].cpu(),
        offset=offsets.cpu(),
    )


def summarize_reach(result: ReachResult, *, per_offset: bool = False) -> list[dict]:
    """One row per offset radius: goals, reach rate, median steps to reach (reached goals), mean final distance.

    ``per_offset=True``: one row per distinct offset instead (its ``"offset"`` added), e.g. to tell the
    direction through a passage from the others at the same radius.
    """
    rows = []
    if per_offset:
        keys, group = torch.unique(result.offset.round(decimals=3), dim=0, return_inverse=True)
    else:
        keys, group = torch.unique(result.radius.round(decimals=3), return_inverse=True)
    for index, key in enumerate(keys):
        mask = group == index
        reached = result.reached[mask]
        steps = result.steps_to_reach[mask][reached]
        rows.append(
            {
                **({"offset": key.tolist()} if per_offset else {}),
                "radius": result.radius[mask][0].item(),
                "goals": int(mask.sum()),
                "reach_rate": reached.float().mean().item(),
                "median_steps": steps.float().median().item() if steps.numel() else float("nan"),
                "mean_min_distance": result.min_distance[mask].mean().item(),
                "mean_final_distance": result.final_distance[mask].mean().item(),
            }
        )
    return rows


def reach_test(
    low_actor: TensorDictModuleBase,
    env_name: str,
    *,
    radii: Sequence[float],
    max_steps: int,
    reach_radius: float,
    num_directions: int = 16,
    oracle_margin: float = 0.5,
    angle_features: Sequence[int] | None = None,
    device: str | torch.device = "cpu",
    seed: int = 0,
    start: Sequence[float] | None = None,
    repeats: int = 1,
    per_offset: bool = False,
    env_kwargs: Mapping[str, Any] | None = None,
) -> list[dict]:
    """:func:`low_level_reach_test` of a low-level actor around ``env_name``'s start, summarised per radius.

    ``num_directions`` goals per radius around the start of a fresh env (or around ``start``, a position in
    a maze); those blocked by the maze walls (or the UR3 boards, inflated by ``oracle_margin``) or outside the
    env's goal box are dropped, and each is tried ``repeats`` times (each try with its own reset noise). The
    envs feed the actor the observation it was trained on (``angle_features``, see
    :class:`~torchrl_dhrl.envs.transforms.AngleFeatures`).

    A start below a narrow passage with a radius across it asks whether the low level can pass it (e.g.
    AntMazeBottleneck's gap: ``start=(16, 4.5)``, ``radii=[6]``: the goal straight up lies past the gap).

    A ``"gymnasium:<id>"`` env is built with ``env_kwargs`` (the arguments of
    :class:`~torchrl_dhrl.envs.GymnasiumGoalEnv`, e.g. a run's test reset options): a gymnasium-robotics maze
    starts at the centre of its resets' one ``reset_cell`` (``start`` picks the cell holding that point instead)
    and its walls are those of its map; another env starts where its reset puts it.

    Returns:
        one row per radius, or per offset with ``per_offset=True`` (:func:`summarize_reach`).

    Raises:
        ValueError: when no goal lies inside the goal box; on a ``start`` outside the mazes' free space or for
            an arm; for a gymnasium-robotics maze whose resets start in more than one cell; on ``repeats < 1``.

    Examples:
        >>> from torchrl_dhrl.modules import LowLevelActor
        >>> actor = LowLevelActor(6, 2, action_max=1.0, action_dim=2, goal_indices=[0, 1], num_cells=(8,))
        >>> rows = reach_test(actor, "PointMaze", radii=[0.5, 1.0], max_steps=5, reach_radius=0.5, num_directions=4)
        >>> [row["radius"] for row in rows]
        [0.5, 1.0]
    """
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}.")
    device = torch.device(device)
    reset, gymnasium = None, gymnasium_id(env_name) is not None
    if gymnasium:
        env_kwargs, start, boxes = _gymnasium_start(env_name, env_kwargs, start, seed)
    else:
        probe = make_env(env_name, num_envs=1, seed=seed, device=device)
        if start is not None:  # validated by the env (free space, mazes only) before any rollout
            reset = TensorDict(start=torch.tensor([list(start)], dtype=torch.float32), batch_size=[1]).to(device)
        achieved = probe.reset(reset)["achieved_goal"][0]
        start = achieved if reset is None else reset["start"][0]
        boxes = obstacle_boxes(env_name)
    offsets = reach_offsets(start.shape[-1], radii, num_directions, seed=seed)
    if boxes is not None:
        walls = LineOfSightDistance(
            1.0, boxes=boxes, margin=oracle_margin, goal_indices=range(start.shape[-1])
        )
        offsets = visible_offsets(start.cpu(), offsets, walls)
    if not gymnasium:  # goals stay inside the env's goal box (the Reacher3D fingertip starts 2 cm from its edge)
        spec = probe.observation_spec["desired_goal"].space
        low, high = spec.low.reshape(-1).cpu(), spec.high.reshape(-1).cpu()
        goals = start.cpu() + offsets
        offsets = offsets[((goals >= low) & (goals <= high)).all(-1)]
    if offsets.shape[0] == 0:
        raise ValueError(f"No reach-test goal around the start {start.tolist()} lies inside the goal box.")
    offsets = offsets.repeat(repeats, 1)
    env = make_env(env_name, num_envs=offsets.shape[0], seed=seed, device=device, env_kwargs=env_kwargs)
    features = [AngleFeatures(angle_features)] if angle_features else []  # the observation the actor was trained on
    if features:
        env = TransformedEnv(env, Compose(*features))
    result = low_level_reach_test(
        env,
        low_actor,
        offsets,
        max_steps=max_steps,
        reach_radius=reach_radius,
        start=None if reset is None else start,
    )
    return summarize_reach(result, per_offset=per_offset)


def _gymnasium_start(
    env_name: str, env_kwargs: Mapping[str, Any] | None, start: Sequence[float] | None, seed: int
) -> tuple[dict[str, Any], Tensor, Tensor | None]:
    """A ``"gymnasium:<id>"`` env's reach-test start: the env arguments (a ``start`` turned into the ``reset_cell``
    holding it), the start (a maze's start cell centre, else the achieved goal after a reset) and the maze's wall
    boxes (``None`` for an env without a gymnasium-robotics maze)."""
    env_kwargs = dict(env_kwargs or {})
    probe = make_env(env_name, num_envs=1, seed=seed, env_kwargs=env_kwargs)
    if start is not None:  # a gymnasium-robotics maze starts its agent at a cell's centre
        env_kwargs["reset_options"] = {"reset_cell": list(probe.reset_cell_at(start))}
        probe = make_env(env_name, num_envs=1, seed=seed, env_kwargs=env_kwargs)
    maze = probe.maze_geometry()
    if maze is None:
        return env_kwargs, probe.reset()["achieved_goal"][0], None
    if maze.start is None:
        raise ValueError(
            f"{env_name}'s resets start anywhere (reset options {env_kwargs.get('reset_options')}): the reach test "
            "needs one start, given by reset options with one `reset_cell` (a run's `gymnasium.eval_reset_options`) "
            "or by `start`."
        )
    return env_kwargs, torch.as_tensor(maze.start, dtype=torch.float32), maze.boxes
