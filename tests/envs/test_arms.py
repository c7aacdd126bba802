"""UR3Obstacle's boards: geometry, collisions detected, the straight reach blocked, a detour that works."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from torchrl_dhrl.envs import GoalSimulation, get_arm_spec

GOAL = np.array([0.375, 0.18, 0.1])  # inside the bin, behind the fence
# A collision-free joint-space detour to GOAL (found offline by inverse kinematics): lift the flange to
# z = 0.38 above the start, swing over the fence to above the goal, come down into the bin.
DETOUR = (
    (-0.271, -1.806, -0.986, -1.92, 1.571, 0.0),
    (0.721, -2.126, -0.512, -2.074, 1.571, 0.0),
    (0.721, -2.309, -1.615, -0.789, 1.571, 0.0),
)


def _board_contacts(model, data) -> list[tuple[str, str]]:
    """(arm geom, board geom) pairs in contact in ``data`` (after mj_forward / mj_step)."""
    pairs = []
    for contact in data.contact[: data.ncon]:
        names = sorted((model.geom(contact.geom1).name, model.geom(contact.geom2).name))
        if names[0].startswith("board") and names[1].startswith("ur3/"):
            pairs.append((names[1], names[0]))
    return pairs


class _ContactLog:
    """Arm-board contacts of env 0 after every env step, from its own MjData and a fresh collision pass."""

    def __init__(self, sim):
        self.sim, self.probe, self.pairs = sim, mujoco.MjData(sim.model), []

    def record(self):
        model, data = self.sim.model, self.sim.datas[0]
        self.probe.qpos[:] = data.qpos
        mujoco.mj_forward(model, self.probe)
        self.pairs += _board_contacts(model, data) + _board_contacts(model, self.probe)


def _start(sim):
    spec = sim.spec
    sim.reset(goals=GOAL)
    sim.set_state(0, spec.agent.init_qpos)  # the noise-free start posture
    return _ContactLog(sim)


def test_board_geometry():
    spec = get_arm_spec("UR3Obstacle")
    model = spec.compile_model()
    boards = [model.geom(f"board_{k}") for k in range(3)]
    for geom, box in zip(boards, spec.boards, strict=True):
        np.testing.assert_allclose(geom.pos, box.center)
        np.testing.assert_allclose(geom.size, box.half_size)
        assert min(geom.size) <= 0.005  # thin: 1 cm thick
        assert model.geom_conaffinity[geom.id] and not model.geom_contype[geom.id]
    # The fence lies between the start (y < 0) and the test goals (y > 0), taller than the goal region.
    sim = GoalSimulation(spec, 1)
    sim.set_state(0, spec.agent.init_qpos)
    fence = spec.boards[0]
    assert sim.achieved_goal[0, 1] < fence.center[1] - fence.half_size[1] < spec.test_goals.low[1]
    assert 2 * fence.half_size[2] > spec.test_goals.high[2] + spec.success_threshold


def test_collisions_with_boards_are_detected():
    """Turning the low arm's base joint sweeps it through the fence: contacts in the middle, none at the ends.

    The posture on the far side (base turned by 1 rad) is free: the boards block the path, not the goal.
    """
    spec = get_arm_spec("UR3Obstacle")
    sim = GoalSimulation(spec, 1)
    touched = []
    for turn in np.linspace(0.0, 1.0, 11):
        q = np.array(spec.agent.init_qpos)
        q[0] += turn
        sim.set_state(0, q)
        touched.append({b for _, b in _board_contacts(sim.model, sim.datas[0])})
    assert touched[0] == touched[-1] == set() and sim.achieved_goal[0, 1] > 0.1
    assert {"board_0"} in touched and set().union(*touched) == {"board_0"}


def test_straight_reach_is_blocked():
    """Driving the flange along the straight line to a goal behind the fence: the arm hits the fence."""
    spec = get_arm_spec("UR3Obstacle")
    sim = GoalSimulation(spec, 1, seed=0)
    log = _start(sim)
    model, data = sim.model, sim.datas[0]
    site = model.site(spec.achieved_goal_site).id
    jacobian = np.zeros((3, model.nv))
    distances = []
    for _ in range(60):
        mujoco.mj_jacSite(model, data, jacobian, None, site)
        error = GOAL - sim.achieved_goal[0]
        velocity = error * min(1.0, 0.02 / np.linalg.norm(error))  # 2 cm per step along the line
        dq = np.linalg.pinv(jacobian) @ velocity
        sim.step(np.clip(dq / (2 / 3 * spec.agent.max_delta), -1, 1)[None])
        log.record()
        distances.append(np.linalg.norm(sim.achieved_goal[0] - GOAL))
    assert {board for _, board in log.pairs} == {"board_0"}  # the fence stops it
    assert min(distances) > spec.success_threshold + 0.02


def test_joint_space_straight_line_is_blocked():
    """Servoing all joints straight to the goal posture (the last detour posture) also hits the fence."""
    spec = get_arm_spec("UR3Obstacle")
    sim = GoalSimulation(spec, 1, seed=0)
    log = _start(sim)
    for _ in range(40):
        error = np.array(DETOUR[-1]) - sim.observation[0, 3:9]
        sim.step((error / max(spec.agent.max_delta, np.abs(error).max()))[None])
        log.record()
    assert "board_0" in {board for _, board in log.pairs}
    assert not sim.evaluate()[1][0]


def test_detour_reaches_the_goal_without_collision():
    """The scripted joint-space detour, executed by the env's servos, reaches the goal touching no board."""
    spec = get_arm_spec("UR3Obstacle")
    sim = GoalSimulation(spec, 1, seed=0)
    log = _start(sim)
    waypoints = [np.array(w) for w in DETOUR]
    success = []
    for _ in range(70):
        error = waypoints[0] - sim.observation[0, 3:9]
        if np.abs(error).max() < 0.03 and len(waypoints) > 1:
            waypoints.pop(0)
            error = waypoints[0] - sim.observation[0, 3:9]
        # One direction for all joints (a straight joint-space segment), at most max_delta per step.
        _, succeeded, _ = sim.step((error / max(spec.agent.max_delta, np.abs(error).max()))[None])
        success.append(bool(succeeded[0]))
        log.record()
    assert log.pairs == []
    assert len(waypoints) == 1 and success[-1] and not success[0]
    assert np.linalg.norm(sim.achieved_goal[0] - GOAL) < 0.01


@pytest.mark.parametrize("name", ["Reacher3D", "UR3Obstacle"])
def test_no_obstacles_in_reacher(name):
    """Reacher3D is free space (no boards, no table); UR3Obstacle has its three boards and a table."""
    spec = get_arm_spec(name)
    model = spec.compile_model()
    boards = [g for g in range(model.ngeom) if model.geom(g).name.startswith("board")]
    floor = model.geom("floor").id
    if name == "Reacher3D":
        assert boards == [] and model.geom_conaffinity[floor] == 0
    else:
        assert len(boards) == 3 and model.geom_conaffinity[floor] == 1
