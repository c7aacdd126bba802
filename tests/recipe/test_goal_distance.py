"""recipes/goal_distance.py: success against the goal's distance on a gymnasium-robotics maze. The distances
against networkx on random maps (walls, cells cut off, the maps' letter cells), the bands' figures against a direct
pooling, and end to end a DHRL agent and a SAC + HER model tested on every goal cell of PointMaze_UMaze-v3, each
goal cell reaching the env."""

from __future__ import annotations

import csv
import json
import random
from pathlib import Path

import networkx as nx
import numpy as np
import pytest
from _recipe import load_recipe, recipe_config

goal_distance = load_recipe("goal_distance")


def _random_map(rng: random.Random, rows: int, cols: int, walls: float) -> list[list]:
    """A maze map with a wall border, random inner walls and free cells written as the maps write them (0, "r",
    "g", "c")."""
    grid = [[1] * cols for _ in range(rows)]
    for r in range(1, rows - 1):
        for c in range(1, cols - 1):
            grid[r][c] = 1 if rng.random() < walls else rng.choice([0, 0, 0, "r", "g", "c"])
    return grid


@pytest.mark.parametrize("seed", range(25))
def test_maze_distances_match_networkx_shortest_paths(seed):
    rng = random.Random(seed)
    grid = _random_map(rng, rng.randint(3, 9), rng.randint(3, 11), walls=rng.choice([0.0, 0.2, 0.4, 0.6]))
    free = [(r, c) for r, row in enumerate(grid) for c, v in enumerate(row) if v != 1]
    if not free:  # every inner cell a wall: no start to give
        with pytest.raises(ValueError, match="is not a free cell"):
            goal_distance.maze_distances(grid, (1, 1))
        return
    start = rng.choice(free)
    graph = nx.grid_2d_graph(len(grid), len(grid[0]))
    graph.remove_nodes_from([(r, c) for r, row in enumerate(grid) for c, v in enumerate(row) if v == 1])
    expected = nx.single_source_shortest_path_length(graph, start)
    assert goal_distance.maze_distances(grid, start) == expected  # cut-off cells left out of both


@pytest.mark.parametrize("start", [(0, 0), (1, 2), (5, 1), (1, -1)])
def test_a_start_on_a_wall_or_off_the_map_is_refused(start):
    grid = [[1, 1, 1, 1], [1, 0, 1, 1], [1, 0, 0, 1], [1, 1, 1, 1]]
    with pytest.raises(ValueError, match=rf"--start {start[0]} {start[1]} is not a free cell of the 4 x 4 maze map"):
        goal_distance.maze_distances(grid, start)


@pytest.mark.parametrize("max_distance, width", [(1, 1), (1, 3), (7, 3), (9, 3), (15, 4), (5, 10)])
def test_the_bands_cover_every_distance_once(max_distance, width):
    bands = goal_distance.distance_bands(max_distance, width)
    covered = [d for low, high in bands for d in range(low, high + 1)]
    assert covered == list(range(1, max_distance + 1))
    assert all(high - low + 1 <= width for low, high in bands)


def test_the_band_table_pools_episodes_per_agent_and_averages_agents_per_kind():
    rng = np.random.default_rng(0)
    rows = []
    cells = [((1, c), d) for c, d in zip(range(1, 8), [1, 2, 2, 3, 4, 5, 5], strict=True)]
    for agent, kind in (("a/dhrl_s0", "DHRL"), ("a/dhrl_s1", "DHRL"), ("a/sac_s0", "SAC + HER")):
        for (row, col), distance in cells:
            episodes = int(rng.integers(1, 12))  # unequal episodes: pooled, not averaged per cell
            rows.append({"agent": agent, "kind": kind, "goal_row": row, "goal_col": col, "distance": distance,
                         "episodes": episodes, "successes": int(rng.integers(0, episodes + 1))})
    table = goal_distance.band_table([{k: str(v) for k, v in row.items()} for row in rows], width=3)
    lines = table.strip().splitlines()
    assert lines[0] == ("| goal distance (cells) | goal cells | DHRL, mean ± std | SAC + HER, mean ± std | dhrl_s0 | "
                        "dhrl_s1 | sac_s0 |")
    for line, (low, high) in zip(lines[2:], [(1, 3), (4, 5)], strict=True):
        inside = [r for r in rows if low <= r["distance"] <= high]

        def pooled(agent, inside=inside):
            mine = [r for r in inside if r["agent"] == agent]
            return sum(r["successes"] for r in mine) / sum(r["episodes"] for r in mine)

        dhrl = [pooled("a/dhrl_s0"), pooled("a/dhrl_s1")]
        cols = [c.strip() for c in line.strip("|").split("|")]
        assert cols[0] == f"{low}-{high}" and cols[1] == str(len({(r['goal_row'], r['goal_col']) for r in inside}))
        assert cols[2] == f"{100 * np.mean(dhrl):.1f}% ± {100 * np.std(dhrl, ddof=1):.1f}"
        assert cols[3] == f"{100 * pooled('a/sac_s0'):.1f}%"  # one agent: no spread
        assert cols[4:] == [f"{100 * pooled(a):.0f}%" for a in ("a/dhrl_s0", "a/dhrl_s1", "a/sac_s0")]


def test_each_goal_cell_holds_its_kinds_pooled_success_and_the_rest_is_empty():
    rows = [  # two DHRL agents with unequal episodes on (1, 2), one SAC + HER agent; (2, 1) tested by DHRL only
        {"agent": "d0", "kind": "DHRL", "goal_row": 1, "goal_col": 2, "episodes": 10, "successes": 10},
        {"agent": "d1", "kind": "DHRL", "goal_row": 1, "goal_col": 2, "episodes": 30, "successes": 0},
        {"agent": "d0", "kind": "DHRL", "goal_row": 2, "goal_col": 1, "episodes": 10, "successes": 3},
        {"agent": "s0", "kind": "SAC + HER", "goal_row": 1, "goal_col": 2, "episodes": 10, "successes": 7},
    ]
    dhrl = goal_distance.cell_success([{k: str(v) for k, v in r.items()} for r in rows], "DHRL")
    assert dhrl.shape == (4, 4)  # the outer walls around rows 1-2 and columns 1-2
    assert dhrl[1, 2] == pytest.approx(10 / 40) and dhrl[2, 1] == pytest.approx(0.3)
    assert np.isnan(np.delete(dhrl.reshape(-1), [1 * 4 + 2, 2 * 4 + 1])).all()
    sac = goal_distance.cell_success(rows, "SAC + HER")
    assert sac[1, 2] == pytest.approx(0.7) and np.isnan(sac[2, 1])


@pytest.fixture(scope="module")
def agents(tmp_path_factory):
    """A smoke-trained DHRL run and a short SAC + HER run on PointMaze_UMaze-v3, both started in cell (3, 1)."""
    pytest.importorskip("gymnasium_robotics")
    pytest.importorskip("stable_baselines3")
    root = tmp_path_factory.mktemp("goal_distance")
    load_recipe().train(
        recipe_config("env=gymnasium", "env_name=gymnasium:PointMaze_UMaze-v3", "preset=smoke", "device=cpu",
                      "logger.backend=none", "plots.every_epochs=0", "threads=1",
                      "gymnasium.reset_options={reset_cell:[3,1]}"),
        run_dir=root / "dhrl",
    )
    goal_distance._sac_module().main(["--env-id", "PointMaze_UMaze-v3", "--steps", "600", "--eval-every", "600",
                          "--eval-episodes", "1", "--learning-starts", "300", "--final-episodes", "1",
                          "--reset-options", '{"reset_cell": [3, 1]}', "--out", str(root / "sac")])
    return root


@pytest.mark.recipe
def test_every_goal_cell_is_tested_and_reaches_the_env(agents, tmp_path, monkeypatch):
    """Each agent gets a row per free cell but the start, with its distance, and the env each goal cell's episodes
    run in puts the goal in that cell (for DHRL, the test envs the run's evaluation builds; for SAC + HER, the
    baseline's env)."""
    import gymnasium as gym

    seen = {"DHRL": [], "SAC + HER": []}
    dhrl_outcomes, sac_successes = goal_distance.episode_outcomes, goal_distance._sac_module().episode_successes

    def dhrl_recording(env, policy, batches, seed, upside_down=None):
        outcome = dhrl_outcomes(env, policy, batches, seed, upside_down)
        seen["DHRL"].append(env.reset()["desired_goal"].reshape(-1, 2)[:, :2].numpy())
        return outcome

    monkeypatch.setattr(goal_distance, "episode_outcomes", dhrl_recording)

    real_module = goal_distance._sac_module

    def sac_module():
        module = real_module()

        def recording(model, env, episodes, seeds=None):
            obs, _ = env.reset(seed=int(seeds[0]))
            seen["SAC + HER"].append(np.asarray(obs["desired_goal"]).reshape(1, 2))
            return sac_successes(model, env, episodes, seeds)

        module.episode_successes = recording
        return module

    monkeypatch.setattr(goal_distance, "_sac_module", sac_module)
    out = tmp_path / "umaze"
    rows = goal_distance.main([str(agents / "dhrl"), str(agents / "sac"), "--start", "3", "1", "--episodes", "2",
                               "--band", "2", "--out", str(out)])
    maze = gym.make("PointMaze_UMaze-v3").unwrapped.maze
    expected = goal_distance.maze_distances(maze.maze_map, (3, 1))
    goals = sorted((c for c in expected if expected[c] > 0), key=lambda c: (expected[c], c))
    for kind in ("DHRL", "SAC + HER"):
        mine = [r for r in rows if r["kind"] == kind]
        assert [(r["goal_row"], r["goal_col"]) for r in mine] == goals
        assert [r["distance"] for r in mine] == [expected[g] for g in goals]
        assert all(0 <= r["successes"] <= r["episodes"] for r in mine)
        assert len(seen[kind]) == len(goals)
        for goal, positions in zip(goals, seen[kind], strict=True):
            cells = {tuple(int(v) for v in maze.cell_xy_to_rowcol(p)) for p in positions}
            assert cells == {goal}, (kind, goal, positions)
    with (out.with_suffix(".csv")).open() as file:
        assert [{k: str(v) for k, v in r.items()} for r in rows] == list(csv.DictReader(file))
    assert out.with_suffix(".png").is_file() and (tmp_path / "umaze_cells.png").is_file()
    assert {(r["start_row"], r["start_col"]) for r in rows} == {(3, 1)}
    table = out.with_suffix(".md").read_text()
    assert "PointMaze_UMaze-v3, start cell (3, 1), 6 goal cells, 2 deterministic test episodes" in table
    # the table again from the CSV alone, no episode run
    redrawn = tmp_path / "again"
    goal_distance.main(["--from-csv", str(out.with_suffix(".csv")), "--band", "2", "--out", str(redrawn)])
    assert redrawn.with_suffix(".md").read_text().split("\n\n", 1)[1] == table.split("\n\n", 2)[2]


@pytest.mark.recipe
def test_agents_on_different_mazes_are_refused_before_any_episode(agents, tmp_path, monkeypatch, capsys):
    other = tmp_path / "sac_medium"
    other.mkdir()
    config = (agents / "sac" / "config.json").read_text().replace("PointMaze_UMaze-v3", "PointMaze_Open-v3")
    (other / "config.json").write_text(config)
    (other / "model.zip").write_bytes((agents / "sac" / "model.zip").read_bytes())
    monkeypatch.setattr(goal_distance, "episode_outcomes", lambda *a, **k: pytest.fail("an episode ran"))
    with pytest.raises(SystemExit):
        goal_distance.main([str(agents / "dhrl"), str(other), "--start", "3", "1", "--out", str(tmp_path / "x")])
    assert "the agents are on different envs, maze maps or right_flipped_after" in capsys.readouterr().err


def test_agents_whose_ant_is_righted_differently_are_refused_before_any_episode(tmp_path, monkeypatch, capsys):
    """A DHRL agent tested with the flipped ant righted and a SAC + HER one without would not face the same env."""
    from types import SimpleNamespace

    def fake(path, device):
        rf = None if Path(path).name == "plain" else 10
        return SimpleNamespace(env_id="AntMaze_Medium-v5", make_kwargs={}, right_flipped_after=rf,
                               successes=lambda *a: pytest.fail("an episode ran"))

    monkeypatch.setattr(goal_distance, "load_agent", fake)
    with pytest.raises(SystemExit):
        goal_distance.main([str(tmp_path / "righted"), str(tmp_path / "plain"), "--start", "1", "1",
                            "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert "different envs, maze maps or right_flipped_after" in err and "None" in err and "10" in err


@pytest.mark.recipe
def test_a_sac_model_is_tested_with_its_own_right_flipped_after(agents, tmp_path, monkeypatch):
    """The baseline's env of every goal cell gets the model's --right-flipped-after (its config.json)."""
    folder = tmp_path / "sac_righted"
    folder.mkdir()
    config = json.loads((agents / "sac" / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps(config | {"right_flipped_after": 7}))
    (folder / "model.zip").write_bytes((agents / "sac" / "model.zip").read_bytes())
    real_module, seen = goal_distance._sac_module, []

    def sac_module():
        module = real_module()
        real_env = module._env

        def recording(env_id, options, make_kwargs, right_flipped_after=None):
            seen.append(right_flipped_after)
            return real_env(env_id, options, make_kwargs)  # a point maze has no ant to right

        module._env = recording
        return module

    monkeypatch.setattr(goal_distance, "_sac_module", sac_module)
    agent = goal_distance.load_agent(folder, "cpu")
    assert agent.right_flipped_after == 7
    agent.successes((3, 1), (1, 1), 1, 0)
    assert seen == [7, 7]  # the env it loads with, then the goal cell's


def test_a_run_of_another_env_is_named_and_refused(tmp_path, monkeypatch):
    # a built-in task's run
    monkeypatch.setattr(goal_distance, "agent_from_checkpoint", lambda *a, **k: ({"env_name": "AntMaze"}, object()))
    monkeypatch.setattr(goal_distance, "agent_checkpoint_file", lambda path: path)
    with pytest.raises(SystemExit, match="env_name=AntMaze is not a gymnasium-robotics maze"):
        goal_distance.load_agent(tmp_path, "cpu")
