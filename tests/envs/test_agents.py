"""Agent models and dynamics: the point's velocity drive, walls stopping it, the ant's stability."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from torchrl_dhrl.envs import AntAgent, GoalSimulation, PointAgent, compile_maze_model

ANT_MAZES = ["AntMazeSmall", "AntMaze", "AntMazeBottleneck", "AntMazeComplex"]


def _place_point(sim, x, y, yaw):
    data = sim.datas[0]
    data.qpos[:] = (x, y, yaw)
    data.qvel[:] = 0.0
    mujoco.mj_forward(sim.model, data)
    sim.observation[0] = np.concatenate([data.qpos, data.qvel])


def test_ant_model_facts():
    model = compile_maze_model("AntMaze")
    assert (model.nq, model.nv, model.nu) == (15, 14, 8)
    assert model.opt.timestep == 0.02 and model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
    motors = [model.joint(model.actuator_trnid[k, 0]).name for k in range(model.nu)]
    assert motors == [f"ant/{p}_{n}" for n in (4, 1, 2, 3) for p in ("hip", "ankle")]
    np.testing.assert_allclose(model.actuator_ctrlrange, np.tile([-30.0, 30.0], (8, 1)))
    np.testing.assert_allclose(model.actuator_gear[:, 0], 1.0)
    hinges = {model.joint(j).name: j for j in range(1, model.njnt)}
    for n in (1, 2, 3, 4):
        np.testing.assert_allclose(model.jnt_range[hinges[f"ant/hip_{n}"]], np.deg2rad([-30, 30]))
        sign = 1 if n in (1, 4) else -1
        np.testing.assert_allclose(
            np.sort(model.jnt_range[hinges[f"ant/ankle_{n}"]]), np.sort(sign * np.deg2rad([30, 70]))
        )
        # Ankle axis perpendicular to the leg, in the plane.
        assert abs(model.jnt_axis[hinges[f"ant/ankle_{n}"]][2]) < 1e-12
    root = model.joint("ant/root/")
    assert model.jnt_type[root.id] == mujoco.mjtJoint.mjJNT_FREE and model.dof_damping[0] == 0.0
    np.testing.assert_allclose(model.dof_damping[6:], 1.0)
    np.testing.assert_allclose(model.dof_armature[6:], 1.0)
    assert model.geom("ant/torso_geom").size[0] == 0.25
    # The reset pose is the model's qpos0 (the reference's gym env resets around the state at load).
    np.testing.assert_array_equal(np.array(AntAgent().init_qpos), model.qpos0)


@pytest.mark.parametrize("maze", ANT_MAZES)
def test_ant_stands_on_four_feet(maze):
    """In the reference's folded pose every lower leg points down to the floor, and from the reset pose the ant
    settles on its four feet.

    Independent computation: the lower leg (length 0.4 * sqrt(2)) leaves its ankle at (+-0.4, +-0.4, 0.55)
    and the ankle angle of 1 rad (legs 1, 4) or -1 rad (legs 2, 3) folds it down by 1 rad, so its tip lies at
    height 0.55 - 0.4 sqrt(2) sin(1) and at 0.4 + 0.4 cos(1) from the torso along each axis.
    """
    model = compile_maze_model(maze)
    data = mujoco.MjData(model)
    folded = (0.0, 0.0, 0.55, 1.0, 0.0, 0.0, 0.0) + (0.0, 1.0, 0.0, -1.0, 0.0, -1.0, 0.0, 1.0)
    data.qpos[:] = folded
    mujoco.mj_forward(model, data)
    length = 0.4 * np.sqrt(2.0)
    tip_height = 0.55 - length * np.sin(1.0)
    tip_offset = 0.4 + 0.4 * np.cos(1.0)
    for leg, (dx, dy) in [
        ("front_left", (1, 1)),
        ("front_right", (-1, 1)),
        ("back_left", (-1, -1)),
        ("back_right", (1, -1)),
    ]:
        geom = model.geom(f"ant/{leg}_lower_geom").id
        axis = data.geom_xmat[geom].reshape(3, 3)[:, 2] * model.geom_size[geom][1]
        ends = np.stack([data.geom_xpos[geom] + axis, data.geom_xpos[geom] - axis])
        tip = ends[np.argmin(ends[:, 2])]
        np.testing.assert_allclose(tip, [dx * tip_offset, dy * tip_offset, tip_height], atol=1e-6)
    # Across each ankle's whole range the foot stays below its ankle (no leg can fold upwards).
    hinges = {model.joint(j).name: j for j in range(1, model.njnt)}
    for n, leg in enumerate(["front_left", "front_right", "back_left", "back_right"], start=1):
        joint = hinges[f"ant/ankle_{n}"]
        for angle in np.linspace(*model.jnt_range[joint], 5):
            data.qpos[:] = folded
            data.qpos[model.jnt_qposadr[joint]] = angle
            mujoco.mj_forward(model, data)
            geom = model.geom(f"ant/{leg}_lower_geom").id
            ankle_height = data.xpos[model.geom_bodyid[geom]][2]
            axis = data.geom_xmat[geom].reshape(3, 3)[:, 2] * model.geom_size[geom][1]
            lowest = min(data.geom_xpos[geom][2] + axis[2], data.geom_xpos[geom][2] - axis[2])
            assert lowest < ankle_height - 0.2, (leg, angle)
    # Left alone, the ant settles on its four feet: each lower leg touches the floor, the torso does not.
    data.qpos[:] = AntAgent().init_qpos
    data.qvel[:] = 0.0
    for _ in range(250):
        mujoco.mj_step(model, data)
    floor = model.geom("floor").id
    touching = {
        model.geom(int(g)).name
        for c in data.contact[: data.ncon]
        for g in (c.geom1, c.geom2)
        if floor in (c.geom1, c.geom2) and g != floor
    }
    assert {
        f"ant/{leg}_lower_geom" for leg in ("front_left", "front_right", "back_left", "back_right")
    } <= touching
    assert "ant/torso_geom" not in touching
    assert data.qpos[2] > 0.3
    for n in (1, 2, 3, 4):  # the joint limits folded the ankles into their ranges (slack for soft limits)
        joint = hinges[f"ant/ankle_{n}"]
        low, high = model.jnt_range[joint]
        assert low - 0.05 <= data.qpos[model.jnt_qposadr[joint]] <= high + 0.05


def test_ant_scene_contact_parameters():
    """Every geom the ant touches carries the reference default class's contact parameters (MuJoCo mixes
    the two geoms' solref/solimp, so the floor and walls must carry them too)."""
    model = compile_maze_model("AntMazeBottleneck")
    names = [model.geom(g).name for g in range(model.ngeom)]
    contact = [g for g, n in enumerate(names) if n.startswith(("ant/", "wall_", "floor"))]
    assert len(contact) > 20
    for g in contact:
        np.testing.assert_allclose(model.geom_solimp[g][:3], [0.8, 0.8, 0.01], err_msg=names[g])
        np.testing.assert_allclose(model.geom_solref[g], [0.02, 1.0], err_msg=names[g])
        np.testing.assert_allclose(model.geom_margin[g], 0.01, err_msg=names[g])
    # The bottleneck's walls keep their own friction.
    assert any(np.allclose(model.geom_friction[g], [2.0, 0.1, 0.002]) for g in contact)


def test_bottleneck_walls_have_the_reference_friction():
    """All 20 walls of the reference's ``ant_maze_bottleneck.xml`` (18 blocks, 2 thin walls) have friction
    (2, 0.1, 0.002); the other mazes' blocks take the ant's (1, 0.5, 0.5), as their references."""
    model = compile_maze_model("AntMazeBottleneck")
    walls = [g for g in range(model.ngeom) if model.geom(g).name.startswith("wall_")]
    assert len(walls) == 20
    for g in walls:
        np.testing.assert_array_equal(model.geom_friction[g], [2.0, 0.1, 0.002], err_msg=model.geom(g).name)
    for name in ("AntMazeSmall", "AntMaze", "AntMazeComplex"):
        model = compile_maze_model(name)
        walls = [g for g in range(model.ngeom) if model.geom(g).name.startswith("wall_")]
        assert walls
        for g in walls:
            np.testing.assert_array_equal(model.geom_friction[g], [1.0, 0.5, 0.5], err_msg=model.geom(g).name)


@pytest.mark.parametrize("seed", [0, 1, 7])
def test_bottleneck_start_is_exactly_the_origin_with_the_other_noise_unchanged(seed):
    """The reference's ``reset_model`` draws the reset noise, then sets ``qpos[:2]`` to the start: x, y exactly
    (0, 0); every other qpos and qvel entry and the goal as AntMaze's reset (same agent, same draws)."""
    bottleneck = GoalSimulation("AntMazeBottleneck", num_envs=4, seed=seed)
    plain = GoalSimulation("AntMaze", num_envs=4, seed=seed)
    for _ in range(3):
        bottleneck.reset()
        plain.reset()
        np.testing.assert_array_equal(bottleneck.observation[:, :2], 0.0)
        np.testing.assert_array_equal(bottleneck.achieved_goal, 0.0)
        assert (plain.observation[:, :2] != 0.0).all() and (np.abs(plain.observation[:, :2]) <= 0.1).all()
        np.testing.assert_array_equal(bottleneck.observation[:, 2:], plain.observation[:, 2:])
        np.testing.assert_array_equal(bottleneck.desired_goal, plain.desired_goal)
    # an explicit start is exact there too
    bottleneck.reset(starts=[4.0, 0.0])
    np.testing.assert_array_equal(bottleneck.achieved_goal, np.tile([4.0, 0.0], (4, 1)))


def test_ant_collides_only_with_floor_and_walls():
    model = compile_maze_model("AntMaze")
    ant = [g for g in range(model.ngeom) if model.geom(g).name.startswith("ant/")]
    static = [g for g in range(model.ngeom) if model.geom(g).name.startswith(("wall_", "floor"))]

    def collide(a, b):
        return bool(
            model.geom_contype[a] & model.geom_conaffinity[b]
            or model.geom_contype[b] & model.geom_conaffinity[a]
        )

    assert all(collide(a, s) for a in ant for s in static)
    assert not any(collide(a, b) for a in ant for b in ant if a != b)
    goal = model.geom("goal_geom").id
    assert not any(collide(goal, g) for g in range(model.ngeom) if g != goal)


def test_point_free_motion_matches_reference_kinematics():
    """In free space one env step moves the point by 0.2 * forward along the new heading, as the reference."""
    sim = GoalSimulation("PointMaze")
    _place_point(sim, 6.0, 0.0, 0.0)
    yaw = 0.0
    x, y = 6.0, 0.0
    for action in [(1.0, 0.0), (0.5, 0.25), (-1.0, -0.1), (2.0, 1.0)]:  # the last one is clipped
        forward = np.clip(action[0], -1, 1)
        yaw += np.clip(action[1], -0.25, 0.25)
        x, y = x + 0.2 * forward * np.cos(yaw), y + 0.2 * forward * np.sin(yaw)
        sim.step(np.array([action]))
        np.testing.assert_allclose(sim.observation[0, :3], [x, y, yaw], atol=1e-9)


@pytest.mark.parametrize(
    "start, heading, axis, limit",
    [
        ((0.0, 0.0), np.pi / 2, 1, 2.0),  # up into the inner wall (its face at y = 2)
        ((8.0, 0.0), 0.0, 0, 10.0),  # right into the outer wall (x = 10)
        ((0.0, 8.0), np.pi, 0, -2.0),  # left into the outer wall (x = -2)
    ],
)
def test_point_cannot_tunnel_through_walls(start, heading, axis, limit):
    """Driving the point straight into a wall at full speed for 500 steps: it stops at the face."""
    sim = GoalSimulation("PointMaze")
    _place_point(sim, *start, heading)
    agent = sim.agent
    reach = agent.nose_offset + agent.nose_half_size[0]  # the nose tip leads
    positions = []
    for _ in range(500):
        sim.step(np.array([[1.0, 0.0]]))
        positions.append(sim.observation[0, axis])
    positions = np.array(positions)
    sign = np.sign(limit - start[axis]) if limit != start[axis] else 1.0
    penetration = sign * (positions - limit) + reach
    assert penetration.max() < 0.02  # the nose tip never enters the wall (beyond soft-contact slack)
    assert penetration[-1] > -0.05  # and it did reach the wall


def test_point_model_facts():
    model = compile_maze_model("PointMaze")
    assert [model.joint(j).name for j in range(model.njnt)] == ["point/ballx", "point/bally", "point/rot"]
    assert model.geom("point/pointbody").size[0] == 0.5
    np.testing.assert_allclose(model.geom("point/pointarrow").size, [0.5, 0.1, 0.1])
    np.testing.assert_allclose(model.geom("point/pointarrow").pos, [0.6, 0.0, 0.5])
    agent = PointAgent()
    assert agent.control_period == pytest.approx(0.02)
    assert model.opt.timestep * agent.frame_skip == pytest.approx(0.02)
    # The point does not touch the floor (no vertical dof), only walls.
    floor = model.geom("floor").id
    assert model.geom_conaffinity[floor] == 0


@pytest.mark.parametrize(
    "name",
    ["AntMaze"] + [pytest.param(name, marks=pytest.mark.slow) for name in ANT_MAZES if name != "AntMaze"],
)
def test_ant_random_rollout_is_stable(name):
    """600 random steps (the full episode length) on 3 envs: finite, torso height bounded, it moves."""
    sim = GoalSimulation(name, 3, seed=0)
    sim.reset()
    start = sim.observation.copy()
    rng = np.random.default_rng(0)
    heights = []
    for _ in range(600):
        sim.step(rng.uniform(-30.0, 30.0, size=(3, 8)))
        heights.append(sim.observation[:, 2].copy())
    heights = np.array(heights)
    assert np.isfinite(sim.observation).all()
    assert heights.min() > 0.1 and heights.max() < 1.5
    assert (np.linalg.norm(sim.observation[:, :2] - start[:, :2], axis=1) > 0.05).all()
    joints = sim.observation[:, 7:15]
    assert (np.abs(joints - start[:, 7:15]).max(axis=1) > 0.1).all()
    # Joints stay (softly) within their ranges: |hip| <= 30 deg, ankles <= 70 deg, with slack.
    assert np.abs(joints).max() < np.deg2rad(80)


def test_reset_noise_statistics():
    """qpos ~ init + U(-0.1, 0.1) (quaternion renormalised), qvel ~ N(0, 0.1)."""
    sim = GoalSimulation("AntMaze", 400, seed=0)
    sim.reset()
    qpos, qvel = sim.observation[:, :15], sim.observation[:, 15:]
    init = np.array(AntAgent().init_qpos)
    noise = np.delete(qpos - init, [3, 4, 5, 6], axis=1)
    assert np.abs(noise).max() <= 0.1
    assert noise.std() == pytest.approx(0.2 / np.sqrt(12), rel=0.05)
    np.testing.assert_allclose(np.linalg.norm(qpos[:, 3:7], axis=1), 1.0)
    assert qvel.std() == pytest.approx(0.1, rel=0.05) and abs(qvel.mean()) < 0.01


def test_simulation_errors():
    sim = GoalSimulation("AntMaze", 2)
    with pytest.raises(ValueError, match="actions of shape"):
        sim.step(np.zeros((2, 3)))
    with pytest.raises(ValueError, match="finite"):
        sim.step(np.full((2, 8), np.nan))
    with pytest.raises(ValueError, match="outside"):
        sim.reset(goals=[[0.0, 30.0], [0.0, 0.0]])
    with pytest.raises(ValueError, match="shape"):
        sim.reset(goals=np.zeros((3, 2)))
    with pytest.raises(ValueError, match="num_envs"):
        GoalSimulation("AntMaze", 0)
    with pytest.raises(ValueError, match="max_episode_steps"):
        GoalSimulation("AntMaze", max_episode_steps=0)
    with pytest.raises(ValueError, match="Valid names"):
        GoalSimulation("AntMazeHuge")
