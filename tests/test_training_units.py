"""Unit tests of the training machinery: checkpoints, RNG states, the loss updater, the oracle distance,
goal shifting inside an env and evaluation."""

import os
import random

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs
from torchrl_dhrl.envs import make_env

from torchrl_dhrl.modules import GoalConditionedCritic, HighLevelActor
from torchrl_dhrl.objectives import HighLevelLoss, make_optimizers
from torchrl_dhrl.planner import (
    FrontierGoalShifting,
    GoalShiftOnReset,
    GraphPlanner,
    LandmarkGraph,
    LineOfSightDistance,
)
from torchrl_dhrl.training import (
    CHECKPOINT_COMPONENTS,
    LossUpdater,
    NonFiniteLossError,
    evaluate,
    load_checkpoint,
    make_checkpoint,
    restore_checkpoint,
    save_checkpoint,
)


# ---------------------------------------------------------------- checkpoints
def _registry(weight: float, counters: dict, history: list):
    """A checkpoint registry of small stand-ins: a linear layer for the state-dict components."""
    from torchrl.collectors import Collector

    net = torch.nn.Linear(3, 1)
    torch.nn.init.constant_(net.weight, weight)
    env = make_env("PointMaze", num_envs=1, seed=0, max_episode_steps=4)
    collector = Collector(env, None, frames_per_batch=4, total_frames=-1)
    parts = dict.fromkeys(("agent", "low_updater", "high_updater", "low_rb", "high_rb"), net)
    registry = make_checkpoint(
        config={"seed": 0},
        train_env=env,
        eval_env=env,
        collector=collector,
        counters=counters,
        history=history,
        **parts,
    )
    return registry, net


def test_checkpoint_round_trip_and_atomicity(tmp_path, monkeypatch):
    path = tmp_path / "run" / "checkpoint"
    counters, history = {"step": 1}, [{"loss": 0.5}]
    registry, net = _registry(1.0, counters, history)
    save_checkpoint(registry, path)
    loaded = load_checkpoint(path)
    assert sorted(loaded) == sorted(CHECKPOINT_COMPONENTS)
    assert loaded["counters"]["step"] == 1 and torch.equal(loaded["agent"]["weight"], torch.ones(1, 3))

    from torchrl.checkpoint import StateDictCheckpointAdapter

    real_save = StateDictCheckpointAdapter.save
    calls = {"n": 0}

    def crash(self, component, path, **kwargs):  # writes some components, then dies
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real_save(self, component, path, **kwargs)

    counters["step"] = 2
    torch.nn.init.constant_(net.weight, 2.0)
    monkeypatch.setattr(StateDictCheckpointAdapter, "save", crash)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(registry, path)
    monkeypatch.undo()
    loaded = load_checkpoint(path)  # the previous checkpoint survives, whole
    assert loaded["counters"]["step"] == 1 and torch.equal(loaded["agent"]["weight"], torch.ones(1, 3))
    assert [p.name for p in path.parent.iterdir()] == ["checkpoint"]  # no staging directory left
    restore_checkpoint(registry, path)
    assert counters == {"step": 1} and torch.equal(net.weight, torch.ones(1, 3))
    with pytest.raises(FileNotFoundError, match="No checkpoint"):
        load_checkpoint(tmp_path / "missing.pt")


def test_rng_state_round_trip(tmp_path):
    registry, _ = _registry(1.0, {}, [])
    path = save_checkpoint(registry, tmp_path / "checkpoint")
    first = (random.random(), np.random.rand(), torch.rand(3))
    restore_checkpoint(registry, path)
    second = (random.random(), np.random.rand(), torch.rand(3))
    assert first[0] == second[0] and first[1] == second[1] and torch.equal(first[2], second[2])


# ---------------------------------------------------------------- updater
def _high_level_setup(batch=8, num_cells=(16,)):
    low, high = [-4.0, -4.0], [20.0, 20.0]
    actor = HighLevelActor(6, 2, low, high, num_cells=num_cells)
    critic = GoalConditionedCritic(
        6,
        2,
        action_low=low,
        action_high=high,
        goal_key="desired_goal",
        action_key="subgoal",
        relative_goal=False,
        num_cells=num_cells,
    )
    loss = HighLevelLoss(actor, critic)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=batch)
    n = 40
    rb.extend(
        TensorDict(
            {
                "observation": torch.randn(n, 6),
                "desired_goal": torch.randn(n, 2),
                "subgoal": torch.rand(n, 2) * 24 - 4,
                ("next", "observation"): torch.randn(n, 6),
                ("next", "reward"): -torch.ones(n, 1),
            },
            [n],
        )
    )
    return loss, rb


def _params(module):
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


def test_updater_delays_actor_steps_and_polyak():
    torch.manual_seed(0)
    loss, rb = _high_level_setup()
    updater = LossUpdater(loss, rb, make_optimizers(loss), polyak=0.5, target_update_interval=3)
    actor_keys = [k for k in loss.state_dict() if k.startswith("actor_network_params")]
    target_keys = [k for k in loss.state_dict() if k.startswith("target_critic")]
    before = _params(loss)
    out = updater.step()  # update 1: actor_update_interval=2 -> no actor step on the first call
    after = _params(loss)
    actor_moved = any(not torch.equal(before[k], after[k]) for k in actor_keys)
    assert bool(out["actor_updated"]) == actor_moved
    assert all(torch.equal(before[k], after[k]) for k in target_keys)  # targets wait for update 3
    updater.step()
    updater.step()
    assert updater.num_updates == 3
    later = _params(loss)
    assert any(not torch.equal(after[k], later[k]) for k in target_keys)
    # the Polyak rule: target <- 0.5 target + 0.5 online at update 3
    key = next(k for k in target_keys if k.endswith("weight"))
    online = later[key.replace("target_critic_network_params", "critic_network_params")]
    torch.testing.assert_close(later[key], 0.5 * after[key] + 0.5 * online)


def test_updater_run_averages_and_state_dict():
    torch.manual_seed(0)
    loss, rb = _high_level_setup()
    updater = LossUpdater(loss, rb, make_optimizers(loss))
    assert updater.run(0) is None
    means = updater.run(4)
    assert updater.num_updates == 4 and means["actor_updated"].item() == pytest.approx(0.5)
    state = updater.state_dict()
    other_loss, other_rb = _high_level_setup()
    other = LossUpdater(other_loss, other_rb, make_optimizers(other_loss))
    other.load_state_dict(state)
    assert other.num_updates == 4
    assert (
        other.optimizers["critic"].state_dict()["state"].keys()
        == state["optimizers"]["critic"]["state"].keys()
    )


def test_updater_stops_on_nan_before_changing_parameters():
    torch.manual_seed(0)
    loss, rb = _high_level_setup()
    rb.storage._storage["next", "reward"][:] = float("nan")
    updater = LossUpdater(loss, rb, make_optimizers(loss))
    before = _params(loss)
    with pytest.raises(NonFiniteLossError, match="non-finite loss"):
        updater.step()
    after = _params(loss)
    assert all(torch.equal(before[k], after[k]) for k in before if k != "update_count")
    with pytest.raises(ValueError, match="polyak"):
        LossUpdater(loss, rb, make_optimizers(loss), polyak=1.5)
    with pytest.raises(ValueError, match="optimizers"):
        LossUpdater(loss, rb, {"critic": None})


def test_loss_terms_equal_forward_with_the_decision_given():
    """``loss_terms(td, update_actor)`` (the entry point of LossUpdater and of the CUDA graphs) is ``forward``
    with the actor term switched; neither counts anything."""
    loss, rb = _high_level_setup(batch=16)
    data = rb.sample()
    state = {k: v.clone() for k, v in loss.state_dict().items()}
    for call in range(1, 5):
        update_actor = call % 2 == 0
        torch.manual_seed(call)
        out = loss(data)  # every term, every call
        torch.manual_seed(call)
        terms = loss.loss_terms(data, update_actor=update_actor)
        assert bool(out["actor_updated"]) and bool(terms["actor_updated"]) == update_actor
        assert terms.keys() == out.keys()
        for key in out.keys():
            if update_actor or key not in ("loss_actor", "actor_updated"):
                assert torch.equal(out[key], terms[key]), key
    assert state.keys() == loss.state_dict().keys()  # no count in the loss
    assert all(torch.equal(v, loss.state_dict()[k]) for k, v in state.items())


@pytest.mark.parametrize("interval", [1, 2, 3])
def test_updater_owns_the_delayed_actor_schedule_and_resumes_it(interval):
    torch.manual_seed(0)
    loss, rb = _high_level_setup()
    updater = LossUpdater(loss, rb, make_optimizers(loss), actor_update_interval=interval)
    flags = [bool(updater.step()["actor_updated"]) for _ in range(5)]
    assert flags == [k % interval == 0 for k in range(1, 6)]
    state = updater.state_dict()
    other_loss, other_rb = _high_level_setup()
    resumed = LossUpdater(other_loss, other_rb, make_optimizers(other_loss), actor_update_interval=interval)
    resumed.load_state_dict(state)
    assert resumed.actor_update_due() == (6 % interval == 0)
    assert [bool(resumed.step()["actor_updated"]) for _ in range(3)] == [k % interval == 0 for k in (6, 7, 8)]
    with pytest.raises(ValueError, match="actor_update_interval"):
        LossUpdater(loss, rb, make_optimizers(loss), actor_update_interval=0)


def test_old_checkpoints_with_the_loss_step_count_still_load():
    loss, _ = _high_level_setup()
    state = loss.state_dict()
    state["update_count"] = torch.tensor(7)  # written before the schedule moved to LossUpdater
    other, _ = _high_level_setup()
    other.load_state_dict(state)
    assert all(torch.equal(v, other.state_dict()[k]) for k, v in loss.state_dict().items())


def test_updater_cudagraphs_needs_a_cuda_loss():
    loss, rb = _high_level_setup()
    with pytest.raises(ValueError, match="needs the loss on a CUDA device"):
        LossUpdater(loss, rb, make_optimizers(loss), cudagraphs=True)


# ---------------------------------------------------------------- oracle distance
def _blocked_by_sampling(start, end, boxes, n=4001):
    t = torch.linspace(0, 1, n).view(1, n, 1)
    points = start.unsqueeze(1) + t * (end - start).unsqueeze(1)  # [P, n, d]
    inside = (points.unsqueeze(2) >= boxes[:, 0]) & (points.unsqueeze(2) <= boxes[:, 1])  # [P, n, W, d]
    return inside.all(-1).any(-1).any(-1)


def test_line_of_sight_matches_dense_sampling():
    torch.manual_seed(0)
    boxes = torch.tensor([[[1.0, -1.0], [2.0, 3.0]], [[-3.0, 2.0], [0.5, 2.5]], [[4.0, 4.0], [6.0, 4.2]]])
    oracle = LineOfSightDistance(0.5, boxes=boxes)
    start, end = torch.rand(400, 2) * 10 - 4, torch.rand(400, 2) * 10 - 4
    d = oracle(start, end)
    blocked = _blocked_by_sampling(start, end, boxes)
    free = ~blocked
    torch.testing.assert_close(d[free], (end - start)[free].norm(dim=-1) / 0.5)
    # dense sampling can miss a corner clip but never reports a false block
    assert (d[blocked] == 1e4).all()
    assert (d == 1e4).float().mean() >= blocked.float().mean()
    assert ((d == 1e4) & free).float().mean() < 0.01


def test_line_of_sight_axis_parallel_and_broadcast():
    wall = torch.tensor([[[1.0, -5.0], [2.0, 5.0]]])
    oracle = LineOfSightDistance(1.0, boxes=wall, margin=0.5)
    states = torch.tensor([[0.0, 0.0], [0.0, 6.0]])
    goals = torch.tensor([[3.0, 0.0], [3.0, 6.0], [0.0, 3.0]])
    d = oracle(states[:, None], goals[None])
    assert d.shape == (2, 3)
    # (0,0)->(3,0) crosses the wall; (0,6)->(3,6) passes 1 above it but inside the 0.5 margin? no: 6 > 5.5
    assert d[0, 0] == 1e4 and d[1, 1] == pytest.approx(3.0) and d[0, 2] == pytest.approx(3.0)
    with pytest.raises(ValueError, match="boxes"):
        LineOfSightDistance(1.0, boxes=torch.zeros(2, 2))
    with pytest.raises(ValueError, match="speed"):
        LineOfSightDistance(0.0)


def test_line_of_sight_builds_the_same_graph_under_reduced_precision_building():
    # the recipe's preset=cpu builds graphs with planner.build_dtype=bfloat16; the oracle has no network, so
    # with_autocast is the identity and the graph is the float32 one, bit for bit
    torch.manual_seed(0)
    boxes = torch.tensor([[[1.0, -1.0], [2.0, 3.0]], [[-3.0, 2.0], [0.5, 2.5]]])
    oracle = LineOfSightDistance(0.5, boxes=boxes, margin=0.2)
    assert oracle.with_autocast(torch.bfloat16) is oracle and oracle.with_autocast(None) is oracle
    candidates = torch.rand(300, 2) * 10 - 4
    graphs = []
    for dtype in (None, torch.bfloat16):
        graph = LandmarkGraph(cutoff=6.0, max_landmarks=40, early_stop=0.0, build_autocast_dtype=dtype)
        GraphPlanner(graph, oracle, goal_dim=2).build(candidates, candidates.clone())
        graphs.append(graph)
    assert graphs[0].num_landmarks == 40
    for key, value in graphs[0].state_dict().items():
        torch.testing.assert_close(graphs[1].state_dict()[key], value, rtol=0, atol=0)


# ---------------------------------------------------------------- FGS inside the env
def _line_planner():
    dist = lambda s, g: (g - s[..., :2]).norm(dim=-1) / 0.2  # noqa: E731
    planner = GraphPlanner(LandmarkGraph(cutoff=30.0, max_landmarks=20, early_stop=0.0), dist, goal_dim=2)
    ys = torch.linspace(0, 8, 41)
    line = torch.stack([torch.zeros_like(ys), ys], -1)  # covers PointMaze's test goal (0, 8)
    states = torch.cat([line, torch.zeros(41, 4)], -1)  # PointMaze observations: x, y, yaw, velocities
    return planner.build(states, line)


def test_goal_shift_on_reset_in_env():
    planner = _line_planner()
    fgs = FrontierGoalShifting(planner, noise=0.0, generator=torch.Generator().manual_seed(0))
    env = TransformedEnv(
        make_env("PointMaze", num_envs=3, seed=0, eval=True, max_episode_steps=5), GoalShiftOnReset(fgs)
    )
    check_env_specs(env)
    td = env.reset()
    assert td["goal_shifted"].all()  # the test goal (0, 8) is inside the graph
    for g in td["desired_goal"]:  # shifted goals are landmarks (noise 0)
        assert (planner.landmark_goals - g).norm(dim=-1).min() < 1e-5
    assert not torch.equal(td["desired_goal"], torch.tensor([0.0, 8.0]).expand(3, 2))
    rollout = env.rollout(5, auto_reset=False, tensordict=td)
    # the held goal replaces the env's goal at every step
    assert torch.equal(rollout["next", "desired_goal"], td["desired_goal"].unsqueeze(1).expand(3, 5, 2))
    # a partial reset shifts only the envs being reset
    held = rollout[:, -1]["next"].clone()
    planner.clear_graph()
    held["_reset"] = torch.tensor([[True], [False], [False]])
    out = env.reset(held)
    assert out["goal_shifted"].squeeze(-1).tolist() == [False, True, True]
    assert torch.equal(out["desired_goal"][1:], held["desired_goal"][1:])
    assert torch.equal(out["desired_goal"][0], torch.tensor([0.0, 8.0]))


def test_goal_shift_without_graph_keeps_goals_and_partial_reset():
    planner = GraphPlanner(LandmarkGraph(cutoff=30.0), lambda s, g: (g - s[..., :2]).norm(dim=-1), goal_dim=2)
    env = TransformedEnv(
        make_env("PointMaze", num_envs=2, seed=0, max_episode_steps=3),
        GoalShiftOnReset(FrontierGoalShifting(planner)),
    )
    td = env.reset()
    assert not td["goal_shifted"].any() and torch.equal(td["episode_goal"], td["desired_goal"])
    with pytest.raises(TypeError, match="FrontierGoalShifting"):
        GoalShiftOnReset(planner)


# ---------------------------------------------------------------- evaluation
def test_evaluate_final_vs_any_time_success():
    env = make_env("PointMaze", num_envs=2, seed=0, eval=True, max_episode_steps=4)
    goal = torch.tensor([0.0, 0.4])  # within the 2.5 success radius of the start
    td = env.reset(TensorDict({"desired_goal": goal.expand(2, 2)}, [2]))
    assert td["is_success"].all()
    still = lambda td: td.set("action", torch.zeros(*td.batch_size, 2))  # noqa: E731
    result = evaluate(env, still, max_steps=4)  # evaluate resets to the test goal (0, 8): never reached
    assert result.success == 0.0 and result.any_success == 0.0
    assert result.final_distance == pytest.approx(8.0, abs=0.5)
    assert result.rollout.shape == (2, 4)


def test_evaluate_last_steps_and_final_speed_on_a_crafted_rollout():
    """Two 12-step episodes: one passes through the goal ball and leaves it, one arrives and stays."""

    class Recorded:
        def __init__(self, rollout):
            self.recorded = rollout

        def rollout(self, max_steps, policy, break_when_any_done=False):
            return self.recorded

    t = torch.arange(12.0)
    ag = torch.stack(
        [torch.stack([t * 0.5, torch.zeros(12)], -1), torch.stack([t.clamp(max=6.0), t * 0], -1)], 0
    )
    nxt = torch.cat([ag[:, 1:], ag[:, -1:] + torch.tensor([[[0.5, 0.0]], [[0.0, 0.0]]])], 1)
    inside = torch.zeros(2, 12, 1, dtype=torch.bool)
    inside[0, 3:6] = True  # passes through the ball at steps 3-5
    inside[1, 5:] = True  # arrives at step 5 and stays
    rollout = TensorDict(
        {
            "achieved_goal": ag,
            ("next", "achieved_goal"): nxt,
            ("next", "desired_goal"): torch.full((2, 12, 2), 6.0),
            ("next", "is_success"): inside,
        },
        [2, 12],
    )
    result = evaluate(Recorded(rollout), None, max_steps=12)
    assert result.success == 0.5 and result.any_success == 1.0
    assert result.last_steps_success == pytest.approx(
        (3 + 7) / 20
    )  # of steps 2-11: 3-5 (ep. 0), 5-11 (ep. 1)
    assert result.final_speed == pytest.approx((0.5 + 0.0) / 2)
    assert evaluate(Recorded(rollout), None, 12, last_steps=3).last_steps_success == pytest.approx(3 / 6)


@pytest.mark.skipif(
    os.environ.get("MUJOCO_GL", "").lower() not in ("egl", "osmesa"),
    reason="offscreen rendering needs MUJOCO_GL=egl or osmesa (an OpenGL backend)",
)
def test_record_video(tmp_path):
    from PIL import Image

    from torchrl_dhrl.training import record_video

    env = make_env("PointMaze", num_envs=2, seed=0, eval=True, max_episode_steps=9)
    still = lambda td: td.set("action", torch.zeros(*td.batch_size, 2))  # noqa: E731
    path = record_video(TransformedEnv(env), still, 9, tmp_path / "episode.gif", every=4, size=64)
    with Image.open(path) as gif:
        assert gif.n_frames == 3 and gif.size == (64, 64)
