"""The diagnose scripts on recipe runs: recipes/diagnose_planning.py (planning_ablations: paired goals, the
agent left as it was), diagnose_observations.py, diagnose_low_level.py (the reach test from a checkpoint),
diagnose_exploration.py, diagnose_high_level.py (the subgoal landscape, walls counted against the geometry)
and diagnose_graph.py (with the recipe's ``diag/`` columns)."""

import csv
import importlib.util
import math
import shutil
import sys

import pytest
import torch
import yaml
from _recipe import RECIPES, load_recipe, recipe_config
from torchrl_dhrl.envs.geometry import MazeGeometry

from torchrl_dhrl.diagnostics import DIAG_KEYS, planning_ablations
from torchrl_dhrl.recipe import success_curve_series
from torchrl_dhrl.training import evaluation

pytestmark = pytest.mark.recipe


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    path = tmp_path_factory.mktemp("run")
    load_recipe().train(
        # the reference's raw 17-D observation (Reacher3D's default feeds its two rolls as (sin, cos): 19-D)
        recipe_config(
            "env=Reacher3D", "angle_features=null", "preset=smoke", "logger.backend=none", "plots.every_epochs=0"
        ),
        run_dir=path,
    )
    return path


def test_variants_are_paired_and_leave_the_agent_unchanged(run_dir, monkeypatch):
    dhrl_utils = load_recipe("dhrl_utils")
    cfg, agent = dhrl_utils.agent_from_checkpoint(run_dir)
    env = dhrl_utils.build_environment(cfg, torch.device("cpu"), eval=True, agent=agent)
    assert agent.planner.has_graph
    landmarks = agent.planner.graph.landmark_goals.clone()
    radius = agent.planner.reach_radius
    state = env.base_env.state_dict()
    goals, graph_seen, subgoal_is_goal, rules = [], [], [], []
    real = evaluation.evaluate

    def recording(env_, policy, steps, **kwargs):
        result = real(env_, policy, steps, **kwargs)
        goals.append(result.rollout["desired_goal"][:, 0].clone())
        graph_seen.append(agent.planner.has_graph)
        subgoal_is_goal.append(torch.equal(result.rollout["subgoal"], result.rollout["desired_goal"]))
        rules.append(agent.planner.graph.unreachable)
        return result

    module = sys.modules[
        "torchrl_dhrl.diagnostics.planning_ablations"
    ]  # the package exports the function by that name
    monkeypatch.setattr(module, "evaluate", recording)
    rows = planning_ablations(agent, env, 40, reach_radii=[0.5, 2.0], repeats=2)
    assert [r["variant"] for r in rows] == [
        "as trained",
        "reach_radius=0.5",
        "reach_radius=2",
        "goal as subgoal",
        "unreachable=subgoal",
        "no graph",
        "flat",
    ]
    assert all(r["episodes"] == 2 * env.batch_size.numel() for r in rows)
    for r in rows:
        assert 0.0 <= r["success"] <= r["any_success"] <= 1.0 and r["final_distance"] > 0
    # every variant meets the same two batches of goals (Reacher3D draws them at random per episode)
    assert len(goals) == 14
    for k in range(2, 14, 2):
        torch.testing.assert_close(goals[k], goals[0], rtol=0, atol=0)
        torch.testing.assert_close(goals[k + 1], goals[1], rtol=0, atol=0)
    assert not torch.equal(goals[0], goals[1])
    assert graph_seen == [True] * 10 + [False] * 2 + [True] * 2  # the graph is gone only for "no graph"
    # the planner is handed the real goal only in "goal as subgoal"
    assert subgoal_is_goal == [False] * 6 + [True] * 2 + [False] * 6
    assert rules == ["nearest_landmark"] * 8 + ["subgoal"] * 2 + ["nearest_landmark"] * 4
    # left as it was
    torch.testing.assert_close(agent.planner.graph.landmark_goals, landmarks, rtol=0, atol=0)
    assert agent.planner.reach_radius == radius and agent.planner.graph.unreachable == "nearest_landmark"
    after = env.base_env.state_dict()
    assert set(after) == set(state)


def test_cli_prints_a_row_per_variant(run_dir, capsys):
    rows = load_recipe("diagnose_planning").main(
        [str(run_dir), "--reach-radii", "0.3", "--cutoffs", "45", "--repeats", "1"]
    )
    out = capsys.readouterr().out
    assert (
        len(rows) == 7
        and "goal as subgoal" in out
        and "unreachable=subgoal" in out
        and "no graph" in out
        and "flat" in out
        and "reach_radius=0.3" in out
        and "cutoff=45" in out
    )


def test_planning_oracle_options_replace_the_recorded_geometry(tmp_path, monkeypatch, capsys):
    """diagnose_planning.py --oracle on a gymnasium maze: a recorded margin that closes the maze (0.4.0's 0.5 on a
    1-unit maze) is refused in one line naming --oracle-margin; --oracle-margin and --oracle-speed replace the
    record's in the oracle's walls and speed."""
    run = tmp_path / "run"
    load_recipe().train(
        recipe_config("env=gymnasium", "env_name=gymnasium:PointMaze_UMaze-v3", "preset=smoke", "logger.backend=none",
                      "plots.every_epochs=0", "total_steps=160", "gymnasium.reset_options={reset_cell:[3,1]}"),
        run_dir=run,
    )
    script = load_recipe("diagnose_planning")
    real_load, real_ablations = script.agent_from_checkpoint, script.planning_ablations

    def recorded_with(margin):
        def load(path, device):
            cfg, agent = real_load(path, device)
            cfg["planner"]["oracle_margin"] = margin
            return cfg, agent

        return load

    monkeypatch.setattr(script, "agent_from_checkpoint", recorded_with(0.5))
    with pytest.raises(SystemExit) as refused:
        script.main([str(run), "--oracle", "--repeats", "1"])
    assert refused.value.code == 2
    assert "planner.oracle_margin=0.5" in capsys.readouterr().err
    oracles = []

    def ablations(*args, oracle, **kwargs):
        oracles.append(oracle)
        return real_ablations(*args, oracle=oracle, **kwargs)

    monkeypatch.setattr(script, "planning_ablations", ablations)
    rows = script.main([str(run), "--oracle", "--oracle-margin", "0.125", "--oracle-speed", "0.04", "--repeats", "1"])
    assert "oracle graph" in [row["variant"] for row in rows]
    monkeypatch.setattr(script, "agent_from_checkpoint", recorded_with(0.125))
    script.main([str(run), "--oracle", "--repeats", "1"])
    assert oracles[0].speed == 0.04 and oracles[1].speed != 0.04
    torch.testing.assert_close(oracles[0].boxes, oracles[1].boxes)  # --oracle-margin 0.125 = a record of 0.125
    for bad in (["--oracle-margin", "-1"], ["--oracle-speed", "0"]):
        with pytest.raises(SystemExit) as refused:
            script.main([str(run), "--oracle", *bad])
        assert refused.value.code == 2


def test_bad_repeats(run_dir):
    dhrl_utils = load_recipe("dhrl_utils")
    cfg, agent = dhrl_utils.agent_from_checkpoint(run_dir)
    env = dhrl_utils.build_environment(cfg, torch.device("cpu"), eval=True, agent=agent)
    with pytest.raises(ValueError, match="repeats"):
        planning_ablations(agent, env, 40, repeats=0)


def test_observation_ranges_against_the_buffer(run_dir, capsys):
    """diagnose_observations: the maximum and the quantiles of |observation| over the stored states."""
    script = load_recipe("diagnose_observations")
    ranges = script.observation_ranges(run_dir, quantiles=(0.5, 1.0))
    dhrl_utils = load_recipe("dhrl_utils")
    cfg, agent = dhrl_utils.agent_from_checkpoint(run_dir)
    low_rb, _ = dhrl_utils.build_replay_buffers(cfg, agent, torch.device("cpu"))
    from torchrl_dhrl.recipe import load_checkpoint

    low_rb.load_state_dict(load_checkpoint(run_dir, components=("low_rb",))["low_rb"])
    obs = low_rb[:]["observation"].reshape(-1, 17).abs()
    assert ranges["entries"] == obs.shape[0] == len(low_rb)
    torch.testing.assert_close(ranges["max"], obs.max(0).values)
    torch.testing.assert_close(ranges["quantiles"][1.0], obs.max(0).values)  # all rows: fewer than SAMPLE
    torch.testing.assert_close(ranges["quantiles"][0.5], obs.quantile(0.5, dim=0))
    script.main([str(run_dir)])
    assert "stored states" in capsys.readouterr().out


def test_goal_as_subgoal_needs_the_policy_planner(run_dir):
    dhrl_utils = load_recipe("dhrl_utils")
    _, agent = dhrl_utils.agent_from_checkpoint(run_dir)
    with pytest.raises(ValueError, match="planner"):
        evaluation.goal_as_subgoal(agent.policy, agent.low_actor)
    policy = evaluation.goal_as_subgoal(agent.policy, agent.planner)
    assert [type(m).__name__ for m in policy.module][1:3] == ["TensorDictModule", "GraphPlanner"]
    assert len(agent.policy.module) == 3  # the agent's own policy is left as it was


# the recipe side: a checkpoint's agent rebuilt from its configuration
reach_test_from_checkpoint = load_recipe("diagnose_low_level").reach_test_from_checkpoint


def test_reach_test_from_a_recipe_checkpoint_and_cli(tmp_path, capsys):
    load_recipe().train(
        recipe_config("env=PointMaze", "preset=smoke", "logger.backend=none"), run_dir=tmp_path
    )
    rows = reach_test_from_checkpoint(tmp_path, num_directions=8)
    # PointMaze: cutoff 30 x speed 0.2 = 6 -> radii 1.5, 3, 6, 9 along the bottom corridor
    assert [row["radius"] for row in rows] == pytest.approx([1.5, 3.0, 6.0, 9.0])
    assert all(0.0 <= row["reach_rate"] <= 1.0 and row["goals"] >= 1 for row in rows)
    import importlib.util

    spec = importlib.util.spec_from_file_location("diagnose", RECIPES / "diagnose_low_level.py")
    cli = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cli)
    cli_rows = cli.main(
        [str(tmp_path / "checkpoint"), "--radii", "1", "2", "--directions", "4", "--steps", "20"]
    )
    assert [row["radius"] for row in cli_rows] == pytest.approx([1.0, 2.0])
    assert "reached" in capsys.readouterr().out
    argv = ["--radii", "2", "--directions", "4", "--steps", "5", "--start", "8", "4", "--repeats", "2"]
    cli_rows = cli.main([str(tmp_path / "checkpoint"), *argv, "--per-offset"])
    assert sorted(row["offset"][1] for row in cli_rows) == [-2.0, 2.0]  # up and down the right-hand corridor
    assert all(row["goals"] == 2 for row in cli_rows)
    assert "(0.00, 2.00)" in capsys.readouterr().out
    # from points along the U (path length from the start, checked on a finer independent grid), clear of the walls
    # by three agent radii (1.5)
    argv = ["--radii", "1", "--directions", "4", "--steps", "5", "--progress", "4", "12", "18", "90", "95"]
    cli_rows = cli.main([str(tmp_path), *argv])
    assert [round(row["progress"]) for row in cli_rows[:3]] == [4, 12, 18]
    assert len(cli_rows) == 4 and 18 < cli_rows[3]["progress"] < 21  # past the U's end: its farthest point, once
    cli_rows = cli_rows[:3]
    fine = MazeGeometry.from_maze("PointMaze", margin=0.5, resolution=0.1)
    starts = torch.tensor([row["start"] for row in cli_rows])
    torch.testing.assert_close(fine.path_length(torch.zeros(2), starts), torch.tensor([4.0, 12.0, 18.0]), atol=0.8, rtol=0)
    assert not fine.in_walls(starts, margin=1.5).any()
    out = capsys.readouterr().out
    assert "progress          start" in out and "(7.5, 6.2)" in out
    with pytest.raises(SystemExit):  # a start and progress: one line
        cli.main([str(tmp_path), *argv, "--start", "8", "4"])
    assert "Give a start or progress along the maze, not both" in capsys.readouterr().err


@pytest.mark.parametrize("angles", ["null", "[4,6]"])
def test_reach_test_keeps_goals_inside_the_goal_box(angles, tmp_path):
    """The Reacher3D fingertip starts 2 cm inside the goal box's x = 1 face: offsets beyond it are dropped.
    With ``angle_features`` the reach test's env feeds the actor the 19-D observation it was trained on."""
    load_recipe().train(
        recipe_config(
            "env=Reacher3D",
            "preset=smoke",
            "logger.backend=none",
            "plots.every_epochs=0",
            f"angle_features={angles}",
        ),
        run_dir=tmp_path,
    )
    rows = reach_test_from_checkpoint(tmp_path, radii=[0.01, 0.5], num_directions=8, max_steps=5)
    near, far = rows
    assert near["goals"] == 8  # a 1 cm ball around the start lies inside the box
    assert 1 <= far["goals"] < 8  # half a metre out: the directions towards +x leave it


def test_the_script_reads_a_run(tmp_path, capsys):
    run = tmp_path / "run"
    load_recipe().train(
        recipe_config("env=PointMaze", "preset=smoke", "logger.backend=none", "plots.every_epochs=0"),
        run_dir=run,
    )
    capsys.readouterr()  # the training's own output
    with (run / "metrics.csv").open() as file:  # the training episodes, per epoch
        rows = list(csv.DictReader(file))
    episodes = [int(float(r["train/episodes"])) for r in rows]
    assert episodes == [
        int(r["episodes"]) - int(p["episodes"])
        for p, r in zip([{"episodes": 0}, *rows[:-1]], rows, strict=True)
    ]
    frontier = [float(r["train/frontier"]) for r in rows]
    assert frontier == sorted(frontier) and frontier[0] > 0.0  # never recedes
    assert all(float(r["train/max_progress"]) <= f + 1e-6 for r, f in zip(rows, frontier, strict=True))
    assert all(0.0 <= float(r["train/success"]) <= float(r["train/any_success"]) <= 1.0 for r in rows)
    assert "train/goal_shifted" not in rows[0]  # PointMaze trains without FGS
    out, summary = load_recipe("diagnose_exploration").main([str(run), "--episodes", "3", "--rows", "2"])
    printed = capsys.readouterr().out
    assert summary["episodes"] == len(out.episode_ids) <= 3 and len(out.episode_ids) >= 1
    assert (
        "goals lay beyond it" in printed and len(printed.strip().splitlines()) == 4
    )  # header, 2 rows, summary
    assert all(math.isfinite(v) for v in out.max_progress.tolist())
    assert (out.max_progress <= summary["explored"] + 1e-6).all()
    assert summary["reached_frontier"] == int((out.max_progress >= 0.9 * summary["explored"]).sum())
    # --box: every stored training episode entered the whole arena, none a box outside it, per group of 2
    episodes_run = int(float(rows[-1]["episodes"]))
    load_recipe("diagnose_exploration").main(
        [str(run), "--rows", "0", "--per", "2", "--box", "arena", "-100", "100", "-100", "100"]
        + ["--box", "outside", "50", "60", "50", "60"]
    )
    printed = capsys.readouterr().out.splitlines()
    assert printed[0].split() == ["episodes", "arena", "outside"]
    assert printed[1].split() == ["0-1", "2", "of", "2", "0", "of", "2"]
    assert printed[-2].split() == ["all", str(episodes_run), "of", str(episodes_run), "0", "of", str(episodes_run)]
    with pytest.raises(SystemExit):
        load_recipe("diagnose_exploration").main([str(run), "--box", "gap", "a", "1", "2", "3"])
    assert "the bounds must be numbers" in capsys.readouterr().err
    with pytest.raises(SystemExit, match="--upside-down needs an ant maze run"):
        load_recipe("diagnose_exploration").main([str(run), "--rows", "0", "--upside-down"])


def test_the_upside_down_steps_of_an_ant_run_per_group_of_episodes(tmp_path, capsys, monkeypatch):
    """gymnasium-robotics' ant maze, a few 10-step episodes: the rows are the per-episode shares of the stored steps
    upside down, averaged per group, and the count of episodes that ended so, read from the buffer directly (the
    test made a torso height threshold, so that both outcomes occur in 10-step episodes)."""
    pytest.importorskip("gymnasium_robotics")
    from torchrl_dhrl.recipe import load_checkpoint

    run = tmp_path / "run"
    load_recipe().train(
        recipe_config("env=gymnasium", "env_name=gymnasium:AntMaze_UMaze-v5", "preset=smoke", "logger.backend=none",
                      "plots.every_epochs=0", "episode_length=10", "total_steps=60", "threads=1"),
        run_dir=run,
    )
    script = load_recipe("diagnose_exploration")
    cfg, agent = load_recipe("dhrl_utils").agent_from_checkpoint(run)
    low_rb, _ = load_recipe("dhrl_utils").build_replay_buffers(cfg, agent, torch.device("cpu"))
    low_rb.load_state_dict(load_checkpoint(run, components=("low_rb",))["low_rb"])
    steps = low_rb.storage[: len(low_rb.storage)]
    height = steps["next", "observation"][..., 2].reshape(-1)
    threshold = float(height.median())
    monkeypatch.setattr(script, "upside_down_test", lambda cfg: lambda obs: obs[..., 2] < threshold)
    capsys.readouterr()
    script.main([str(run), "--rows", "0", "--upside-down", "--per", "2"])
    printed = capsys.readouterr().out.splitlines()
    ids = steps["collector", "traj_ids"].reshape(-1)
    episodes = sorted(set(ids.tolist()))
    shares = [float((height[ids == e] < threshold).float().mean()) for e in episodes]
    ended = [bool(height[ids == e][-1] < threshold) for e in episodes]
    assert printed[0].split() == ["episodes", "steps", "upside", "down", "ended", "upside", "down"]
    for row, start in zip(printed[1:], range(0, len(episodes), 2), strict=False):
        group = slice(start, start + 2)
        label = f"{start}-{start + len(shares[group]) - 1}"
        expected = [label, f"{sum(shares[group]) / len(shares[group]):.1%}", str(sum(ended[group])), "of", str(len(shares[group]))]
        assert row.split() == expected
    assert printed[len(range(0, len(episodes), 2)) + 1].split()[:2] == ["all", f"{sum(shares) / len(shares):.1%}"]
    assert 0 < sum(ended) < len(ended) or 0 < sum(shares) < len(shares)  # the check saw both outcomes


def test_script_on_a_pointmaze_run(tmp_path, capsys):
    from _recipe import load_recipe, recipe_config

    torch.manual_seed(0)
    load_recipe().train(
        recipe_config("env=PointMaze", "preset=smoke", "logger.backend=none", "plots.every_epochs=0"),
        run_dir=tmp_path,
    )
    import csv

    with (tmp_path / "metrics.csv").open() as file:
        rows = list(csv.DictReader(file))
    for row in rows:  # every epoch logs the critic's landscape at the first test start
        assert float(row["diag/start_q_range"]) >= 0.0
        assert float(row["diag/start_best_subgoal_in_wall"]) in (0.0, 1.0)
        assert 0.0 <= float(row["diag/start_top_subgoals_in_walls"]) <= 1.0
        assert float(row["diag/start_actor_q_gap"]) == float(row["diag/start_actor_q_gap"])  # not NaN
    picture = tmp_path / "landscape.png"
    report = load_recipe("diagnose_high_level").main(
        [str(tmp_path), "--resolution", "1", "--plot", str(picture), "--along"]
    )
    out = capsys.readouterr().out
    assert "actor's subgoal" in out and "best free subgoal" in out and picture.stat().st_size > 1000
    geometry = MazeGeometry.from_maze("PointMaze")
    # PointMaze's subgoal box is the arena [-2, 10]^2; the U's inner wall, joined to the left outer wall, fills
    # -6 < x < 6, 2 < y < 6: 8 x 3 of the 13 x 13 grid points (x = -2 lies inside the joined walls)
    assert report["walls_share"] == pytest.approx(24 / 169)
    assert report["actor_in_wall"] == bool(geometry.in_walls(report["actor_subgoal"][None])[0])
    assert not bool(geometry.in_walls(report["best_free_subgoal"][None])[0])
    assert report["best_free_q"] <= report["best_q"] and report["starts"] >= 1
    assert 0.0 <= report["top_in_walls"] <= 1.0 and 0.0 <= report["actor_in_walls_over_starts"] <= 1.0
    # along one or two test episodes: a row per new subgoal (every c_h steps, from step 0)
    along = report["along"]
    episodes = sorted({row["episode"] for row in along})
    assert 1 <= len(episodes) <= 2 and "along test episode" in out
    for episode in episodes:
        steps = [row["step"] for row in along if row["episode"] == episode]
        assert steps[0] == 0 and all(b > a for a, b in zip(steps, steps[1:], strict=False))


def test_recipe_logs_diag_columns_and_the_tool_reads_the_checkpoint(tmp_path, capsys):
    run = tmp_path / "run"
    load_recipe().train(
        recipe_config("env=PointMaze", "preset=smoke", "logger.backend=none", "plots.every_epochs=0"),
        run_dir=run,
    )
    with (run / "metrics.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert set(DIAG_KEYS) <= set(rows[0])
    graph_keys = (
        "diag/edges_crossing_walls",
        "diag/edges_shortcut",
        "diag/distance_rank_corr",
        "diag/graph_distance_rank_corr",
        "diag/landmark_coverage",
        "diag/landmark_progress",
        "diag/reachable_landmarks",
        "diag/reachable_progress",
        "diag/goal_to_reachable",
    )
    for row in rows:
        has_graph = int(row["graph/landmarks"]) > 0
        for key in DIAG_KEYS:
            value = float(row[key])
            if key in graph_keys and not has_graph:
                assert math.isnan(value), key
            else:
                assert math.isfinite(value), (key, row["epoch"])
        assert 0.0 <= float(row["diag/subgoals_in_walls"]) <= 1.0
        assert float(row["diag/start_subgoal_feasible"]) in (0.0, 1.0)
        assert -2.0 <= float(row["diag/start_subgoal_x"]) <= 10.0  # the subgoal box
    assert not math.isfinite(float(rows[0]["diag/landmark_coverage"]))  # warm-up epoch: no graph
    assert all(int(r["graph/landmarks"]) > 0 for r in rows[1:])
    # the success curve draws the coverage (from the first graph on) and the training episodes' success
    series = success_curve_series([{**r, "env_steps": int(r["env_steps"])} for r in rows])
    coverage = series["landmark coverage of the free space"]
    assert coverage == (
        [int(r["env_steps"]) for r in rows[1:]],
        [float(r["diag/landmark_coverage"]) for r in rows[1:]],
    )
    assert series["training episodes' success"][1] == [float(r["train/success"]) for r in rows]

    spec = importlib.util.spec_from_file_location("diagnose_graph", RECIPES / "diagnose_graph.py")
    cli = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cli)
    plot = tmp_path / "scatter.png"
    diagnosis, table, budgets = cli.main([str(run), "--pairs", "4", "--plot", str(plot)])
    assert budgets is None
    out = capsys.readouterr().out
    assert "diag/edges_crossing_walls" in out and "learned vs true distances" in out
    assert "Plans from the first test start (" in out and "landmarks reachable" in out
    reach = diagnosis.reach
    assert reach["reachable_landmarks"] == diagnosis.metrics["diag/reachable_landmarks"]
    assert 0.0 < reach["reachable_landmarks"] <= 1.0 and reach["bridge_distance"] >= 0.0
    assert plot.stat().st_size > 1000
    assert 1 <= len(table) <= 4 and all(row["true"] >= 0 for row in table)
    assert diagnosis.metrics["graph/landmarks"] == int(rows[-1]["graph/landmarks"])
    assert math.isfinite(diagnosis.metrics["diag/distance_rank_corr"])
    assert 0.0 <= diagnosis.metrics["diag/waypoints_in_walls"] <= 1.0
    pairs = diagnosis.pairs
    assert pairs["true"].shape == pairs["learned"].shape == pairs["graph"].shape and pairs["true"].numel() > 0
    # without the evaluation rollout: the subgoal fractions are NaN, the graph numbers the same
    quick, _, (budgets, buffer_progress) = cli.main(
        [
            str(run / "checkpoint"),
            "--no-rollout",
            "--pairs",
            "0",
            "--plot",
            str(plot),
            "--budgets",
            "4:50",
            "100:1000",
        ]
    )
    assert math.isnan(quick.metrics["diag/subgoals_in_walls"])
    assert quick.metrics["diag/distance_rank_corr"] == diagnosis.metrics["diag/distance_rank_corr"]
    # the graph rebuilt from the run's buffer: never past the buffer's furthest state; the run's own graph kept
    assert "the buffer's furthest state" in capsys.readouterr().out
    assert [(row["max_landmarks"], row["candidates"]) for row in budgets] == [(4, 50), (100, 1000)]
    assert 0.0 < budgets[0]["progress_mean"] <= budgets[1]["progress_max"] <= buffer_progress + 1e-5
    assert quick.metrics["graph/landmarks"] == diagnosis.metrics["graph/landmarks"]
    with pytest.raises(SystemExit):
        cli.main([str(run), "--no-rollout", "--budgets", "300-6000"])


def test_the_scripts_read_a_gymnasium_maze_run(tmp_path, capsys):
    """A gymnasium-robotics maze's run (fixed start cell) through the checkpoint scripts, measured against the env's
    own map: the graph's diagnosis, the high level's subgoal landscape (its walls those of the map), the exploration
    of its training episodes (progress within the maze's farthest free point)."""
    pytest.importorskip("gymnasium_robotics")
    from _recipe import load_recipe, recipe_config
    from torchrl_dhrl.envs import GymnasiumGoalEnv

    start = "gymnasium.reset_options={reset_cell:[3,1]}"
    load_recipe().train(
        recipe_config("env=gymnasium", "env_name=gymnasium:PointMaze_UMaze-v3", "preset=smoke", start,
                      "logger.backend=none", "plots.every_epochs=0", "total_steps=240"),
        run_dir=tmp_path,
    )
    capsys.readouterr()
    walls = GymnasiumGoalEnv("PointMaze_UMaze-v3", reset_options={"reset_cell": [3, 1]}).maze_geometry()
    diagnosis, _, _ = load_recipe("diagnose_graph").main([str(tmp_path), "--pairs", "2", "--no-rollout"])
    with (tmp_path / "metrics.csv").open() as file:
        last = list(csv.DictReader(file))[-1]
    assert diagnosis.metrics["graph/landmarks"] == int(last["graph/landmarks"])
    assert diagnosis.metrics["diag/edges_crossing_walls"] == pytest.approx(float(last["diag/edges_crossing_walls"]))
    report = load_recipe("diagnose_high_level").main([str(tmp_path), "--resolution", "0.5"])
    assert 0.0 < report["walls_share"] < 1.0  # the U's inner wall lies inside the subgoal box
    assert report["actor_in_wall"] == bool(walls.in_walls(report["actor_subgoal"][None])[0])
    # a run kept as results keep it (the saved agent, no checkpoint): the same landscape
    kept = tmp_path / "kept"
    kept.mkdir()
    shutil.copytree(tmp_path / "agent", kept / "agent")
    shutil.copy(tmp_path / "config.yaml", kept / "config.yaml")
    again = load_recipe("diagnose_high_level").main([str(kept), "--resolution", "0.5"])
    assert again["walls_share"] == report["walls_share"]
    assert torch.equal(torch.as_tensor(again["actor_subgoal"]), torch.as_tensor(report["actor_subgoal"]))
    out, summary = load_recipe("diagnose_exploration").main([str(tmp_path), "--episodes", "3", "--rows", "1"])
    farthest = walls.path_length(walls.start, walls.cell_centers[walls.free]).max().item()
    assert 0.0 < summary["explored"] <= farthest + 1e-6 and len(out.episode_ids) >= 1
    capsys.readouterr()
    # the reach test from the run's test start cell (3, 1), walls of the map: all four directions at 0.3, only the
    # corridor's (+x) at 1.0
    rows = load_recipe("diagnose_low_level").main(
        [str(tmp_path), "--radii", "0.3", "1.0", "--directions", "4", "--steps", "5", "--oracle-margin", "0.125"]
    )
    assert [(round(row["radius"], 3), row["goals"]) for row in rows] == [(0.3, 4), (1.0, 1)]
    assert "radius  goals  reached" in capsys.readouterr().out
    # along the U from the start cell: 2 units of path reach the cell (3, 3), (1, -1), from whose centre the test runs
    rows = load_recipe("diagnose_low_level").main(
        [str(tmp_path), "--radii", "0.3", "--directions", "4", "--steps", "5", "--oracle-margin", "0.125"]
        + ["--progress", "2"]
    )
    assert len(rows) == 1 and rows[0]["progress"] == pytest.approx(2.0, abs=0.1) and rows[0]["goals"] == 4
    assert GymnasiumGoalEnv("PointMaze_UMaze-v3").reset_cell_at(rows[0]["start"]) == (3, 3)
    capsys.readouterr()
    with pytest.raises(SystemExit):  # a start in a wall: one line
        load_recipe("diagnose_low_level").main([str(tmp_path), "--start", "-1", "0"])
    assert "lies in cell (2, 1), a wall, of PointMaze_UMaze-v3" in capsys.readouterr().err
    # --oracle-margin in place of the run's recorded radius (0.125, derived from the U's 1-unit cells): 0.6 closes its
    # corridors, so only the option can make the scripts refuse the run, in one line naming it
    assert float(yaml.safe_load((tmp_path / "config.yaml").read_text())["planner"]["oracle_margin"]) == 0.125
    for script, extra in (("diagnose_graph", ["--no-rollout", "--pairs", "0"]), ("diagnose_exploration", ["--rows", "0"])):
        with pytest.raises(SystemExit):
            load_recipe(script).main([str(tmp_path), *extra, "--oracle-margin", "0.6"])
        err = capsys.readouterr().err
        assert "planner.oracle_margin=0.6" in err and "Give the agent's radius with --oracle-margin." in err
    # a smaller radius grows the walls less: no edge crosses the bare walls that does not cross the grown ones
    cli = load_recipe("diagnose_graph")
    recorded, _ = cli.graph_diagnosis_from_checkpoint(tmp_path, rollout=False)
    bare, cfg = cli.graph_diagnosis_from_checkpoint(tmp_path, rollout=False, oracle={"oracle_margin": 0.0})
    assert cfg["planner"]["oracle_margin"] == 0.0
    assert bare.metrics["diag/edges_crossing_walls"] <= recorded.metrics["diag/edges_crossing_walls"]
