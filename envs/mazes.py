"""The table of the five DHRL mazes: every fact of each environment in one :class:`MazeSpec`."""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
from dm_control import mjcf

from .agents import AntAgent, PointAgent
from .arena import (
    _OVERVIEW_FOVY,
    OVERVIEW_CAMERA,
    add_boxes,
    add_camera,
    add_floor,
    add_goal_marker,
    new_scene,
)
from .goals import BoxGoalSampler, FixedGoalSampler, FreeCellGoalSampler, GoalSampler
from .layouts import BOTTLENECK_WALL_FRICTION, COMPLEX_MAZE, U_MAZE, MazeLayout, bottleneck_walls
from .task import TaskSpec, lookup_spec

__all__ = ["MazeSpec", "MAZES", "MAZE_NAMES", "get_maze_spec", "build_maze_mjcf", "compile_maze_model"]


@dataclass(frozen=True)
class MazeSpec(TaskSpec):
    """Everything that defines one maze environment (a :class:`~torchrl_dhrl.envs.TaskSpec`).

    The observation is ``qpos ++ qvel`` of the agent and the achieved goal its (x, y), ``qpos[:2]``.

    Args:
        name (str): the environment name (e.g. ``"AntMaze"``); the Gymnasium id is ``dhrl/<name>-v0``.
        layout (MazeLayout): grid, scale and walls.
        agent (AntAgent or PointAgent): the agent, with its timestep, frame skip and reset noise.
        episode_length (int): env steps per episode (time limit, truncation only).
        success_threshold (float): evaluation success radius, measured on the final state.
        train_goals (GoalSampler): goal distribution of training episodes.
        test_goals (tuple of (x, y)): the fixed evaluation goals; one is drawn per episode.
        reward_threshold (float): the sparse reward is ``0`` within this distance of the goal, else ``-1``.
            Defaults to ``0.5``.
        start_position_noise (bool): whether the reset noise moves the start position (``qpos[:2]``); ``False``
            puts the agent exactly at its start after drawing the same noise (AntMazeBottleneck, as the
            reference's ``reset_model``). Defaults to ``True``.

    Examples:
        >>> from torchrl_dhrl.envs import get_maze_spec
        >>> spec = get_maze_spec("AntMaze")
        >>> spec.layout.scale, spec.episode_length, spec.success_threshold, spec.test_goals
        (8.0, 600, 5.0, ((0.0, 16.0),))
        >>> spec.gym_id
        'dhrl/AntMaze-v0'
    """

    name: str
    layout: MazeLayout
    agent: AntAgent | PointAgent
    episode_length: int
    success_threshold: float
    train_goals: GoalSampler
    test_goals: tuple[tuple[float, float], ...]
    reward_threshold: float = 0.5
    start_position_noise: bool = True

    @property
    def test_goal_sampler(self) -> FixedGoalSampler:
        """Sampler over :attr:`test_goals` (uniform choice of one per episode)."""
        return FixedGoalSampler(self.test_goals)

    @property
    def goal_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)`` of the goal space: the arena inside the outer walls."""
        return self.layout.bounds

    @property
    def reference_goal(self) -> np.ndarray:
        """The first test goal."""
        return np.asarray(self.test_goals[0], dtype=np.float64)

    @property
    def obs_dim(self) -> int:
        """Size of the observation (``qpos ++ qvel``: 29 for the ant, 6 for the point)."""
        return self.agent.obs_dim

    def build_mjcf(self):
        """The maze scene, see :func:`~torchrl_dhrl.envs.build_maze_mjcf`."""
        return build_maze_mjcf(self)


def _u_maze_train_goals(scale: float) -> BoxGoalSampler:
    """Uniform in the U maze's arena, rejecting the inner wall block ``x < 1.5 s`` and ``s/2 < y < 1.5 s``."""
    half = scale / 2
    return BoxGoalSampler(
        low=(-half, -half),
        high=(5 * half, 5 * half),
        excluded=((-np.inf, 3 * half, half, 3 * half),),
    )


def _make_mazes() -> dict[str, MazeSpec]:
    ant = AntAgent()
    small = MazeLayout(U_MAZE, scale=4.0)
    large = MazeLayout(U_MAZE, scale=8.0)
    complex_layout = MazeLayout(COMPLEX_MAZE, scale=8.0)
    specs = [
        MazeSpec(
            name="PointMaze",
            layout=small,
            agent=PointAgent(),
            episode_length=600,
            success_threshold=2.5,
            train_goals=_u_maze_train_goals(4.0),
            test_goals=((0.0, 8.0),),
        ),
        MazeSpec(
            name="AntMazeSmall",
            layout=small,
            agent=ant,
            episode_length=600,
            success_threshold=2.5,
            train_goals=_u_maze_train_goals(4.0),
            test_goals=((0.0, 8.0),),
        ),
        MazeSpec(
            name="AntMaze",
            layout=large,
            agent=ant,
            episode_length=600,
            success_threshold=5.0,
            train_goals=_u_maze_train_goals(8.0),
            test_goals=((0.0, 16.0),),
        ),
        MazeSpec(
            name="AntMazeBottleneck",
            # As the reference: all 20 walls with the thin walls' friction, the start exactly at (0, 0).
            layout=MazeLayout(
                U_MAZE,
                scale=8.0,
                extra_walls=bottleneck_walls(),
                wall_friction=BOTTLENECK_WALL_FRICTION,
            ),
            agent=ant,
            episode_length=600,
            success_threshold=5.0,
            # As the reference: the thin walls are not excluded from the train goals.
            train_goals=_u_maze_train_goals(8.0),
            test_goals=((0.0, 16.0),),
            start_position_noise=False,
        ),
        MazeSpec(
            name="AntMazeComplex",
            layout=complex_layout,
            agent=ant,
            episode_length=2000,
            success_threshold=5.0,
            train_goals=FreeCellGoalSampler(complex_layout, low=(-4.0, -4.0), high=(52.0, 52.0)),
            test_goals=((40.0, 8.0), (16.0, 48.0), (40.0, 48.0), (16.0, 32.0)),
        ),
    ]
    return {spec.name: spec for spec in specs}


#: Every maze by name.
MAZES: dict[str, MazeSpec] = _make_mazes()
#: The valid maze names, in the paper's order.
MAZE_NAMES: tuple[str, ...] = tuple(MAZES)


def get_maze_spec(maze: str | MazeSpec) -> MazeSpec:
    """Returns the :class:`MazeSpec` of ``maze``, a name (``"AntMaze"`` or ``"dhrl/AntMaze-v0"``) or a spec.

    Raises:
        ValueError: for an unknown name (the message lists the valid ones).
        TypeError: for anything else than a string or a :class:`MazeSpec`.

    Examples:
        >>> from torchrl_dhrl.envs import get_maze_spec
        >>> get_maze_spec("dhrl/PointMaze-v0").agent.action_dim
        2
    """
    return lookup_spec(maze, MAZES, MazeSpec, "maze")


def build_maze_mjcf(maze: str | MazeSpec) -> mjcf.RootElement:
    """Builds the MJCF model of a maze programmatically from its grid.

    The arena holds a floor plane, one box per wall cell (and the extra walls), a visual-only mocap goal
    marker and a top-down camera; the agent is attached at the origin (the start cell's centre).

    Args:
        maze (str or MazeSpec): a maze name or spec.

    Returns:
        the :class:`dm_control.mjcf.RootElement` of the whole scene.

    Examples:
        >>> from torchrl_dhrl.envs import build_maze_mjcf
        >>> root = build_maze_mjcf("AntMazeSmall")
        >>> len([g for g in root.worldbody.find_all("geom") if g.name and g.name.startswith("wall")])
        18
    """
    spec = get_maze_spec(maze)
    agent = spec.agent
    root = new_scene(spec.name, agent)
    low, high = spec.layout.extent
    center = (low + high) / 2
    half_extent = float(np.max(high - low)) / 2
    contact = agent.scene_contact
    add_floor(root, center, half_extent, collides=agent.touches_floor, contact=contact)
    add_boxes(root, spec.layout.wall_boxes, prefix="wall", contact=contact)
    add_goal_marker(root, spec.reward_threshold)
    # A camera looking straight down (-z) with +y up; high enough to see the whole grid.
    height = half_extent / np.tan(np.deg2rad(_OVERVIEW_FOVY) / 2) * 1.05
    add_camera(root, OVERVIEW_CAMERA, (center[0], center[1], height))
    agent.attach_to(root)
    return root


def compile_maze_model(maze: str | MazeSpec) -> mujoco.MjModel:
    """Compiles a fresh :class:`mujoco.MjModel` of a maze (the MJCF text is built once and cached).

    Examples:
        >>> from torchrl_dhrl.envs import compile_maze_model
        >>> model = compile_maze_model("AntMaze")
        >>> model.nq, model.nv, model.nu, model.opt.timestep
        (15, 14, 8, 0.02)
    """
    return get_maze_spec(maze).compile_model()
