"""The native batched TorchRL env (``GoalEnv`` / ``make_env``): the mazes and the arm tasks through the
TorchRL factory: specs, seeding, resets, goals, rewards, success, time limit, collectors."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch
from scipy import stats
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs.utils import check_env_specs, step_mdp
from torchrl_dhrl.envs import (
    ARM_NAMES,
    ENV_NAMES,
    MAZE_NAMES,
    ArmSpec,
    GoalEnv,
    GoalSimulation,
    get_arm_spec,
    get_env_spec,
    get_maze_spec,
    make_env,
    sparse_reward,
)


@pytest.mark.parametrize("num_envs", [1, 3])
@pytest.mark.parametrize("name", MAZE_NAMES)
def test_check_env_specs(name, num_envs):
    env = make_env(name, num_envs=num_envs, seed=0, max_episode_steps=2)
    check_env_specs(env)
    assert env.batch_size == torch.Size([num_envs])
    td = env.reset()
    spec = get_maze_spec(name)
    assert (
        td["observation"].shape == (num_envs, spec.agent.obs_dim) and td["observation"].dtype == torch.float32
    )
    assert td["achieved_goal"].dtype == torch.float32 and td["desired_goal"].dtype == torch.float32
    assert td["is_success"].dtype == torch.bool and td["is_success"].shape == (num_envs, 1)
    assert td["step_count"].dtype == torch.int64 and (td["step_count"] == 0).all()
    torch.testing.assert_close(td["achieved_goal"], td["observation"][:, :2])


def _rollout(env, actions):
    td = env.reset()
    out = []
    for action in actions:
        td["action"] = action
        td = env.step(td)
        out.append(td["next"].clone())
        td = step_mdp(td)
    return torch.stack(out, 1)


@pytest.mark.parametrize("name", ["PointMaze", "AntMazeComplex"])
def test_seeding_is_deterministic(name):
    torch.manual_seed(0)
    env = make_env(name, num_envs=2)
    actions = env.action_spec.rand((5,))
    runs = []
    for seed in (3, 3, 4):
        assert env.set_seed(seed) != seed  # returns the next seed, as TorchRL expects
        runs.append(_rollout(env, actions))
    assert (runs[0] == runs[1]).all()
    assert not torch.equal(runs[0]["observation"], runs[2]["observation"])
    # The two envs of a batch use different streams.
    assert not torch.equal(runs[0]["observation"][0], runs[0]["observation"][1])
    # Seeding at construction gives the same first observation.
    a, b = make_env(name, num_envs=2, seed=7).reset(), make_env(name, num_envs=2, seed=7).reset()
    assert (a == b).all()


def test_env_streams_do_not_depend_on_batch_neighbours():
    """Each env draws from its own RNG stream: resetting the other envs does not change what it draws."""
    env = make_env("AntMaze", num_envs=3, seed=11)
    first = env.reset()["desired_goal"][0].clone()
    env2 = make_env("AntMaze", num_envs=3, seed=11)
    env2.reset(TensorDict({"_reset": torch.tensor([[False], [True], [True]])}, [3]))
    # Env 0 was not reset in env2: its own stream is untouched, so its next reset draws the same goal.
    second = env2.reset(TensorDict({"_reset": torch.tensor([[True], [False], [False]])}, [3]))[
        "desired_goal"
    ][0]
    torch.testing.assert_close(first, second)
    # Env i's stream depends only on (seed, i): env 0 of a 3-env batch starts like a 1-env env.
    single = make_env("AntMaze", num_envs=1, seed=11).reset()
    torch.testing.assert_close(single["desired_goal"][0], first)


def test_partial_reset_leaves_other_envs_untouched():
    torch.manual_seed(0)
    env_a, env_b = make_env("AntMaze", num_envs=3, seed=5), make_env("AntMaze", num_envs=3, seed=5)
    actions = env_a.action_spec.rand((8,))
    td_a, td_b = env_a.reset(), env_b.reset()
    for t in range(8):
        if t == 4:
            before = td_a.clone()
            td_a = env_a.reset(td_a.set("_reset", torch.tensor([[False], [True], [False]])))
            for i in (0, 2):
                assert (td_a[i].exclude("_reset") == before[i].exclude("_reset")).all()
            assert td_a["step_count"][:, 0].tolist() == [4, 0, 4]
            assert not torch.equal(td_a["observation"][1], before["observation"][1])
        td_a = step_mdp(env_a.step(td_a.set("action", actions[t])))
        td_b = step_mdp(env_b.step(td_b.set("action", actions[t])))
    # Envs 0 and 2 followed exactly the same trajectory with and without env 1's reset.
    for i in (0, 2):
        torch.testing.assert_close(td_a["observation"][i], td_b["observation"][i], rtol=0, atol=0)
    assert td_a["step_count"][:, 0].tolist() == [8, 4, 8]


def test_explicit_goals_through_reset_tensordict():
    env = make_env("AntMazeSmall", num_envs=3, seed=0)
    goals = torch.tensor([[0.0, 8.0], [8.0, 8.0], [9.0, -1.0]])
    td = env.reset(TensorDict({"desired_goal": goals}, [3]))
    torch.testing.assert_close(td["desired_goal"], goals)
    # A masked reset with goals only changes the reset envs' goals.
    mask = torch.tensor([[False], [True], [False]])
    td = env.reset(TensorDict({"desired_goal": torch.zeros(3, 2), "_reset": mask}, [3]))
    torch.testing.assert_close(td["desired_goal"][1], torch.zeros(2))
    np.testing.assert_array_equal(env.simulation.desired_goal, [[0.0, 8.0], [0.0, 0.0], [9.0, -1.0]])
    # Automatic resets inside a rollout draw fresh goals.
    env = make_env("AntMazeSmall", num_envs=3, seed=0, max_episode_steps=2)
    rollout = env.rollout(
        4,
        break_when_any_done=False,
        tensordict=env.reset(TensorDict({"desired_goal": goals}, [3])),
        auto_reset=False,
    )
    torch.testing.assert_close(rollout["desired_goal"][:, 1], goals)
    assert not torch.isclose(rollout["desired_goal"][:, 2], goals).all(-1).any()
    # Goals outside the arena or of the wrong shape are refused.
    with pytest.raises(ValueError, match="outside the AntMazeSmall arena"):
        env.reset(TensorDict({"desired_goal": torch.tensor([[0.0, 8.0], [0.0, 11.0], [0.0, 0.0]])}, [3]))
    with pytest.raises(ValueError, match="shape"):
        env.reset(TensorDict({"desired_goal": torch.zeros(3, 3)}, [3]))


@pytest.mark.parametrize("name", ["PointMaze", "AntMazeBottleneck"])
def test_start_positions_through_reset_tensordict(name):
    free = torch.tensor([[0.0, 0.0], [16.0, 4.0], [0.0, 16.0]])  # start, right corridor, goal corridor
    scale = 4.0 if name == "PointMaze" else 8.0
    starts = free * (scale / 8.0)
    env = make_env(name, num_envs=3, seed=0)
    reference = make_env(name, num_envs=3, seed=0)
    td = env.reset(TensorDict({"start": starts}, [3]))
    plain = reference.reset()
    # the reset pose moved to the start; the same noise and goals as a plain reset (same random draws)
    offset = env.simulation.observation[:, :2] - reference.simulation.observation[:, :2]
    np.testing.assert_allclose(offset, starts.double().numpy(), atol=1e-12)
    torch.testing.assert_close(td["achieved_goal"] - plain["achieved_goal"], starts)
    torch.testing.assert_close(td["desired_goal"], plain["desired_goal"])
    torch.testing.assert_close(td["observation"][:, 2:], plain["observation"][:, 2:])
    # an episode goes on from there; a masked reset moves only the reset env
    td = env.step(td.set("action", torch.zeros(3, *env.action_spec.shape[1:])))
    assert ((td["next", "achieved_goal"] - starts).norm(dim=-1) < 0.5).all()
    mask = torch.tensor([[False], [True], [False]])
    before = env.simulation.achieved_goal.copy()
    td = env.reset(TensorDict({"start": torch.zeros(3, 2), "_reset": mask}, [3]))
    assert td["achieved_goal"][1].norm() < 0.2
    np.testing.assert_array_equal(env.simulation.achieved_goal[[0, 2]], before[[0, 2]])
    # in a wall, outside the arena, of the wrong shape: refused, naming the start
    inside = torch.tensor([[8.0, 8.0], [0.0, 0.0], [0.0, 0.0]]) * (scale / 8.0)
    with pytest.raises(ValueError, match=r"Start \[\d.*inside a wall"):
        env.reset(TensorDict({"start": inside}, [3]))
    with pytest.raises(ValueError, match=f"Start .* outside the {name} arena: starts must be in"):
        env.reset(TensorDict({"start": torch.full((3, 2), 100.0)}, [3]))
    with pytest.raises(ValueError, match="'start' passed to reset must have shape"):
        env.reset(TensorDict({"start": torch.zeros(3, 3)}, [3]))


def test_bottleneck_gap_is_narrower_than_the_resting_ant_but_not_one_with_ankles_folded_past_0_64():
    # The gap between AntMazeBottleneck's extra walls (x in 15.4..17.0) is too narrow for the ant's reset pose
    # (legs spread about 2 wide) anywhere across it. With the hips at 0 the ant is 2 x (0.48 + 0.4 cos(ankle))
    # across: below 1.6 once the ankles fold past about 0.64 rad (limit 1.22). Passing is a skill, not a block.
    env = make_env("AntMazeBottleneck", num_envs=1, seed=0)
    for x in np.linspace(15.6, 16.8, 5):
        with pytest.raises(ValueError, match="inside a wall"):
            env.reset(TensorDict({"start": torch.tensor([[x, 8.0]])}, [1]))
    env.reset(TensorDict({"start": torch.tensor([[16.2, 5.5]])}, [1]))  # just below the gap: clear
    sim = env.simulation
    model = sim.model

    def overlaps_with_ankles_at(angle: float) -> bool:
        pose = np.array(sim.agent.init_qpos, dtype=np.float64)
        pose[:3] = (16.2, 8.0, 0.55)
        for joint in range(model.njnt):
            if "ankle" in model.joint(joint).name:
                pose[model.jnt_qposadr[joint]] = angle * np.sign(model.jnt_range[joint].sum())
        sim.set_state(0, pose)
        return bool(sim._overlaps_wall(sim.datas[0]))

    assert overlaps_with_ankles_at(0.5) and overlaps_with_ankles_at(0.62)
    assert not overlaps_with_ankles_at(0.66) and not overlaps_with_ankles_at(0.9)
    assert not overlaps_with_ankles_at(1.22)


def test_start_is_refused_for_the_arms():
    env = make_env("Reacher3D", num_envs=1, seed=0)
    with pytest.raises(ValueError, match="starts is for the mazes.*Reacher3D"):
        env.reset(TensorDict({"start": torch.zeros(1, 3)}, [1]))


@pytest.mark.parametrize("name", ["PointMaze", "AntMaze"])
def test_reward_success_and_time_limit(name):
    spec = get_maze_spec(name)
    env = make_env(name, num_envs=4, seed=1, max_episode_steps=6)
    torch.manual_seed(1)
    rollout = env.rollout(13, break_when_any_done=False)
    nxt = rollout["next"]
    distance = (nxt["achieved_goal"] - nxt["desired_goal"]).norm(dim=-1, keepdim=True)
    expected = torch.from_numpy(sparse_reward(nxt["achieved_goal"].numpy(), nxt["desired_goal"].numpy()))
    torch.testing.assert_close(nxt["reward"], expected[..., None].float())
    torch.testing.assert_close(nxt["reward"], -(distance > 0.5).float())
    assert torch.equal(nxt["is_success"], distance <= spec.success_threshold)
    assert torch.equal(nxt["done"], nxt["truncated"]) and not nxt["terminated"].any()
    assert nxt["truncated"][0, :, 0].tolist() == [t % 6 == 5 for t in range(13)]
    assert nxt["step_count"][0, :, 0].tolist() == [1, 2, 3, 4, 5, 6, 1, 2, 3, 4, 5, 6, 1]
    assert rollout["step_count"][0, :, 0].tolist() == [0, 1, 2, 3, 4, 5, 0, 1, 2, 3, 4, 5, 0]


def test_success_on_scripted_point_rollout():
    """Drive the point straight at an explicit goal: success (within 2.5) and reward (within 0.5) follow."""
    env = make_env("PointMaze", seed=0)
    td = env.reset(TensorDict({"desired_goal": torch.tensor([[6.0, 0.0]])}, [1]))
    assert not td["is_success"].any()  # the start is about 6 away
    yaw = float(td["observation"][0, 2])
    distances, successes, rewards = [], [], []
    for t in range(40):
        turn = -yaw if t == 0 else 0.0  # the reset yaw noise is below the 0.25 turn limit
        td = env.step(td.set("action", torch.tensor([[1.0, turn]])))
        nxt = td["next"]
        distances.append(float((nxt["achieved_goal"] - nxt["desired_goal"]).norm()))
        successes.append(bool(nxt["is_success"]))
        rewards.append(float(nxt["reward"]))
        td = step_mdp(td)
    distances = np.array(distances)
    np.testing.assert_array_equal(successes, distances <= 2.5)
    np.testing.assert_array_equal(rewards, np.where(distances <= 0.5, 0.0, -1.0))
    assert any(successes) and not all(successes) and max(rewards) == 0.0
    # The point moves 0.2 per step towards the goal until it passes it.
    np.testing.assert_allclose(np.diff(distances[:20]), -0.2, atol=0.02)


def test_eval_goals():
    env = make_env("AntMaze", num_envs=2, eval=True, seed=0)
    assert env.reset()["desired_goal"].tolist() == [[0.0, 16.0], [0.0, 16.0]]
    env.eval_goals = False
    assert env.reset()["desired_goal"].tolist() != [[0.0, 16.0], [0.0, 16.0]]
    complex_env = make_env("AntMazeComplex", num_envs=50, eval=True, seed=0)
    goals = {tuple(g) for g in complex_env.reset()["desired_goal"].tolist()}
    assert goals == set(get_maze_spec("AntMazeComplex").test_goals)


def test_collector_keeps_episodes_apart():
    """With a Collector over 3 envs, each trajectory id is one env's episode with consecutive step counts."""
    env = make_env("PointMaze", num_envs=3, seed=0, max_episode_steps=7)
    collector = Collector(env, policy=None, frames_per_batch=60, total_frames=60)
    batch = next(iter(collector))
    collector.shutdown()
    assert batch.batch_size == (3, 20)
    traj = batch["collector", "traj_ids"]
    steps = batch["step_count"][..., 0]
    for i in range(3):
        new_episode = steps[i, 1:] == 0
        assert torch.equal(traj[i, 1:] != traj[i, :-1], new_episode)
        assert torch.equal(torch.where(new_episode, 0, steps[i, :-1] + 1), steps[i, 1:])
    ids_per_env = [set(traj[i].tolist()) for i in range(3)]
    assert not (
        ids_per_env[0] & ids_per_env[1] or ids_per_env[0] & ids_per_env[2] or ids_per_env[1] & ids_per_env[2]
    )
    # The goal is constant within an episode and changes between episodes.
    for tid in traj.unique():
        goals = batch["desired_goal"][traj == tid]
        assert (goals == goals[0]).all()


def test_errors():
    with pytest.raises(ValueError, match="Valid names: PointMaze, AntMazeSmall"):
        make_env("AntMazeHuge")
    with pytest.raises(TypeError):
        make_env(3)
    env = make_env("AntMaze", num_envs=2)
    td = env.reset()
    with pytest.raises(ValueError, match="expects an 'action' of shape"):
        env.step(td.set("action", torch.zeros(2, 2)))
    assert isinstance(make_env("dhrl/AntMaze-v0"), GoalEnv)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_device():
    env = make_env("AntMaze", num_envs=2, seed=0, device="cuda")
    check_env_specs(env)
    td = env.rollout(3)
    assert td["observation"].device.type == "cuda" and td["next", "reward"].device.type == "cuda"
    # fresh envs with the same seed: the one above has advanced its RNG streams
    env, cpu = make_env("AntMaze", num_envs=2, seed=0, device="cuda"), make_env("AntMaze", num_envs=2, seed=0)
    torch.manual_seed(0)
    actions = cpu.action_spec.rand((3,))
    torch.testing.assert_close(
        _rollout(env, actions.cuda())["observation"].cpu(), _rollout(cpu, actions)["observation"]
    )


@pytest.mark.parametrize("name", ["PointMaze", "AntMaze", "Reacher3D"])
def test_state_dict_round_trip_continues_exactly(name):
    """Saving mid-episode and loading into a fresh env continues steps and future resets bit for bit."""
    # seeded: after some draws of actions (13 of 60 seeds) a point's solver warm start is all zeros, which the
    # check below takes for a warm start not restored; the test ran unseeded and failed with such draws
    torch.manual_seed(0)
    env = make_env(name, num_envs=2, seed=3, max_episode_steps=6)
    env.reset()
    actions = torch.rand(12, *env.action_spec.shape) * 2 - 1
    td = env.rand_step(env.reset())
    for a in actions[:4]:
        td = env.step_and_maybe_reset(td.set("action", a.clone()))[1]
    state = env.state_dict()
    other = make_env(name, num_envs=2, seed=99, max_episode_steps=6)
    other.reset()
    other.load_state_dict(state)
    for a, b in zip(env.simulation.datas, other.simulation.datas, strict=True):  # the solver's warm start too
        assert a.qacc_warmstart.any() and np.array_equal(a.qacc_warmstart, b.qacc_warmstart)
    td_other = td.clone()
    for a in actions[4:]:  # crosses the episode end: the automatic reset must draw the same goals and noise
        out, td = env.step_and_maybe_reset(td.set("action", a.clone()))
        out_other, td_other = other.step_and_maybe_reset(td_other.set("action", a.clone()))
        for key in ("observation", "achieved_goal", "desired_goal", "step_count"):
            assert torch.equal(out["next", key], out_other["next", key])
            assert torch.equal(td[key], td_other[key])
    with pytest.raises(ValueError, match="does not fit"):
        make_env(name, num_envs=3, seed=0).load_state_dict(state)


def test_loads_states_saved_without_the_warm_start():
    """States of the full physics only (checkpoints written before the warm start was saved) still load."""
    env = make_env("AntMaze", num_envs=2, seed=0)
    env.rollout(5)
    state = env.state_dict()
    sim = env.simulation
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    physics = np.zeros((2, mujoco.mj_stateSize(sim.model, spec)))
    for i, data in enumerate(sim.datas):
        mujoco.mj_getState(sim.model, data, physics[i], spec)
    assert physics.shape != np.shape(state["_extra_state"]["physics"])
    other = make_env("AntMaze", num_envs=2, seed=1)
    other.load_state_dict({"_extra_state": {**state["_extra_state"], "physics": physics}})
    for a, b in zip(sim.datas, other.simulation.datas, strict=True):
        assert np.array_equal(a.qpos, b.qpos) and np.array_equal(a.qvel, b.qvel)


OBS_DIMS = {"Reacher3D": 17, "UR3Obstacle": 15}


def test_names_and_specs():
    assert ARM_NAMES == ("Reacher3D", "UR3Obstacle")
    assert ENV_NAMES == MAZE_NAMES + ARM_NAMES
    reacher, ur3 = get_arm_spec("Reacher3D"), get_arm_spec("dhrl/UR3Obstacle-v0")
    assert isinstance(get_env_spec("Reacher3D"), ArmSpec)
    assert (reacher.episode_length, reacher.success_threshold, reacher.reward_threshold) == (100, 0.25, 0.25)
    assert reacher.agent.timestep == 0.01 and reacher.agent.frame_skip == 2 and reacher.agent.ctrl_limit == 20
    assert (ur3.episode_length, ur3.success_threshold, ur3.reward_threshold) == (100, 0.08, 0.08)
    for spec in (reacher, ur3):
        assert spec.goal_dim == 3 and spec.obs_dim == OBS_DIMS[spec.name]


@pytest.mark.parametrize("num_envs", [1, 3])
@pytest.mark.parametrize("name", ARM_NAMES)
def test_arm_check_env_specs(name, num_envs):
    env = make_env(name, num_envs=num_envs, seed=0, max_episode_steps=2)
    check_env_specs(env)
    td = env.reset()
    assert td["observation"].shape == (num_envs, OBS_DIMS[name]) and td["observation"].dtype == torch.float32
    assert td["achieved_goal"].shape == (num_envs, 3) and td["achieved_goal"].dtype == torch.float32
    assert td["desired_goal"].shape == (num_envs, 3) and td["desired_goal"].dtype == torch.float32
    assert td["is_success"].dtype == torch.bool and td["is_success"].shape == (num_envs, 1)
    assert td["step_count"].dtype == torch.int64 and (td["step_count"] == 0).all()
    assert env.action_spec.shape == (num_envs, get_arm_spec(name).agent.action_dim)


def test_observation_layouts():
    """Reacher3D: 7 joint angles, the goal, 7 joint velocities. UR3Obstacle: flange position, angles, velocities."""
    env = make_env("Reacher3D", num_envs=2, seed=0)
    td = env.rollout(3, break_when_any_done=False)
    sim = env.simulation
    torch.testing.assert_close(td["next", "observation"][:, -1, 7:10], td["desired_goal"][:, -1])
    np.testing.assert_allclose(sim.observation[:, :7], [d.qpos for d in sim.datas])
    np.testing.assert_allclose(sim.observation[:, 10:], [d.qvel for d in sim.datas])
    env = make_env("UR3Obstacle", num_envs=2, seed=0)
    td = env.rollout(3, break_when_any_done=False)
    sim = env.simulation
    assert torch.equal(td["next", "achieved_goal"], td["next", "observation"][..., :3])
    np.testing.assert_allclose(sim.observation[:, 3:9], [d.qpos for d in sim.datas])
    np.testing.assert_allclose(sim.observation[:, 9:], [d.qvel for d in sim.datas])


def _arm_rollout(env, actions):
    td = env.reset()
    out = []
    for action in actions:
        td = env.step(td.set("action", action))
        out.append(td["next"].clone())
        td = step_mdp(td)
    return torch.stack(out, 1)


@pytest.mark.parametrize("name", ARM_NAMES)
def test_arm_seeding_is_deterministic(name):
    torch.manual_seed(0)
    env = make_env(name, num_envs=2)
    actions = env.action_spec.rand((5,))
    runs = []
    for seed in (3, 3, 4):
        env.set_seed(seed)
        runs.append(_arm_rollout(env, actions))
    assert (runs[0] == runs[1]).all()
    assert not torch.equal(runs[0]["observation"], runs[2]["observation"])
    assert not torch.equal(runs[0]["desired_goal"][0], runs[0]["desired_goal"][1])
    a, b = make_env(name, num_envs=2, seed=7).reset(), make_env(name, num_envs=2, seed=7).reset()
    assert (a == b).all()
    # Env i's stream depends only on (seed, i): env 0 of a 2-env batch starts like a 1-env env.
    torch.testing.assert_close(make_env(name, seed=7).reset()["observation"][0], a["observation"][0])


def test_reacher_goal_distribution():
    """Train and test goals: (0, 0.25, 0) + N(0, 0.1) per axis, through env resets (one RNG stream per env)."""
    env = make_env("Reacher3D", num_envs=400, seed=0)
    for eval_goals in (False, True):
        env.eval_goals = eval_goals
        goals = env.reset()["desired_goal"].double().numpy()
        np.testing.assert_allclose(goals.mean(0), [0.0, 0.25, 0.0], atol=0.02)  # 4 standard errors
        np.testing.assert_allclose(goals.std(0), 0.1, rtol=0.12)
        for axis, mean in enumerate((0.0, 0.25, 0.0)):
            # standardised first: some scipy versions reject loc/scale args for "norm"
            assert stats.kstest((goals[:, axis] - mean) / 0.1, "norm").pvalue > 1e-3
    sampler = get_arm_spec("Reacher3D").train_goals
    many = sampler.sample(np.random.default_rng(0), 20000)
    np.testing.assert_allclose(many.mean(0), [0.0, 0.25, 0.0], atol=0.003)
    np.testing.assert_allclose(many.std(0), 0.1, rtol=0.02)


def test_ur3_goal_distributions():
    spec = get_arm_spec("UR3Obstacle")
    env = make_env("UR3Obstacle", num_envs=300, seed=0, eval=True)
    test = env.reset()["desired_goal"].double().numpy()
    low, high = np.array(spec.test_goals.low), np.array(spec.test_goals.high)
    assert ((test >= low) & (test <= high)).all()
    for axis in range(3):  # uniform in the test box, behind the fence (y > 0) inside the bin
        assert stats.kstest((test[:, axis] - low[axis]) / (high[axis] - low[axis]), "uniform").pvalue > 1e-3
    fence, front, far = spec.boards
    assert (test[:, 1] > fence.center[1] + 0.05).all() and (test[:, 1] < far.center[1] - 0.05).all()
    assert (test[:, 0] < front.center[0] - 0.05).all() and (test[:, 2] < 2 * fence.half_size[2]).all()
    # Train goals cover both sides of the fence and keep 5 cm away from every board.
    train = spec.train_goals.sample(np.random.default_rng(0), 5000)
    assert (train[:, 1] < 0).mean() > 0.3 and (train[:, 1] > 0).mean() > 0.3
    for board in spec.boards:
        inside = (np.abs(train - board.center) < np.array(board.half_size) + 0.05).all(-1)
        assert not inside.any()


@pytest.mark.parametrize("name", ARM_NAMES)
def test_arm_reward_success_and_time_limit(name):
    spec = get_arm_spec(name)
    env = make_env(name, num_envs=2, seed=1, max_episode_steps=6)
    torch.manual_seed(1)
    rollout = env.rollout(13, break_when_any_done=False)
    nxt = rollout["next"]
    distance = (nxt["achieved_goal"] - nxt["desired_goal"]).norm(dim=-1, keepdim=True)
    expected = sparse_reward(nxt["achieved_goal"].numpy(), nxt["desired_goal"].numpy(), spec.reward_threshold)
    torch.testing.assert_close(nxt["reward"], torch.from_numpy(expected)[..., None].float())
    assert torch.equal(nxt["is_success"], distance <= spec.success_threshold)
    assert torch.equal(nxt["done"], nxt["truncated"]) and not nxt["terminated"].any()
    assert nxt["truncated"][0, :, 0].tolist() == [t % 6 == 5 for t in range(13)]
    # The default time limit is the task's 100 steps.
    full = make_env(name, seed=0)
    assert full.max_episode_steps == 100
    flags = full.rollout(100, break_when_any_done=False)["next", "truncated"][0, :, 0]
    assert flags.nonzero().flatten().tolist() == [99]


@pytest.mark.parametrize("name", ARM_NAMES)
def test_success_threshold_boundary(name):
    """Goals just inside / outside the thresholds around the achieved goal give success and reward 0 / -1."""
    spec = get_arm_spec(name)
    sim = GoalSimulation(name, 4, seed=0)
    sim.reset()
    direction = np.array([1.0, 2.0, -2.0]) / 3.0
    radii = np.array([0.99, 1.01, 0.5, 3.0]) * spec.success_threshold
    sim.desired_goal[:] = sim.achieved_goal + radii[:, None] * direction
    reward, success = sim.evaluate()
    assert success.tolist() == [True, False, True, False]
    assert reward.tolist() == [0.0, -1.0, 0.0, -1.0]  # reward and success radii coincide for the arms


def test_explicit_goals_and_errors():
    env = make_env("UR3Obstacle", num_envs=2, seed=0)
    goals = torch.tensor([[0.375, 0.18, 0.1], [0.3, -0.2, 0.3]])
    td = env.reset(TensorDict({"desired_goal": goals}, [2]))
    torch.testing.assert_close(td["desired_goal"], goals)
    np.testing.assert_allclose(env.simulation.datas[0].mocap_pos[0], [0.375, 0.18, 0.1])  # the marker follows
    with pytest.raises(
        ValueError, match=r"outside the UR3Obstacle arena: goals must be in x in .*z in \[0.0, 0.7\]"
    ):
        env.reset(TensorDict({"desired_goal": torch.tensor([[0.0, 0.0, 0.9], [0.0, 0.0, 0.1]])}, [2]))
    with pytest.raises(ValueError, match="shape"):
        env.reset(TensorDict({"desired_goal": torch.zeros(2, 2)}, [2]))
    with pytest.raises(ValueError, match="expects an 'action' of shape"):
        env.step(td.set("action", torch.zeros(2, 7)))
    with pytest.raises(ValueError, match="Valid names: .*Reacher3D, UR3Obstacle"):
        make_env("UR5Obstacle")
    assert isinstance(make_env("dhrl/Reacher3D-v0"), GoalEnv)


def test_reacher_reset_is_noise_free():
    """As in the reference: every episode starts at the zero posture, at rest (no qpos or qvel noise)."""
    spec = get_arm_spec("Reacher3D")
    assert spec.agent.init_qpos == (0.0,) * 7 and spec.agent.qpos_noise == spec.agent.qvel_noise == 0.0
    sim = GoalSimulation("Reacher3D", 300, seed=0)
    sim.reset()
    assert not sim.observation[:, :7].any() and not sim.observation[:, 10:].any()


# How far a limited joint may pass its range in a random episode. Reacher3D keeps the reference model's soft
# joint limits (MuJoCo's default solref/solimp): its light upper-arm roll and wrist flex (about 0.05 kg m^2
# of joint-space inertia) overshoot by up to ~0.3 rad when random +-20 N m torques throw them at a limit.
LIMIT_SLACK = {"Reacher3D": 0.4, "UR3Obstacle": 0.05}


@pytest.mark.parametrize("name", ARM_NAMES)
def test_random_rollout_is_stable(name):
    """A full episode of uniformly random actions: finite, joints within their (soft) limits, the arm moves."""
    spec = get_arm_spec(name)
    env = make_env(name, num_envs=4, seed=0)
    torch.manual_seed(0)
    rollout = env.rollout(spec.episode_length, break_when_any_done=False)
    assert torch.isfinite(rollout["next", "observation"]).all()
    moved = (rollout["next", "achieved_goal"][:, -1] - rollout["achieved_goal"][:, 0]).norm(dim=-1)
    assert (moved > 0.02).all()
    model = env.simulation.model
    qpos = np.array([d.qpos for d in env.simulation.datas])
    limited = model.jnt_limited.astype(bool)
    low, high = model.jnt_range[limited].T
    slack = LIMIT_SLACK[name]
    assert ((qpos[:, limited] > low - slack) & (qpos[:, limited] < high + slack)).all()


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("name", ARM_NAMES)
def test_arm_cuda_device(name):
    env = make_env(name, num_envs=2, seed=0, device="cuda")
    check_env_specs(env)
    td = env.rollout(3)
    assert td["achieved_goal"].device.type == "cuda" and td["next", "reward"].device.type == "cuda"
