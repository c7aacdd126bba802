"""GymnasiumGoalEnv: a Gymnasium goal env (gymnasium-robotics' PointMaze_UMaze-v3) as an env of the goal-env contract,
its exact state, its goal space, the achieved goal put into an observation that leaves it out (AntMaze_UMaze-v5), the
refusal of an env that ends episodes itself; and check_goal_env's float32 and truncation checks."""

from __future__ import annotations

import re

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs
from torchrl_dhrl.envs import (
    AntAgent,
    GoalEnvError,
    GymnasiumGoalEnv,
    check_goal_env,
    goal_extent,
    goal_indices_of,
    goal_speed,
    gymnasium_id,
    make_env,
)

pytest.importorskip("gymnasium_robotics")
UMAZE = "PointMaze_UMaze-v3"
ANT_UMAZE = "AntMaze_UMaze-v5"
LARGE = "PointMaze_Large-v3"
TERMINATING = "DhrlTestTerminatingPoint-v0"


class TerminatingPoint(gym.Env):
    """A tiny Gymnasium goal env that ends an episode itself and has no ``continuing_task`` attribute to say so
    beforehand: a point in [-1, 1]^2 moving 0.1 per action unit, terminated at step ``terminate_at`` of its episodes
    from the ``from_episode``-th on (resets of this instance, counted from 1), unless the class is ``fixed``."""

    fixed = False  # "the user fixed the env's code": it never terminates

    def __init__(self, terminate_at: int = 3, from_episode: int = 1):
        box = gym.spaces.Box(-np.inf, np.inf, (2,), np.float64)
        self.observation_space = gym.spaces.Dict(observation=box, achieved_goal=box, desired_goal=box)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.terminate_at, self.from_episode = terminate_at, from_episode
        self.episodes, self.steps = 0, 0
        self.pos, self.goal = np.zeros(2), np.zeros(2)

    def _obs(self):
        return {"observation": self.pos.copy(), "achieved_goal": self.pos.copy(), "desired_goal": self.goal.copy()}

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.episodes, self.steps = self.episodes + 1, 0
        self.pos, self.goal = self.np_random.uniform(-0.5, 0.5, 2), self.np_random.uniform(-1.0, 1.0, 2)
        return self._obs(), {}

    def step(self, action):
        self.pos = np.clip(self.pos + 0.1 * np.asarray(action, dtype=np.float64), -1.0, 1.0)
        self.steps += 1
        terminated = not self.fixed and self.episodes >= self.from_episode and self.steps >= self.terminate_at
        reward = float(self.compute_reward(self.pos, self.goal, {}))
        return self._obs(), reward, terminated, False, {"is_success": reward == 0.0}

    def compute_reward(self, achieved_goal, desired_goal, info):
        return -(np.linalg.norm(np.asarray(achieved_goal) - desired_goal, axis=-1) > 0.2).astype(np.float64)


if TERMINATING not in gym.registry:
    gym.register(TERMINATING, entry_point=TerminatingPoint, max_episode_steps=40)


def test_the_adapter_meets_the_contract():
    env = make_env(f"gymnasium:{UMAZE}", num_envs=2, seed=0)
    assert isinstance(env, GymnasiumGoalEnv) and env.max_episode_steps == 300  # the env's TimeLimit
    check_goal_env(env, goal_indices=[0, 1], steps=3)
    check_env_specs(env)
    td = env.rollout(4)
    assert td["next", "observation"].dtype == torch.float32 and td["next", "is_success"].shape == (2, 4, 1)
    assert td["next", "step_count"][0, :, 0].tolist() == [1, 2, 3, 4]
    assert gymnasium_id(f"gymnasium:{UMAZE}") == UMAZE and gymnasium_id("PointMaze") is None


def test_episodes_truncate_at_max_episode_steps_and_reset_options_apply():
    env = GymnasiumGoalEnv(UMAZE, 1, seed=1, max_episode_steps=7, reset_options={"reset_cell": [3, 1]})
    check_goal_env(env, goal_indices=[0, 1], steps=15)  # truncation at 7 and 14, checked
    starts = torch.stack([env.reset()["achieved_goal"][0] for _ in range(5)])
    assert ((starts - torch.tensor([-1.0, -1.0])).abs() <= 0.26).all()  # cell (3, 1) of the U: (-1, -1) +- noise


def test_success_comes_from_the_env_info_or_a_distance():
    env = GymnasiumGoalEnv(UMAZE, 1, seed=0)
    assert env.success_radius() == pytest.approx(0.45, abs=1e-5)  # read from compute_reward
    td = env.reset()
    far = (td["achieved_goal"] - td["desired_goal"]).norm().item()
    env = GymnasiumGoalEnv(UMAZE, 1, seed=0, success_threshold=far + 1.0)
    assert env.reset()["is_success"].all() and env.success_radius() == far + 1.0


def test_the_state_dict_resumes_the_simulation_exactly():
    actions = torch.rand(12, 2, 2, generator=torch.Generator().manual_seed(0)) * 2 - 1
    env = GymnasiumGoalEnv(UMAZE, 2, seed=3)
    td = env.reset()
    for k in range(6):
        td = env.step(td.set("action", actions[k]))["next"]
    state = env.state_dict()
    straight = []
    for k in range(6, 12):
        td = env.step(td.set("action", actions[k]))["next"]
        straight.append(td.exclude("reward"))
    straight.append(env.reset())  # the next episode's goals come from the restored random streams too
    resumed = GymnasiumGoalEnv(UMAZE, 2, seed=99)
    resumed.reset()
    resumed.load_state_dict(state)
    td, out = resumed._output(), []
    for k in range(6, 12):
        td = resumed.step(td.set("action", actions[k]))["next"]
        out.append(td.exclude("reward"))
    out.append(resumed.reset())
    for a, b in zip(straight, out, strict=True):
        assert (a == b).all()


def test_goal_space_helpers():
    env = GymnasiumGoalEnv(UMAZE, 1, seed=0)
    assert goal_indices_of(env) == [0, 1]
    low, high = goal_extent(env, episodes=8)
    assert all(-2.2 < v < -1.0 for v in low) and all(1.0 < v < 2.2 for v in high)  # the U spans [-1.5, 1.5]^2
    assert goal_indices_of(make_env("Reacher3D", seed=0)) is None  # the arm's goal is not in its observation


def test_goal_speed_is_the_agents_top_speed():
    """The built-in env files' hand-set oracle speeds (PointMaze 0.2, AntMaze 0.1: the ant's random steps), and the
    gymnasium point's top speed measured on the raw env held at full thrust along a corridor (its velocity is clipped:
    constant after about 22 steps); deterministic, the global torch random state untouched."""
    assert goal_speed(make_env("PointMaze", seed=0)) == pytest.approx(0.2, abs=0.002)
    assert goal_speed(make_env("AntMaze", seed=0)) == pytest.approx(0.1, rel=0.15)
    raw = gym.make(LARGE)
    obs, _ = raw.reset(seed=0, options={"reset_cell": [1, 1]})  # 4 free cells to the right
    path = [obs["achieved_goal"]]
    for _ in range(40):
        path.append(raw.step(np.array([1.0, 0.0], dtype=np.float32))[0]["achieved_goal"])
    top = float(np.linalg.norm(np.diff(np.array(path), axis=0), axis=1)[-10:].mean())
    env = GymnasiumGoalEnv(LARGE, 1, seed=0)
    state = torch.get_rng_state()
    speed = goal_speed(env)
    assert torch.equal(torch.get_rng_state(), state) and goal_speed(env) == speed
    assert speed == pytest.approx(top, rel=0.01) and top == pytest.approx(0.0523, abs=1e-3)


def test_bad_arguments_and_envs_are_refused():
    with pytest.raises(ValueError, match="`success_threshold` must be None or a number > 0"):
        GymnasiumGoalEnv(UMAZE, success_threshold=0.0)
    with pytest.raises(ValueError, match="`reset_options`"):
        GymnasiumGoalEnv(UMAZE, reset_options=[1, 2])
    with pytest.raises(GoalEnvError, match="No Gymnasium env 'NoSuchMaze-v0'"):
        GymnasiumGoalEnv("NoSuchMaze-v0")
    with pytest.raises(GoalEnvError, match="Dict observation"):
        GymnasiumGoalEnv("Pendulum-v1")
    with pytest.raises(ValueError, match="`achieved_goal_in_observation` must be None or a bool"):
        GymnasiumGoalEnv(UMAZE, achieved_goal_in_observation="yes")


def test_an_env_that_says_it_ends_episodes_itself_is_refused_at_construction():
    """The maze says so (``continuing_task=False``): refused before a step, naming the argument and what is accepted
    (it used to train until an episode first reached its goal, which can be hours in)."""
    with pytest.raises(GoalEnvError, match=r"^PointMaze_UMaze-v3 has continuing_task=False \(`make_kwargs`=\{'continuing_task': "
                       r"False\}\).*accepted: continuing_task=True"):
        GymnasiumGoalEnv(UMAZE, 1, seed=0, make_kwargs={"continuing_task": False})
    assert GymnasiumGoalEnv(UMAZE, 1, seed=0, make_kwargs={"continuing_task": True}).max_episode_steps == 300


def test_an_env_that_cannot_say_so_is_refused_at_the_end_of_the_episode_it_ended_naming_the_fix():
    """No ``continuing_task`` to tell beforehand: the copy that terminated is held at its last state to the episode's
    end (a whole episode, which a training loop stores), ``refusal`` says why meanwhile (a loop stops there with a
    checkpoint), and the next step raises it."""
    env = GymnasiumGoalEnv(TERMINATING, 2, seed=0, make_kwargs={"terminate_at": 3, "from_episode": 3})
    assert not hasattr(env._envs[0].unwrapped, "continuing_task") and not env.achieved_goal_in_observation
    # copy 0 resets for the 3rd time (with the construction's reset) in the 2nd episode, copy 1 in the 3rd
    actions = torch.full((2, 2), 0.5)
    td = env.reset()
    for _ in range(40):
        td = env.step(td.set("action", actions))["next"]
    assert env.refusal is None and td["truncated"].all()
    td = env.reset()
    out = [td := env.step(td.set("action", actions))["next"] for _ in range(40)]
    message = (r"ended an episode itself \(terminated\) after 3 of 40 steps.*make the env continuing, by a "
               r"`make_kwargs` option of its own .* or in its code or a wrapper")
    assert re.search(message, env.refusal)
    held = torch.stack([o["observation"][0] for o in out[2:]])
    assert (held == held[0]).all() and not (out[2]["observation"][1] == out[3]["observation"][1]).all()
    assert not any(o["terminated"].any() for o in out) and out[-1]["truncated"].all()
    assert [o["step_count"][0, 0].item() for o in out] == list(range(1, 41))
    assert all(torch.equal(o["reward"][0], out[2]["reward"][0]) for o in out[2:])
    td = env.reset()
    with pytest.raises(GoalEnvError, match=message):
        env.step(td.set("action", actions))


def test_the_achieved_goal_goes_first_into_an_observation_that_leaves_it_out():
    """AntMaze_UMaze-v5 observes the torso without its x, y (105 entries): the adapter prepends the achieved goal,
    so ``goal_indices`` are ``[0, 1]``; PointMaze_UMaze-v3's observation [x, y, vx, vy] holds it and stays as it is."""
    env = make_env(f"gymnasium:{ANT_UMAZE}", num_envs=2, seed=0)
    assert env.achieved_goal_in_observation and env.observation_spec["observation"].shape == (2, 107)
    check_env_specs(env)
    check_goal_env(env, goal_indices=[0, 1], steps=3)
    td = env.rollout(5)
    assert td["next", "observation"].shape == (2, 5, 107)
    assert torch.equal(td["next", "observation"][..., :2], td["next", "achieved_goal"])
    assert torch.equal(td["observation"][..., :2], td["achieved_goal"])  # the resets' too
    assert goal_indices_of(env) == [0, 1]
    bare = GymnasiumGoalEnv(ANT_UMAZE, 1, seed=0, achieved_goal_in_observation=False)
    assert bare.observation_spec["observation"].shape == (1, 105) and goal_indices_of(bare) is None
    point = GymnasiumGoalEnv(UMAZE, 2, seed=0)
    assert not point.achieved_goal_in_observation and point.observation_spec["observation"].shape == (2, 4)
    forced = GymnasiumGoalEnv(UMAZE, 2, seed=0, achieved_goal_in_observation=True)
    obs = forced.rollout(3)["next", "observation"]
    assert obs.shape == (2, 3, 6) and torch.equal(obs[..., :2], obs[..., 2:4])  # [goal, x, y, vx, vy]


def test_check_goal_env_wants_float32_and_the_true_episode_length():
    env64 = make_env("PointMaze", num_envs=1, seed=0, max_episode_steps=5)
    env64.observation_spec["observation"].dtype = torch.float64
    with pytest.raises(GoalEnvError, match=r"observation.*float64; expected torch.float32.*DoubleToFloat"):
        check_goal_env(env64, steps=0)
    # an env that claims 40 steps and truncates at 5 (and one that claims 3)
    for claim, what in ((40, "truncated at step 5"), (3, "did not truncate at step 3")):
        liar = TransformedEnv(make_env("PointMaze", num_envs=1, seed=0, max_episode_steps=5))
        liar.max_episode_steps = claim
        with pytest.raises(GoalEnvError, match=what):
            check_goal_env(liar, steps=12)
    truthful = TransformedEnv(make_env("PointMaze", num_envs=1, seed=0, max_episode_steps=5))
    truthful.max_episode_steps = 5
    check_goal_env(truthful, steps=12)


def test_fixed_goals_replace_the_env_goals_in_turn_for_rewards_and_success():
    env = GymnasiumGoalEnv(UMAZE, 2, seed=0, goals=[[1.0, 1.0], [-1.0, -1.0]], reset_options={"reset_cell": [3, 1]})
    first, second = env.reset(), env.reset()
    assert first["desired_goal"].tolist() == [[1.0, 1.0]] * 2 and second["desired_goal"].tolist() == [[-1.0, -1.0]] * 2
    # the second goal is in the start cell: success within 0.45, as the env itself judges it after a step
    distance = (second["achieved_goal"] - second["desired_goal"]).norm(dim=-1, keepdim=True)
    assert torch.equal(second["is_success"], distance <= 0.45)
    td = env.step(second.set("action", torch.zeros(2, 2)))["next"]
    distance = (td["achieved_goal"] - td["desired_goal"]).norm(dim=-1, keepdim=True)
    assert torch.equal(td["is_success"], distance <= 0.45) and td["desired_goal"].tolist() == [[-1.0, -1.0]] * 2
    with pytest.raises(ValueError, match="`goals` must be None or a goal"):
        GymnasiumGoalEnv(UMAZE, goals="north")


def test_a_desired_goal_passed_to_reset_sets_the_goals_of_the_envs_being_reset_only():
    env = GymnasiumGoalEnv(UMAZE, 3, seed=0, goals=[[1.0, 1.0]], reset_options={"reset_cell": [3, 1]})
    first = env.reset()
    goals = torch.tensor([[-1.0, -1.0], [0.5, -1.0], [2.0, 2.0]])
    mask = torch.tensor([[True], [False], [True]])
    td = env.reset(TensorDict({"desired_goal": goals, "_reset": mask}, batch_size=[3]))
    # envs 0 and 2 take the passed goals (over the fixed ones), env 1 is not reset and keeps its goal and state
    assert td["desired_goal"][[0, 2]].tolist() == [[-1.0, -1.0], [2.0, 2.0]]
    assert [e.unwrapped.goal.tolist() for e in env._envs] == [[-1.0, -1.0], [1.0, 1.0], [2.0, 2.0]]
    # the env rewards and judges the passed goals (the same within 0.45 as the env itself)
    step = env.step(td.set("action", torch.zeros(3, 2)))["next"]
    goals[1] = torch.tensor([1.0, 1.0])
    torch.testing.assert_close(step["achieved_goal"][1], first["achieved_goal"][1])  # still at its first start
    assert step["desired_goal"].tolist() == goals.tolist()
    distance = (step["achieved_goal"] - goals).norm(dim=-1, keepdim=True)
    assert torch.equal(step["is_success"], distance <= 0.45)
    assert torch.equal(step["reward"], (distance <= 0.45).float())  # the maze's sparse reward: 1 at its goal
    # the next automatic reset draws the fixed goal again
    assert env.reset()["desired_goal"].tolist() == [[1.0, 1.0]] * 3
    with pytest.raises(GoalEnvError, match=r"'desired_goal' passed to reset must have shape \(3, 2\), got \(3, 3\)"):
        env.reset(TensorDict({"desired_goal": torch.zeros(3, 3)}, batch_size=[3]))
    with pytest.raises(GoalEnvError, match="'start' entry passed to reset moves the built-in mazes' agents only"):
        env.reset(TensorDict({"start": torch.zeros(3, 2)}, batch_size=[3]))


def test_the_recipe_names_a_bad_test_goal_key():
    from _recipe import recipe_config

    from torchrl_dhrl.recipe import ConfigError
    from torchrl_dhrl.recipe.routing import check_components

    cfg = recipe_config(f"env_name=gymnasium:{UMAZE}", "gymnasium.eval_goals=[[1.0,1.0],[-1.0,1.0]]")
    check_components(cfg, goal_dim=2, error=ConfigError)
    cfg["gymnasium"]["eval_goals"] = "north"
    with pytest.raises(ConfigError, match=r"^`gymnasium.eval_goals` must be None or a goal"):
        check_components(cfg, goal_dim=2, error=ConfigError)


@pytest.mark.recipe
def test_a_run_refused_at_a_late_terminated_step_stops_with_a_checkpoint_that_resumes(tmp_path, monkeypatch):
    """An env that cannot say beforehand that it ends episodes (no ``continuing_task``) terminates in the 4th batch,
    after 3 epochs and before any periodic checkpoint: the run stops at that batch's end (the batch unused) naming the
    fix, with a checkpoint, and once the env is fixed (in its code: the same configuration) it resumes to its end."""
    from _recipe import load_recipe, metrics_rows, recipe_config

    from torchrl_dhrl.recipe import checkpoint_file

    recipe = load_recipe()
    overrides = (
        "env=gymnasium", f"env_name=gymnasium:{TERMINATING}", "preset=smoke", "device=cpu", "logger.backend=none",
        "plots.every_epochs=0", "threads=1", "checkpoint.every_epochs=5", "schedule.eval_flat=false",
        # copy 0 of the training env resets for the 5th time (with the construction's reset) in the 4th batch
        "gymnasium.make_kwargs={terminate_at:3,from_episode:5}", "goal_indices=[0,1]",
        "high.subgoal_low=[-1.2,-1.2]", "high.subgoal_high=[1.2,1.2]", "high.subgoal_noise=0.2",
        "low.reward_threshold=0.2", "planner.reach_radius=0.2", "fgs.noise=0.3", "planner.oracle_speed=0.1",
    )
    run_dir = tmp_path / "run"
    with pytest.raises(SystemExit, match=r"ended an episode itself \(terminated\) after 3 of 40 steps.*resume="
    ):
        recipe.train(recipe_config(*overrides), run_dir=run_dir)
    assert checkpoint_file(run_dir).exists()
    assert [row["env_steps"] for row in metrics_rows(run_dir)] == ["80", "160", "240"]
    monkeypatch.setattr(TerminatingPoint, "fixed", True)
    recipe.train(recipe_config(*overrides, f"resume={run_dir}"), run_dir=run_dir)
    assert [row["env_steps"] for row in metrics_rows(run_dir)] == ["80", "160", "240", "320", "400", "480"]


@pytest.mark.parametrize(
    ("env_id", "start_cell", "far_cell"), [("PointMaze_Large-v3", (1, 1), (7, 10)), ("AntMaze_Medium-v5", (1, 1), (6, 6))]
)
def test_a_gymnasium_maze_s_geometry_is_its_map(env_id, start_cell, far_cell):
    """The geometry of a gymnasium-robotics maze against the maze's own map: with no margin a grid cell is free exactly
    where the env's ``cell_xy_to_rowcol`` puts it in an open map cell; the start is the reset cell's centre; the path
    length from it to a far cell lies between the straight line and the 4-connected cell path (networkx); an inner wall
    cell's centre is in a wall."""
    import networkx as nx

    env = GymnasiumGoalEnv(env_id, 1, seed=0, reset_options={"reset_cell": list(start_cell)})
    maze = env._envs[0].unwrapped.maze
    geometry = env.maze_geometry()
    scale = maze.maze_size_scaling
    assert geometry.scale == scale
    torch.testing.assert_close(geometry.start, torch.as_tensor(maze.cell_rowcol_to_xy(np.array(start_cell)), dtype=torch.float32))
    grid = np.asarray(maze.maze_map)
    centres = geometry.cell_centers.reshape(-1, 2).numpy()
    open_cells = np.array([grid[tuple(maze.cell_xy_to_rowcol(c))] == 0 for c in centres])
    assert np.array_equal(geometry.free.reshape(-1).numpy(), open_cells)
    # the arena is the rectangle inside the outer wall ring
    rows, cols = grid.shape
    assert (geometry.arena_high - geometry.arena_low).tolist() == [(cols - 2) * scale, (rows - 2) * scale]
    cells = nx.grid_2d_graph(rows, cols)
    cells.remove_nodes_from([(r, c) for r, c in list(cells) if grid[r, c] == 1])
    hops = nx.shortest_path_length(cells, start_cell, far_cell)
    far = torch.as_tensor(maze.cell_rowcol_to_xy(np.array(far_cell)), dtype=torch.float32)
    length = geometry.path_length(geometry.start, far.reshape(1, 2)).item()
    assert (far - geometry.start).norm().item() <= length <= hops * scale + 1e-4
    wall = next((r, c) for r in range(rows) for c in range(cols) if grid[r, c] == 1 and 0 < r < rows - 1 and 0 < c < cols - 1)
    centre = torch.as_tensor(maze.cell_rowcol_to_xy(np.array(wall)), dtype=torch.float32)
    assert geometry.in_walls(centre).item() and not geometry.in_walls(geometry.start).item()
    # a margin narrows the free space; resets without one fixed cell leave no start (no progress to measure)
    assert geometry.free.float().mean() > env.maze_geometry(margin=scale / 8).free.float().mean()
    assert GymnasiumGoalEnv(env_id, 1, seed=0).maze_geometry().start is None
    assert GymnasiumGoalEnv(env_id, 1, seed=0, reset_options=[{"reset_cell": [1, 1]}, {"reset_cell": list(far_cell)}]).maze_geometry().start is None
    assert GymnasiumGoalEnv(TERMINATING, 1, seed=0).maze_geometry() is None  # no maze


# ---- right_flipped_after: gymnasium-robotics' ant mazes ------------------------------------------------------------


def _flip(maze_env, qx: float = 1.0) -> None:
    """Turns the ant of an unwrapped ant maze upside down in place (half a turn about the torso's x axis, or a tilt
    between), at rest, and re-observes nothing: the next step reads the new state."""
    data = maze_env.ant_env.data
    qpos, qvel = data.qpos.copy(), np.zeros_like(data.qvel)
    quat = np.array([np.sqrt(max(0.0, 1 - qx * qx)), qx, 0.0, 0.0])
    qpos[2], qpos[3:7] = 0.3, quat / np.linalg.norm(quat)
    maze_env.ant_env.set_state(qpos, qvel)


def _overlaps_wall(maze_env) -> bool:
    """Whether a geom of the ant penetrates a wall block of the maze, from the maze's own wall list (the geoms the
    maze builder names ``block_*``)."""
    import mujoco

    model, data = maze_env.ant_env.model, maze_env.ant_env.data
    mujoco.mj_forward(model, data)
    walls = {i for i in range(model.ngeom) if (mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, i) or "").startswith("block")}
    return any(c.dist < 0 and (c.geom[0] in walls) != (c.geom[1] in walls) for c in data.contact[: data.ncon])


def test_upright_pose_keeps_position_and_heading_and_stands_the_body_up():
    """Against scipy's rotations, over random orientations (upside down, tilted, upright, the vertical x axis):
    the body keeps its (x, y) and the heading of its x axis projected on the floor, and stands up (no tilt)."""
    from scipy.spatial.transform import Rotation
    from torchrl_dhrl.envs.agents import upright_pose

    rng = np.random.default_rng(0)
    quats = np.concatenate([Rotation.random(200, random_state=1).as_quat(), [[0, 0, 0, 1], [0, 1, 0, 0], [1, 0, 0, 0]]])
    qpos = np.zeros((len(quats), 15))
    qpos[:, :3] = rng.uniform(-5, 5, (len(quats), 3))
    qpos[:, 3], qpos[:, 4:7] = quats[:, 3], quats[:, :3]  # MuJoCo's (w, x, y, z)
    rest = np.concatenate([[0.0, 0.0, 0.75, 1.0, 0.0, 0.0, 0.0], rng.uniform(-1, 1, 8)])
    out = upright_pose(qpos, rest)
    assert np.allclose(out[:, :2], qpos[:, :2]) and np.allclose(out[:, 2], 0.75) and np.allclose(out[:, 7:], rest[7:])
    after = Rotation.from_quat(np.concatenate([out[:, 4:7], out[:, 3:4]], axis=1))
    assert np.allclose(after.apply([0.0, 0.0, 1.0]), [0.0, 0.0, 1.0], atol=1e-9)  # the up axis points up
    x_before, x_after = Rotation.from_quat(quats).apply([1.0, 0.0, 0.0]), after.apply([1.0, 0.0, 0.0])
    flat = np.hypot(x_before[:, 0], x_before[:, 1]) > 1e-6  # a heading to keep
    heading = np.arctan2(x_before[flat, 1], x_before[flat, 0])
    assert np.allclose(np.angle(np.exp(1j * (np.arctan2(x_after[flat, 1], x_after[flat, 0]) - heading))), 0.0, atol=1e-9)


@pytest.mark.parametrize("after", [1, 4])
def test_a_gymnasium_ant_upside_down_for_right_flipped_after_steps_is_righted_and_the_episode_goes_on(after):
    env = make_env(f"gymnasium:{ANT_UMAZE}", num_envs=2, seed=0, right_flipped_after=after)
    plain = GymnasiumGoalEnv(ANT_UMAZE, 2, seed=0)
    assert env.right_flipped_after == after and "right_flipped_after=4" in repr(make_env(f"gymnasium:{ANT_UMAZE}", right_flipped_after=4))
    td, td_plain = env.reset(), plain.reset()
    _flip(env._envs[0].unwrapped)  # copy 0 upside down, copy 1 as it is
    _flip(plain._envs[0].unwrapped)
    zero = torch.zeros(2, 8)
    for step in range(1, after + 3):
        td = env.step(td.set("action", zero))["next"]
        td_plain = plain.step(td_plain.set("action", zero))["next"]
        flipped = AntAgent.is_upside_down(td["observation"])
        assert bool(flipped[0]) == (step < after), step  # righted at its `after`-th step upside down
        assert not flipped[1] and bool(AntAgent.is_upside_down(td_plain["observation"])[0])  # never righted: stays
        assert td["step_count"][0].item() == step and not td["done"].any()  # the episode goes on
    assert torch.allclose(td["achieved_goal"][0], td_plain["achieved_goal"][0], atol=0.3)  # where it lay
    assert env.upside_down_steps.tolist() == [0, 0] and plain.upside_down_steps.tolist() == [0, 0]


def test_a_righted_ant_is_moved_clear_of_the_walls():
    """A flipped ant lying against a wall, where its standing legs would overlap the wall, stands up clear of it
    (the nearest clear place, within 2 units); the reward and success are those of where it stands."""
    from torchrl_dhrl.envs.gymnasium_goal_env import _right_ant

    env = GymnasiumGoalEnv(ANT_UMAZE, 1, seed=0, reset_options={"reset_cell": [1, 1]}, right_flipped_after=1)
    env.reset()
    maze = env._envs[0].unwrapped
    x, y = maze.maze.cell_rowcol_to_xy(np.array([1, 1]))
    wall_y = y + maze.maze.maze_size_scaling / 2  # the wall above cell (1, 1): row 0
    data = maze.ant_env.data
    qpos = data.qpos.copy()
    qpos[:2] = (x, wall_y - 0.45)
    maze.ant_env.set_state(qpos, np.zeros_like(data.qvel))
    _flip(maze)
    upright_there = data.qpos.copy()
    upright_there[2:7] = (0.75, 1.0, 0.0, 0.0, 0.0)
    maze.ant_env.set_state(upright_there, np.zeros_like(data.qvel))
    assert _overlaps_wall(maze)  # standing where it lies would overlap the wall
    _flip(maze)
    obs = _right_ant(maze)
    assert not _overlaps_wall(maze) and not AntAgent.is_upside_down(maze.ant_env.data.qpos)
    moved = np.linalg.norm(obs["achieved_goal"] - (x, wall_y - 0.45))
    assert 0.0 < moved <= 2.0 + 1e-9 and obs["achieved_goal"][1] < wall_y - 0.45  # away from the wall
    assert np.allclose(obs["observation"][:1], 0.75) and np.array_equal(obs["achieved_goal"], data.qpos[:2])


def test_a_righted_step_s_success_follows_success_threshold_where_given():
    """The step that rights the ant reports success as every other step does: within ``success_threshold`` where
    given (here any distance in the maze), else the env's own 0.45."""
    zero = torch.zeros(1, 8)
    for threshold, expected in ((100.0, True), (None, False)):
        env = GymnasiumGoalEnv(ANT_UMAZE, 1, seed=0, right_flipped_after=1, success_threshold=threshold)
        td = env.reset()
        _flip(env._envs[0].unwrapped)
        td = env.step(td.set("action", zero))["next"]
        assert not AntAgent.is_upside_down(td["observation"]).any()  # righted at this step
        assert td["is_success"].item() is expected


def test_the_upside_down_count_is_part_of_the_state_dict():
    """Stopped with the ant upside down for 3 of its 5 steps, a resumed env rights it at the same step as the
    uninterrupted one."""
    zero = torch.zeros(1, 8)
    env = GymnasiumGoalEnv(ANT_UMAZE, 1, seed=0, right_flipped_after=5)
    td = env.reset()
    _flip(env._envs[0].unwrapped)
    for _ in range(3):
        td = env.step(td.set("action", zero))["next"]
    state = env.state_dict()
    assert state["upside_down_steps"].tolist() == [3]
    resumed = GymnasiumGoalEnv(ANT_UMAZE, 1, seed=7, right_flipped_after=5)
    resumed.reset()
    resumed.load_state_dict(state)
    td_resumed = resumed._output()
    for _ in range(2):
        td = env.step(td.set("action", zero))["next"]
        td_resumed = resumed.step(td_resumed.set("action", zero))["next"]
        assert (td.exclude("reward") == td_resumed.exclude("reward")).all()
    assert not AntAgent.is_upside_down(td_resumed["observation"]).any()
    legacy = {k: v for k, v in state.items() if k != "upside_down_steps"}  # saved before the count existed
    resumed.load_state_dict(legacy)
    assert resumed.upside_down_steps.tolist() == [0]


def test_the_gymnasium_wrapper_rights_the_ant_as_the_adapter_does():
    """RightFlippedAnt (a Gymnasium pipeline's, e.g. the SAC + HER baseline's) and the adapter's
    right_flipped_after give the same states, rewards and successes for the same actions."""
    from torchrl_dhrl.envs import RightFlippedAnt

    gym_env = RightFlippedAnt(gym.make(ANT_UMAZE), after=3)
    env = GymnasiumGoalEnv(ANT_UMAZE, 1, seed=5, right_flipped_after=3)
    obs, _ = gym_env.reset(seed=5)
    td = env.reset()
    assert np.allclose(obs["achieved_goal"], td["achieved_goal"][0].numpy(), atol=1e-6)
    _flip(gym_env.unwrapped)
    _flip(env._envs[0].unwrapped)
    actions = np.random.default_rng(0).uniform(-1, 1, (6, 8))
    righted = []
    for action in actions:
        obs, reward, _, _, info = gym_env.step(action)
        td = env.step(td.set("action", torch.as_tensor(action, dtype=torch.float32).reshape(1, 8)))["next"]
        assert np.allclose(obs["achieved_goal"], td["achieved_goal"][0].numpy(), atol=1e-5)
        assert np.allclose(obs["observation"], td["observation"][0, 2:].numpy(), atol=1e-4)
        assert reward == td["reward"].item() and info["success"] == td["is_success"].item()
        righted.append(info.get("righted", False))
    assert righted[:3] == [False, False, True]
    with pytest.raises(ValueError, match="ant mazes"):
        RightFlippedAnt(gym.make(UMAZE), after=3)
    with pytest.raises(ValueError, match="positive number of env steps"):
        RightFlippedAnt(gym.make(ANT_UMAZE), after=0)


def test_right_flipped_after_is_refused_where_there_is_no_ant():
    from torchrl_dhrl.envs import is_gymnasium_ant_maze

    from torchrl_dhrl.factory import make_environment

    assert is_gymnasium_ant_maze(ANT_UMAZE) and is_gymnasium_ant_maze("AntMaze_Large_Diverse_GR-v5")
    assert not is_gymnasium_ant_maze(UMAZE) and not is_gymnasium_ant_maze(TERMINATING)
    with pytest.raises(GoalEnvError, match="applies to gymnasium-robotics' ant mazes"):
        GymnasiumGoalEnv(UMAZE, 1, right_flipped_after=10)
    with pytest.raises(ValueError, match="`right_flipped_after` rights a flipped ant"):
        make_environment(f"gymnasium:{UMAZE}", right_flipped_after=10)
    with pytest.raises(ValueError, match="right_flipped_after"):
        GymnasiumGoalEnv(ANT_UMAZE, 1, right_flipped_after=0)
    assert make_environment(f"gymnasium:{ANT_UMAZE}", right_flipped_after=10).right_flipped_after == 10
