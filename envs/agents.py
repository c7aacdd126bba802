"""The two agents of the DHRL mazes, built programmatically with :mod:`dm_control.mjcf`.

Both agents are written from the published facts of the HIRO-lineage models (body sizes, joints, ranges,
actuators); no XML file is involved. Each agent knows how to

* build its MJCF model (:meth:`build_mjcf`) and attach it to an arena (:meth:`attach_to`), adding the root
  joints on the attachment frame so that ``qpos[:2]`` is the agent's (x, y) in world coordinates;
* turn a batch of policy actions into the quantity written into ``MjData`` before stepping
  (:meth:`command`): motor torques for the ant, joint velocities for the point.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

with warnings.catch_warnings():
    # dm_control probes GLFW when imported; without a display that only warns (MJCF building and our
    # offscreen rendering, which follows MUJOCO_GL, never use GLFW).
    warnings.filterwarnings("ignore", message=".*DISPLAY.*")
    from dm_control import mjcf

__all__ = ["AntAgent", "PointAgent", "MazeAgent", "MotorControl", "upright_pose"]

# Collision bits. Agent geoms carry ``contype=AGENT_CONTYPE, conaffinity=0`` so that two agent geoms never
# collide (``(c1.contype & c2.conaffinity) | (c2.contype & c1.conaffinity) == 0``), while walls (and the
# floor, for agents that touch it) carry ``conaffinity=AGENT_CONTYPE`` so that agents collide with them.
AGENT_CONTYPE = 1


def upright_pose(qpos: np.ndarray, rest_qpos: np.ndarray) -> np.ndarray:
    """A free-floating body's rest pose ``rest_qpos`` moved to the (x, y) of ``qpos`` and turned to its heading.

    ``qpos[..., :7]`` is the root's position and quaternion ``(w, x, y, z)``; the heading is the yaw of the root's
    x axis projected on the floor (``0`` when that axis is vertical). Every other entry (height, joints) is
    ``rest_qpos``'s. Used to right a flipped ant (:meth:`AntAgent.upright_qpos`, and gymnasium-robotics' ant
    mazes in :class:`~torchrl_dhrl.envs.GymnasiumGoalEnv`).

    Examples:
        >>> import numpy as np
        >>> flipped = np.zeros(15)
        >>> flipped[:3] = (2.0, 3.0, 0.3)
        >>> flipped[3:7] = (0.0, 0.0, 1.0, 0.0)  # half a turn about y: upside down, heading pi
        >>> rest = np.zeros(15)
        >>> rest[2:4] = (0.75, 1.0)
        >>> upright_pose(flipped, rest)[:7].round(3).tolist()
        [2.0, 3.0, 0.75, 0.0, 0.0, 0.0, 1.0]
    """
    qpos = np.asarray(qpos, dtype=np.float64)
    w, x, y, z = (qpos[..., k] for k in range(3, 7))
    yaw = np.arctan2(2.0 * (x * y + w * z), 1.0 - 2.0 * (y * y + z * z))
    out = np.broadcast_to(np.asarray(rest_qpos, dtype=np.float64), qpos.shape).copy()
    out[..., :2] = qpos[..., :2]
    out[..., 3] = np.cos(yaw / 2.0)
    out[..., 4:6] = 0.0
    out[..., 6] = np.sin(yaw / 2.0)
    return out


class MotorControl:
    """Mixin of agents driven by motors: an action is a vector of torques, clipped and written to ``ctrl``.

    The agent provides ``ctrl_limit`` (the symmetric control range) and ``action_dim``.

    Examples:
        >>> import numpy as np
        >>> from torchrl_dhrl.envs import AntAgent
        >>> AntAgent().command(np.array([[40.0, -5.0, 0, 0, 0, 0, 0, -31.0]]), None).tolist()
        [[30.0, -5.0, 0.0, 0.0, 0.0, 0.0, 0.0, -30.0]]
    """

    #: The MjData field :meth:`command` writes: motor torques.
    control_field = "ctrl"

    @property
    def action_low(self) -> np.ndarray:
        """Lower bound of the action box."""
        return np.full(self.action_dim, -self.ctrl_limit)

    @property
    def action_high(self) -> np.ndarray:
        """Upper bound of the action box."""
        return np.full(self.action_dim, self.ctrl_limit)

    def command(self, actions: np.ndarray, qpos: np.ndarray) -> np.ndarray:
        """Motor torques for a batch of actions ``[N, action_dim]`` (clipped to the control range)."""
        return np.clip(actions, -self.ctrl_limit, self.ctrl_limit)

    def normalize_qpos(self, qpos: np.ndarray) -> None:
        """Nothing to renormalise (no quaternion in ``qpos``)."""


@dataclass(frozen=True)
class AntAgent(MotorControl):
    """The 8-motor quadruped of the HIRO-lineage ant mazes.

    A torso sphere with four legs; each leg is a fixed segment from the torso, a hip body (z-axis hinge) and
    an ankle body (hinge about the in-plane axis perpendicular to the leg). Legs are numbered as in the
    reference: 1 = front left (+x, +y), 2 = front right (-x, +y), 3 = back left (-x, -y),
    4 = back right (+x, -y). Motors drive the 8 joints directly (gear 1) in the reference order
    ``hip_4, ankle_4, hip_1, ankle_1, hip_2, ankle_2, hip_3, ankle_3``.

    The observation is ``qpos[:15] ++ qvel[:14]`` (29-D): torso position, torso quaternion (w, x, y, z),
    the 8 joint angles in leg order 1-4 (hip, ankle), then the torso linear and angular velocity and the 8
    joint velocities. No time feature.

    Args:
        torso_radius (float): radius of the torso sphere. Defaults to ``0.25``.
        torso_height (float): height of the torso body in the model (``qpos0``). Defaults to ``0.75``.
        leg_radius (float): radius of the leg capsules. Defaults to ``0.08``.
        upper_leg (float): per-axis extent of the fixed and hip segments, ``(+-0.2, +-0.2, 0)``.
            Defaults to ``0.2``.
        lower_leg (float): per-axis extent of the ankle segment, ``(+-0.4, +-0.4, 0)``. Defaults to ``0.4``.
        hip_range_deg (float): the hips move in ``[-hip_range_deg, hip_range_deg]``. Defaults to ``30``.
        ankle_range_deg (tuple of float): the ankle range of legs 1 and 4; legs 2 and 3 use its negation.
            Defaults to ``(30, 70)``.
        armature (float): joint armature. Defaults to ``1``.
        damping (float): joint damping (the free root joint has none). Defaults to ``1``.
        density (float): geom density. Defaults to ``5``.
        friction (tuple of float): geom friction (slide, torsion, roll). Defaults to ``(1, 0.5, 0.5)``.
        margin (float): geom contact margin. Defaults to ``0.01``.
        solref (tuple of float): contact ``solref`` of every geom of the scene (the reference's default
            class; MuJoCo's default). Defaults to ``(0.02, 1)``.
        solimp (tuple of float): contact ``solimp`` of every geom of the scene: the reference's default
            class gives the ant, the floor and the walls ``(0.8, 0.8, 0.01)``, softer than MuJoCo's
            ``(0.9, 0.95, 0.001)``. Defaults to ``(0.8, 0.8, 0.01)``.
        ctrl_limit (float): motors accept torques in ``[-ctrl_limit, ctrl_limit]``. Defaults to ``30``.
        init_qpos (tuple of float): reset pose before noise: the model's ``qpos0``, torso (0, 0, 0.75),
            identity quaternion and every joint at 0, as in the reference, whose gym ``MujocoEnv`` resets
            around the state at load (its XML's custom ``init_qpos`` numeric, torso at 0.55 with the ankles at
            +-1 rad, is never read). The ankles start outside their ranges; the joint limits fold the legs down
            within 3 env steps while the ant drops onto its feet; the torso settles at about 0.38 after about 100.
        qpos_noise (float): reset noise ``U(-qpos_noise, qpos_noise)`` on every ``qpos`` entry (the
            quaternion is renormalised afterwards). Defaults to ``0.1``.
        qvel_noise (float): reset noise ``N(0, qvel_noise)`` on every ``qvel`` entry. Defaults to ``0.1``.
        timestep (float): MuJoCo timestep. Defaults to ``0.02``.
        frame_skip (int): physics steps per environment step. Defaults to ``5`` (0.1 s per env step).
        integrator (str): MuJoCo integrator. Defaults to ``"RK4"``.
        reference_engine (bool): emulate MuJoCo 2.0 (the reference's ``mujoco_py`` 2.0.2.8) where MuJoCo 3
            differs: (1) a contact's margin was the larger of its two geoms' margins, MuJoCo 3 takes their sum,
            so every geom of the scene (the ant's, and through :attr:`scene_contact` the floor's and the walls')
            gets half of ``margin`` (0.005: 0.01 per contact, as the reference; the ant only touches static
            geoms); (2) before MuJoCo 2.1.2 the compiler approximated a capsule's mass and inertia by a solid
            cylinder of the capsule's radius and length ``L + radius`` (``L`` the ``fromto`` length: the
            cylindrical section extended by half the radius at both ends), so every leg body gets an explicit
            ``<inertial>`` of that cylinder (the torso's sphere was exact in 2.0 and is left alone): the ant weighs
            0.879 instead of 0.911. Defaults to ``False`` (MuJoCo 3's own margins and exact capsules).

    Examples:
        >>> from torchrl_dhrl.envs import AntAgent
        >>> ant = AntAgent()
        >>> ant.obs_dim, ant.action_dim
        (29, 8)
        >>> ant.build_mjcf().find_all("actuator")[0].joint.name
        'hip_4'
    """

    torso_radius: float = 0.25
    torso_height: float = 0.75
    leg_radius: float = 0.08
    upper_leg: float = 0.2
    lower_leg: float = 0.4
    hip_range_deg: float = 30.0
    ankle_range_deg: tuple[float, float] = (30.0, 70.0)
    armature: float = 1.0
    damping: float = 1.0
    density: float = 5.0
    friction: tuple[float, float, float] = (1.0, 0.5, 0.5)
    margin: float = 0.01
    solref: tuple[float, float] = (0.02, 1.0)
    solimp: tuple[float, float, float] = (0.8, 0.8, 0.01)
    ctrl_limit: float = 30.0
    # Torso position, identity quaternion, then (hip, ankle) of legs 1-4: the model's qpos0.
    init_qpos: tuple[float, ...] = (0.0, 0.0, 0.75) + (1.0, 0.0, 0.0, 0.0) + (0.0,) * 8
    qpos_noise: float = 0.1
    qvel_noise: float = 0.1
    timestep: float = 0.02
    frame_skip: int = 5
    integrator: str = "RK4"
    reference_engine: bool = False

    #: Legs in reference order 1-4: (name, in-plane direction, sign of the ankle range).
    legs = (
        ("front_left", (1.0, 1.0), 1.0),
        ("front_right", (-1.0, 1.0), -1.0),
        ("back_left", (-1.0, -1.0), -1.0),
        ("back_right", (1.0, -1.0), 1.0),
    )
    #: Motor order of the reference: leg numbers 4, 1, 2, 3, hip then ankle.
    motor_leg_order = (4, 1, 2, 3)

    @property
    def obs_dim(self) -> int:
        """Size of the observation vector (``qpos[:15] ++ qvel[:14]``)."""
        return 29

    @property
    def action_dim(self) -> int:
        """Number of motors."""
        return 8

    @property
    def touches_floor(self) -> bool:
        """Whether the agent's geoms collide with the floor (the ant walks on it)."""
        return True

    @property
    def geom_margin(self) -> float:
        """The ``margin`` of every geom of the scene: :attr:`margin`, or half of it with :attr:`reference_engine`.

        MuJoCo 3 adds the two geoms' margins of a contact where MuJoCo 2.0 took the larger; with equal margins
        on both sides, half of ``margin`` each gives the reference's ``margin`` per contact.

        Examples:
            >>> from torchrl_dhrl.envs import AntAgent
            >>> AntAgent().geom_margin, AntAgent(reference_engine=True).geom_margin
            (0.01, 0.005)
        """
        return self.margin / 2.0 if self.reference_engine else self.margin

    @property
    def scene_contact(self) -> dict:
        """Contact parameters the arena gives the floor and the walls.

        In the reference every geom of the scene (floor and wall blocks included) takes the model's default
        class; MuJoCo mixes the two geoms' ``solref``/``solimp`` of a contact, so the static geoms must carry
        the ant's values for its contacts to be the reference's (and the margin :attr:`geom_margin`).
        """
        return {
            "solref": self.solref,
            "solimp": self.solimp,
            "friction": self.friction,
            "margin": self.geom_margin,
        }

    def capsule_inertial(self, fromto) -> dict:
        """MuJoCo 2.0's mass and inertia of a leg capsule from ``fromto``, as ``<inertial>`` attributes.

        Before MuJoCo 2.1.2 the compiler approximated a capsule of radius ``r`` and segment length ``L`` by a
        solid cylinder of radius ``r`` and height ``h = L + r`` about the segment's centre: mass
        ``density pi r^2 h``, inertia ``m r^2 / 2`` about the axis and ``m (3 r^2 + h^2) / 12`` across it.
        The inertial frame sits at the segment's centre with its z axis along the segment.

        Examples:
            >>> from torchrl_dhrl.envs import AntAgent
            >>> inertial = AntAgent().capsule_inertial((0.0, 0.0, 0.0, 0.4, 0.4, 0.0))
            >>> round(inertial["mass"], 5), inertial["pos"]
            (0.06491, (0.2, 0.2, 0.0))
        """
        start, end = np.asarray(fromto[:3], dtype=np.float64), np.asarray(fromto[3:], dtype=np.float64)
        axis = end - start
        length = float(np.linalg.norm(axis))
        radius = self.leg_radius
        height = length + radius
        mass = self.density * np.pi * radius**2 * height
        transverse = mass * (3.0 * radius**2 + height**2) / 12.0
        axial = mass * radius**2 / 2.0
        # The rotation taking z onto the segment's direction u: the half-way quaternion (1 + z.u, z x u).
        u = axis / length
        quat = np.array([1.0 + u[2], -u[1], u[0], 0.0])
        if quat[0] < 1e-12:  # u = -z: half a turn about x
            quat = np.array([0.0, 1.0, 0.0, 0.0])
        quat /= np.linalg.norm(quat)
        return {
            "pos": tuple(float(v) for v in (start + end) / 2.0),
            "quat": tuple(float(v) for v in quat),
            "mass": float(mass),
            "diaginertia": (float(transverse), float(transverse), float(axial)),
        }

    def _add_capsule(self, body, name: str, fromto) -> None:
        """A leg capsule in ``body`` (with MuJoCo 2.0's inertial under :attr:`reference_engine`)."""
        body.add("geom", name=name, type="capsule", size=[self.leg_radius], fromto=fromto)
        if self.reference_engine:
            body.add("inertial", **self.capsule_inertial(fromto))

    def build_mjcf(self) -> mjcf.RootElement:
        """Builds the ant model (torso at the model origin, no root joint; see :meth:`attach_to`)."""
        root = mjcf.RootElement(model="ant")
        root.compiler.angle = "radian"
        root.default.joint.armature = self.armature
        root.default.joint.damping = self.damping
        root.default.joint.limited = True
        geom = root.default.geom
        geom.contype = AGENT_CONTYPE
        geom.conaffinity = 0
        geom.condim = 3
        geom.density = self.density
        geom.friction = self.friction
        geom.margin = self.geom_margin
        geom.solref = self.solref
        geom.solimp = self.solimp
        geom.rgba = (0.8, 0.6, 0.4, 1.0)

        torso = root.worldbody.add("body", name="torso")
        torso.add("geom", name="torso_geom", type="sphere", size=[self.torso_radius])
        torso.add(
            "camera", name="track", mode="trackcom", pos=(0.0, -6.0, 6.0), xyaxes=(1, 0, 0, 0, 0.7, 0.7)
        )
        hip_range = np.deg2rad([-self.hip_range_deg, self.hip_range_deg])
        joints = {}
        for number, (leg, (dx, dy), sign) in enumerate(self.legs, start=1):
            upper = (self.upper_leg * dx, self.upper_leg * dy, 0.0)
            lower = (self.lower_leg * dx, self.lower_leg * dy, 0.0)
            ankle_range = np.sort(sign * np.deg2rad(self.ankle_range_deg))
            leg_body = torso.add("body", name=f"{leg}_leg")
            self._add_capsule(leg_body, f"aux_{number}_geom", (0.0, 0.0, 0.0) + upper)
            hip_body = leg_body.add("body", name=f"aux_{number}", pos=upper)
            joints[f"hip_{number}"] = hip_body.add(
                "joint", name=f"hip_{number}", type="hinge", axis=(0, 0, 1), range=hip_range
            )
            self._add_capsule(hip_body, f"{leg}_upper_geom", (0.0, 0.0, 0.0) + upper)
            ankle_body = hip_body.add("body", name=f"{leg}_foot", pos=upper)
            # In-plane axis perpendicular to the leg direction (dx, dy): sign * (-dy, dx, 0). A positive
            # angle about (-dy, dx, 0) folds the lower leg down, so with the sign the ankle range (positive
            # for legs 1 and 4, negative for 2 and 3) keeps every foot below its ankle, as in the reference.
            axis = (-sign * dy, sign * dx, 0.0)
            joints[f"ankle_{number}"] = ankle_body.add(
                "joint", name=f"ankle_{number}", type="hinge", axis=axis, range=ankle_range
            )
            self._add_capsule(ankle_body, f"{leg}_lower_geom", (0.0, 0.0, 0.0) + lower)
        for number in self.motor_leg_order:
            for part in ("hip", "ankle"):
                root.actuator.add(
                    "motor",
                    name=f"{part}_{number}_motor",
                    joint=joints[f"{part}_{number}"],
                    gear=[1],
                    ctrllimited=True,
                    ctrlrange=(-self.ctrl_limit, self.ctrl_limit),
                )
        return root

    def attach_to(self, arena: mjcf.RootElement) -> mjcf.Element:
        """Attaches the ant to ``arena`` with a free root joint (no damping) on the attachment frame."""
        frame = arena.worldbody.attach(self.build_mjcf())
        frame.pos = (0.0, 0.0, self.torso_height)
        frame.add("freejoint", name="root")
        return frame

    @staticmethod
    def is_upside_down(observation):
        """Whether the torso's up axis points below the horizon, from observations ``[..., 29]``.

        The torso quaternion ``(w, x, y, z)`` sits at ``observation[..., 3:7]``; the world z component of the
        torso's z axis is ``1 - 2 (x^2 + y^2)``. Works on NumPy arrays and torch tensors alike.

        Examples:
            >>> import numpy as np
            >>> from torchrl_dhrl.envs import AntAgent
            >>> obs = np.zeros((2, 29))
            >>> obs[0, 3] = 1.0  # identity: upright
            >>> obs[1, 4] = 1.0  # half a turn about x: upside down
            >>> AntAgent.is_upside_down(obs).tolist()
            [False, True]
        """
        x, y = observation[..., 4], observation[..., 5]
        return 1.0 - 2.0 * (x * x + y * y) < 0.0

    def upright_qpos(self, qpos: np.ndarray) -> np.ndarray:
        """The reset pose (:attr:`init_qpos`, no noise) moved to the ant's (x, y) and turned to its heading.

        The heading is the yaw of the torso's x axis projected on the floor (``0`` when that axis is vertical).
        Used by :class:`~torchrl_dhrl.envs.GoalSimulation` to right a flipped ant (``right_flipped_after``).

        Examples:
            >>> import numpy as np
            >>> from torchrl_dhrl.envs import AntAgent
            >>> flipped = np.zeros(15)
            >>> flipped[:3] = (2.0, 3.0, 0.3)
            >>> flipped[3:7] = (0.0, 1.0, 0.0, 0.0)  # half a turn about x: upside down, heading 0
            >>> AntAgent().upright_qpos(flipped)[:7].round(3).tolist()
            [2.0, 3.0, 0.75, 1.0, 0.0, 0.0, 0.0]
        """
        return upright_pose(qpos, self.init_qpos)

    def normalize_qpos(self, qpos: np.ndarray) -> None:
        """Renormalises the torso quaternion ``qpos[..., 3:7]`` in place (after additive reset noise)."""
        quat = qpos[..., 3:7]
        quat /= np.linalg.norm(quat, axis=-1, keepdims=True)


@dataclass(frozen=True)
class PointAgent:
    """The HIRO-lineage point agent, driven through velocities so that MuJoCo contacts stop it at walls.

    One body with a sphere (radius 0.5, centre 0.5 above the floor) and a small box "nose" 0.6 ahead,
    on x-slide, y-slide and yaw-hinge joints (no limits, no damping). The action is
    ``(forward, turn)`` in ``[-1, 1] x [-0.25, 0.25]``.

    The reference agent is kinematic: ``yaw += turn`` then ``(x, y) += step_length * forward *
    (cos yaw, sin yaw)`` written straight into ``qpos``, which can teleport the point through thin walls.
    Here the same displacement is turned into joint velocities over the control period
    ``T = timestep * frame_skip``: ``qvel = (step_length * forward * cos(yaw + turn) / T,
    step_length * forward * sin(yaw + turn) / T, turn / T)``, and MuJoCo integrates them with contacts
    active, so walls push back within every substep. In free space an env step moves the point exactly
    as the reference (the heading turns during the step instead of before it); the body's mass is lumped
    on the yaw axis so that turning does not couple into the translation. The frame skip is split
    into ``frame_skip`` substeps of ``timestep``: 4 substeps of 0.005 s give the reference's 0.02 s per
    env step while keeping each substep's travel (at most 0.05) far below the sphere radius.

    The observation is ``qpos[:3] ++ qvel[:3]``: ``(x, y, yaw, vx, vy, yaw_rate)``. The point has no
    vertical degree of freedom, so it does not collide with the floor.

    Args:
        radius (float): radius of the body sphere. Defaults to ``0.5``.
        nose_half_size (tuple of float): half sizes of the nose box. Defaults to ``(0.5, 0.1, 0.1)``.
        nose_offset (float): distance of the nose centre ahead of the body centre. Defaults to ``0.6``.
        density (float): geom density. Defaults to ``100``.
        friction (tuple of float): geom friction. Defaults to ``(1, 0.5, 0.5)``.
        step_length (float): displacement per env step at ``forward = 1``. Defaults to ``0.2``.
        forward_limit (float): ``forward`` is clipped to ``[-forward_limit, forward_limit]``.
            Defaults to ``1``.
        turn_limit (float): ``turn`` (radians per env step) is clipped to ``[-turn_limit, turn_limit]``.
            Defaults to ``0.25``.
        init_qpos (tuple of float): reset pose before noise ``(x, y, yaw)``. Defaults to zeros.
        qpos_noise (float): reset noise ``U(-qpos_noise, qpos_noise)`` on ``qpos``. Defaults to ``0.1``.
        qvel_noise (float): reset noise ``N(0, qvel_noise)`` on ``qvel``. Defaults to ``0.1``.
        contact_timeconst (float): ``solref`` time constant of the point's contacts (its geoms take
            priority over the walls'). Defaults to ``0.01``, the stiffest value MuJoCo allows at this
            timestep: pushing into a wall at full speed leaves no visible penetration.
        timestep (float): MuJoCo timestep of one substep. Defaults to ``0.005``.
        frame_skip (int): substeps per env step. Defaults to ``4`` (0.02 s per env step, as the reference).
        integrator (str): MuJoCo integrator. Defaults to ``"Euler"``.

    Examples:
        >>> import numpy as np
        >>> from torchrl_dhrl.envs import PointAgent
        >>> point = PointAgent()
        >>> point.obs_dim, point.action_dim
        (6, 2)
        >>> qvel = point.command(np.array([[1.0, 0.0]]), np.zeros((1, 3)))
        >>> (qvel * point.control_period).round(3).tolist()  # displacement over one env step
        [[0.2, 0.0, 0.0]]
    """

    radius: float = 0.5
    nose_half_size: tuple[float, float, float] = (0.5, 0.1, 0.1)
    nose_offset: float = 0.6
    density: float = 100.0
    friction: tuple[float, float, float] = (1.0, 0.5, 0.5)
    step_length: float = 0.2
    forward_limit: float = 1.0
    turn_limit: float = 0.25
    init_qpos: tuple[float, ...] = (0.0, 0.0, 0.0)
    qpos_noise: float = 0.1
    qvel_noise: float = 0.1
    contact_timeconst: float = 0.01
    timestep: float = 0.005
    frame_skip: int = 4
    integrator: str = "Euler"

    #: The MjData field :meth:`command` writes: the joint velocities of (x, y, yaw).
    control_field = "qvel"

    @property
    def obs_dim(self) -> int:
        """Size of the observation vector (``qpos[:3] ++ qvel[:3]``)."""
        return 6

    @property
    def action_dim(self) -> int:
        """``(forward, turn)``."""
        return 2

    @property
    def action_low(self) -> np.ndarray:
        """Lower bound of the action box."""
        return np.array([-self.forward_limit, -self.turn_limit])

    @property
    def action_high(self) -> np.ndarray:
        """Upper bound of the action box."""
        return np.array([self.forward_limit, self.turn_limit])

    @property
    def touches_floor(self) -> bool:
        """The point slides on x/y joints only: it has no contact with the floor."""
        return False

    @property
    def scene_contact(self) -> dict:
        """No extra contact attributes for the floor and walls (MuJoCo's defaults; the point's own
        ``solref`` and ``priority`` decide its wall contacts)."""
        return {}

    @property
    def control_period(self) -> float:
        """Simulated seconds per env step."""
        return self.timestep * self.frame_skip

    def build_mjcf(self) -> mjcf.RootElement:
        """Builds the point model with its x-slide, y-slide and yaw-hinge joints."""
        root = mjcf.RootElement(model="point")
        root.compiler.angle = "radian"
        root.default.joint.limited = False
        root.default.joint.armature = 0.0
        root.default.joint.damping = 0.0
        geom = root.default.geom
        geom.contype = AGENT_CONTYPE
        geom.conaffinity = 0
        geom.condim = 3
        geom.density = self.density
        geom.friction = self.friction
        geom.margin = 0.0
        geom.priority = 1
        geom.solref = (self.contact_timeconst, 1.0)
        geom.rgba = (0.8, 0.6, 0.4, 1.0)
        body = root.worldbody.add("body", name="torso")
        # The mass of both geoms (at ``density``) is lumped at the sphere centre, on the yaw axis: with the
        # nose's off-axis mass, turning would push the translation sideways during the step.
        volume = 4.0 / 3.0 * np.pi * self.radius**3 + 8.0 * float(np.prod(self.nose_half_size))
        mass = self.density * volume
        body.add(
            "inertial", pos=(0.0, 0.0, self.radius), mass=mass, diaginertia=[0.4 * mass * self.radius**2] * 3
        )
        body.add("joint", name="ballx", type="slide", axis=(1, 0, 0))
        body.add("joint", name="bally", type="slide", axis=(0, 1, 0))
        body.add("joint", name="rot", type="hinge", axis=(0, 0, 1))
        body.add("geom", name="pointbody", type="sphere", size=[self.radius], pos=(0.0, 0.0, self.radius))
        body.add(
            "geom",
            name="pointarrow",
            type="box",
            size=self.nose_half_size,
            pos=(self.nose_offset, 0.0, self.radius),
        )
        body.add("camera", name="track", mode="trackcom", pos=(0.0, -6.0, 6.0), xyaxes=(1, 0, 0, 0, 0.7, 0.7))
        return root

    def attach_to(self, arena: mjcf.RootElement) -> mjcf.Element:
        """Attaches the point to ``arena`` at the origin (its joints live in the point's own body)."""
        return arena.worldbody.attach(self.build_mjcf())

    def command(self, actions: np.ndarray, qpos: np.ndarray) -> np.ndarray:
        """Joint velocities ``[N, 3]`` that realise the reference's displacement over one env step.

        Args:
            actions (np.ndarray): ``[N, 2]`` (forward, turn), clipped to the action box.
            qpos (np.ndarray): ``[N, nq]`` current positions (``qpos[:, 2]`` is the yaw).
        """
        forward = np.clip(actions[:, 0], -self.forward_limit, self.forward_limit)
        turn = np.clip(actions[:, 1], -self.turn_limit, self.turn_limit)
        heading = qpos[:, 2] + turn
        speed = self.step_length * forward / self.control_period
        return np.stack(
            [speed * np.cos(heading), speed * np.sin(heading), turn / self.control_period], axis=-1
        )

    def normalize_qpos(self, qpos: np.ndarray) -> None:
        """No quaternion to renormalise."""


#: Either agent.
MazeAgent = AntAgent | PointAgent
