"""The two robot arms of the DHRL arm tasks, built programmatically with :mod:`dm_control.mjcf`.

Both arms are written from published facts, no XML file is involved:

* :class:`PR2Arm`: the 7-DoF arm of Reacher3D with the PR2 arm's link lengths and joint order (shoulder
  pan, shoulder lift, upper-arm roll, elbow flex, forearm roll, wrist flex, wrist roll), and the link
  shapes, joint damping and integrator of the reference Reacher3D model (so the same dynamics); torque
  motors with ``ctrlrange -20..20``, no gravity;
* :class:`UR3Arm`: the 6-DoF Universal Robots UR3 of UR3Obstacle, whose body frames are the frames of the
  published standard Denavit-Hartenberg table, with position servos.

Each arm knows how to build its MJCF model (:meth:`build_mjcf`), attach it to a scene (:meth:`attach_to`)
and turn a batch of policy actions into the controls written into ``MjData.ctrl`` (:meth:`command`); the
end effector is the site :attr:`ee_site` (``"<model>/<site>"`` once attached).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from .agents import AGENT_CONTYPE, MotorControl

with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message=".*DISPLAY.*")
    from dm_control import mjcf

__all__ = ["PR2Arm", "UR3Arm", "UR3_DH"]

_ARM_RGBA = (0.75, 0.75, 0.8, 1.0)
_JOINT_RGBA = (0.25, 0.35, 0.6, 1.0)
_LENS_RGBA = (0.1, 0.1, 0.1, 1.0)

# Link shapes of the PR2-like arm (m), those of the reference Reacher3D model; every geom has the density
# PR2Arm.density, so these fix the masses and inertias. Shoulder: a column along the pan axis (z from,
# z to, radius) and a head on its top, two spheres with lenses at x = -+x, y (x, y, radius).
_PR2_COLUMN = (-0.4, 0.2, 0.1)
_PR2_HEAD = ((0.06, 0.05, 0.05), (0.06, 0.09, 0.03))
# Per flex/roll pair (shoulder lift / upper-arm roll, elbow flex / forearm roll, wrist flex / wrist roll):
# the housing of the flex joint across the link (along y) and the collar of the roll joint along it (x),
# ``(half-length, radius)`` each, and the radius of the link capsule that follows (upper arm, forearm).
_PR2_HOUSINGS = ((0.1, 0.1), (0.02, 0.06), (0.02, 0.01))
_PR2_COLLARS = ((0.1, 0.02), (0.1, 0.02), (0.02, 0.01))
_PR2_LINK_RADII = (0.06, 0.05)
# Hand, on the wrist roll: a palm across it (capsule along z at x: x, half-length, radius) and two fingers
# with knuckles at (x, +-y), each a splayed phalanx (dx, +-dy) and a straight one (dx, 0), of one radius.
_PR2_PALM = (0.05, 0.02, 0.05)
_PR2_FINGERS = (0.07691, 0.03, 0.09137, 0.00495, 0.01)


def _new_arm_model(name: str, damping: float, armature: float, collides: bool) -> mjcf.RootElement:
    """An empty arm model: hinge defaults and arm geoms that collide with static geoms only."""
    root = mjcf.RootElement(model=name)
    root.compiler.angle = "radian"
    root.default.joint.type = "hinge"
    root.default.joint.damping = damping
    root.default.joint.armature = armature
    geom = root.default.geom
    geom.contype = AGENT_CONTYPE if collides else 0
    geom.conaffinity = 0
    geom.condim = 3
    geom.rgba = _ARM_RGBA
    return root


def _capsule(body: mjcf.Element, name: str, start, end, radius: float, mass=None, rgba=None) -> None:
    """A capsule from ``start`` to ``end``; its mass is ``mass``, or its volume times the geom density."""
    extra = {} if mass is None else {"mass": mass}
    if rgba is not None:
        extra["rgba"] = rgba
    body.add(
        "geom",
        name=name,
        type="capsule",
        fromto=tuple(float(v) for v in (*start, *end)),
        size=[radius],
        **extra,
    )


def _joint_range(limit) -> dict:
    return {"limited": False} if limit is None else {"limited": True, "range": tuple(limit)}


@dataclass(frozen=True)
class PR2Arm(MotorControl):
    """The 7-DoF PR2-like arm of Reacher3D: torque motors, no gravity, no contacts.

    Kinematics: the PR2 arm's link lengths, 0.1 m from the shoulder pan axis to the shoulder lift axis,
    0.4 m upper arm (shoulder lift to elbow flex) and 0.321 m forearm (elbow flex to wrist flex); the
    fingertip site, the achieved goal, lies 0.16828 m beyond the wrist flex axis, between the two finger
    joints (the reference's end-effector point). Joints, in ``qpos`` order: shoulder pan (about z), shoulder
    lift (y), upper-arm roll (x, along the upper arm), elbow flex (y), forearm roll (x), wrist flex (y),
    wrist roll (x), one body each (``<joint>_link``). At zero angles the arm is stretched along the base's
    x axis. Ranges are the PR2 right arm's; the forearm and wrist rolls are continuous.

    Dynamics: those of the reference Reacher3D model. Every geom is a capsule or sphere of density 1000
    (kg/m^3): a 0.6 m shoulder column of radius 0.1 with a head on top, housings at the flex joints and
    collars at the roll joints, the upper arm and forearm capsules and a hand with palm and two fingers;
    46.2 kg in all, joint-space inertia 3.57 (shoulder pan) and 2.30 (shoulder lift) kg m^2 at the zero
    posture. Joint damping is 10 on the two shoulder joints, 1 on the elbow and 0.1 on the rolls and the
    wrist flex; armature 0.04; RK4 integration, 0.01 s steps, two per env step. Under a full +20 torque on
    every joint the fingertip moves about 0.017 m per env step after 5 steps (the elbow and wrist, straight
    at the start, press on their limits; the light rolls spin up to ~40 rad/s); once released, the damped
    shoulder halves its speed in about 9 env steps, while the rolls, damped by only 0.1, keep the hand
    moving for tens of steps. Joint limits are MuJoCo's default soft limits: thrown at a limit by random
    torques, the light upper-arm roll and wrist flex overshoot it by up to ~0.3 rad, as in the reference.
    The arm collides with nothing (Reacher3D has no obstacles and no gravity). Actions are the 7 joint
    torques, clipped to ``[-ctrl_limit, ctrl_limit]``. Episodes start at the zero posture, at rest, without
    noise: the fingertip at ``(0.989, -0.188, 0)``, 1.08 m from the goal mean.

    Args:
        shoulder_offset (float): pan axis to lift axis. Defaults to ``0.1``.
        upper_arm (float): upper arm length. Defaults to ``0.4``.
        forearm (float): forearm length. Defaults to ``0.321``.
        hand (float): wrist flex axis to the fingertip site. Defaults to ``0.16828``.
        joint_ranges (tuple): ``(low, high)`` per joint in radians, ``None`` for a continuous joint.
            Defaults to the PR2 right arm's.
        damping (tuple of float): joint damping per joint (N m s / rad). Defaults to
            ``(10, 10, 0.1, 1, 0.1, 0.1, 0.1)``.
        armature (float): joint armature (kg m^2). Defaults to ``0.04``.
        density (float): density of every geom (kg/m^3). Defaults to ``1000`` (MuJoCo's default).
        ctrl_limit (float): motors accept torques in ``[-ctrl_limit, ctrl_limit]``. Defaults to ``20``.
        base_pos (tuple of float): world position of the shoulder (pan axis). Defaults to
            ``(0, -0.188, 0)``.
        base_yaw (float): heading of the arm's forward axis in the world. Defaults to ``0`` (+x).
        init_qpos (tuple of float): reset posture before noise. Defaults to zeros (the stretched arm).
        qpos_noise (float): reset noise ``U(-qpos_noise, qpos_noise)`` on every joint angle. Defaults to
            ``0`` (the reference resets without noise).
        qvel_noise (float): reset noise ``N(0, qvel_noise)`` on every joint velocity. Defaults to ``0``.
        timestep (float): MuJoCo timestep. Defaults to ``0.01``.
        frame_skip (int): physics steps per env step. Defaults to ``2``.
        integrator (str): MuJoCo integrator. Defaults to ``"RK4"``.

    Examples:
        >>> from torchrl_dhrl.envs import PR2Arm
        >>> arm = PR2Arm()
        >>> arm.action_dim, arm.action_high.tolist()[:2], arm.ee_site
        (7, [20.0, 20.0], 'pr2/fingertip')
        >>> [j.name for j in arm.build_mjcf().find_all("joint")][:3]
        ['shoulder_pan', 'shoulder_lift', 'upper_arm_roll']
        >>> arm.damping[:4], arm.integrator
        ((10.0, 10.0, 0.1, 1.0), 'RK4')
    """

    shoulder_offset: float = 0.1
    upper_arm: float = 0.4
    forearm: float = 0.321
    hand: float = 0.16828
    joint_ranges: tuple = (
        (-2.2854, 1.714602),
        (-0.5236, 1.3963),
        (-3.9, 0.8),
        (-2.3213, 0.0),
        None,
        (-2.094, 0.0),
        None,
    )
    damping: tuple[float, ...] = (10.0, 10.0, 0.1, 1.0, 0.1, 0.1, 0.1)
    armature: float = 0.04
    density: float = 1000.0
    ctrl_limit: float = 20.0
    base_pos: tuple[float, float, float] = (0.0, -0.188, 0.0)
    base_yaw: float = 0.0
    init_qpos: tuple[float, ...] = (0.0,) * 7
    qpos_noise: float = 0.0
    qvel_noise: float = 0.0
    timestep: float = 0.01
    frame_skip: int = 2
    integrator: str = "RK4"

    #: Joint names in ``qpos`` order.
    joint_names = (
        "shoulder_pan",
        "shoulder_lift",
        "upper_arm_roll",
        "elbow_flex",
        "forearm_roll",
        "wrist_flex",
        "wrist_roll",
    )
    #: The model name (prefix of every element once attached).
    model_name = "pr2"
    #: Gravity of the scene: none.
    gravity = (0.0, 0.0, 0.0)

    @property
    def action_dim(self) -> int:
        """Number of motors (one per joint)."""
        return 7

    @property
    def ee_site(self) -> str:
        """Full name of the fingertip site (the achieved goal)."""
        return f"{self.model_name}/fingertip"

    def build_mjcf(self) -> mjcf.RootElement:
        """Builds the arm: the shoulder pan body, a flex body and a roll body at each of the shoulder lift,
        the elbow and the wrist (the hand rolls with the wrist), and one motor per joint."""
        root = _new_arm_model(self.model_name, 0.0, self.armature, collides=False)
        root.default.geom.density = self.density
        ranges = dict(zip(self.joint_names, self.joint_ranges, strict=True))
        damping = dict(zip(self.joint_names, self.damping, strict=True))

        def link(parent: mjcf.Element, joint: str, axis, pos=(0.0, 0.0, 0.0), **frame) -> mjcf.Element:
            body = parent.add("body", name=f"{joint}_link", pos=pos, **frame)
            body.add("joint", name=joint, axis=axis, damping=damping[joint], **_joint_range(ranges[joint]))
            return body

        yaw = self.base_yaw
        shoulder = link(
            root.worldbody,
            "shoulder_pan",
            (0, 0, 1),
            self.base_pos,
            quat=(np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)),
        )
        z_low, z_high, column_radius = _PR2_COLUMN
        _capsule(shoulder, "column", (0, 0, z_low), (0, 0, z_high), column_radius, rgba=_JOINT_RGBA)
        for side, sign in (("l", -1.0), ("r", 1.0)):
            for part, (x, y, radius), rgba in zip(
                ("head", "lens"), _PR2_HEAD, (_ARM_RGBA, _LENS_RGBA), strict=True
            ):
                shoulder.add(
                    "geom",
                    name=f"{part}_{side}",
                    type="sphere",
                    pos=(sign * x, y, z_high),
                    size=[radius],
                    rgba=rgba,
                )
        pairs = zip(
            self.joint_names[1::2],
            self.joint_names[2::2],
            (self.shoulder_offset, self.upper_arm, self.forearm),
            _PR2_HOUSINGS,
            _PR2_COLLARS,
            (
                ("upper_arm", self.upper_arm, _PR2_LINK_RADII[0]),
                ("forearm", self.forearm, _PR2_LINK_RADII[1]),
                None,
            ),
            strict=True,
        )
        parent = shoulder
        for flex, roll, offset, (housing, housing_radius), (collar, collar_radius), segment in pairs:
            flex_body = link(parent, flex, (0, 1, 0), (offset, 0.0, 0.0))
            _capsule(
                flex_body,
                f"{flex}_housing",
                (0, -housing, 0),
                (0, housing, 0),
                housing_radius,
                rgba=_JOINT_RGBA,
            )
            parent = link(flex_body, roll, (1, 0, 0))
            _capsule(
                parent, f"{roll}_collar", (-collar, 0, 0), (collar, 0, 0), collar_radius, rgba=_JOINT_RGBA
            )
            if segment is not None:
                name, length, radius = segment
                _capsule(parent, name, (0, 0, 0), (length, 0, 0), radius)
        palm_x, palm_half, palm_radius = _PR2_PALM
        _capsule(parent, "palm", (palm_x, 0, -palm_half), (palm_x, 0, palm_half), palm_radius)
        knuckle_x, knuckle_y, phalanx, splay, finger_radius = _PR2_FINGERS
        for side, sign in (("l", 1.0), ("r", -1.0)):
            knuckle = np.array((knuckle_x, sign * knuckle_y, 0.0))
            tip = knuckle + (phalanx, sign * splay, 0.0)
            _capsule(parent, f"finger_{side}", knuckle, tip, finger_radius)
            _capsule(parent, f"finger_tip_{side}", tip, tip + (phalanx, 0.0, 0.0), finger_radius)
        parent.add("site", name="fingertip", pos=(self.hand, 0.0, 0.0), size=[0.02], rgba=(0.1, 0.8, 0.1, 1))
        for name in self.joint_names:
            root.actuator.add(
                "motor",
                name=f"{name}_motor",
                joint=name,
                gear=[1],
                ctrllimited=True,
                ctrlrange=(-self.ctrl_limit, self.ctrl_limit),
            )
        return root

    def attach_to(self, scene: mjcf.RootElement) -> mjcf.Element:
        """Attaches the arm to ``scene`` (the shoulder sits at :attr:`base_pos`)."""
        return scene.worldbody.attach(self.build_mjcf())


#: The UR3's published standard DH parameters ``(d, a, alpha)`` per joint (metres, radians).
UR3_DH: tuple[tuple[float, float, float], ...] = (
    (0.1519, 0.0, np.pi / 2),
    (0.0, -0.24365, 0.0),
    (0.0, -0.21325, 0.0),
    (0.11235, 0.0, np.pi / 2),
    (0.08535, 0.0, -np.pi / 2),
    (0.0819, 0.0, 0.0),
)


@dataclass(frozen=True)
class UR3Arm:
    """The 6-DoF UR3 arm of UR3Obstacle, with gravity-compensated position servos.

    Kinematics: body ``link_k`` (k = 1..6) carries joint ``k`` as a hinge about its own z axis, and its
    child sits at ``(a_k, 0, d_k)`` rotated by ``alpha_k`` about x: the frames of the published standard
    DH table :data:`UR3_DH` (``T_k = Rz(q_k) Tz(d_k) Tx(a_k) Rx(alpha_k)``). The end-effector site is the
    flange centre, the origin of DH frame 6, so its world position is the DH forward kinematics of ``qpos``
    (the base frame is the world frame; the base sits on the table at the origin).

    Collision geometry: capsules along the links, offset along the joint axes as on the real arm (shoulder
    offset 0.12 m, elbow offset back by 0.093 m; the DH ``d4`` is what remains), radii 4.5 to 3.2 cm.
    Masses are the UR3's published link masses (2.0, 3.42, 1.26, 0.8, 0.8, 0.35 kg), spread over the
    capsules; MuJoCo derives the inertias from the capsule shapes. The arm collides with the table and the
    boards, not with itself. Every body has ``gravcomp=1``: like the real UR3 controller, gravity is
    compensated, so a zero action holds the posture.

    Control: one position servo per joint (``kp`` per joint, joint damping as the velocity gain, torque
    limited to the UR3's rated joint torques 56, 56, 28, 12, 12, 12 N m). An action ``a`` in ``[-1, 1]^6``
    offsets each servo target from the measured joint angle by ``max_delta * a`` radians (clipped to the
    joint range), so the action is a joint-velocity command. Position servos rather than torque motors: they make
    the arm hold its posture, stop softly against a board instead of bouncing, and keep the action scale
    the same for the heavy shoulder and the light wrist; relative targets keep a uniformly random action
    a random walk around the current posture (absolute targets would pull the arm towards the middle of
    the joint ranges). No hidden state: the target is a function of the current observation.

    Args:
        dh (tuple): the DH table ``(d, a, alpha)`` per joint. Defaults to :data:`UR3_DH`.
        link_masses (tuple of float): link masses (kg). Defaults to the UR3's.
        joint_limit (float): every joint moves in ``[-joint_limit, joint_limit]``. Defaults to ``2 pi``
            (the UR3's +-360 degrees).
        max_delta (float): servo target offset (radians) of a unit action. Defaults to ``0.15``: since the
            target is re-centred on the measured angle every step, a held unit action turns a joint by
            ``2/3 * max_delta = 0.1`` rad per env step (2 rad/s) at steady state (the UR3's rated speeds are
            3.1 and 6.3 rad/s).
        kp (tuple of float): servo stiffness per joint (N m / rad). Defaults to ``(400, 400, 200, 60, 60,
            40)``.
        damping (tuple of float): joint damping per joint (the servo's velocity gain, N m s / rad).
            Defaults to ``kp * 0.05 s``, ``(20, 20, 10, 3, 3, 2)`` (the same response time for every joint).
        armature (tuple of float): reflected rotor inertia per joint. Defaults to ``(0.2, 0.2, 0.1, 0.02,
            0.02, 0.02)``.
        torque_limits (tuple of float): servo torque limits (N m). Defaults to the UR3's ratings.
        init_qpos (tuple of float): reset posture before noise. Defaults to an elbow-up posture with the tool
            pointing down and the flange at about ``(0.3, -0.2, 0.1)``.
        qpos_noise (float): reset noise ``U(-qpos_noise, qpos_noise)`` on every joint angle. Defaults to
            ``0.05``.
        qvel_noise (float): reset noise ``N(0, qvel_noise)`` on every joint velocity. Defaults to ``0``
            (the servo would erase it within a step anyway).
        timestep (float): MuJoCo timestep. Defaults to ``0.005``.
        frame_skip (int): physics steps per env step. Defaults to ``10`` (0.05 s per env step).
        integrator (str): MuJoCo integrator. Defaults to ``"implicitfast"``.

    Examples:
        >>> import numpy as np
        >>> from torchrl_dhrl.envs import UR3Arm
        >>> arm = UR3Arm()
        >>> arm.action_dim, arm.ee_site
        (6, 'ur3/flange')
        >>> target = arm.command(np.array([[1.0, -2.0, 0, 0, 0, 0]]), np.zeros((1, 6)))
        >>> target.round(3).tolist()  # joint 2's action is clipped to -1
        [[0.15, -0.15, 0.0, 0.0, 0.0, 0.0]]
    """

    dh: tuple[tuple[float, float, float], ...] = UR3_DH
    link_masses: tuple[float, ...] = (2.0, 3.42, 1.26, 0.8, 0.8, 0.35)
    joint_limit: float = 2 * np.pi
    max_delta: float = 0.15
    kp: tuple[float, ...] = (400.0, 400.0, 200.0, 60.0, 60.0, 40.0)
    damping: tuple[float, ...] = (20.0, 20.0, 10.0, 3.0, 3.0, 2.0)
    armature: tuple[float, ...] = (0.2, 0.2, 0.1, 0.02, 0.02, 0.02)
    torque_limits: tuple[float, ...] = (56.0, 56.0, 28.0, 12.0, 12.0, 12.0)
    init_qpos: tuple[float, ...] = (-0.271, -2.151, -1.943, -0.618, 1.571, 0.0)
    qpos_noise: float = 0.05
    qvel_noise: float = 0.0
    timestep: float = 0.005
    frame_skip: int = 10
    integrator: str = "implicitfast"

    #: The MjData field :meth:`command` writes: the servo targets.
    control_field = "ctrl"
    #: The model name (prefix of every element once attached).
    model_name = "ur3"
    #: Gravity of the scene (compensated on the arm by ``gravcomp``).
    gravity = (0.0, 0.0, -9.81)
    #: Shoulder offset along the joint-2 axis and elbow offset along joint 3's (real UR3 geometry, m).
    shoulder_offset = 0.12
    elbow_offset = 0.0273

    @property
    def action_dim(self) -> int:
        """One action per joint."""
        return 6

    @property
    def action_low(self) -> np.ndarray:
        """Lower bound of the action box (``-1``: the largest backward step)."""
        return -np.ones(self.action_dim)

    @property
    def action_high(self) -> np.ndarray:
        """Upper bound of the action box (``1``: the largest forward step)."""
        return np.ones(self.action_dim)

    @property
    def ee_site(self) -> str:
        """Full name of the flange site (the achieved goal)."""
        return f"{self.model_name}/flange"

    def command(self, actions: np.ndarray, qpos: np.ndarray) -> np.ndarray:
        """Servo targets ``qpos + max_delta * clip(actions, -1, 1)``, clipped to the joint range.

        Args:
            actions (np.ndarray): ``[N, 6]`` actions.
            qpos (np.ndarray): ``[N, 6]`` current joint angles.
        """
        target = qpos + self.max_delta * np.clip(actions, -1.0, 1.0)
        return np.clip(target, -self.joint_limit, self.joint_limit)

    def normalize_qpos(self, qpos: np.ndarray) -> None:
        """Nothing to renormalise (hinges only)."""

    def _link_geoms(self) -> tuple[tuple[tuple, tuple, float, float], ...]:
        """Capsules ``(start, end, radius, mass)`` of links 1-6 in their own (DH ``k - 1``) frames."""
        (d1, _, _), (_, a2, _), (_, a3, _), (d4, _, _), (d5, _, _), (d6, _, _) = self.dh
        s, e = self.shoulder_offset, self.elbow_offset
        m1, m2, m3, m4, m5, m6 = self.link_masses
        return (
            (((0, 0, 0.09), (0, 0, d1), 0.045, m1),),
            (((0, 0, -0.03), (0, 0, s), 0.045, 0.3 * m2), ((0, 0, s), (a2, 0, s), 0.04, 0.7 * m2)),
            (((0, 0, s), (0, 0, e), 0.038, 0.25 * m3), ((0, 0, e), (a3, 0, e), 0.035, 0.75 * m3)),
            (((0, 0, e), (0, 0, d4), 0.032, m4),),
            (((0, 0, -0.03), (0, 0, d5), 0.032, m5),),
            (((0, 0, -0.02), (0, 0, d6), 0.032, m6),),
        )

    def build_mjcf(self) -> mjcf.RootElement:
        """Builds the UR3: a static base on the table and links 1-6 on the DH frames, with servos."""
        root = _new_arm_model(self.model_name, 0.0, 0.0, collides=True)
        root.worldbody.add(
            "geom",
            name="base_geom",
            type="cylinder",
            pos=(0, 0, 0.045),
            size=(0.064, 0.045),
            rgba=_JOINT_RGBA,
        )
        parent, child_pos, child_quat = root.worldbody, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)
        for k, ((d, a, alpha), capsules) in enumerate(zip(self.dh, self._link_geoms(), strict=True), start=1):
            body = parent.add("body", name=f"link_{k}", pos=child_pos, quat=child_quat, gravcomp=1.0)
            body.add(
                "joint",
                name=f"joint_{k}",
                axis=(0, 0, 1),
                range=(-self.joint_limit, self.joint_limit),
                limited=True,
                damping=self.damping[k - 1],
                armature=self.armature[k - 1],
            )
            for j, (start, end, radius, mass) in enumerate(capsules):
                _capsule(
                    body, f"link_{k}_geom_{j}", start, end, radius, mass, _JOINT_RGBA if j == 0 else None
                )
            parent, child_pos, child_quat = (
                body,
                (a, 0.0, d),
                (np.cos(alpha / 2), np.sin(alpha / 2), 0.0, 0.0),
            )
        parent.add("site", name="flange", pos=child_pos, size=[0.015], rgba=(0.1, 0.8, 0.1, 1))
        for k in range(1, 7):
            root.actuator.add(
                "position",
                name=f"servo_{k}",
                joint=f"joint_{k}",
                kp=self.kp[k - 1],
                ctrllimited=True,
                ctrlrange=(-self.joint_limit, self.joint_limit),
                forcelimited=True,
                forcerange=(-self.torque_limits[k - 1], self.torque_limits[k - 1]),
            )
        return root

    def attach_to(self, scene: mjcf.RootElement) -> mjcf.Element:
        """Attaches the arm to ``scene`` with its base frame at the world origin."""
        return scene.worldbody.attach(self.build_mjcf())
