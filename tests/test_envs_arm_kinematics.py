"""Arm kinematics and models: achieved goals against MuJoCo sites and against independent numpy FK."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from torchrl_dhrl.envs import GoalSimulation, get_arm_spec

# Published UR3 standard DH parameters (d, a, alpha), written out here independently of the package.
UR3_D = (0.1519, 0.0, 0.0, 0.11235, 0.08535, 0.0819)
UR3_A = (0.0, -0.24365, -0.21325, 0.0, 0.0, 0.0)
UR3_ALPHA = (np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0)
# PR2 arm link lengths (m): pan axis -> lift axis, upper arm, forearm, wrist flex -> fingertip (the point
# between the two finger joints, the reference Reacher3D's end-effector point).
PR2_LINKS = (0.1, 0.4, 0.321, 0.16828)


def _rz(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def _ry(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])


def _rx(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def _tr(x=0.0, y=0.0, z=0.0):
    out = np.eye(4)
    out[:3, 3] = (x, y, z)
    return out


def ur3_dh_fk(q):
    """Flange position of the UR3 by the standard DH product ``prod_k Rz(q_k) Tz(d_k) Tx(a_k) Rx(alpha_k)``."""
    transform = np.eye(4)
    for qk, d, a, alpha in zip(q, UR3_D, UR3_A, UR3_ALPHA, strict=True):
        transform = transform @ _rz(qk) @ _tr(z=d) @ _tr(x=a) @ _rx(alpha)
    return transform[:3, 3]


def pr2_fk(q, base=(0.0, -0.188, 0.0), yaw=0.0):
    """Fingertip of the PR2-like arm: pan (z), then (flex about y, roll about x) at the lift, elbow and wrist."""
    offset, upper, fore, hand = PR2_LINKS
    t = _tr(*base) @ _rz(yaw) @ _rz(q[0]) @ _tr(x=offset)
    t = t @ _ry(q[1]) @ _rx(q[2]) @ _tr(x=upper)
    t = t @ _ry(q[3]) @ _rx(q[4]) @ _tr(x=fore)
    t = t @ _ry(q[5]) @ _rx(q[6]) @ _tr(x=hand)
    return t[:3, 3]


def _random_angles(spec, rng, n):
    model = spec.compile_model()
    low = np.where(model.jnt_limited, model.jnt_range[:, 0], -np.pi)
    high = np.where(model.jnt_limited, model.jnt_range[:, 1], np.pi)
    return rng.uniform(low, high, size=(n, model.nq))


def test_ur3_flange_matches_dh_forward_kinematics():
    """For random joint angles, achieved_goal (MuJoCo site) == the DH table's FK computed in numpy."""
    spec = get_arm_spec("UR3Obstacle")
    sim = GoalSimulation(spec, 1)
    rng = np.random.default_rng(0)
    for q in _random_angles(spec, rng, 50):
        sim.set_state(0, q)
        np.testing.assert_allclose(sim.achieved_goal[0], ur3_dh_fk(q), atol=1e-6, rtol=0)
        np.testing.assert_array_equal(sim.observation[0, :3], sim.achieved_goal[0])
    # The zero posture is the arm stretched along -x at shoulder height: a known closed form.
    sim.set_state(0, np.zeros(6))
    np.testing.assert_allclose(
        sim.achieved_goal[0], [-0.24365 - 0.21325, -0.11235 - 0.0819, 0.1519 - 0.08535]
    )


def test_ur3_achieved_goal_follows_steps():
    """After env steps (servo motion, gravity, contacts) the achieved goal is the FK of the new joint angles."""
    sim = GoalSimulation("UR3Obstacle", 3, seed=0)
    sim.reset()
    rng = np.random.default_rng(0)
    for _ in range(15):
        sim.step(rng.uniform(-1, 1, size=(3, 6)))
        for i in range(3):
            np.testing.assert_allclose(sim.achieved_goal[i], ur3_dh_fk(sim.observation[i, 3:9]), atol=1e-6)


def test_reacher_fingertip_matches_pr2_kinematics():
    spec = get_arm_spec("Reacher3D")
    sim = GoalSimulation(spec, 1)
    for q in _random_angles(spec, np.random.default_rng(1), 50):
        sim.set_state(0, q)
        np.testing.assert_allclose(sim.achieved_goal[0], pr2_fk(q), atol=1e-9, rtol=0)


def test_reacher_achieved_goal_moves_exactly_as_the_site():
    """Setting joint angles moves achieved_goal exactly as the fingertip site moves (not the joint angles)."""
    spec = get_arm_spec("Reacher3D")
    sim = GoalSimulation(spec, 1, seed=0)
    model = sim.model
    reference = mujoco.MjData(model)
    site = model.site("pr2/fingertip").id

    def site_position(q):
        reference.qpos[:] = q
        mujoco.mj_forward(model, reference)
        return reference.site_xpos[site].copy()

    rng = np.random.default_rng(0)
    q_prev = np.array(spec.agent.init_qpos)
    sim.set_state(0, q_prev)
    ag_prev = sim.achieved_goal[0].copy()
    for q in _random_angles(spec, rng, 20):
        sim.set_state(0, q)
        np.testing.assert_array_equal(sim.achieved_goal[0], site_position(q))
        np.testing.assert_allclose(
            sim.achieved_goal[0] - ag_prev, site_position(q) - site_position(q_prev), atol=1e-12
        )
        assert not np.allclose(sim.achieved_goal[0], q[:3])  # the reference's bug: joint angles as goals
        q_prev, ag_prev = q, sim.achieved_goal[0].copy()
    # Through env steps with random torques, too.
    sim.reset()
    for _ in range(10):
        sim.step(rng.uniform(-20, 20, size=(1, 7)))
        np.testing.assert_array_equal(sim.achieved_goal[0], site_position(sim.observation[0, :7]))


def test_reacher_model_facts():
    spec = get_arm_spec("Reacher3D")
    model = spec.compile_model()
    assert (model.nq, model.nv, model.nu) == (7, 7, 7)
    assert model.opt.timestep == 0.01 and spec.agent.frame_skip == 2
    np.testing.assert_array_equal(model.opt.gravity, [0.0, 0.0, 0.0])
    np.testing.assert_allclose(model.actuator_ctrlrange, np.tile([-20.0, 20.0], (7, 1)))
    np.testing.assert_allclose(model.actuator_gear[:, 0], 1.0)
    names = [model.joint(j).name for j in range(7)]
    assert names == [
        "pr2/" + n
        for n in (
            "shoulder_pan",
            "shoulder_lift",
            "upper_arm_roll",
            "elbow_flex",
            "forearm_roll",
            "wrist_flex",
            "wrist_roll",
        )
    ]
    assert [model.actuator(k).trnid[0] for k in range(7)] == list(range(7))
    # Rolls are continuous, flexes limited as on the PR2 right arm.
    assert model.jnt_limited.tolist() == [1, 1, 1, 1, 0, 1, 0]
    np.testing.assert_allclose(model.jnt_range[3], [-2.3213, 0.0])
    # No contacts at all: every arm geom has contype 0.
    arm = [g for g in range(model.ngeom) if model.geom(g).name.startswith("pr2/")]
    assert arm and not model.geom_contype[arm].any()
    # A zero action and zero velocity hold the arm still (no gravity, no springs).
    sim = GoalSimulation(spec, 1)
    sim.set_state(0, spec.agent.init_qpos)
    before = sim.observation.copy()
    sim.step(np.zeros((1, 7)))
    np.testing.assert_allclose(sim.observation, before, atol=1e-12)


def test_ur3_model_facts():
    spec = get_arm_spec("UR3Obstacle")
    model = spec.compile_model()
    assert (model.nq, model.nv, model.nu) == (6, 6, 6)
    links = [model.body(f"ur3/link_{k}").id for k in range(1, 7)]
    np.testing.assert_allclose(model.body_mass[links], [2.0, 3.42, 1.26, 0.8, 0.8, 0.35])
    assert (model.body_inertia[links] > 0).all()
    np.testing.assert_allclose(model.body_gravcomp[links], 1.0)
    np.testing.assert_allclose(model.jnt_range, np.tile([-2 * np.pi, 2 * np.pi], (6, 1)))
    assert (model.actuator_biastype == mujoco.mjtBias.mjBIAS_AFFINE).all()  # position servos
    np.testing.assert_allclose(np.abs(model.actuator_forcerange[:, 1]), [56, 56, 28, 12, 12, 12])
    np.testing.assert_allclose(model.opt.gravity, [0.0, 0.0, -9.81])


def test_ur3_servo_holds_and_moves():
    """Zero action holds the posture under gravity; a held unit action turns a joint ~0.1 rad per step."""
    spec = get_arm_spec("UR3Obstacle")
    sim = GoalSimulation(spec, 1)
    sim.set_state(0, spec.agent.init_qpos)
    start = sim.observation[0, 3:9].copy()
    for _ in range(20):
        sim.step(np.zeros((1, 6)))
    np.testing.assert_allclose(sim.observation[0, 3:9], start, atol=1e-6)
    action = np.zeros((1, 6))
    action[0, 5] = 1.0
    angles = []
    for _ in range(6):
        sim.step(action)
        angles.append(sim.observation[0, 8])
    assert np.diff(angles)[2:] == pytest.approx(0.1, rel=0.05)
    np.testing.assert_allclose(sim.observation[0, 3:8], start[:5], atol=1e-3)  # the other joints stay


@pytest.mark.parametrize("name", ["Reacher3D", "UR3Obstacle"])
def test_start_posture(name):
    """The reset posture is collision-free and its end effector is far from every test goal."""
    spec = get_arm_spec(name)
    sim = GoalSimulation(spec, 1)
    sim.set_state(0, spec.agent.init_qpos)
    assert sim.datas[0].ncon == 0
    goals = spec.test_goals.sample(np.random.default_rng(0), 2000)
    distance = np.linalg.norm(goals - sim.achieved_goal[0], axis=-1)
    assert np.mean(distance <= spec.success_threshold) < 0.05


def test_reacher_test_goals_are_reached_by_a_scripted_controller():
    """Jacobian-transpose control (within the +-20 torque box) brings the fingertip to every sampled test goal
    within the 100-step episode and holds it there: the goals are reachable and the dynamics controllable;
    doing nothing never succeeds. The reference arm is heavy (46 kg, fingertip at most ~0.045 m per step
    under full torque) and starts stretched out 1.08 m from the goal mean, so this takes tens of steps; a
    small elbow bias bends the arm out of its straight (singular) start posture."""
    sim = GoalSimulation("Reacher3D", 20, seed=0, eval_goals=True)
    sim.reset()
    idle = sim.evaluate()[1].mean()
    model = sim.model
    site = model.site(sim.spec.achieved_goal_site).id
    jacobian = np.zeros((3, model.nv))
    elbow_bias = np.zeros(7)
    elbow_bias[3] = -5.0
    first_success = np.full(20, -1)
    for t in range(sim.spec.episode_length):
        actions = []
        for i, data in enumerate(sim.datas):
            mujoco.mj_jacSite(model, data, jacobian, None, site)
            error = sim.desired_goal[i] - sim.achieved_goal[i]
            actions.append(jacobian.T @ (300.0 * error) - 2.0 * data.qvel + elbow_bias)
        _, success, _ = sim.step(np.clip(actions, -20.0, 20.0))
        first_success[(first_success < 0) & success] = t + 1
    assert success.all() and idle == 0.0
    assert 10 < first_success.min() and first_success.max() <= 80
