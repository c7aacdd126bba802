"""benchmarks/sac_her_baseline.py, the SAC + HER baseline next to the recipe's gymnasium runs: evaluated as the
recipe evaluates (the final model over N seeded test episodes, counted in whole episodes, recorded with the code
and machine), resumable from its checkpoint (whole episodes in the HER buffer), stopped by SIGTERM with a
checkpoint, and bad arguments refused before any training."""

from __future__ import annotations

import importlib.util
import json
import os
import pickle
import signal
from pathlib import Path

import pytest
import yaml

pytest.importorskip("stable_baselines3")
pytest.importorskip("gymnasium_robotics")

pytestmark = pytest.mark.slow

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "sac_her_baseline.py"
#: PointMaze_UMaze-v3: 300-step episodes; a run of 4 episodes evaluated after each 2, learning after the first.
ARGS = [
    "--env-id",
    "PointMaze_UMaze-v3",
    "--eval-every",
    "600",
    "--eval-episodes",
    "2",
    "--learning-starts",
    "300",
    "--final-episodes",
    "3",
    "--final-seed",
    "5",
    "--reset-options",
    '{"reset_cell": [3, 1]}',
]


def _load():
    spec = importlib.util.spec_from_file_location("sac_her_baseline", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("sac") / "run"
    _load().main([*ARGS, "--steps", "1200", "--out", str(out)])
    return out


def test_the_final_model_is_evaluated_as_the_recipe_evaluates(run):
    from stable_baselines3 import SAC

    baseline = _load()
    record = yaml.safe_load((run / "final_eval.yaml").read_text())
    assert record["env_name"] == "gymnasium:PointMaze_UMaze-v3" and record["env_steps"] == 1200
    assert record["episodes"] == 3 and isinstance(record["successes"], int) and record["seed"] == 5
    assert record["success"] == record["successes"] / 3 and record["episode_length"] == 300
    assert record["reset_options"] == {
        "reset_cell": [3, 1]
    }  # the test episodes' own, defaulting to training's
    assert record["versions"]["stable-baselines3"] and {"commit", "modified"} <= set(record["code"])
    # independently: the saved model, a fresh env, episode i reset with seed 5 + i
    env = baseline._env("PointMaze_UMaze-v3", {"reset_cell": [3, 1]}, {})
    model = SAC.load(run / "model.zip", env=baseline._env("PointMaze_UMaze-v3", None, {}), device="cpu")
    final, anytime = [], []
    for i in range(3):
        obs, info = env.reset(seed=5 + i)
        reached = False
        for _ in range(300):
            action, _ = model.predict(obs, deterministic=True)
            obs, _, terminated, truncated, info = env.step(action)
            reached |= bool(info["success"])
        final.append(bool(info["success"]))
        anytime.append(reached)
    assert record["successes"] == sum(final) and record["any_successes"] == sum(anytime)
    metrics = (run / "metrics.csv").read_text().splitlines()
    assert metrics[0] == "env_steps,eval/success,eval/any_success,time/wall_s"
    assert [line.split(",")[0] for line in metrics[1:]] == ["600", "1200"]
    (start,) = yaml.safe_load((run / "provenance.yaml").read_text())
    assert start["env_steps"] == 0 and "--steps 1200" in start["command"] and start["threads"] == 1


def test_resume_continues_the_metrics_and_keeps_whole_episodes(run, tmp_path):
    out = tmp_path / "run"
    import shutil

    shutil.copytree(run, out)
    before = json.loads((out / "checkpoint" / "state.json").read_text())
    _load().main([*ARGS, "--steps", "1800", "--out", str(out), "--resume"])
    state = json.loads((out / "checkpoint" / "state.json").read_text())
    assert state["env_steps"] == 1800 and state["rows"][:2] == before["rows"]
    assert [row["env_steps"] for row in state["rows"]] == [600, 1200, 1800]
    assert state["rows"][2]["time/wall_s"] >= before["wall_s"]  # the wall clock over both starts
    starts = yaml.safe_load((out / "provenance.yaml").read_text())
    assert [s["env_steps"] for s in starts] == [0, 1200]
    with (out / "checkpoint" / "replay_buffer.pkl").open("rb") as file:
        buffer = pickle.load(file)
    assert buffer.pos == 1800 and (buffer.ep_length[:1800] == 300).all()  # six whole episodes, none cut
    assert yaml.safe_load((out / "final_eval.yaml").read_text())["env_steps"] == 1800
    # --evaluate-only: the same record again from the saved model
    again = yaml.safe_load((out / "final_eval.yaml").read_text())
    _load().main([*ARGS, "--out", str(out), "--evaluate-only"])
    redone = yaml.safe_load((out / "final_eval.yaml").read_text())
    assert (redone["successes"], redone["env_steps"]) == (again["successes"], again["env_steps"])


def test_sigterm_stops_at_an_episode_end_with_a_checkpoint(run, tmp_path, monkeypatch):
    import shutil

    out = tmp_path / "run"
    shutil.copytree(run, out)
    baseline = _load()
    real = baseline.episode_successes

    def evaluate_then_sigterm(*args, **kwargs):
        result = real(*args, **kwargs)
        os.kill(os.getpid(), signal.SIGTERM)
        return result

    monkeypatch.setattr(baseline, "episode_successes", evaluate_then_sigterm)
    handler = signal.getsignal(signal.SIGTERM)
    with pytest.raises(SystemExit) as stopped:
        baseline.main([*ARGS, "--steps", "3000", "--out", str(out), "--resume"])
    assert stopped.value.code == 130
    state = json.loads((out / "checkpoint" / "state.json").read_text())
    assert state["env_steps"] == 1800 and [row["env_steps"] for row in state["rows"]] == [600, 1200, 1800]
    assert signal.getsignal(signal.SIGTERM) is handler  # put back
    assert not (out / ".checkpoint.stage").exists() and not (out / ".checkpoint.old").exists()
    # the run stopped short has its agent: model.zip is the checkpoint's model (1800 steps), not the 1200-step one
    from stable_baselines3 import SAC

    def actor(path):
        env = baseline._env("PointMaze_UMaze-v3", None, {})  # HER's buffer class wants it to load
        return SAC.load(path, env=env, device="cpu").policy.actor.state_dict()

    saved, checkpointed = actor(out / "model.zip"), actor(out / "checkpoint" / "model.zip")
    earlier = actor(run / "model.zip")
    assert all((saved[k] == checkpointed[k]).all() for k in saved)
    assert any((saved[k] != earlier[k]).any() for k in saved)
    monkeypatch.setattr(baseline, "episode_successes", real)
    alone = tmp_path / "model_only"  # a results folder keeps model.zip, not the checkpoint
    alone.mkdir()
    shutil.copyfile(out / "model.zip", alone / "model.zip")
    baseline.main([*ARGS, "--out", str(alone), "--evaluate-only"])
    assert yaml.safe_load((alone / "final_eval.yaml").read_text())["env_steps"] == 1800


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--eval-every", "500"], "must be multiples of PointMaze_UMaze-v3's episode length"),
        (["--steps", "1000"], "must be multiples of PointMaze_UMaze-v3's episode length"),
        (["--resume"], "--resume: no checkpoint"),
        (
            ["--learning-starts", "299"],
            "--learning-starts (299) must be at least PointMaze_UMaze-v3's episode length",
        ),
    ],
)
def test_bad_arguments_are_refused_before_training(tmp_path, capsys, extra, message):
    with pytest.raises(SystemExit):
        _load().main([*ARGS, "--steps", "1200", "--out", str(tmp_path / "new"), *extra])
    assert message in capsys.readouterr().err
    assert not (tmp_path / "new" / "metrics.csv").exists()


def test_right_flipped_after_wraps_the_ant_mazes_and_is_refused_elsewhere(tmp_path, capsys):
    """--right-flipped-after gives the baseline the recipe's righting (RightFlippedAnt) on an ant maze; on an env
    without an ant it is refused before training, naming the option."""
    from torchrl_dhrl.envs import RightFlippedAnt

    module = _load()
    env = module._env("AntMaze_UMaze-v5", {"reset_cell": [1, 1]}, {}, 10)
    assert isinstance(env, RightFlippedAnt) and env.after == 10
    assert not isinstance(module._env("AntMaze_UMaze-v5", None, {}), RightFlippedAnt)
    with pytest.raises(SystemExit):
        module.main([*ARGS, "--steps", "1200", "--right-flipped-after", "10", "--out", str(tmp_path / "new")])
    assert "--right-flipped-after: RightFlippedAnt rights a flipped ant" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()


def test_an_existing_checkpoint_is_not_overwritten(run, capsys):
    with pytest.raises(SystemExit):
        _load().main([*ARGS, "--steps", "1200", "--out", str(run)])
    assert "already holds a checkpoint; continue it with --resume" in capsys.readouterr().err


@pytest.mark.parametrize("killed", ["after the first rename", "between the renames, the stage complete"])
def test_a_save_killed_between_its_renames_is_recovered(run, tmp_path, killed):
    import shutil

    out = tmp_path / "run"
    shutil.copytree(run, out)
    if killed == "after the first rename":  # the previous checkpoint renamed away, no stage
        (out / "checkpoint").rename(out / ".checkpoint.old")
    else:  # the new checkpoint staged completely, the previous one renamed away
        shutil.copytree(out / "checkpoint", out / ".checkpoint.stage")
        (out / "checkpoint").rename(out / ".checkpoint.old")
    _load().main([*ARGS, "--steps", "1500", "--out", str(out), "--resume"])
    state = json.loads((out / "checkpoint" / "state.json").read_text())
    assert state["env_steps"] == 1500 and [row["env_steps"] for row in state["rows"]] == [600, 1200]
    assert not (out / ".checkpoint.stage").exists() and not (out / ".checkpoint.old").exists()
