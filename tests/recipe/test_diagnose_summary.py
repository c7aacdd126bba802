"""recipes/diagnose_summary.py: one row per run of where along the maze it stops and which checks hold; each check
of ``findings`` on its own and at its boundary, the figures read from the committed Bottleneck runs, the
planning variants from a saved agent, bad runs refused before any work."""

import csv
import math
import shutil
from pathlib import Path

import pytest
import torch
import yaml
from _recipe import load_recipe, recipe_config

pytestmark = pytest.mark.recipe

ROOT = Path(__file__).resolve().parents[2]
BOTTLENECK = ROOT / "results" / "antmazebottleneck_cps"


@pytest.fixture(scope="module")
def summary():
    return load_recipe("diagnose_summary")


#: A run every check passes: the episodes, the landmarks and the plans reach the goal (40 along, radius 5), the
#: start's subgoal free, the planning variants as good as the agent.
CLEAN = {
    "frontier": 40.0,
    "landmark_progress": 38.0,
    "reachable_progress": 38.0,
    "reachable_landmarks": 1.0,
    "bridge_distance": math.inf,
    "start_subgoal_feasible": 1.0,
    "start_best_subgoal_in_wall": 0.0,
    "start_actor_q_gap": 0.0,
}
CLEAN_ABLATIONS = {
    "as trained": 0.5,
    "goal as subgoal": 0.55,
    "oracle graph": 0.55,
    "oracle graph, goal": 0.5,
}


def _findings(summary, changes=None, ablations=None):
    return summary.findings(
        CLEAN | (changes or {}),
        goal=40.0,
        tolerance=5.0,
        cutoff=30.0,
        ablations=CLEAN_ABLATIONS | (ablations or {}),
    )


@pytest.mark.parametrize(
    "changes, ablations, expected",
    [
        ({"frontier": 34.9}, None, ["exploration: training episodes reach 34.9 of 40.0"]),
        (
            {"upside_down": 0.358, "ended_upside_down": 0.6},
            None,
            ["flipped ant: 36% of the training steps upside down, 60% of the episodes end so (right_flipped_after)"],
        ),
        ({"upside_down": 0.0999, "ended_upside_down": 0.2}, None, []),  # below a tenth of the steps
        ({"upside_down": 0.1}, None, ["flipped ant: 10% of the training steps upside down (right_flipped_after)"]),
        (
            {"frontier": 35.0, "landmark_progress": 35.0, "reachable_progress": 35.0},
            None,
            [],
        ),  # at the boundary
        (
            {"landmark_progress": 34.0, "reachable_progress": 34.0},
            None,
            ["landmarks: none past 34.0 (the episodes reach 40.0)"],
        ),
        # the episodes got less far than the goal: the landmarks are compared with the episodes
        (
            {"frontier": 20.0, "landmark_progress": 14.0, "reachable_progress": 14.0},
            None,
            [
                "exploration: training episodes reach 20.0 of 40.0",
                "landmarks: none past 14.0 (the episodes reach 20.0)",
            ],
        ),
        (
            {"reachable_progress": 30.0, "reachable_landmarks": 0.9, "bridge_distance": 31.25},
            None,
            [
                "graph cut: plans from the start reach 30.0 of 38.0 (90% of the landmarks; bridge 31.2 steps, cutoff 30)"
            ],
        ),
        ({"reachable_progress": 30.0, "reachable_landmarks": 1.0}, None, []),  # every landmark reachable
        (
            {"reachable_progress": 30.0, "reachable_landmarks": 0.9, "bridge_distance": math.inf},
            None,
            ["graph cut: plans from the start reach 30.0 of 38.0 (90% of the landmarks)"],
        ),
        ({}, {"oracle graph": 0.6}, ["learned distances: the oracle graph 60% vs 50% as trained"]),
        ({}, {"oracle graph": 0.59, "oracle graph, goal": 0.4}, []),  # below the margin
        (
            {},
            {"oracle graph": 0.2, "oracle graph, goal": 0.7},
            ["learned distances: the oracle graph 70% vs 50% as trained"],
        ),
        (
            {"start_subgoal_feasible": 0.0, "start_actor_q_gap": 1.38},
            None,
            [
                "high level: its subgoal at the start lies in a wall (1.38 in Q below its critic's best free subgoal)"
            ],
        ),
        (
            {"start_subgoal_feasible": 0.0, "start_actor_q_gap": -0.1},
            None,
            ["high level: its subgoal at the start lies in a wall"],
        ),
        ({}, {"goal as subgoal": 0.61}, ["high level: the goal as subgoal 61% vs 50% as trained"]),
        (
            {},
            {"unreachable=subgoal": 0.6},
            [
                "graph fallback: straight for the subgoals the graph cannot reach 60% vs 50% as trained "
                "(planner.unreachable=subgoal)"
            ],
        ),
        ({}, {"unreachable=subgoal": 0.59}, []),  # below the margin
        (
            {"start_best_subgoal_in_wall": 1.0},
            None,
            ["high-level critic: its best subgoal at the start lies in a wall"],
        ),
        (
            {},
            {"as trained": 0.0, "goal as subgoal": 0.0, "oracle graph": 0.05, "oracle graph, goal": 0.05},
            ["low level: 5% along the oracle graph's route to the goal"],
        ),
        # the oracle's graph fails too, but the landmarks stop short: exploration's, not the low level's
        (
            {"frontier": 20.0, "landmark_progress": 19.0, "reachable_progress": 19.0},
            {"as trained": 0.0, "goal as subgoal": 0.0, "oracle graph": 0.0, "oracle graph, goal": 0.0},
            ["exploration: training episodes reach 20.0 of 40.0"],
        ),
    ],
)
def test_each_check_holds_on_its_own(summary, changes, ablations, expected):
    assert _findings(summary, changes, ablations) == expected


def test_missing_figures_skip_their_checks(summary):
    """A run older than a column (NaN or absent) and no planning variants: only the checks with their figures."""
    figures = {"frontier": 10.0, "landmark_progress": math.nan, "start_subgoal_feasible": math.nan}
    assert summary.findings(figures, goal=40.0, tolerance=5.0, cutoff=30.0) == [
        "exploration: training episodes reach 10.0 of 40.0"
    ]
    assert summary.findings({}, goal=40.0, tolerance=5.0, cutoff=30.0, ablations={"as trained": 0.0}) == []


def test_several_checks_hold_together_in_a_fixed_order(summary):
    out = _findings(
        summary,
        {
            "frontier": 30.0,
            "upside_down": 0.2,
            "start_subgoal_feasible": 0.0,
            "start_actor_q_gap": 2.0,
            "start_best_subgoal_in_wall": 1.0,
        },
        {
            "as trained": 0.0,
            "goal as subgoal": 0.3,
            "unreachable=subgoal": 0.5,
            "oracle graph": 0.4,
            "oracle graph, goal": 0.0,
        },
    )
    assert [f.split(":")[0] for f in out] == [
        "exploration",
        "flipped ant",
        "learned distances",
        "high level",
        "high level",
        "graph fallback",
        "high-level critic",
        "low level",
    ]


def _last_row(path: Path) -> dict:
    with (path / "metrics.csv").open() as file:
        return list(csv.DictReader(file))[-1]


def test_the_committed_bottleneck_runs(summary, capsys, tmp_path):
    """Read with the csv module: each row's figures are the run's last evaluation, G the path to (0, 16) round the
    bottleneck maze (40.1, as the runs' diagnoses measured it); the findings follow."""
    runs = [str(BOTTLENECK / f"seed{k}") for k in range(4)]
    out = tmp_path / "table.md"
    rows = summary.main([*runs, "--out", str(out)])
    printed = capsys.readouterr().out
    assert out.read_text() == printed and len(printed.splitlines()) == 2 + 4
    for k, row in enumerate(rows):
        metrics = _last_row(BOTTLENECK / f"seed{k}")
        assert row["env_steps"] == int(float(metrics["env_steps"])) == 993_000
        assert row["success"] == float(metrics["eval/success"])
        assert row["frontier"] == float(metrics["train/frontier"])
        assert row["landmark_progress"] == float(metrics["diag/landmark_progress"])
        assert (
            row["goal"] == pytest.approx(40.1, abs=0.05) and row["tolerance"] == 5.0 and row["cutoff"] == 30.0
        )
        assert math.isnan(row["reachable_progress"])  # these runs predate the column: no graph-cut check
        assert row["ablations"] == {}
    # 36.1 of 40.1: within the success radius of the goal; the ant on its back for a fifth of the training steps
    upside_down, ended = (float(_last_row(BOTTLENECK / "seed0")[k]) for k in ("train/upside_down", "train/ended_upside_down"))
    assert upside_down >= 0.1 and rows[0]["findings"] == [
        f"flipped ant: {upside_down:.0%} of the training steps upside down, {ended:.0%} of the episodes end so "
        "(right_flipped_after)"
    ]
    assert rows[2]["findings"][0] == "exploration: training episodes reach 26.1 of 40.1"
    assert all(
        any(f.startswith("high level: its subgoal at the start lies in a wall") for f in r["findings"])
        for r in rows[1:]
    )
    assert rows[1]["findings"][-1] == "high-level critic: its best subgoal at the start lies in a wall"
    # --at: the last evaluation at or before
    early = summary.main([runs[0], "--at", "500000"])[0]
    with (BOTTLENECK / "seed0" / "metrics.csv").open() as file:
        evaluated = [
            r for r in csv.DictReader(file) if r["eval/success"] and float(r["env_steps"]) <= 500_000
        ]
    assert early["env_steps"] == int(float(evaluated[-1]["env_steps"]))


@pytest.fixture(scope="module")
def pointmaze_run(tmp_path_factory):
    path = tmp_path_factory.mktemp("pointmaze")
    torch.manual_seed(0)
    load_recipe().train(
        recipe_config("env=PointMaze", "preset=smoke", "logger.backend=none", "plots.every_epochs=0"),
        run_dir=path,
    )
    return path


def test_ablations_from_the_saved_agent(summary, pointmaze_run, capsys):
    (row,) = summary.main([str(pointmaze_run), "--ablations", "--repeats", "1"])
    counters = load_recipe("dhrl_utils").load_checkpoint(pointmaze_run / "agent", components=("counters",))
    assert row["agent_steps"] == counters["counters"]["env_steps"] == row["env_steps"]
    assert set(row["ablations"]) == {*summary.VARIANTS, "episodes"} and row["ablations"]["episodes"] >= 1
    assert all(0.0 <= row["ablations"][name] <= 1.0 for name in summary.VARIANTS)
    assert (
        0.0 <= row["reachable_landmarks"] <= 1.0 and row["reachable_progress"] >= 0.0
    )  # measured on the graph
    header = capsys.readouterr().out.splitlines()[0]
    assert "oracle graph, goal (" in header and header.endswith("| findings |")


def test_bad_runs_are_refused_before_any_work(summary, pointmaze_run, tmp_path, monkeypatch):
    def no_work(*args, **kwargs):
        raise AssertionError("a run was summarized before every run was checked")

    monkeypatch.setattr(summary, "summarize_run", no_work)
    with pytest.raises(SystemExit, match="no metrics.csv"):
        summary.main([str(pointmaze_run), str(tmp_path)])
    reacher = ROOT / "results" / "reacher3d_quick" / "seed0"
    with pytest.raises(SystemExit, match=r"env_name='Reacher3D' is not a maze; accepted: PointMaze.*gymnasium:AntMaze_\*"):
        summary.main([str(pointmaze_run), str(reacher)])
    with pytest.raises(SystemExit, match="--ablations needs the run's agent/ or checkpoint/"):
        summary.main([str(pointmaze_run), str(BOTTLENECK / "seed0"), "--ablations"])


def test_a_gymnasium_maze_run_from_its_metrics(summary, tmp_path, monkeypatch):
    """A gymnasium-robotics maze with a fixed start: the goal's progress G is the farthest test goal's path length from
    the start cell on the env's own map (independently: the test env's goals against the maze geometry), the frontier
    and the graph figures come from its metrics; --ablations re-evaluates its agent; a run without a fixed start is
    refused."""
    pytest.importorskip("gymnasium_robotics")
    from torchrl_dhrl.envs import GymnasiumGoalEnv

    gym = ("env=gymnasium", "env_name=gymnasium:PointMaze_UMaze-v3", "preset=smoke", "logger.backend=none",
           "plots.every_epochs=0", "total_steps=160")
    start = "gymnasium.reset_options={reset_cell:[3,1]}"
    load_recipe().train(recipe_config(*gym, start, "gymnasium.eval_reset_options={reset_cell:[3,1],goal_cell:[1,1]}"),
                        run_dir=tmp_path / "run")
    (row,) = summary.main([str(tmp_path / "run")])
    geometry = GymnasiumGoalEnv("PointMaze_UMaze-v3", reset_options={"reset_cell": [3, 1]}).maze_geometry(margin=0.125)
    cfg = yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())
    test = load_recipe("dhrl_utils").build_environment(cfg, torch.device("cpu"), eval=True)  # the recipe's test envs
    goals = test.reset()["desired_goal"]
    assert ((goals - torch.tensor([-1.0, 1.0])).abs() <= 0.25 + 1e-6).all()  # cell (1, 1) with the env's noise
    goal = geometry.path_length(geometry.start, goals).max().item()
    assert row["goal"] == pytest.approx(goal) and 3.5 < goal < 6.0  # around the U: two cells down, two across
    last = _last_row(tmp_path / "run")
    assert row["frontier"] == pytest.approx(float(last["train/frontier"]))
    assert row["tolerance"] == 0.45 and "findings" in row
    # --ablations: the saved agent re-evaluated, the oracle variants against the maze's own walls
    (ablated,) = summary.main([str(tmp_path / "run"), "--ablations", "--repeats", "1"])
    assert set(ablated["ablations"]) == {*summary.VARIANTS, "episodes"}
    assert all(0.0 <= ablated["ablations"][name] <= 1.0 for name in summary.VARIANTS)
    # a run recorded with the ant mazes' 0.5 (0.4.0 and earlier): refused before any work, naming the option that
    # fixes it; with it, the same row as the run recorded with the derived margin
    old = tmp_path / "old"
    shutil.copytree(tmp_path / "run", old)
    cfg["planner"]["oracle_margin"] = 0.5
    (old / "config.yaml").write_text(yaml.safe_dump(cfg))
    with pytest.raises(SystemExit, match=r"old: planner.oracle_margin=0.5 on env_name=gymnasium:PointMaze_UMaze-v3: "
                                         r"margin=0.5 leaves no free cell.*--oracle-margin"):
        summary.main([str(tmp_path / "run"), str(old)])
    (again,) = summary.main([str(old), "--oracle-margin", "0.125"])
    assert again["goal"] == row["goal"] and again["frontier"] == row["frontier"]
    # --oracle-speed: the oracle variants step at the given speed instead of the record's
    oracles = []

    def ablations(agent, env, steps, *, repeats, oracle):
        oracles.append(oracle)
        return [{"variant": name, "success": 0.0, "episodes": repeats} for name in summary.VARIANTS]

    monkeypatch.setattr(summary, "planning_ablations", ablations)
    summary.main([str(old), "--ablations", "--repeats", "1", "--oracle-margin", "0.125", "--oracle-speed", "0.04"])
    summary.main([str(tmp_path / "run"), "--ablations", "--repeats", "1"])
    assert [oracle.speed for oracle in oracles] == [0.04, cfg["planner"]["oracle_speed"]]
    torch.testing.assert_close(oracles[0].boxes, oracles[1].boxes)  # the margin given = the one recorded
    with pytest.raises(SystemExit) as bad:
        summary.main([str(old), "--oracle-speed", "0"])
    assert bad.value.code == 2
    load_recipe().train(recipe_config(*gym), run_dir=tmp_path / "anywhere")
    with pytest.raises(SystemExit, match="no fixed start"):
        summary.main([str(tmp_path / "anywhere")])
