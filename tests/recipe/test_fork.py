"""``fork=<run>``: a new run from another run's checkpoint, with the seed and the hyperparameters no state holds
changed (``FORK_MUTABLE_KEYS``). A fork without changes goes on exactly like a resume; a forked run resumes
exactly; every forkable hyperparameter is in effect in the objects the fork trains with; a new seed re-seeds the
training streams and leaves the test episodes' alone; bad forks fail before anything is written."""

import pytest
import torch
from _recipe import TIMING_COLUMNS, load_recipe, metrics_rows, recipe_config

from torchrl_dhrl.planner import ConnectedEdgeRule
from torchrl_dhrl.recipe import (
    FORK_MUTABLE_KEYS,
    RESUME_MUTABLE_KEYS,
    ConfigError,
    check_resume_config,
    load_checkpoint,
    read_provenance,
)

pytestmark = pytest.mark.recipe

recipe = load_recipe()

BASE = ("env=PointMaze", "preset=smoke", "logger.backend=csv", "plots.every_epochs=0", "device=cpu")


def _rows(run_dir):
    return metrics_rows(run_dir, drop=TIMING_COLUMNS)


def _params(run_dir):
    out = {}

    def flat(state, prefix):
        for key, value in state.items():
            if isinstance(value, dict):
                flat(value, f"{prefix}{key}.")
            elif isinstance(value, torch.Tensor):
                out[f"{prefix}{key}"] = value

    flat(load_checkpoint(run_dir / "checkpoint", components=("agent",))["agent"], "")
    return out


def _train(run_dir, *overrides):
    return recipe.train(recipe_config(*BASE, *overrides), run_dir=run_dir)


def _capture_build_run(monkeypatch) -> dict:
    """``built["parts"]``: the parts the next run trains with (the recipe's ``build_run``, recorded)."""
    built = {}
    build_run = recipe.build_run

    def capture(cfg, device):
        built["parts"] = parts = build_run(cfg, device)
        return parts

    monkeypatch.setattr(recipe, "build_run", capture)
    return built


@pytest.fixture(scope="module")
def parent(tmp_path_factory):
    """A 240-step run: the state every test forks from."""
    run_dir = tmp_path_factory.mktemp("parent")
    _train(run_dir, "total_steps=240")
    return run_dir


@pytest.fixture(scope="module")
def fork_resumed(parent, tmp_path_factory):
    """parent (240) -> fork without changes (to 360) -> resumed (to 480)."""
    fork = tmp_path_factory.mktemp("fork")
    before = (parent / "checkpoint" / "manifest.json").read_bytes()
    _train(fork, "total_steps=360", f"fork={parent}")
    assert f"fork: {parent / 'checkpoint'}" in (fork / "config.yaml").read_text()
    stopped = load_checkpoint(fork / "checkpoint", components=("counters",))["counters"]["env_steps"]
    _train(fork, "total_steps=480", f"resume={fork}")  # `fork` left out: the run keeps where it came from
    assert f"fork: {parent / 'checkpoint'}" in (fork / "config.yaml").read_text()
    # the fork's provenance starts with the fork (not the parent's starts), its resume appended
    starts = read_provenance(fork)
    assert [s["env_steps"] for s in starts] == [240, stopped]
    assert starts[0]["forked_from"] == str(parent / "checkpoint") and "forked_from" not in starts[1]
    assert [s["env_steps"] for s in read_provenance(parent)] == [0]
    assert (parent / "checkpoint" / "manifest.json").read_bytes() == before  # the parent is untouched
    return fork


def test_a_fork_without_changes_goes_on_exactly_and_resumes_exactly(parent, fork_resumed, tmp_path):
    """parent (240) -> fork (to 360) -> resume (to 480) == 480 straight, bit for bit."""
    straight, fork = tmp_path / "straight", fork_resumed
    _train(straight, "total_steps=480")
    assert _rows(fork) == _rows(straight)  # the parent's epochs, then the same losses, graphs, successes
    a, b = _params(straight), _params(fork)
    assert a.keys() == b.keys()
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, msg=key)
    counters = load_checkpoint(fork / "checkpoint", components=("counters",))["counters"]
    assert counters["forks"] == [{"checkpoint": str(parent / "checkpoint"), "env_steps": 240, "seed": 0}]
    assert counters["env_steps"] == 480
    assert (fork / "success_curve.png").stat().st_size > 1000


def test_every_forkable_hyperparameter_is_in_effect(parent, tmp_path, monkeypatch):
    """Each experiment key of FORK_MUTABLE_KEYS, changed at once, holds its new value in the objects the fork
    trains with after the checkpoint was restored into them (none is overwritten by a restored state)."""
    built = _capture_build_run(monkeypatch)
    new = {
        "high.subgoal_test_ratio": 0.5,
        "high.subgoal_test_threshold": 2.5,
        "high.subgoal_miss_penalty": 0.7,
        "high.gradual_penalty": 1.5,
        "high.far_from_graph_factor": 1.0,
        "schedule.eval_every_epochs": 2,
        "schedule.eval_flat": False,
        "planner.edge_rule": "connected",
        "planner.unreachable": "subgoal",
        "high.critic_candidates": 4,
        "high.candidate_noise": 0.5,
        "high.landmark_candidates": True,
    }
    # every experiment key a fork may change is checked here (a key added to the tuple needs its check; the ant
    # mazes' right_flipped_after in the test below)
    assert set(new) | {"fork", "seed", "right_flipped_after"} == set(FORK_MUTABLE_KEYS) - set(RESUME_MUTABLE_KEYS)
    saved = load_checkpoint(parent / "checkpoint", components=("config",))["config"]
    for key, value in new.items():
        section, name = key.split(".")
        assert saved[section][name] != value, key  # a real change
    _train(tmp_path, "total_steps=480", f"fork={parent}", *(f"{k}={str(v).lower()}" for k, v in new.items()))
    agent = built["parts"].agent
    assert isinstance(agent.planner.graph.edge_rule, ConnectedEdgeRule)  # used from the fork's next build on
    assert agent.planner.graph.unreachable == "subgoal"  # read at every query
    selector = agent.high_policy.selector
    assert selector.num_candidates == 4 and selector.landmark_candidates is True
    assert selector.sigma.eq(0.5).all()
    relabel = built["parts"].high_rb.relabel[1]  # HindsightSubgoalRelabel
    assert relabel.subgoal_test_ratio == 0.5
    assert relabel.subgoal_test_threshold == 2.5
    assert relabel.subgoal_miss_penalty == 0.7
    assert relabel.gradual_penalty == 1.5
    cutoff = saved["planner"]["cutoff"]
    assert relabel.far_from_graph_threshold == 1.0 * cutoff
    assert relabel.distance_from_graph.keywords["at_most"] == 1.0 * cutoff  # the graph query's bound too
    rows = _rows(tmp_path)
    before, after = rows[:3], rows[3:]  # the parent's three epochs (240 steps), then the fork's
    assert all(r["eval/success"] != "" and r["eval/flat_success"] != "" for r in before)
    assert [r["eval/success"] != "" for r in after] == [int(r["epoch"]) % 2 == 0 for r in after]
    assert all(r.get("eval/flat_success", "") == "" for r in after)


def test_a_fork_or_a_test_time_variant_rights_the_flipped_ant(tmp_path, monkeypatch):
    """``right_flipped_after`` on an ant maze: a fork's training and test envs right a flipped ant (the parent's did
    not), and a saved agent re-evaluated with it as a variant gets an env that does."""
    ant = ("env=AntMazeSmall", *BASE[1:])
    parent, fork = tmp_path / "parent", tmp_path / "fork"
    recipe.train(recipe_config(*ant, "total_steps=160"), run_dir=parent)
    built = _capture_build_run(monkeypatch)
    recipe.train(recipe_config(*ant, "total_steps=240", f"fork={parent}", "right_flipped_after=5"), run_dir=fork)
    parts = built["parts"]
    assert [env.base_env._sim.right_flipped_after for env in (parts.train_env, parts.eval_env)] == [5, 5]
    saved = load_checkpoint(fork / "checkpoint", components=("config", "counters"))
    assert saved["config"]["right_flipped_after"] == 5 and saved["counters"]["env_steps"] == 240
    parent_config = load_checkpoint(parent / "checkpoint", components=("config",))["config"]
    assert parent_config["right_flipped_after"] is None
    dhrl_utils = load_recipe("dhrl_utils")
    cfg, agent = dhrl_utils.agent_from_checkpoint(parent / "checkpoint", changes={"right_flipped_after": 10})
    env = dhrl_utils.build_environment(cfg, torch.device("cpu"), eval=True, agent=agent)
    assert cfg["right_flipped_after"] == 10 and env.base_env._sim.right_flipped_after == 10


def test_a_new_seed_reseeds_the_training_streams_not_the_test_episodes(parent, fork_resumed, tmp_path):
    """Two forks with seed 1 agree bit for bit; they differ from the seed-0 fork in what they learn, while
    the test episodes' streams (the eval envs' RNGs) stay those of the seed-0 fork."""
    runs = {"same": fork_resumed}
    for name, seed in (("one", 1), ("one_again", 1)):
        runs[name] = tmp_path / name
        _train(runs[name], "total_steps=480", f"fork={parent}", f"seed={seed}")
    assert _rows(runs["one"]) == _rows(runs["one_again"])
    same, one = _rows(runs["same"]), _rows(runs["one"])
    assert same[:3] == one[:3]  # the parent's epochs
    assert [r["low/loss_policy_qvalue"] for r in same[3:]] != [r["low/loss_policy_qvalue"] for r in one[3:]]
    params = _params(runs["same"]), _params(runs["one"])
    assert not all(torch.equal(params[0][key], params[1][key]) for key in params[0])
    rngs = {
        name: load_checkpoint(run / "checkpoint", components=("eval_env", "train_env"))
        for name, run in runs.items()
    }
    eval_rngs = [rngs[name]["eval_env"]["_extra_state"]["rngs"] for name in ("same", "one")]
    train_rngs = [rngs[name]["train_env"]["_extra_state"]["rngs"] for name in ("same", "one")]
    assert eval_rngs[0] == eval_rngs[1]
    assert train_rngs[0] != train_rngs[1]
    counters = load_checkpoint(runs["one"] / "checkpoint", components=("counters",))["counters"]
    assert counters["forks"][0]["seed"] == 1


@pytest.mark.parametrize(
    "overrides, match",
    [
        (("total_steps=240",), r"`total_steps` 240 with `fork=.*`: the checkpoint is at 240 env steps"),
        (
            ("total_steps=480", "low.actor_lr=0.1"),
            r"low.actor_lr 0.0001 -> 0.1 .*On fork only .*without `fork`",
        ),
        (("total_steps=480", "low.hidden=[64]"), r"low.hidden \[32, 32\] -> \[64\]"),
        (("total_steps=480", "high.subgoal_noise=1.0"), r"high.subgoal_noise 2.0 -> 1.0"),
    ],
)
def test_a_bad_fork_fails_before_anything_is_written(parent, tmp_path, overrides, match):
    target = tmp_path / "fork"
    with pytest.raises(ConfigError, match=match):
        _train(target, f"fork={parent}", *overrides)
    assert not target.exists()


def test_fork_paths_are_checked(parent, tmp_path):
    with pytest.raises(
        ConfigError, match=r"a fork is a new run; choose a run_dir other than the forked run's"
    ):
        _train(parent, "total_steps=480", f"fork={parent}")
    with pytest.raises(ConfigError, match=r"`fork=.*nowhere.*`: no checkpoint at"):
        _train(tmp_path / "a", "total_steps=480", f"fork={tmp_path / 'nowhere'}")
    with pytest.raises(ConfigError, match=r"`fork` must be null or a path, got 5"):
        _train(tmp_path / "a", "total_steps=480", "fork=5")
    # resuming a run with a `fork` it was not forked from
    with pytest.raises(ConfigError, match=r"with `fork=.*`: that run was not forked; leave `fork` out"):
        _train(parent, "total_steps=480", f"resume={parent}", f"fork={parent}")
    other = tmp_path / "other"
    _train(other, "total_steps=320", f"fork={parent}")
    with pytest.raises(ConfigError, match=r"that run was forked from .*parent.*checkpoint"):
        _train(other, "total_steps=480", f"resume={other}", f"fork={other}")
    # a fork into a directory that already holds a checkpoint (an earlier fork): continue it with resume
    with pytest.raises(ConfigError, match=r"already holds a checkpoint.*resume="):
        _train(other, "total_steps=480", f"fork={parent}")


def test_check_resume_config_names_the_action():
    saved = {"seed": 0, "high": {"far_from_graph_factor": 3.0}, "low": {"actor_lr": 1e-4}}
    notes = check_resume_config(
        saved,
        {"seed": 2, "high": {"far_from_graph_factor": 1.0}, "low": {"actor_lr": 1e-4}},
        mutable=FORK_MUTABLE_KEYS,
    )
    assert notes == ["high.far_from_graph_factor: 3.0 -> 1.0", "seed: 0 -> 2"]
    with pytest.raises(ConfigError, match=r"On resume only .*without `resume`"):
        check_resume_config(saved, {**saved, "seed": 2})
    with pytest.raises(ConfigError, match=r"On fork only .*without `fork`"):
        check_resume_config(
            saved, {**saved, "low": {"actor_lr": 0.1}}, mutable=FORK_MUTABLE_KEYS, action="fork"
        )
