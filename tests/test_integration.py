"""End-to-end composition: env + HighLevelPolicy + GraphPlanner + low-level policy in a Collector,
relabelled replay, one SQGC and one high-level update, and a graph built from the learned distance."""

import torch
from tensordict.nn import TensorDictSequential
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage
from torchrl.envs import Compose, TransformedEnv

import torchrl_dhrl as dhrl


def test_full_dhrl_pipeline_on_pointmaze():
    torch.manual_seed(0)
    num_envs, steps = 2, 40
    env = dhrl.make_env("PointMaze", num_envs=num_envs, seed=0, max_episode_steps=25)
    obs_dim = env.observation_spec["observation"].shape[-1]
    high = dhrl.HighLevelPolicy(obs_dim, 2, [-2.0, -2.0], [10.0, 10.0], interval=5, num_cells=(32, 32))
    actor = dhrl.LowLevelActor(obs_dim, 2, env.action_spec, num_cells=(32, 32), goal_indices=(0, 1))
    pc, gc = (  # policy and graph critics, both seeing the relative goal (the old component default)
        dhrl.GoalConditionedCritic(
            obs_dim, 2, env.action_spec, num_cells=(32, 32), goal_key="goal", relative_goal=True, goal_indices=(0, 1)
        )
        for _ in range(2)
    )
    loss = dhrl.SQGCLoss(actor, pc, gc)
    distance = dhrl.GoalDistance.from_loss(loss)
    planner = dhrl.GraphPlanner(
        dhrl.LandmarkGraph(cutoff=30.0, max_landmarks=20, early_stop=0.0), distance, 2
    )
    env = TransformedEnv(env, Compose(high.make_primer(), planner.make_primer()))
    policy = TensorDictSequential(high, planner, dhrl.make_low_level_policy(actor))

    rb = dhrl.RelabelReplayBuffer(  # samples come out with hindsight goals and rewards
        storage=LazyTensorStorage(1000, ndim=2),
        relabel=[dhrl.FutureGoalRelabel(window=150, goal_key="waypoint")],
        batch_size=64,
    )
    collector = Collector(env, policy, frames_per_batch=num_envs * 20, total_frames=num_envs * steps)
    for i, batch in enumerate(collector):
        assert batch.shape == (num_envs, 20)
        # subgoals are held between issues, waypoints are always set
        assert batch["new_subgoal"].any() and not batch["new_subgoal"].all()
        assert torch.isfinite(batch["waypoint"]).all()
        rb.extend(batch.exclude("planner", ("next", "planner")))  # [num_envs, T]: time-major storage
        if i == 0:
            # rebuild the graph from buffer states with the learned distance
            data = rb[:].reshape(-1)
            planner.build(data["observation"], data["achieved_goal"])
            assert planner.has_graph and 2 <= planner.num_landmarks <= 20
    collector.shutdown()

    sample = rb.sample()
    out = loss(sample)
    total = out["loss_policy_qvalue"] + out["loss_graph_qvalue"] + out["loss_actor"]
    assert torch.isfinite(total)
    total.backward()
    grads = [p.grad for p in loss.parameters() if p.requires_grad and p.grad is not None]
    assert grads and any(g.abs().sum() > 0 for g in grads)
