"""Reacher3D's plant against the reference implementation's dynamics.

The reference figures below were measured with MuJoCo 3.17 on the official repository's model
(``jayLEE0301/dhrl_official``, ``envs/fetchenv/assets/reacher3d.xml``, loaded with
``mujoco.MjModel.from_xml_string`` after dropping its obsolete ``coordinate="local"`` attribute), with the
reference env's protocol: reset to ``qpos = 0, qvel = 0``, ``ctrl`` held for ``frame_skip = 2`` physics
steps per env step, the end effector taken 0.16828 m along the wrist-roll axis (the point the reference's
``get_EE_pos`` computes, between the two finger joints) and goals ``(0, 0.25, 0) + N(0, 0.1)`` per axis.
The model itself is not part of this repository; ours is built independently with ``dm_control.mjcf``.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from torchrl_dhrl.envs import GoalSimulation, get_arm_spec, make_env

# --- reference figures (official reacher3d.xml, MuJoCo 3.17) -------------------------------------------
REF_MASS = 46.187  # kg, the 7 arm links (the implementation notes: "about 46 kg")
REF_INERTIA_PAN_LIFT = (3.5672, 2.3009)  # joint-space inertia diagonal at the zero posture (kg m^2)
REF_TIP_AT_RESET = (0.98928, -0.188, 0.0)  # 1.082 m from the goal mean (the notes: "about 1.09 m")
# Fingertip displacement per env step under +20 N m on every joint from the reset posture, steps 1..6; "after
# 5 steps" is step 6 (the notes: "about 0.016 m per env step after 5 steps").
REF_SPEED_UNDER_TORQUE = (0.00544, 0.00621, 0.00792, 0.00997, 0.01327, 0.01652)
# After 5 env steps of full torque, then zero torque: the fingertip's path over the next 10 env steps, and
# the env steps until the shoulder's joint speed |(pan, lift)| falls below 50% and 10% of its value at
# release. The shoulder's damping (10 N m s/rad on ~3 kg m^2) brakes it over some 10-30 steps, while the
# light forearm and wrist rolls, spun up to ~40 rad/s and damped by only 0.1, keep whipping the hand, so the
# fingertip keeps moving ~0.01 m per step for 40 steps and more. It does NOT stop within a few steps (the
# implementation notes say it does; measured on the reference model, it does not).
REF_COAST_PATH_10 = 0.11413  # m
REF_SHOULDER_HALF_STEPS, REF_SHOULDER_TENTH_STEPS = 9, 28
# Uniformly random actions in [-20, 20]^7 (3000 reference episodes): episodes within 0.25 of the goal at
# some step, and at the final (100th) step. The notes: "about 10%" and "about 0%".
REF_RANDOM_ANY, REF_RANDOM_FINAL = 0.0857, 0.0110

JOINT_DAMPING = (10.0, 10.0, 0.1, 1.0, 0.1, 0.1, 0.1)  # pan, lift, upper-arm roll, elbow, forearm roll, wrist


def _arm_bodies(model):
    return [b for b in range(model.nbody) if model.body(b).name.startswith("pr2/")]


def _torque_profile(hold: int, total: int):
    """Fingertip displacement and joint velocities per env step: +20 N m for ``hold`` steps, then zero."""
    sim = GoalSimulation("Reacher3D", 1, seed=0)
    sim.reset()
    tips, qvels = [sim.achieved_goal[0].copy()], []
    for t in range(total):
        sim.step(np.full((1, 7), 20.0 if t < hold else 0.0))
        tips.append(sim.achieved_goal[0].copy())
        qvels.append(sim.observation[0, 10:].copy())
    return np.linalg.norm(np.diff(tips, axis=0), axis=-1), np.array(qvels)


def test_mass_and_joint_space_inertia():
    """Geoms of density 1000 with the reference link shapes: ~46 kg, inertia 3.57 / 2.30 at the pan / lift."""
    spec = get_arm_spec("Reacher3D")
    model = spec.compile_model()
    assert spec.agent.density == 1000.0
    assert model.body_mass[_arm_bodies(model)].sum() == pytest.approx(REF_MASS, rel=0.05)
    assert model.body_mass[_arm_bodies(model)].sum() == pytest.approx(46.0, rel=0.05)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    inertia = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, inertia)
    np.testing.assert_allclose(np.diag(inertia)[:2], REF_INERTIA_PAN_LIFT, rtol=0.05)
    np.testing.assert_allclose(np.diag(inertia)[:2], (3.57, 2.30), rtol=0.05)
    # The shoulder dominates: the light wrist joints are ~70 times easier to accelerate.
    assert np.diag(inertia)[0] > 50 * np.diag(inertia)[6]


def test_damping_armature_and_integrator():
    spec = get_arm_spec("Reacher3D")
    model = spec.compile_model()
    np.testing.assert_allclose(model.dof_damping, JOINT_DAMPING)
    np.testing.assert_allclose(model.dof_armature, 0.04)
    assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4 and spec.agent.integrator == "RK4"
    assert model.opt.timestep == 0.01 and spec.agent.frame_skip == 2
    np.testing.assert_array_equal(model.opt.gravity, 0.0)
    np.testing.assert_allclose(model.actuator_ctrlrange, np.tile([-20.0, 20.0], (7, 1)))
    # The PR2 right arm's ranges (rad); the forearm and wrist rolls are continuous.
    np.testing.assert_allclose(
        model.jnt_range[model.jnt_limited.astype(bool)],
        [[-2.2854, 1.714602], [-0.5236, 1.3963], [-3.9, 0.8], [-2.3213, 0.0], [-2.094, 0.0]],
    )


@pytest.mark.parametrize("seed", [0, 1])
def test_reset_is_the_zero_posture_at_rest(seed):
    """Every reset: all joint angles and velocities exactly 0 (no noise), a fresh goal per env and seed."""
    env = make_env("Reacher3D", num_envs=8, seed=seed)
    td = env.reset()
    observation = td["observation"]
    assert not observation[:, :7].any() and not observation[:, 10:].any()
    for data in env.simulation.datas:
        assert not data.qpos.any() and not data.qvel.any()
    np.testing.assert_allclose(td["achieved_goal"].numpy(), np.tile(REF_TIP_AT_RESET, (8, 1)), atol=1e-6)
    distance = np.linalg.norm(np.asarray(REF_TIP_AT_RESET) - (0.0, 0.25, 0.0))
    assert distance == pytest.approx(1.082, abs=1e-3)
    goals = td["desired_goal"]
    assert len(set(map(tuple, goals.tolist()))) == 8  # one goal per env
    other = make_env("Reacher3D", num_envs=8, seed=seed + 10).reset()["desired_goal"]
    assert not np.isclose(goals.numpy(), other.numpy()).any()  # and per seed
    env.rollout(3, break_when_any_done=False)  # a second reset after moving: at rest again
    again = env.reset()
    assert not again["observation"][:, :7].any() and not again["observation"][:, 10:].any()


def test_speed_under_full_torque():
    """+20 N m on every joint: the fingertip accelerates slowly, 0.0165 m per env step after 5 steps (the old,
    6 times lighter plant made 0.13 m per step)."""
    speed, _ = _torque_profile(hold=6, total=6)
    assert speed[5] == pytest.approx(REF_SPEED_UNDER_TORQUE[5], rel=0.05)
    assert speed[5] == pytest.approx(0.016, rel=0.05)
    np.testing.assert_allclose(speed, REF_SPEED_UNDER_TORQUE, rtol=0.05)


def test_coasting_after_release():
    """Released after 5 steps of full torque, the heavy damped shoulder brakes over 10-30 steps as in the
    reference (not within a few steps: see the reference figures above), and the fingertip's path matches."""
    speed, qvel = _torque_profile(hold=5, total=40)
    assert speed[5:15].sum() == pytest.approx(REF_COAST_PATH_10, rel=0.05)
    shoulder = np.linalg.norm(qvel[:, :2], axis=-1)
    after = shoulder[4:] / shoulder[4]  # from the last torque step on
    assert abs(int(np.argmax(after < 0.5)) - REF_SHOULDER_HALF_STEPS) <= 1
    assert abs(int(np.argmax(after < 0.1)) - REF_SHOULDER_TENTH_STEPS) <= 2
    # The rolls, not the shoulder, keep the hand moving: still spinning fast 20 steps after the release.
    assert np.abs(qvel[24, [4, 6]]).min() > 5.0 and shoulder[24] < 0.3 * shoulder[4]


def test_random_action_success_fractions():
    """Uniform random torques: ~9% of episodes touch the 0.25 ball at some step, ~1% end in it.

    400 episodes: the any-time band is the reference 0.086 +- 3 standard errors (0.014), the final one 0.011
    + 3 standard errors (the old plant touched the ball in ~40% of its random episodes)."""
    n = 400
    sim = GoalSimulation("Reacher3D", n, seed=0)
    sim.reset()
    rng = np.random.default_rng(0)
    ever = np.zeros(n, dtype=bool)
    for _ in range(sim.spec.episode_length):
        _, success, truncated = sim.step(rng.uniform(-20.0, 20.0, size=(n, 7)))
        ever |= success
    assert truncated.all()
    assert REF_RANDOM_ANY - 0.042 <= ever.mean() <= REF_RANDOM_ANY + 0.042
    assert success.mean() <= REF_RANDOM_FINAL + 0.016
