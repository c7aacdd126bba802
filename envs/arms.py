"""The two DHRL robot-arm tasks, Reacher3D and UR3Obstacle: every fact of each in one :class:`ArmSpec`.

Goals are 3-D end-effector positions (world frame, metres) and the achieved goal is read from the arm's
end-effector site, so the same goal space serves the reward, the high level and the graph.

Reacher3D (:class:`~torchrl_dhrl.envs.PR2Arm`, facts of the reference): observation 17-D
``joint angles (7) ++ goal (3) ++ joint velocities (7)``; goals ``(0, 0.25, 0) + N(0, 0.1)`` per axis
(truncated to the workspace box ``[-1, 1]^3``, a 7.5-sigma box) for training and testing; sparse reward
and success within 0.25; 100-step episodes. The plant has the reference model's dynamics (46 kg of
density-1000 links, joint damping 10 on the shoulder, RK4; see :class:`~torchrl_dhrl.envs.PR2Arm`) and
every episode starts from the stretched-out zero posture at rest, without noise, the fingertip 1.08 m from
the goal mean: the arm is slow (about 0.017 m per step after 5 steps of full torque), and uniformly random
torques touch the 0.25 ball in about 9% of the episodes and end in it in about 1%. The reference's high
level used the first three joint angles as the achieved goal by mistake; here the fingertip position is
the achieved goal everywhere.

UR3Obstacle (:class:`~torchrl_dhrl.envs.UR3Arm`; the paper's environment is not public, this is our
design): the UR3 stands at the origin of a table. Three thin boards (1 cm thick, 25 cm tall) make a bin
on the arm's left (y > 0), open on top and towards the base: a fence in the plane y = 0 for
x in [0.25, 0.5], a front board at x = 0.5 and a far board at y = 0.36. The arm starts elbow-up with its
flange low on the right, at (0.3, -0.2, 0.1) (reset noise U(-0.05, 0.05) rad per joint). Test goals are
uniform in the box [0.31, 0.44] x [0.1, 0.27] x [0.05, 0.15], low inside the bin: the straight reach (in
Cartesian or in joint space) runs into the fence, so the end effector has to climb over the boards or
squeeze around the fence's inner end next to the base, and come back down. Train goals are uniform in
[0.15, 0.45] x [-0.3, 0.3] x [0.05, 0.35], on both sides of the fence, minus the boards grown by 5 cm
(like the mazes' train goals, they cover the whole free workspace). Success and sparse reward within
0.08 m: loose for a servoed arm, but below the gap (0.1 m or more) between any test goal and a flange held
outside the bin by a board or hovering above it, so success means getting into the bin, not precision.
100-step episodes of 0.05 s (5 s).
Observation 15-D ``flange position (3) ++ joint angles (6) ++ joint velocities (6)``, so
``achieved_goal`` is ``observation[:3]`` (the low level can use relative goals, as in the mazes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .arena import OVERVIEW_CAMERA, add_boxes, add_camera, add_floor, add_goal_marker, new_scene
from .goals import BoxGoalSampler, GaussianGoalSampler, GoalSampler
from .layouts import WallBox
from .robots import PR2Arm, UR3Arm
from .task import TaskSpec, lookup_spec

__all__ = ["ArmSpec", "ARMS", "ARM_NAMES", "get_arm_spec", "build_arm_mjcf", "ur3_boards"]

_PART_SIZES = {"qpos": "joints", "qvel": "joints", "goal": 3, "achieved": 3}
_BOARD_RGBA = (0.55, 0.4, 0.25, 1.0)


@dataclass(frozen=True)
class ArmSpec(TaskSpec):
    """Everything that defines one robot-arm environment (a :class:`~torchrl_dhrl.envs.TaskSpec`).

    Args:
        name (str): the environment name; the Gymnasium id is ``dhrl/<name>-v0``.
        agent (PR2Arm or UR3Arm): the arm, with its timestep, frame skip, control and reset posture.
        episode_length (int): env steps per episode (time limit, truncation only).
        success_threshold (float): evaluation success radius (m), measured on the final state.
        train_goals (GoalSampler): goal distribution of training episodes.
        test_goals (GoalSampler): goal distribution of evaluation episodes.
        workspace (tuple): ``(low, high)`` corners of the goal space; explicit goals must lie inside.
        typical_goal (tuple of float): the goal an env holds before its first reset.
        observation_layout (tuple of str): parts of the observation (see
            :attr:`~torchrl_dhrl.envs.TaskSpec.observation_layout`). Defaults to ``("qpos", "qvel")``.
        boards (tuple of WallBox): static obstacles. Defaults to none.
        table (bool): whether the floor (z = 0) is a table the arm collides with; otherwise it is a visual
            plane 1 m below. Defaults to ``False``.
        camera_pos (tuple of float): position of the overview camera. Defaults to ``(1.6, -1.6, 1.4)``.
        camera_target (tuple of float): point the overview camera looks at. Defaults to the origin.
        reward_threshold (float): the sparse reward is ``0`` within this distance, else ``-1``.
            Defaults to ``0.25``.

    Examples:
        >>> from torchrl_dhrl.envs import get_arm_spec
        >>> spec = get_arm_spec("UR3Obstacle")
        >>> spec.obs_dim, spec.goal_dim, spec.achieved_goal_site, len(spec.boards)
        (15, 3, 'ur3/flange', 3)
    """

    name: str
    agent: PR2Arm | UR3Arm
    episode_length: int
    success_threshold: float
    train_goals: GoalSampler
    test_goals: GoalSampler
    workspace: tuple[tuple[float, float, float], tuple[float, float, float]]
    typical_goal: tuple[float, float, float]
    observation_layout: tuple[str, ...] = ("qpos", "qvel")
    boards: tuple[WallBox, ...] = ()
    table: bool = False
    camera_pos: tuple[float, float, float] = (1.6, -1.6, 1.4)
    camera_target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    reward_threshold: float = 0.25

    @property
    def achieved_goal_site(self) -> str:
        """The end-effector site of the arm."""
        return self.agent.ee_site

    @property
    def goal_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)`` of the workspace box."""
        return tuple(np.asarray(corner, dtype=np.float64) for corner in self.workspace)

    @property
    def test_goal_sampler(self) -> GoalSampler:
        """The evaluation goal distribution."""
        return self.test_goals

    @property
    def reference_goal(self) -> np.ndarray:
        """:attr:`typical_goal` as an array."""
        return np.asarray(self.typical_goal, dtype=np.float64)

    @property
    def obs_dim(self) -> int:
        """Size of the observation (17 for Reacher3D, 15 for UR3Obstacle)."""
        joints = len(self.agent.init_qpos)
        return sum(joints if _PART_SIZES[p] == "joints" else _PART_SIZES[p] for p in self.observation_layout)

    def build_mjcf(self):
        """The arm scene, see :func:`build_arm_mjcf`."""
        return build_arm_mjcf(self)


def build_arm_mjcf(arm: str | ArmSpec):
    """Builds the MJCF scene of an arm task: floor or table, boards, goal marker, camera and the arm.

    Args:
        arm (str or ArmSpec): an arm task name or spec.

    Returns:
        the :class:`dm_control.mjcf.RootElement` of the whole scene.

    Examples:
        >>> from torchrl_dhrl.envs import build_arm_mjcf
        >>> root = build_arm_mjcf("UR3Obstacle")
        >>> [g.name for g in root.worldbody.find_all("geom") if g.name and g.name.startswith("board")]
        ['board_0', 'board_1', 'board_2']
    """
    spec = get_arm_spec(arm)
    agent = spec.agent
    root = new_scene(spec.name, agent)
    root.option.gravity = agent.gravity
    add_floor(root, (0.0, 0.0), 2.0, height=0.0 if spec.table else -1.0, collides=spec.table)
    add_boxes(root, spec.boards, prefix="board", rgba=_BOARD_RGBA)
    add_goal_marker(root, min(spec.reward_threshold, 0.05))
    add_camera(root, OVERVIEW_CAMERA, spec.camera_pos, spec.camera_target)
    agent.attach_to(root)
    return root


def ur3_boards(height: float = 0.25, thickness: float = 0.01) -> tuple[WallBox, WallBox, WallBox]:
    """The three boards of UR3Obstacle: a bin at x in [0.25, 0.5], y in [0, 0.36], open on top and towards
    the base.

    The fence (in the plane y = 0) starts at x = 0.25, just outside the circle swept by the UR3's shoulder
    housing when the base joint turns, and ends at the front board; the far end is out of the arm's reach.

    Args:
        height (float): board height above the table (m). Defaults to ``0.25``.
        thickness (float): board thickness (m). Defaults to ``0.01``.

    Examples:
        >>> from torchrl_dhrl.envs import ur3_boards
        >>> [board.xy_bounds for board in ur3_boards()]
        [(0.25, 0.5, -0.005, 0.005), (0.495, 0.505, 0.0, 0.36), (0.25, 0.5, 0.355, 0.365)]
    """
    h, t = height / 2, thickness / 2
    return (
        WallBox(center=(0.375, 0.0, h), half_size=(0.125, t, h)),  # fence, between start and goal
        WallBox(center=(0.5, 0.18, h), half_size=(t, 0.18, h)),  # front board
        WallBox(center=(0.375, 0.36, h), half_size=(0.125, t, h)),  # far board
    )


def _make_arms() -> dict[str, ArmSpec]:
    workspace = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    reacher_goals = GaussianGoalSampler((0.0, 0.25, 0.0), (0.1, 0.1, 0.1), *workspace)
    boards = ur3_boards()
    # Train goals: uniform in the reachable box in front of the arm, both sides of the fence, minus the
    # boards grown by 5 cm; test goals: low inside the bin, behind the fence.
    margin = 0.05
    excluded = tuple(
        (
            box.center[0] - box.half_size[0] - margin,
            box.center[0] + box.half_size[0] + margin,
            box.center[1] - box.half_size[1] - margin,
            box.center[1] + box.half_size[1] + margin,
            -np.inf,
            2 * box.half_size[2] + margin,
        )
        for box in boards
    )
    specs = [
        ArmSpec(
            name="Reacher3D",
            agent=PR2Arm(),
            episode_length=100,
            success_threshold=0.25,
            train_goals=reacher_goals,
            test_goals=reacher_goals,
            workspace=workspace,
            observation_layout=("qpos", "goal", "qvel"),
            typical_goal=(0.0, 0.25, 0.0),
            reward_threshold=0.25,
        ),
        ArmSpec(
            name="UR3Obstacle",
            agent=UR3Arm(),
            episode_length=100,
            success_threshold=0.08,
            train_goals=BoxGoalSampler((0.15, -0.3, 0.05), (0.45, 0.3, 0.35), excluded=excluded),
            test_goals=BoxGoalSampler((0.31, 0.1, 0.05), (0.44, 0.27, 0.15)),
            workspace=((-0.6, -0.6, 0.0), (0.6, 0.6, 0.7)),
            observation_layout=("achieved", "qpos", "qvel"),
            typical_goal=(0.375, 0.18, 0.1),
            boards=boards,
            table=True,
            camera_pos=(1.1, -0.9, 0.9),
            camera_target=(0.2, 0.05, 0.1),
            reward_threshold=0.08,
        ),
    ]
    return {spec.name: spec for spec in specs}


#: Every arm task by name.
ARMS: dict[str, ArmSpec] = _make_arms()
#: The valid arm task names.
ARM_NAMES: tuple[str, ...] = tuple(ARMS)


def get_arm_spec(arm: str | ArmSpec) -> ArmSpec:
    """Returns the :class:`ArmSpec` of ``arm``, a name (``"Reacher3D"`` or ``"dhrl/Reacher3D-v0"``) or a spec.

    Raises:
        ValueError: for an unknown name (the message lists the valid ones).
        TypeError: for anything else than a string or an :class:`ArmSpec`.

    Examples:
        >>> from torchrl_dhrl.envs import get_arm_spec
        >>> get_arm_spec("Reacher3D").agent.ctrl_limit
        20.0
    """
    return lookup_spec(arm, ARMS, ArmSpec, "arm task")
