"""GraphPlanner in the TorchRL transform patterns: standalone, replay buffer, composed, env, collector."""

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from torchrl.collectors import Collector
from torchrl.data import Composite, LazyTensorStorage, TensorDictReplayBuffer, Unbounded
from torchrl.envs import Compose, SerialEnv, StepCounter, TransformedEnv
from torchrl.envs.transforms import Transform
from torchrl.envs.utils import check_env_specs
from torchrl.testing.mocking_classes import ContinuousActionVecMockEnv

from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph
from torchrl_dhrl.planner.graph_planner import STATE_ENTRIES

SUBGOAL = (2.5, 2.5)


def euclidean(states, goals):
    return (goals - states[..., :2]).norm(dim=-1)


def grid_planner(**kwargs):
    """Landmarks on a 1-spaced grid of [-3, 3]^2; observations are 7-D (mock env), goals 2-D."""
    xs = torch.arange(-3.0, 3.5, 1.0)
    goals = torch.cartesian_prod(xs, xs)
    states = torch.cat([goals, torch.zeros(goals.shape[0], 5)], -1)
    planner = GraphPlanner(LandmarkGraph(cutoff=1.5), euclidean, 2, **kwargs)
    planner.graph.set_landmarks(states, goals, euclidean)
    return planner


def inputs(batch, seed=0):
    gen = torch.Generator().manual_seed(seed)
    obs = torch.randn(*batch, 7, generator=gen)
    return TensorDict(
        observation=obs,
        achieved_goal=obs[..., :2].clone(),
        subgoal=torch.rand(*batch, 2, generator=gen) * 6 - 3,
        new_subgoal=torch.ones(*batch, 1, dtype=torch.bool),
        batch_size=batch,
    )


class GoalKeys(Transform):
    """Test helper: ``achieved_goal = observation[..., :2]`` and a fixed ``subgoal`` (no new_subgoal flag)."""

    def __init__(self):
        super().__init__(in_keys=["observation"], out_keys=["achieved_goal", "subgoal"])

    def _call(self, next_tensordict):
        obs = next_tensordict["observation"]
        next_tensordict["achieved_goal"] = obs[..., :2].clone()
        next_tensordict["subgoal"] = (
            torch.tensor(SUBGOAL, device=obs.device).expand(*obs.shape[:-1], 2).clone()
        )
        return next_tensordict

    def _reset(self, tensordict, tensordict_reset):
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec):
        shape = observation_spec.shape
        observation_spec["achieved_goal"] = Unbounded((*shape, 2), device=observation_spec.device)
        observation_spec["subgoal"] = Unbounded((*shape, 2), device=observation_spec.device)
        return observation_spec


class HighLevel(TensorDictModuleBase):
    """Test helper: issues a random subgoal every ``every`` calls (counter in ``subgoal_step``)."""

    def __init__(self, every=3):
        super().__init__()
        self.every = every
        self.in_keys = ["subgoal", "subgoal_step"]
        self.out_keys = ["subgoal", "new_subgoal", "subgoal_step"]

    def forward(self, tensordict):
        step = tensordict.get("subgoal_step")
        issue = step % self.every == 0
        fresh = torch.rand(*step.shape[:-1], 2) * 6 - 3
        tensordict.set("subgoal", torch.where(issue, fresh, tensordict.get("subgoal")))
        tensordict.set("new_subgoal", issue)
        tensordict.set("subgoal_step", step + 1)
        return tensordict


def high_level_primer():
    from torchrl.envs import TensorDictPrimer

    spec = Composite(
        subgoal=Unbounded((2,)),
        new_subgoal=Unbounded((1,), dtype=torch.bool),
        subgoal_step=Unbounded((1,), dtype=torch.int64),
    )
    return TensorDictPrimer(spec, default_value=0.0, expand_specs=True)


low_level = TensorDictModule(
    lambda obs, wp: torch.cat([wp - obs[..., :2], torch.zeros(*obs.shape[:-1], 5)], -1).clamp(-1, 1),
    in_keys=["observation", "waypoint"],
    out_keys=["action"],
)


# ----------------------------------------------------------------------------- without env
@pytest.mark.parametrize("batch", [(), (4,), (6, 4)])
def test_no_env_batch_shapes(batch):
    planner = grid_planner()
    td = planner(inputs(batch))
    assert td["waypoint"].shape == (*batch, 2)
    assert td["planner", "path"].shape == (*batch, 32)
    assert td["planner", "budgets"].shape == (*batch, 33)
    for name in ("path_length", "index", "steps", "truncated", "has_plan", "graph_version"):
        assert td["planner", name].shape == (*batch, 1)
    assert td["planner", "has_plan"].all()
    flat = inputs(batch).reshape(-1)
    for i in range(flat.shape[0]):  # each row equals an unbatched call
        single = planner(flat[i].clone())
        assert torch.equal(single["waypoint"], td["waypoint"].reshape(-1, 2)[i])
        assert torch.equal(single["planner", "path"], td["planner", "path"].reshape(-1, 32)[i])


def test_missing_state_defaults_to_replanning_and_state_is_copied_not_aliased():
    planner = grid_planner()
    td = planner(inputs((3,)))
    before = td.clone()
    nxt = td.clone()
    nxt["new_subgoal"].zero_()
    planner._step(before, nxt)  # env mode: reads the root state, writes into "next"
    assert torch.equal(before["planner", "steps"], td["planner", "steps"])  # root left untouched
    moved_on = (nxt["planner", "index"] == 1) & (nxt["planner", "steps"] == 0)
    assert ((nxt["planner", "steps"] == 1) | moved_on).all()
    # without any tracking state (e.g. no primer), every row plans from scratch
    fresh = planner(inputs((3,)).exclude("new_subgoal"))
    assert fresh["planner", "has_plan"].all() and (fresh["planner", "steps"] == 0).all()
    assert torch.equal(fresh["planner", "path"], td["planner", "path"])


def test_inside_a_replay_buffer():
    planner = grid_planner()
    data = planner(inputs((10,)))
    data["new_subgoal"].zero_()
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(10), batch_size=5)
    rb.append_transform(grid_planner())  # a copy with the same graph
    rb.extend(data)
    sample = rb.sample()
    expected = planner(data[sample["index"]].exclude("index", "waypoint"))
    assert torch.equal(sample["waypoint"], expected["waypoint"])
    assert torch.equal(sample["planner", "steps"], expected["planner", "steps"])


def test_composed_in_compose_and_tensordict_sequential():
    planner = grid_planner()
    td = inputs((4,))
    composed = Compose(planner)
    assert torch.equal(composed(td.clone())["waypoint"], planner(td.clone())["waypoint"])
    policy = TensorDictSequential(HighLevel(every=1), planner, low_level)
    td = td.exclude("subgoal", "new_subgoal").set("subgoal_step", torch.zeros(4, 1, dtype=torch.int64))
    td.set("subgoal", torch.zeros(4, 2))
    out = policy(td)
    assert out["action"].shape == (4, 7) and out["new_subgoal"].all() and out["planner", "has_plan"].all()
    assert "waypoint" in policy.out_keys and "observation" in policy.in_keys


# ----------------------------------------------------------------------------- env mode
def make_env_mode_env(planner, batched=False):
    def base():
        return TransformedEnv(ContinuousActionVecMockEnv(), GoalKeys())

    env = SerialEnv(2, base) if batched else base()
    return TransformedEnv(env, Compose(StepCounter(max_steps=4), planner))


@pytest.mark.parametrize("batched", [False, True])
def test_env_mode_check_env_specs_and_rollout(batched):
    planner = grid_planner()
    env = make_env_mode_env(planner, batched)
    check_env_specs(env)
    td = env.reset()
    assert td["planner", "has_plan"].all() and "waypoint" in td.keys()
    rollout = env.rollout(8, break_when_any_done=False)
    steps, index = rollout["next", "planner", "steps"], rollout["next", "planner", "index"]
    prev_steps, prev_index = rollout["planner", "steps"], rollout["planner", "index"]
    # every step spends one more step on the waypoint unless the tracker moved on (or replanned at reset)
    moved = (index != prev_index) | (rollout["next", "step_count"] == 0)
    assert ((steps == prev_steps + 1) | moved).all()
    assert (rollout["planner", "graph_version"] == 1).all()
    wp = rollout["next", "waypoint"]
    on_path = rollout["next", "planner", "index"] < rollout["next", "planner", "path_length"]
    assert torch.equal(wp[~on_path.squeeze(-1)], torch.tensor(SUBGOAL).expand_as(wp)[~on_path.squeeze(-1)])


def test_env_mode_on_the_outer_parallel_env():
    from torchrl.envs import ParallelEnv

    planner = grid_planner()
    env = TransformedEnv(
        ParallelEnv(
            2, lambda: TransformedEnv(ContinuousActionVecMockEnv(), GoalKeys()), mp_start_method="fork"
        ),
        Compose(StepCounter(max_steps=4), planner),
    )
    try:
        check_env_specs(env)
        rollout = env.rollout(6, break_when_any_done=False)
        assert rollout["next", "planner", "has_plan"].all() and rollout["next", "waypoint"].shape == (2, 6, 2)
    finally:
        env.close()


def test_env_mode_partial_reset_only_replans_reset_rows():
    planner = grid_planner()
    env = make_env_mode_env(planner, batched=True)
    td = env.reset()
    td = env.rand_step(td)
    from torchrl.envs.utils import step_mdp

    td = step_mdp(td)
    before = td.clone()
    td["_reset"] = torch.tensor([[True], [False]])
    reset = env.reset(td)
    assert torch.equal(reset["planner", "steps"][1], before["planner", "steps"][1])
    assert reset["planner", "steps"][0].item() == 0 and reset["planner", "has_plan"].all()


# ----------------------------------------------------------------------------- policy mode
def make_policy_mode_env(planner):
    env = TransformedEnv(
        ContinuousActionVecMockEnv(),
        Compose(GoalKeys(), StepCounter(max_steps=5), high_level_primer(), planner.make_primer()),
    )
    return env


def test_policy_mode_primer_carries_state_and_resets():
    planner = grid_planner()
    env = make_policy_mode_env(planner)
    check_env_specs(env)
    policy = TensorDictSequential(HighLevel(every=3), planner, low_level)
    rollout = env.rollout(12, policy, break_when_any_done=False)
    # the state written by the policy at t is what the policy reads at t + 1 (carried by the primer,
    # zeroed across resets): without a new subgoal, the plan of t + 1 is the plan of t, one step on
    carried = ~rollout["next", "done"][:-1].squeeze(-1) & ~rollout["new_subgoal"][1:].squeeze(-1)
    assert carried.sum() >= 4
    for name in ("path", "path_length", "budgets"):
        assert torch.equal(
            rollout["next", "planner", name][:-1][carried], rollout["planner", name][1:][carried]
        )
    prev_steps = rollout["next", "planner", "steps"][:-1][carried]
    prev_index = rollout["next", "planner", "index"][:-1][carried]
    steps, index = rollout["planner", "steps"][1:][carried], rollout["planner", "index"][1:][carried]
    assert (
        ((steps == prev_steps + 1) & (index == prev_index)) | ((steps == 0) & (index == prev_index + 1))
    ).all()
    # replans exactly when a new subgoal is issued (or after a reset)
    replanned = (rollout["planner", "steps"] == 0) & (rollout["planner", "index"] == 0)
    assert (replanned | ~rollout["new_subgoal"]).all()
    assert rollout["planner", "has_plan"].all()
    # after the reset (step_count 0 at t = 5, 10) the primer zeroed the state -> a fresh plan
    first_after_reset = rollout["step_count"].squeeze(-1) == 0
    assert first_after_reset.sum() >= 2
    assert (rollout["planner", "index"][first_after_reset] == 0).all()


def test_primer_is_found_in_the_policy():
    from torchrl.modules.utils import get_primers_from_module

    planner = grid_planner()
    primer = get_primers_from_module(TensorDictSequential(HighLevel(), planner, low_level), warn=False)
    keys = set(primer.primers.keys(True, True))
    assert keys == {("planner", name) for name in STATE_ENTRIES}


def test_policy_mode_with_collector():
    planner = grid_planner()
    env = make_policy_mode_env(planner)
    policy = TensorDictSequential(HighLevel(every=2), planner, low_level)
    collector = Collector(env, policy, frames_per_batch=6, total_frames=12)
    batches = list(collector)
    collector.shutdown()
    assert len(batches) == 2
    for batch in batches:
        assert batch["waypoint"].shape == (6, 2) and batch["planner", "has_plan"].all()
        assert torch.isfinite(batch["waypoint"]).all()
    # the tracking state continues across the collector's batches (t = 5 -> 6, same episode, no new subgoal)
    last, first = batches[0][-1], batches[1][0]
    assert not last["next", "done"].any() and not first["new_subgoal"].any()
    for name in ("path", "path_length", "budgets"):
        assert torch.equal(last["next", "planner", name], first["planner", name])
    steps, index = first["planner", "steps"].item(), first["planner", "index"].item()
    prev_steps, prev_index = last["next", "planner", "steps"].item(), last["next", "planner", "index"].item()
    assert (steps, index) in ((prev_steps + 1, prev_index), (0, prev_index + 1))
