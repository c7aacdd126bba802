"""CUDA runs of the components and the recipe, checked against the same computation on CPU.

The CPU code paths are verified against independent references (numpy FPS, networkx Dijkstra, manual TD3
targets, ground-truth trajectories) in the other test modules; here every component runs on CUDA with the
same inputs and must give the CPU answer, and the recipe runs every phase with ``device=cuda``, resumes on
CUDA and resumes a CUDA checkpoint on CPU. Skipped where no CUDA device exists (CI's machine).
"""

import copy
import shutil
import warnings

import pytest
import torch
from _recipe import load_recipe, recipe_config
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from tests.data.test_future_goals import GoalStream, check_goals
from tests.planner.test_fps import asymmetric_distance, make_candidates
from tests.planner.test_graph_planner import assert_same_collection
from tests.recipe.test_recipe_script import _flat
from torchrl_dhrl.data import FutureGoalRelabel, RelabelReplayBuffer
from torchrl_dhrl.modules import GoalConditionedCritic, HighLevelPolicy, LowLevelActor
from torchrl_dhrl.objectives import HighLevelLoss, SQGCLoss, make_optimizers
from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph, farthest_point_sampling
from torchrl_dhrl.recipe import load_checkpoint
from torchrl_dhrl.training import LossUpdater, NonFiniteLossError

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
]
CUDA = torch.device("cuda")
recipe = load_recipe()
SMOKE = ("env=PointMaze", "preset=smoke", "logger.backend=csv", "plots.every_epochs=0")


@pytest.fixture(autouse=True)
def _no_target_warning():
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="No target network updater")
        yield


def _on(device, *tensors):
    return [t.to(device) for t in tensors]


@pytest.mark.parametrize("strategy", ["dense", "lazy"])
def test_farthest_point_sampling_matches_cpu(strategy):
    states, goals = make_candidates(1500, seed=0)
    expected = farthest_point_sampling(
        states, goals, asymmetric_distance, 200, early_stop=2.0, strategy=strategy
    )
    got = farthest_point_sampling(
        *_on(CUDA, states, goals), asymmetric_distance, 200, early_stop=2.0, strategy=strategy
    )
    assert got.indices.device.type == "cuda"
    assert got.indices.cpu().tolist() == expected.indices.tolist()
    torch.testing.assert_close(got.radius.cpu(), expected.radius, rtol=1e-5, atol=1e-5)


def test_landmark_graph_plans_match_cpu():
    gen = torch.Generator().manual_seed(0)
    points = torch.rand(200, 2, generator=gen) * 20
    states = torch.rand(64, 2, generator=gen) * 22 - 1
    subgoals = torch.rand(64, 2, generator=gen) * 30 - 5
    plans = []
    for device in ("cpu", CUDA):
        graph = LandmarkGraph(cutoff=3.0)
        p = points.to(device)
        graph.set_landmarks(p, p.clone(), asymmetric_distance)
        plans.append(graph.plan(*_on(device, states, subgoals), asymmetric_distance))
    cpu, gpu = plans
    assert gpu.path.device.type == "cuda"
    assert torch.equal(gpu.reachable.cpu(), cpu.reachable) and torch.equal(gpu.length.cpu(), cpu.length)
    assert cpu.reachable.any() and not cpu.reachable.all()
    torch.testing.assert_close(gpu.cost.cpu(), cpu.cost, rtol=1e-5, atol=1e-4)
    for row in range(len(states)):
        n = cpu.length[row]
        assert torch.equal(gpu.path[row, :n].cpu(), cpu.path[row, :n])


def test_graph_planner_transform_on_cuda_matches_cpu():
    states, goals = make_candidates(800, seed=1)
    obs = torch.rand(16, 5) * 20
    td = TensorDict(
        observation=obs,
        achieved_goal=obs[:, :2].clone(),
        subgoal=torch.rand(16, 2) * 20,
        new_subgoal=torch.ones(16, 1, dtype=torch.bool),
        batch_size=[16],
    )
    outs = []
    for device in ("cpu", CUDA):
        planner = GraphPlanner(
            LandmarkGraph(cutoff=4.0, max_landmarks=60, early_stop=0.0), asymmetric_distance, 2
        ).to(device)
        planner.build(*_on(device, states, goals))
        out = planner(td.to(device))
        outs.append(out)
        assert out["waypoint"].device.type == torch.device(device).type
    torch.testing.assert_close(outs[1]["waypoint"].cpu(), outs[0]["waypoint"], rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("fixed_size", [False, True])
def test_capturable_planner_replayed_as_a_cuda_graph_tracks_like_the_planner(fixed_size):
    """``GraphPlanner(capturable=True)`` captured in a CUDA graph (inputs copied into static tensors before
    each replay): the waypoints and tracking state of the host-branching planner, step by step; on a
    ``fixed_size`` graph also across rebuilds to other landmark counts and a clear after the capture."""
    from tests.planner.test_graph_planner import _assert_same_tracking, _planner_pair, _step_td, _walk

    gen = torch.Generator().manual_seed(5)
    graph, planner, capturable = _planner_pair(asymmetric_distance, fixed_size=fixed_size)
    graph.to(CUDA)

    def rebuild(num):
        points = (torch.rand(num, 2, generator=gen) * 12 - 2).to(CUDA)
        states = torch.cat([points, torch.zeros_like(points)], -1)
        graph.set_landmarks(states, points, asymmetric_distance) if num else graph.clear()

    rebuild(40)
    walk = list(_walk(gen, (8,), 30))
    theirs = planner(_step_td(TensorDict(batch_size=[8]), *walk[0]).to(CUDA))
    static = theirs.clone()
    stream = torch.cuda.Stream()
    stream.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(stream):
        for _ in range(3):  # warm-up before the capture
            capturable(static.clone())
    torch.cuda.current_stream().wait_stream(stream)
    # the captured input tensors, in a structure of their own (the call replaces static's entries by its outputs)
    inputs = static.apply(lambda tensor: tensor)
    cuda_graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(cuda_graph):
        out = capturable(static)
    for t, (obs, new, subgoal) in enumerate(walk[1:]):
        if fixed_size and t in (8, 16, 22):  # the captured graph reads the rebuilt graph
            rebuild({8: 25, 16: 0, 22: 57}[t])
        step = _step_td(theirs, obs.to(CUDA), new.to(CUDA), subgoal.to(CUDA))
        inputs.update_(step.select(*inputs.keys(True, True)))
        cuda_graph.replay()
        theirs = planner(step)
        _assert_same_tracking(out.clone(), theirs, planner, exact=False)


def _cuda_agent(capturable_planner):
    from torchrl_dhrl.factory import make_agent, make_environment

    torch.manual_seed(0)
    env = make_environment("PointMaze", CUDA, num_envs=4, seed=0, max_episode_steps=30)
    agent = make_agent(
        env,
        CUDA,
        goal_indices=[0, 1],
        high_policy={
            "subgoal_low": [-2.0, -2.0],
            "subgoal_high": [10.0, 10.0],
            "interval": 5,
            "num_cells": (32,),
        },
        high_critic={"num_cells": (32,)},
        low_actor={"num_cells": (32,), "relative_goal": False},
        low_critic={"num_cells": (32,)},
        capturable_planner=capturable_planner,
    )
    return agent, make_environment("PointMaze", CUDA, num_envs=4, seed=0, max_episode_steps=30, agent=agent)


def test_cudagraph_policy_collects_what_the_eager_policy_does():
    """The collector's ``cudagraph_policy``: the acting policy captured before the graph has landmarks (a reserved
    fixed-size graph) replays the eager policy's plans and actions (exploration off) over three episodes, with
    the graph built after the first and rebuilt after the second (read in place by the captured graph)."""
    from torchrl.envs.utils import ExplorationType

    from torchrl_dhrl.factory import make_collector

    batches = {}
    for captured in (False, True):
        agent, env = _cuda_agent(True)
        collector = make_collector(env, agent, 30, cudagraph_policy={"warmup": 2} if captured else False)
        collector.exploration_type = ExplorationType.DETERMINISTIC
        gen = torch.Generator().manual_seed(3)
        out = []
        for i, batch in enumerate(collector):
            out.append(batch.clone())
            if i == 2:
                break
            points = (torch.rand(40 + 10 * i, 4, generator=gen) * 12 - 2).to(CUDA)
            agent.planner.build(points, points[:, :2])
        collector.shutdown()
        batches[captured] = torch.cat(out, 1)
        if captured:
            assert agent.planner.graph.num_landmarks > 0
    assert_same_collection(batches[True], batches[False])


def test_captured_eval_policy_evaluates_like_the_eager_policy():
    """``make_eval_policy(cudagraph_policy=True)``: the test episodes acted by the policy captured in the first
    evaluation are those of the eager policy, before the graph has landmarks, after its first build and after a
    rebuild (each evaluation from the same env state)."""
    from torchrl_dhrl.factory import make_environment, make_eval_policy
    from torchrl_dhrl.training import evaluate

    agent, _ = _cuda_agent(True)
    eval_env = make_environment("PointMaze", CUDA, num_envs=3, eval=True, max_episode_steps=30, agent=agent)
    captured = make_eval_policy(agent, cudagraph_policy=True)
    assert captured is not agent.policy
    gen = torch.Generator().manual_seed(4)
    for i in range(3):
        if i:
            points = (torch.rand(30 + 20 * i, 4, generator=gen) * 12 - 2).to(CUDA)
            agent.planner.build(points, points[:, :2])
        state = eval_env.base_env.state_dict()
        eager = evaluate(eval_env, agent.policy, 30)
        eval_env.base_env.load_state_dict(state)
        replayed = evaluate(eval_env, captured, 30)
        assert replayed.success == eager.success and replayed.any_success == eager.any_success
        for key in (("next", "observation"), "action", "waypoint", "subgoal"):
            torch.testing.assert_close(
                replayed.rollout[key], eager.rollout[key], rtol=1e-4, atol=1e-4, msg=f"{key} ({i})"
            )


def _low_nets():
    torch.manual_seed(0)
    actor = LowLevelActor(6, 2, action_max=2.0, action_dim=3, num_cells=(64, 64), goal_indices=(0, 1))
    kw = dict(action_max=2.0, action_dim=3, num_cells=(64, 64), gamma=0.99, relative_goal=True, goal_indices=(0, 1))
    return SQGCLoss(
        actor, GoalConditionedCritic(6, 2, **kw), GoalConditionedCritic(6, 2, **kw), target_noise_std=0.0
    )


def _low_batch(n=256):
    g = torch.Generator().manual_seed(1)
    return TensorDict(
        {
            "observation": torch.randn(n, 6, generator=g) * 3,
            "action": torch.rand(n, 3, generator=g) * 4 - 2,
            "goal": torch.randn(n, 2, generator=g) * 3,
            "graph_goal": torch.randn(n, 2, generator=g) * 3,
            ("next", "observation"): torch.randn(n, 6, generator=g) * 3,
            ("next", "reward"): -(torch.rand(n, 1, generator=g) > 0.2).float(),
            ("next", "graph_reward"): -torch.ones(n, 1),
            ("next", "terminated"): torch.zeros(n, 1, dtype=torch.bool),
        },
        [n],
    )


def _losses_and_grads(loss, data, keys):
    out = loss(data)
    total = sum(out[k] for k in keys)
    loss.zero_grad()
    total.backward()
    grads = {n: p.grad.detach().cpu() for n, p in loss.named_parameters() if p.grad is not None}
    return {k: out[k].detach().cpu() for k in keys}, grads


def test_sqgc_loss_on_cuda_matches_cpu():
    cpu = _low_nets()
    gpu = copy.deepcopy(cpu).to(CUDA)
    keys = ("loss_policy_qvalue", "loss_graph_qvalue", "loss_actor")
    data = _low_batch()
    out_cpu, grads_cpu = _losses_and_grads(cpu, data, keys)
    out_gpu, grads_gpu = _losses_and_grads(gpu, data.to(CUDA), keys)
    for k in keys:
        torch.testing.assert_close(out_gpu[k], out_cpu[k], rtol=1e-4, atol=1e-4)
    assert grads_cpu.keys() == grads_gpu.keys() and grads_cpu
    for name in grads_cpu:
        torch.testing.assert_close(grads_gpu[name], grads_cpu[name], rtol=1e-3, atol=1e-4, msg=name)


def test_high_level_loss_on_cuda_matches_cpu():
    torch.manual_seed(0)
    low, high = torch.tensor([-4.0, -4.0]), torch.tensor([20.0, 20.0])
    policy = HighLevelPolicy(5, 2, low, high, interval=10, num_cells=(64, 64))
    critic = GoalConditionedCritic(
        5, 2, action_low=low, action_high=high, relative_goal=False, goal_key="desired_goal",
        action_key="subgoal", num_cells=(64, 64), gamma=0.99,
    )  # fmt: skip
    cpu = HighLevelLoss(policy.actor, critic, target_noise_std=0.0, action_l2=0.01)
    gpu = copy.deepcopy(cpu).to(CUDA)
    g = torch.Generator().manual_seed(2)
    data = TensorDict(
        {
            "observation": torch.randn(128, 5, generator=g) * 5,
            "desired_goal": torch.rand(128, 2, generator=g) * 20,
            "subgoal": low + (high - low) * torch.rand(128, 2, generator=g),
            ("next", "observation"): torch.randn(128, 5, generator=g) * 5,
            ("next", "reward"): -torch.ones(128, 1),
        },
        [128],
    )
    keys = ("loss_qvalue", "loss_actor")
    out_cpu, grads_cpu = _losses_and_grads(cpu, data, keys)
    out_gpu, grads_gpu = _losses_and_grads(gpu, data.to(CUDA), keys)
    for k in keys:
        torch.testing.assert_close(out_gpu[k], out_cpu[k], rtol=1e-4, atol=1e-4)
    for name in grads_cpu:
        torch.testing.assert_close(grads_gpu[name], grads_cpu[name], rtol=1e-3, atol=1e-4, msg=name)


def _updater_run(cudagraphs, steps=13, nan=False, autocast_dtype=None):
    loss = _low_nets().to(CUDA)  # seeds the global RNG: both runs sample the same batches
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(256, device=CUDA), batch_size=64)
    data = _low_batch(200)
    if nan:
        data["next", "reward"][:] = float("nan")
    rb.extend(data.to(CUDA))
    updater = LossUpdater(
        loss,
        rb,
        make_optimizers(loss),
        target_update_interval=3,
        cudagraphs=cudagraphs,
        autocast_dtype=autocast_dtype,
        actor_after_critic_step=False,
    )
    return loss, updater, updater.run(steps)


def test_bfloat16_updates_on_cuda_track_float32():
    """``autocast_dtype=torch.bfloat16`` on CUDA: the hidden layers run in bf16, parameters stay float32,
    and the losses follow the float32 run's (same seeds, same batches)."""
    _, _, full = _updater_run(False)
    dtypes = set()
    loss, updater, mixed = _updater_run(False, autocast_dtype=torch.bfloat16)
    layer = loss.policy_critic.module.ensemble.layers[0]
    hook = layer.register_forward_hook(lambda mod, args, out: dtypes.add(out.dtype))
    updater.step()
    hook.remove()
    assert dtypes == {torch.bfloat16}
    assert all(v.dtype == torch.float32 for v in loss.state_dict().values() if v.is_floating_point())
    for key in ("loss_policy_qvalue", "loss_graph_qvalue", "policy_q", "graph_q"):
        assert torch.isfinite(mixed[key])
        torch.testing.assert_close(mixed[key], full[key], rtol=2e-2, atol=1e-3, msg=key)


def test_cudagraph_updates_match_eager_updates():
    eager_loss, eager, eager_means = _updater_run(False)
    graph_loss, graph, graph_means = _updater_run(True)
    assert set(graph._graphs) == {False, True}  # both graphs captured (3 eager warm-up calls each)
    assert graph.num_updates == eager.num_updates == 13
    for key in eager_means.keys():
        torch.testing.assert_close(graph_means[key], eager_means[key], rtol=1e-4, atol=1e-5, msg=key)
    eager_state, graph_state = eager_loss.state_dict(), graph_loss.state_dict()
    for key, value in eager_state.items():  # online and target networks after 13 updates (4 target updates)
        torch.testing.assert_close(graph_state[key], value, rtol=1e-4, atol=1e-5, msg=key)
    # a resumed updater (eager optimiser state) captures again and keeps training
    _, resumed, _ = _updater_run(True, steps=1)
    resumed.load_state_dict(eager.state_dict())
    assert not resumed._graphs and torch.isfinite(resumed.run(6)["loss_policy_qvalue"])
    with pytest.raises(NonFiniteLossError, match="non-finite"):
        _updater_run(True, steps=8, nan=True)


def test_bfloat16_cudagraph_updates_match_eager_bfloat16_updates():
    """``cudagraphs=True`` with ``autocast_dtype=torch.bfloat16``: the captured update (autocast without its
    weight cache) follows the eager bf16 updater's losses and parameters, and really runs bf16."""
    eager_loss, _, eager_means = _updater_run(False, autocast_dtype=torch.bfloat16)
    graph_loss, graph, graph_means = _updater_run(True, autocast_dtype=torch.bfloat16)
    assert set(graph._graphs) == {False, True}
    for key in eager_means.keys():
        torch.testing.assert_close(graph_means[key], eager_means[key], rtol=1e-3, atol=1e-4, msg=key)
    for key, value in eager_loss.state_dict().items():
        torch.testing.assert_close(graph_loss.state_dict()[key], value, rtol=1e-3, atol=1e-4, msg=key)
    dtypes = set()
    layer = graph_loss.policy_critic.module.ensemble.layers[0]
    hook = layer.register_forward_hook(lambda mod, args, out: dtypes.add(out.dtype))
    graph._graphs = {}  # captured again with the hook: the capture runs the Python forward
    graph.run(4)
    hook.remove()
    assert dtypes == {torch.bfloat16}


def test_capturable_sampler_replayed_as_a_cuda_graph_sees_later_writes():
    """The capture-safe sampler captured alone in a CUDA graph: every replay draws from the rows written so far
    (the device counters move in place) and relabels within the ground-truth windows, seam included."""
    from tests.data.test_relabel_buffer import _filled_buffer

    rb, relabel, stream = _filled_buffer(3, 40, 1, 10, window=9, seed=3, device=CUDA)
    sample = rb.capturable_sampler(batch_size=512)
    for _ in range(3):  # warm-up calls before the capture
        sample()
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        out = sample()
    seen_new_rows = False
    for write in range(1, 9):  # fills the 40 rows at write 4, then wraps
        rb.extend(stream.batch(10).to(CUDA))
        graph.replay()
        batch = out.clone().cpu()
        time = batch["index"][:, 0]
        assert int(time.max()) < min(10 * (write + 1), 40)
        seen_new_rows |= write == 3 and int(time.max()) >= 30
        window = stream.expected_window(batch["achieved_goal"], 9)
        assert torch.equal(
            relabel.window_lengths(batch["index"].to(CUDA), rb.storage, rb.newest_index).cpu(), window
        )
        check_goals(batch, "graph_goal", window)
    assert seen_new_rows


def test_cudagraph_updates_capture_sampling():
    """``cudagraphs=True`` on the low-level buffer: the graphs sample themselves and train (finite losses, moved
    parameters, both graphs), and after new writes keep training on them."""
    from tests.data.test_relabel_buffer import _filled_buffer
    from tests.training.test_updates import _loss

    loss = _loss().to(CUDA)
    start = {k: v.clone() for k, v in loss.state_dict().items()}
    rb, _, stream = _filled_buffer(2, 50, 3, 10, window=6, seed=0, device=CUDA)
    updater = LossUpdater(
        loss,
        rb,
        make_optimizers(loss),
        target_update_interval=3,
        cudagraphs=True,
        actor_after_critic_step=False,
    )
    means = updater.run(10)
    assert updater.sampling_captured and set(updater._graphs) == {False, True}
    rb.extend(stream.batch(10).to(CUDA))
    means2 = updater.run(10)
    for out in (means, means2):
        assert all(bool(torch.isfinite(v)) for k, v in out.items() if k.startswith("loss_"))
    assert sum(not torch.equal(v, start[k]) for k, v in loss.state_dict().items()) > 4


def test_compiled_cudagraph_updates_match_eager_updates():
    """``compile=True cudagraphs=True``: compiled kernels captured in the graphs, sampling captured too; after 16
    updates the parameters follow an eager updater fed by the same capture-safe sampler (random draws inside
    the graphs come from the graph-safe Philox stream, so the batches differ: statistics, not bits)."""
    from tests.training.test_updates import _capture_run, _loss

    graph_loss, graph, graph_outs = _capture_run(graphs=True, compile_=True, steps=16, device=CUDA)
    _, _, eager_outs = _capture_run(graphs=False, steps=16, device=CUDA)
    assert graph.sampling_note == "sampling and relabelling captured, compiled"
    assert set(graph._graphs) == {False, True}
    for graph_means, eager_means in zip(graph_outs, eager_outs, strict=True):
        for key in ("loss_policy_qvalue", "loss_graph_qvalue"):
            assert torch.isfinite(graph_means[key])
            torch.testing.assert_close(graph_means[key], eager_means[key], rtol=0.5, atol=0.05, msg=key)
    assert (
        sum(not torch.equal(v, _loss().to(CUDA).state_dict()[k]) for k, v in graph_loss.state_dict().items())
        > 4
    )


def test_updates_captured_together_on_cuda():
    """``updates_per_graph=5``: five updates per replay (sampling and the Polyak step inside), four patterns over
    20 updates; the losses follow single-update graphs' (statistics: the graphs' Philox draws are arranged
    differently, so the batches differ)."""
    from tests.training.test_updates import _capture_run, _loss

    chunk_loss, chunk, chunk_outs = _capture_run(graphs=True, steps=20, device=CUDA, updates_per_graph=5)
    _, single, single_outs = _capture_run(graphs=True, steps=20, device=CUDA)
    assert len(chunk._chunk_graphs) == 4 and chunk.num_updates == single.num_updates == 20
    for chunk_means, single_means in zip(chunk_outs, single_outs, strict=True):
        for key in ("loss_policy_qvalue", "loss_graph_qvalue"):
            assert torch.isfinite(chunk_means[key])
            torch.testing.assert_close(chunk_means[key], single_means[key], rtol=0.5, atol=0.05, msg=key)
    start = _loss().to(CUDA).state_dict()
    assert sum(not torch.equal(v, start[k]) for k, v in chunk_loss.state_dict().items()) > 4


@pytest.mark.recipe
def test_recipe_with_cudagraphs(tmp_path, capsys):
    summary = recipe.train(
        recipe_config(*SMOKE, "device=cuda", "cudagraphs=true", "total_steps=240"), run_dir=tmp_path
    )
    assert 0.0 <= summary["eval/success"] <= 1.0
    printed = capsys.readouterr().out
    assert "Sampling, low level: sampling and relabelling captured." in printed
    assert "Sampling, high level: capture_sampling=False." in printed  # high.capture_sampling: false by default
    recipe.train(
        recipe_config(  # resumed with ten low-level updates per replay and the acting policy captured
            *SMOKE,
            "device=cuda",
            "cudagraphs=true",
            "updates_per_graph=10",
            "cudagraph_policy=true",
            "high.capture_sampling=null",
            "total_steps=480",
            f"resume={tmp_path}",
        ),
        run_dir=tmp_path,
    )
    assert load_checkpoint(tmp_path)["counters"]["env_steps"] == 480
    printed = capsys.readouterr().out
    assert "Acting: the policy captured as CUDA graphs" in printed
    assert "Sampling, high level: sampling and relabelling captured." in printed  # the gradual penalty's query too


def test_future_goal_relabel_on_a_cuda_buffer():
    torch.manual_seed(0)
    stream = GoalStream(num_envs=4, min_len=5, max_len=40, seed=1)
    relabel = FutureGoalRelabel(window=7)
    rb = RelabelReplayBuffer(
        storage=LazyTensorStorage(4 * 64, ndim=2, device=CUDA), relabel=[relabel], batch_size=1024
    )
    for _ in range(6):
        rb.extend(stream.batch(16))
        sample = rb.sample()
        assert sample["goal"].device.type == "cuda"
        sample = sample.cpu()
        expected = stream.expected_window(sample["achieved_goal"], 7)
        window = relabel.window_lengths(sample["index"].to(CUDA), rb.storage, rb.newest_index)
        assert torch.equal(window.cpu(), expected)
        for key in ("goal", "graph_goal"):
            check_goals(sample, key, expected)


@pytest.mark.recipe
def test_recipe_every_phase_on_cuda_resumes_on_cuda_and_on_cpu(tmp_path):
    torch.manual_seed(0)
    run = tmp_path / "cuda"
    summary = recipe.train(recipe_config(*SMOKE, "device=cuda", "total_steps=240"), run_dir=run)
    assert 0.0 <= summary["eval/success"] <= 1.0
    state = load_checkpoint(run)  # maps to CPU by default
    assert state["counters"]["env_steps"] == 240 and state["counters"]["graph_builds"] >= 1
    tensors = _flat(state["agent"])
    assert tensors and all(t.device.type == "cpu" for t in tensors.values())
    # resume on CUDA and, from a copy of the same checkpoint, on CPU
    cpu_run = tmp_path / "cpu"
    cpu_run.mkdir()
    shutil.copytree(run / "checkpoint", cpu_run / "checkpoint")
    recipe.train(recipe_config(*SMOKE, "device=cuda", "total_steps=480", f"resume={run}"), run_dir=run)
    recipe.train(recipe_config(*SMOKE, "device=cpu", "total_steps=480", f"resume={cpu_run}"), run_dir=cpu_run)
    for path in (run, cpu_run):
        assert load_checkpoint(path)["counters"]["env_steps"] == 480
