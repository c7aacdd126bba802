"""Builds the MuJoCo model of a maze: floor, walls from the grid, goal marker, cameras, and the agent."""

from __future__ import annotations

import functools

import mujoco
import numpy as np
from dm_control import mjcf

from .agents import AGENT_CONTYPE
from .mazes import MazeSpec, get_maze_spec

__all__ = ["build_maze_mjcf", "compile_maze_model", "OVERVIEW_CAMERA", "GOAL_BODY"]

#: Name of the fixed top-down camera that sees the whole maze.
OVERVIEW_CAMERA = "overview"
#: Name of the mocap body that marks the desired goal (visual only).
GOAL_BODY = "goal_marker"
# Offscreen framebuffer size (the largest render the model allows).
_OFFSCREEN_SIZE = 1024
_WALL_RGBA = (0.2, 0.2, 0.3, 1.0)
_GOAL_RGBA = (0.9, 0.1, 0.1, 0.6)
# Vertical field of view of the overview camera, in degrees.
_OVERVIEW_FOVY = 45.0


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
    root = mjcf.RootElement(model=spec.name)
    root.compiler.angle = "radian"
    root.option.timestep = agent.timestep
    root.option.integrator = agent.integrator
    visual_global = getattr(root.visual, "global")
    visual_global.offwidth = _OFFSCREEN_SIZE
    visual_global.offheight = _OFFSCREEN_SIZE
    root.visual.headlight.ambient = (0.3, 0.3, 0.3)
    root.visual.headlight.diffuse = (0.3, 0.3, 0.3)
    root.visual.headlight.specular = (0.0, 0.0, 0.0)

    low, high = spec.layout.extent
    center = (low + high) / 2
    half_extent = float(np.max(high - low)) / 2
    root.asset.add(
        "texture",
        name="grid",
        type="2d",
        builtin="checker",
        width=512,
        height=512,
        rgb1=(0.55, 0.6, 0.55),
        rgb2=(0.45, 0.5, 0.45),
    )
    root.asset.add(
        "material", name="floor", texture="grid", texrepeat=(1, 1), texuniform=True, reflectance=0.0
    )
    root.worldbody.add(
        "light",
        name="sun",
        directional=True,
        pos=(0.0, 0.0, 10.0),
        dir=(0.3, 0.3, -1.0),
        diffuse=(0.6, 0.6, 0.6),
        castshadow=False,
    )
    root.worldbody.add(
        "geom",
        name="floor",
        type="plane",
        material="floor",
        pos=(float(center[0]), float(center[1]), 0.0),
        size=(half_extent, half_extent, 1.0),
        contype=0,
        conaffinity=AGENT_CONTYPE if agent.touches_floor else 0,
        condim=3,
    )
    for k, box in enumerate(spec.layout.wall_boxes):
        extra = {} if box.friction is None else {"friction": box.friction}
        root.worldbody.add(
            "geom",
            name=f"wall_{k}",
            type="box",
            pos=box.center,
            size=box.half_size,
            rgba=_WALL_RGBA,
            contype=0,
            conaffinity=AGENT_CONTYPE,
            condim=3,
            **extra,
        )
    marker = root.worldbody.add("body", name=GOAL_BODY, mocap=True, pos=(0.0, 0.0, 0.0))
    marker.add(
        "geom",
        name="goal_geom",
        type="sphere",
        size=[spec.reward_threshold],
        rgba=_GOAL_RGBA,
        contype=0,
        conaffinity=0,
        group=1,
    )
    # A camera looking straight down (-z) with +y up; high enough to see the whole grid.
    height = half_extent / np.tan(np.deg2rad(_OVERVIEW_FOVY) / 2) * 1.05
    root.worldbody.add(
        "camera",
        name=OVERVIEW_CAMERA,
        pos=(float(center[0]), float(center[1]), float(height)),
        fovy=_OVERVIEW_FOVY,
    )
    agent.attach_to(root)
    return root


@functools.cache
def _maze_xml(maze: MazeSpec) -> str:
    return build_maze_mjcf(maze).to_xml_string()


def compile_maze_model(maze: str | MazeSpec) -> mujoco.MjModel:
    """Compiles a fresh :class:`mujoco.MjModel` of a maze (the MJCF text is built once and cached).

    Examples:
        >>> from torchrl_dhrl.envs import compile_maze_model
        >>> model = compile_maze_model("AntMaze")
        >>> model.nq, model.nv, model.nu, model.opt.timestep
        (15, 14, 8, 0.02)
    """
    spec = get_maze_spec(maze)
    return mujoco.MjModel.from_xml_string(_maze_xml(spec))
