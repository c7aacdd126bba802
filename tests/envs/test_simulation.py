"""The batched simulation core (``GoalSimulation``).

``right_flipped_after``: an env switch (off by default, as the reference) that puts a flipped ant back on its feet.
Checked against scipy's rotations (upside-down test, heading), MuJoCo's own contact list (no wall overlap after
righting), a state round trip, and the recipe's configuration checks and wiring. MuJoCo offscreen rendering
(where OpenGL exists). ``step_threads``: envs stepped in threads give the transitions of one thread, bit for bit."""

from __future__ import annotations

import copy
import os

import numpy as np
import pytest
import torch
from _recipe import recipe_config
from scipy.spatial.transform import Rotation
from torchrl.envs.utils import check_env_specs
from torchrl_dhrl.envs import AntAgent, GoalSimulation, GymGoalEnv, make_env, register_env, unregister_env

from torchrl_dhrl.recipe import with_implied_keys

ANT = AntAgent()
ZERO = np.zeros((1, 8))


def _flipped_qpos(x, y, yaw, roll=np.pi):
    """The reset pose at (x, y), turned by ``yaw`` then rolled by ``roll`` about the torso's own x axis."""
    qpos = np.array(ANT.init_qpos, dtype=np.float64)
    qpos[:3] = (x, y, 0.3)
    quat = Rotation.from_euler("ZX", [yaw, roll]).as_quat()  # scalar last (x, y, z, w)
    qpos[3:7] = np.roll(quat, 1)
    return qpos


def _heading(qpos):
    """Yaw of the torso's x axis projected on the floor (scipy, independent of AntAgent.upright_qpos)."""
    axis = Rotation.from_quat(np.roll(qpos[3:7], -1)).apply([1.0, 0.0, 0.0])
    return np.arctan2(axis[1], axis[0])


def _wall_overlap(sim, index=0, part="ant/"):
    """The deepest penetration (>= 0) between a geom of the ant whose name starts with ``part`` and a wall
    geom, from MuJoCo's contact list."""
    model, data = sim.model, sim.datas[index]
    names = [model.geom(g).name for g in range(model.ngeom)]
    worst = 0.0
    for contact in data.contact[: data.ncon]:
        first, second = (names[g] for g in contact.geom)
        ant_wall = {first[:4], second[:4]} == {"ant/", "wall"} and part in (
            first[: len(part)],
            second[: len(part)],
        )
        worst = max(worst, -contact.dist) if ant_wall else worst
    return worst


def test_a_flipped_ant_stays_flipped_by_default():
    """The reference: nothing rights the ant; it lies on its back for the rest of the episode."""
    sim = GoalSimulation("AntMaze", seed=0)
    assert sim.right_flipped_after is None
    sim.set_state(0, _flipped_qpos(0.0, 0.0, 0.3))
    for _ in range(100):
        sim.step(ZERO)
        assert ANT.is_upside_down(sim.observation[0])
    assert sim.upside_down_steps.tolist() == [0]  # not counted without the switch


@pytest.mark.parametrize("after", [1, 4, 12])
@pytest.mark.parametrize("yaw", [0.0, 1.1, -2.5])
def test_the_ant_is_righted_after_k_steps_upside_down(after, yaw):
    sim = GoalSimulation("AntMaze", seed=0, right_flipped_after=after)
    sim.set_state(0, _flipped_qpos(0.5, 1.0, yaw))  # open floor: nothing to move clear of
    for k in range(1, after):
        sim.step(ZERO)
        assert ANT.is_upside_down(sim.observation[0]) and sim.upside_down_steps.tolist() == [k]
    before = sim.datas[0].qpos.copy()
    sim.step(ZERO)
    qpos, qvel = sim.datas[0].qpos, sim.datas[0].qvel
    assert not ANT.is_upside_down(sim.observation[0]) and sim.upside_down_steps.tolist() == [0]
    np.testing.assert_allclose(qpos[:2], before[:2], atol=1e-12)  # the same place
    assert qpos[2] == ANT.torso_height and np.all(qpos[7:] == 0.0) and np.all(qvel == 0.0)
    # the torso is level and keeps the heading it had on its back (scipy's rotation of the x axis)
    np.testing.assert_allclose(
        Rotation.from_quat(np.roll(qpos[3:7], -1)).apply([0, 0, 1]), [0, 0, 1], atol=1e-12
    )
    np.testing.assert_allclose(np.angle(np.exp(1j * (_heading(qpos) - _heading(before)))), 0.0, atol=1e-9)
    np.testing.assert_allclose(_heading(qpos), yaw, atol=1e-9)
    # the observation and the achieved goal are the new state's
    np.testing.assert_array_equal(sim.observation[0], np.concatenate([qpos, qvel]))
    np.testing.assert_array_equal(sim.achieved_goal[0], qpos[:2])
    # and it then stands on its feet for good (zero torques)
    for _ in range(60):
        sim.step(ZERO)
        assert not ANT.is_upside_down(sim.observation[0])


def test_only_consecutive_steps_upside_down_count():
    """Righting itself resets the count, so does a reset; an ant on its side (not upside down) is left alone."""
    sim = GoalSimulation("AntMaze", seed=0, right_flipped_after=3)
    sim.set_state(0, _flipped_qpos(0.0, 0.0, 0.0, roll=np.pi / 2 - 0.3))  # tilted, still "up" by the test
    assert not ANT.is_upside_down(sim.observation[0])
    sim.step(ZERO)
    assert sim.upside_down_steps.tolist() == [0]
    sim.set_state(0, _flipped_qpos(0.0, 0.0, 0.0))
    sim.step(ZERO)
    sim.step(ZERO)
    assert sim.upside_down_steps.tolist() == [2]
    sim.reset()
    assert sim.upside_down_steps.tolist() == [0]


@pytest.mark.parametrize("maze", ["AntMazeSmall", "AntMaze", "AntMazeBottleneck", "AntMazeComplex"])
def test_a_righted_ant_is_clear_of_the_walls(maze):
    """Flipped ants lying against walls and in corners (random places near walls of every ant maze) come back
    on their feet within 2 of where they lay, overlapping no wall, and stay upright and inside the maze."""
    sim = GoalSimulation(maze, seed=0, right_flipped_after=1)
    low, high = sim.spec.goal_bounds
    rng = np.random.default_rng(0)
    checked = 0
    while checked < 12:
        x, y = rng.uniform(low, high)
        sim.set_state(0, _flipped_qpos(x, y, rng.uniform(-np.pi, np.pi)))
        upright = ANT.upright_qpos(sim.datas[0].qpos)
        sim.set_state(0, upright)
        # a place where the torso is free but the upright ant's spread legs would overlap a wall
        if _wall_overlap(sim, part="ant/torso") > 0.0 or _wall_overlap(sim) < 0.05:
            continue
        checked += 1
        sim.set_state(0, _flipped_qpos(x, y, _heading(upright)))
        sim.step(ZERO)
        qpos = sim.datas[0].qpos.copy()
        assert not ANT.is_upside_down(qpos)
        assert _wall_overlap(sim) == 0.0
        assert np.hypot(qpos[0] - x, qpos[1] - y) <= 2.0 + 0.1
        for _ in range(30):
            sim.step(ZERO)
        assert np.isfinite(sim.observation).all() and not ANT.is_upside_down(sim.observation[0])
        assert np.all(sim.achieved_goal[0] >= low) and np.all(sim.achieved_goal[0] <= high)


def test_the_count_is_part_of_the_state():
    """A state saved mid-count restores the count: both copies right the ant at the same step, bit for bit;
    a state saved before the switch existed (no count) restores as 0."""
    sim = GoalSimulation("AntMazeSmall", num_envs=2, seed=3, right_flipped_after=5)
    sim.reset()
    sim.set_state(1, _flipped_qpos(0.0, 0.0, 0.7))
    for _ in range(3):
        sim.step(ZERO.repeat(2, 0))
    state = sim.get_state()
    assert state["upside_down_steps"].tolist() == [0, 3]
    twin = GoalSimulation("AntMazeSmall", num_envs=2, seed=99, right_flipped_after=5)
    twin.set_full_state(state)
    actions = np.random.default_rng(0).uniform(-30, 30, size=(6, 2, 8))
    for a in actions:
        sim.step(a)
        twin.step(a)
        np.testing.assert_array_equal(sim.observation, twin.observation)
        np.testing.assert_array_equal(sim.upside_down_steps, twin.upside_down_steps)
    old = {k: v for k, v in state.items() if k != "upside_down_steps"}
    twin.set_full_state(old)
    assert twin.upside_down_steps.tolist() == [0, 0]


@pytest.mark.parametrize("value", [0, -2, True, 2.5, "10"])
def test_bad_values_are_refused(value):
    with pytest.raises(ValueError, match="right_flipped_after must be None or a positive number"):
        GoalSimulation("AntMaze", right_flipped_after=value)


@pytest.mark.parametrize("env", ["PointMaze", "Reacher3D", "UR3Obstacle"])
def test_only_the_ant_can_be_righted(env):
    with pytest.raises(ValueError, match=f"right_flipped_after is for the ant mazes.*{env}"):
        GoalSimulation(env, right_flipped_after=10)


def test_the_env_front_ends_pass_it_on():
    env = make_env("AntMazeSmall", num_envs=2, seed=0, right_flipped_after=7)
    assert env.simulation.right_flipped_after == 7
    check_env_specs(env)
    assert make_env("AntMazeSmall").simulation.right_flipped_after is None
    import gymnasium as gym
    import torchrl_dhrl.envs  # noqa: F401 - registers the dhrl/ ids

    assert gym.make("dhrl/AntMaze-v0", right_flipped_after=4).unwrapped._sim.right_flipped_after == 4

    def factory(*, num_envs, seed, device, eval, max_episode_steps):  # noqa: A002
        return make_env("AntMazeSmall", num_envs=num_envs, seed=seed, device=device, eval=eval)

    register_env("MyAnt", factory)
    try:
        with pytest.raises(ValueError, match="right_flipped_after is an option of the built-in ant mazes"):
            make_env("MyAnt", right_flipped_after=3)
    finally:
        unregister_env("MyAnt")


def test_the_recipe_builds_its_envs_with_it():
    """Training and test envs alike; a run saved before the key existed is rebuilt without righting."""
    from dhrl_utils import build_environment

    cfg = recipe_config("env=AntMazeSmall", "preset=smoke", "right_flipped_after=6")
    for evaluation in (False, True):
        env = build_environment(cfg, "cpu", eval=evaluation)
        assert env.simulation.right_flipped_after == 6
    old = {k: v for k, v in cfg.items() if k != "right_flipped_after"}
    assert with_implied_keys(old)["right_flipped_after"] is None
    assert build_environment(with_implied_keys(old), "cpu").simulation.right_flipped_after is None


def test_upright_qpos_over_random_orientations():
    """Property: for random orientations, positions and joint angles the upright pose keeps (x, y) and the
    heading (scipy), is level, at the reset height, joints at the reset pose; quaternions stay unit."""
    rng = np.random.default_rng(1)
    quats = Rotation.random(200, random_state=2).as_quat()
    qpos = rng.uniform(-5, 5, size=(200, 15))
    qpos[:, 3:7] = np.roll(quats, 1, axis=-1)
    out = ANT.upright_qpos(qpos)
    np.testing.assert_array_equal(out[:, :2], qpos[:, :2])
    np.testing.assert_array_equal(out[:, 2], ANT.torso_height)
    np.testing.assert_array_equal(out[:, 7:], np.broadcast_to(np.asarray(ANT.init_qpos)[7:], (200, 8)))
    np.testing.assert_allclose(np.linalg.norm(out[:, 3:7], axis=-1), 1.0, atol=1e-12)
    for before, after in zip(qpos, out, strict=True):
        np.testing.assert_allclose(
            Rotation.from_quat(np.roll(after[3:7], -1)).apply([0, 0, 1]), [0, 0, 1], atol=1e-12
        )
        difference = _heading(after) - _heading(before)
        np.testing.assert_allclose(np.angle(np.exp(1j * difference)), 0.0, atol=1e-9)


_GL = os.environ.get("MUJOCO_GL", "").lower()


@pytest.mark.skipif(
    _GL not in ("egl", "osmesa", "glfw"),
    reason="offscreen rendering needs MUJOCO_GL=egl or osmesa (an OpenGL backend)",
)
def test_offscreen_rendering():
    env = make_env("AntMazeSmall", num_envs=2, seed=0, eval=True)
    env.reset()
    frame = env.render(1, width=96, height=64)
    assert frame.shape == (64, 96, 3) and frame.dtype == torch.uint8 and frame.float().std() > 1.0
    tracked = env.render(0, width=64, height=64, camera="ant/track")
    assert tracked.shape == (64, 64, 3)
    gym_env = GymGoalEnv("PointMaze", render_mode="rgb_array", width=80, height=80)
    gym_env.reset(seed=0)
    assert gym_env.render().shape == (80, 80, 3)
    gym_env.close()
    env.close()


# ---- stepping the envs in threads -------------------------------------------------------------------------------


@pytest.mark.parametrize("task", ["PointMaze", "AntMazeSmall", "Reacher3D", "UR3Obstacle"])
@pytest.mark.parametrize("threads", [2, 3, 8])
def test_threaded_steps_equal_sequential_steps(task, threads):
    """``step_threads``: 5 envs stepped by 2, 3 or 8 (capped at 5) threads give the states, observations, rewards
    and successes of one thread, bit for bit, over random actions and partial resets."""
    sims = [GoalSimulation(task, 5, seed=3, step_threads=n, max_episode_steps=12) for n in (1, threads)]
    assert sims[1].step_threads == min(threads, 5) and sum(len(g) for g in sims[1]._groups) == 5
    rng = np.random.default_rng(0)
    for sim in sims:
        sim.reset()
    for t in range(30):
        actions = rng.uniform(-1.5, 1.5, size=(5, sims[0].action_dim)) * sims[0].agent.action_high
        outs = [sim.step(actions) for sim in sims]
        for a, b in zip(outs[0], outs[1], strict=True):
            np.testing.assert_array_equal(a, b)
        for name in ("observation", "achieved_goal", "desired_goal", "step_count"):
            np.testing.assert_array_equal(getattr(sims[0], name), getattr(sims[1], name), err_msg=name)
        if t % 7 == 6:
            mask = rng.random(5) < 0.5
            for sim in sims:
                sim.reset(mask)
    for i in range(5):
        np.testing.assert_array_equal(sims[0].datas[i].qpos, sims[1].datas[i].qpos)
        np.testing.assert_array_equal(sims[0].datas[i].qvel, sims[1].datas[i].qvel)
    for sim in sims:
        sim.close()


def test_threaded_steps_copy_close_and_refuse_bad_counts():
    """A copy of a simulation with running threads starts its own; ``close`` stops them and a later step restarts
    them; a bad count is refused, and ``make_env`` keeps the option to the built-in envs."""
    sim = GoalSimulation("AntMazeSmall", 4, seed=0, step_threads=2)
    sim.reset()
    sim.step(np.zeros((4, 8)))
    assert sim._pool is not None
    twin = copy.deepcopy(sim)
    assert twin._pool is None
    np.testing.assert_array_equal(twin.step(np.ones((4, 8)))[0], sim.step(np.ones((4, 8)))[0])
    sim.close()
    assert sim._pool is None
    sim.step(np.zeros((4, 8)))
    assert sim._pool is not None
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="step_threads must be a positive integer"):
            GoalSimulation("PointMaze", 2, step_threads=bad)
    with pytest.raises(ValueError, match="step_threads is an option of the built-in envs"):
        make_env("gymnasium:PointMaze_UMaze-v3", step_threads=2)
    env = make_env("PointMaze", num_envs=3, seed=0, step_threads=2)
    assert env._sim.step_threads == 2
    env.close()


def test_step_threads_key_reaches_the_training_and_test_envs():
    from dhrl_utils import build_environment

    cfg = with_implied_keys(recipe_config("env=AntMazeSmall", "preset=smoke", "num_envs=2", "step_threads=2"))
    for eval_ in (False, True):
        env = build_environment(cfg, torch.device("cpu"), eval=eval_)
        assert env.simulation.step_threads == 2
        env.close()
