"""Builds MuJoCo scenes: shared pieces (floor, static boxes, goal marker, cameras) and the maze arenas."""

from __future__ import annotations

import numpy as np
from dm_control import mjcf

from .agents import AGENT_CONTYPE
from .layouts import WallBox
from .task import GOAL_BODY, OVERVIEW_CAMERA

__all__ = [
    "OVERVIEW_CAMERA",
    "GOAL_BODY",
    "new_scene",
    "add_floor",
    "add_boxes",
    "add_goal_marker",
    "add_camera",
]

# Offscreen framebuffer size (the largest render the model allows).
_OFFSCREEN_SIZE = 1024
_WALL_RGBA = (0.2, 0.2, 0.3, 1.0)
_GOAL_RGBA = (0.9, 0.1, 0.1, 0.6)
# Vertical field of view of the overview camera, in degrees.
_OVERVIEW_FOVY = 45.0


def new_scene(name: str, agent) -> mjcf.RootElement:
    """An empty scene with the agent's timestep and integrator, a headlight and a large offscreen buffer.

    Examples:
        >>> from torchrl_dhrl.envs import AntAgent
        >>> from torchrl_dhrl.envs.arena import add_boxes, new_scene
        >>> from torchrl_dhrl.envs.layouts import WallBox
        >>> root = new_scene("demo", AntAgent())
        >>> root.option.timestep, root.option.integrator
        (0.02, 'RK4')
        >>> [geom.name for geom in add_boxes(root, (WallBox((0.0, 0.0, 1.0), (1.0, 1.0, 1.0)),), prefix="wall")]
        ['wall_0']
    """
    root = mjcf.RootElement(model=name)
    root.compiler.angle = "radian"
    root.option.timestep = agent.timestep
    root.option.integrator = agent.integrator
    visual_global = getattr(root.visual, "global")
    visual_global.offwidth = _OFFSCREEN_SIZE
    visual_global.offheight = _OFFSCREEN_SIZE
    root.visual.headlight.ambient = (0.3, 0.3, 0.3)
    root.visual.headlight.diffuse = (0.3, 0.3, 0.3)
    root.visual.headlight.specular = (0.0, 0.0, 0.0)
    return root


def add_floor(
    root: mjcf.RootElement,
    center,
    half_extent: float,
    *,
    height: float = 0.0,
    collides: bool,
    contact: dict | None = None,
) -> mjcf.Element:
    """A checkered floor plane (square, ``half_extent`` wide) under a directional light.

    ``collides`` makes agent geoms collide with it (``conaffinity``); ``contact`` holds extra contact
    attributes of the plane (``solref``, ``solimp``, ``friction``, ``margin``).
    """
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
    return root.worldbody.add(
        "geom",
        name="floor",
        type="plane",
        material="floor",
        pos=(float(center[0]), float(center[1]), height),
        size=(half_extent, half_extent, 1.0),
        contype=0,
        conaffinity=AGENT_CONTYPE if collides else 0,
        condim=3,
        **(contact or {}),
    )


def add_boxes(
    root: mjcf.RootElement,
    boxes: tuple[WallBox, ...],
    *,
    prefix: str,
    rgba=_WALL_RGBA,
    contact: dict | None = None,
) -> list[mjcf.Element]:
    """Static box geoms ``<prefix>_<k>`` that agents collide with (walls, boards).

    ``contact`` holds extra contact attributes of every box; a box's own ``friction`` takes precedence.
    """
    geoms = []
    for k, box in enumerate(boxes):
        extra = dict(contact or {})
        if box.friction is not None:
            extra["friction"] = box.friction
        geoms.append(
            root.worldbody.add(
                "geom",
                name=f"{prefix}_{k}",
                type="box",
                pos=box.center,
                size=box.half_size,
                rgba=rgba,
                contype=0,
                conaffinity=AGENT_CONTYPE,
                condim=3,
                **extra,
            )
        )
    return geoms


def add_goal_marker(root: mjcf.RootElement, radius: float) -> mjcf.Element:
    """The visual-only mocap sphere :data:`GOAL_BODY` that the simulation moves to the desired goal."""
    marker = root.worldbody.add("body", name=GOAL_BODY, mocap=True, pos=(0.0, 0.0, 0.0))
    marker.add(
        "geom",
        name="goal_geom",
        type="sphere",
        size=[radius],
        rgba=_GOAL_RGBA,
        contype=0,
        conaffinity=0,
        group=1,
    )
    return marker


def add_camera(root: mjcf.RootElement, name: str, pos, target=None, fovy: float = _OVERVIEW_FOVY):
    """A fixed camera at ``pos`` looking at ``target`` (``None``: straight down, +y up in the image)."""
    extra = {}
    if target is not None:
        forward = np.asarray(target, dtype=np.float64) - np.asarray(pos, dtype=np.float64)
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, (0.0, 0.0, 1.0))
        right /= np.linalg.norm(right)
        up = np.cross(right, forward)
        extra["xyaxes"] = tuple(float(v) for v in (*right, *up))
    return root.worldbody.add("camera", name=name, pos=tuple(float(v) for v in pos), fovy=fovy, **extra)




