"""GraphPlanner: waypoint tracking, replanning, checkpoints and the composed landmark graph; the TorchRL
transform patterns (standalone, replay buffer, composed, env, collector); the capturable tracker
(``GraphPlanner(capturable=True)``: it plans every env and keeps the new plans where a replan is due, so that
the acting policy compiles as one graph), whose waypoints and state equal the host-branching tracker's over
random walks with new subgoals, rebuilds and partial resets, and which ``torch.compile(fullgraph=True)``
traces."""

import io
import math

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

from tests.planner.test_distances import LATTICE, STATES, manhattan
from tests.planner.test_graph import (
    DISTANCES,
    _set_random_landmarks,
    line_of_sight_distance,
    u_maze_candidates,
)
from torchrl_dhrl.planner import GraphPlanner, LandmarkGraph
from torchrl_dhrl.planner.graph_planner import STATE_ENTRIES

INF = math.inf


def euclidean(states, goals):
    return (goals - states[..., :2]).norm(dim=-1)


def line_planner(max_path_length=32, **kwargs):
    """Six landmarks on the x axis at 0, 1, ..., 5, one unit (= one step) apart."""
    planner = GraphPlanner(LandmarkGraph(cutoff=1.5), euclidean, 2, max_path_length=max_path_length, **kwargs)
    points = torch.stack([torch.arange(6.0), torch.zeros(6)], -1)
    planner.graph.set_landmarks(points, points.clone(), euclidean)
    return planner


def step_td(obs, subgoal, new):
    obs = torch.as_tensor(obs, dtype=torch.float32).reshape(-1, 2)
    num = obs.shape[0]
    return TensorDict(
        observation=obs,
        achieved_goal=obs.clone(),
        subgoal=torch.as_tensor(subgoal, dtype=torch.float32).reshape(-1, 2).expand(num, 2),
        new_subgoal=torch.full((num, 1), new, dtype=torch.bool),
        batch_size=[num],
    )


def advance(planner, td, obs, new=False, subgoal=None):
    """The next env step: same tracking state, new observation."""
    td = td.clone()
    obs = torch.as_tensor(obs, dtype=torch.float32).reshape(td["observation"].shape)
    td["observation"], td["achieved_goal"] = obs, obs.clone()
    td["new_subgoal"] = torch.full_like(td["new_subgoal"], new)
    if subgoal is not None:
        td["subgoal"] = torch.as_tensor(subgoal, dtype=torch.float32).expand_as(td["subgoal"]).clone()
    return planner(td)


# ----------------------------------------------------------------------------- plans and tracking
def test_direct_edge_wins_when_shorter_and_no_graph_means_subgoal():
    planner = line_planner()
    plan = planner.plan(torch.tensor([[2.0, 0.3]]), torch.tensor([[2.5, 0.3]]))
    assert plan.length.item() == 0 and plan.cost.item() == pytest.approx(0.5)
    empty = GraphPlanner(LandmarkGraph(cutoff=1.5), euclidean, 2)
    assert not empty.has_graph and torch.isinf(empty.distance_from_graph(torch.zeros(3, 2))).all()
    td = empty(step_td([[0.0, 0.0], [1.0, 1.0]], [7.0, 7.0], True))
    assert torch.equal(td["waypoint"], torch.full((2, 2), 7.0))
    assert (td["planner", "path_length"] == 0).all() and td["planner", "has_plan"].all()
    empty.graph.set_landmarks(torch.zeros(0, 2), torch.zeros(0, 2), euclidean)
    assert not empty.has_graph


def test_distance_from_graph_is_min_over_landmarks():
    planner = line_planner()
    goals = torch.tensor([[[2.2, 1.0], [7.0, 0.0]], [[-1.0, 0.0], [3.0, 0.0]]])
    expected = torch.cdist(goals.reshape(-1, 2), planner.landmark_states).min(-1).values.reshape(2, 2)
    torch.testing.assert_close(planner.distance_from_graph(goals), expected)


def test_tracking_advances_by_radius_and_by_timeout_then_chases_subgoal():
    planner = line_planner(reach_radius=0.5)
    td = planner(step_td([0.0, 0.0], [5.0, 0.0], True))
    # landmarks 0..4 then the subgoal (which lies on landmark 5: an equally short route)
    assert td["planner", "path"][0, :6].tolist() == [0, 1, 2, 3, 4, -1]
    assert td["planner", "path_length"].item() == 5
    assert td["planner", "budgets"][0, :7].tolist() == pytest.approx([0, 1, 1, 1, 1, 1, INF])
    assert td["waypoint"][0].tolist() == [0.0, 0.0] and td["planner", "index"].item() == 0
    td = advance(planner, td, [0.0, 0.0])  # landmark 0 reached
    assert td["waypoint"][0].tolist() == [1.0, 0.0] and td["planner", "steps"].item() == 0
    td = advance(planner, td, [0.6, 0.0])  # within 0.5 of landmark 1
    assert td["waypoint"][0].tolist() == [2.0, 0.0]
    td = advance(planner, td, [0.6, 0.0])  # 1 step on landmark 2, budget 1: keep going
    assert td["waypoint"][0].tolist() == [2.0, 0.0] and td["planner", "steps"].item() == 1
    td = advance(planner, td, [0.6, 0.0])  # 2 steps > budget 1: time out, next waypoint
    assert td["waypoint"][0].tolist() == [3.0, 0.0] and td["planner", "index"].item() == 3
    for x in (3.0, 4.0):
        td = advance(planner, td, [x, 0.0])
    assert td["planner", "index"].item() == 5 and td["waypoint"][0].tolist() == [5.0, 0.0]
    for _ in range(3):  # after the path: the subgoal, forever
        td = advance(planner, td, [9.0, 9.0])
        assert td["planner", "index"].item() == 5 and td["waypoint"][0].tolist() == [5.0, 0.0]
    assert td["planner", "steps"].item() == 3


def test_replan_on_new_subgoal_only():
    planner = line_planner()
    td = planner(step_td([0.0, 0.0], [5.0, 0.0], True))
    td = advance(planner, td, [0.0, 0.0])
    td = advance(planner, td, [2.0, 0.0], subgoal=[0.0, 0.0])  # subgoal changed, no new_subgoal flag
    assert td["planner", "path"][0, :5].tolist() == [0, 1, 2, 3, 4]
    td = advance(planner, td, [2.0, 0.0], new=True, subgoal=[0.0, 0.0])
    expected = planner.plan(torch.tensor([[2.0, 0.0]]), torch.tensor([[0.0, 0.0]]))
    assert td["planner", "path"][0].tolist() == expected.path[0].tolist()
    assert td["planner", "path"][0, 0].item() in (1, 2) and td["planner", "index"].item() == 0
    assert td["planner", "budgets"][0, : td["planner", "path_length"].item() + 1].sum().item() == 2.0


def test_graph_rebuild_triggers_replan_and_truncated_paths_replan_when_used_up():
    planner = line_planner(max_path_length=2)
    td = planner(step_td([0.0, 0.0], [5.0, 0.0], True))
    assert td["planner", "path"][0].tolist() == [0, 1] and td["planner", "truncated"].item()
    assert td["planner", "budgets"][0, 2].item() == INF  # no final hop stored for a cut path
    td = advance(planner, td, [0.0, 0.0])
    td = advance(planner, td, [1.0, 0.0])  # stored part used up: replan from x = 1
    expected = planner.plan(torch.tensor([[1.0, 0.0]]), torch.tensor([[5.0, 0.0]]))
    assert td["planner", "path"][0].tolist() == expected.path[0].tolist()
    assert td["planner", "index"].item() == 0 and td["planner", "graph_version"].item() == 1
    # a rebuild changes landmark indices: the stale plan is dropped at the next step
    shifted = torch.stack([torch.arange(6.0) + 0.25, torch.zeros(6)], -1).flip(0)
    planner.graph.set_landmarks(shifted, shifted.clone(), euclidean)
    td = advance(planner, td, [1.0, 0.0])
    assert td["planner", "graph_version"].item() == 2 and td["planner", "index"].item() == 0
    assert torch.equal(td["waypoint"][0], shifted[td["planner", "path"][0, 0]])


def test_batch_of_envs_with_different_subgoals_and_leading_dims():
    planner = line_planner()
    obs = torch.tensor([[[0.0, 0.0], [5.0, 0.0], [2.0, 0.0]], [[3.0, 0.0], [0.0, 0.0], [1.0, 0.0]]])
    subgoals = torch.tensor([[[5.0, 0.0], [0.0, 0.0], [2.0, 0.0]], [[0.0, 0.0], [3.0, 0.0], [9.0, 9.0]]])
    td = TensorDict(
        observation=obs,
        achieved_goal=obs.clone(),
        subgoal=subgoals,
        new_subgoal=torch.ones(2, 3, 1, dtype=torch.bool),
        batch_size=[2, 3],
    )
    td = planner(td)
    for i in range(2):
        for j in range(3):
            single = planner(step_td(obs[i, j], subgoals[i, j], True))
            assert torch.equal(td["planner", "path"][i, j], single["planner", "path"][0])
            assert torch.equal(td["waypoint"][i, j], single["waypoint"][0])
    waypoints, mask = planner.planned_waypoints(td)
    assert waypoints.shape == (2, 3, 33, 2) and mask.shape == (2, 3, 33)
    path = planner.planned_path(td, (0, 0))
    assert path[:, 0].tolist() == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]  # landmarks 0..4, then the subgoal
    assert planner.planned_path(td, (1, 2))[-1].tolist() == [9.0, 9.0]


# ----------------------------------------------------------------------------- checkpoints
def test_state_dict_round_trip_with_a_different_landmark_count():
    states, goals = u_maze_candidates(spacing=1.0)
    source = GraphPlanner(
        LandmarkGraph(cutoff=6.0, max_landmarks=60, early_stop=2.0), line_of_sight_distance, 2
    )
    source.build(states, goals)
    other = GraphPlanner(
        LandmarkGraph(cutoff=6.0, max_landmarks=60, early_stop=2.0), line_of_sight_distance, 2
    )
    other.build(states[:30], goals[:30])
    assert other.num_landmarks != source.num_landmarks
    buffer = io.BytesIO()
    torch.save(source.state_dict(), buffer)
    buffer.seek(0)
    other.load_state_dict(torch.load(buffer))
    fresh = GraphPlanner(LandmarkGraph(cutoff=6.0), line_of_sight_distance, 2)
    fresh.load_state_dict(source.state_dict())
    for target in (other, fresh):
        for name, value in source.state_dict().items():
            assert torch.equal(target.state_dict()[name], value), name
        td = step_td([[0.0, 0.0], [8.0, 8.0]], [[0.0, 8.0], [0.0, 0.0]], True)
        td = td.set("observation", torch.cat([td["observation"], torch.zeros(2, 3)], -1))
        assert torch.equal(target(td.clone())["planner", "path"], source(td.clone())["planner", "path"])
    # the distance function (e.g. the learner's critics) is not part of the planner's state
    assert all(name.startswith("graph.") for name in source.state_dict()) and not list(source.parameters())


def test_input_validation():
    with pytest.raises(ValueError, match="goal_dim"):
        GraphPlanner(LandmarkGraph(), euclidean, 0)
    with pytest.raises(TypeError, match="callable"):
        GraphPlanner(LandmarkGraph(), 3.0, 2)
    with pytest.raises(ValueError, match="cutoff"):
        LandmarkGraph(cutoff=-1.0)
    with pytest.raises(ValueError, match="start_fallback_factor"):
        LandmarkGraph(start_fallback_factor=0.5)
    planner = line_planner()
    with pytest.raises(KeyError, match="subgoal"):
        planner(step_td([0.0, 0.0], [5.0, 0.0], True).exclude("subgoal"))
    with pytest.raises(ValueError, match="goal_dim"):
        td = step_td([0.0, 0.0], [5.0, 0.0], True)
        planner(td.set("subgoal", torch.zeros(1, 3)))
    with pytest.raises(ValueError, match="features"):
        planner.plan(torch.zeros(1, 4), torch.zeros(1, 2))
    with pytest.raises(ValueError, match="candidate_goals"):
        planner.build(torch.zeros(5, 2), torch.zeros(5, 3))


# ------------------------------------------------------------------ composition
def test_the_planner_is_composed_of_a_landmark_graph():
    graph = LandmarkGraph(cutoff=1.5, max_landmarks=25, early_stop=0.0)
    planner = GraphPlanner(graph, manhattan, goal_dim=2, reach_radius=0.1, max_path_length=4)
    assert planner.graph is graph and dict(planner.named_children()) == {"graph": graph}
    planner.build(STATES, LATTICE.clone())
    assert graph.num_landmarks == 25 and all(k.startswith("graph.") for k in planner.state_dict())
    assert planner.max_path_length == 4 and planner.reach_radius == 0.1
    with pytest.raises(
        TypeError, match=r"`graph` must be a LandmarkGraph, e\.g\. GraphPlanner\(LandmarkGraph"
    ):
        GraphPlanner(manhattan, LandmarkGraph(), 2)  # distance and graph swapped
    with pytest.raises(TypeError, match="with_autocast"):
        GraphPlanner(LandmarkGraph(build_autocast_dtype=torch.bfloat16), manhattan, 2)


# ----------------------------------------------------------------------------- the TorchRL transform patterns
SUBGOAL = (2.5, 2.5)


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


# ----------------------------------------------------------------------------- the capturable tracker
def _planner_pair(distance, max_path_length=4, reach_radius=0.5, fixed_size=False, plan_on_demand=True):
    graph = LandmarkGraph(cutoff=3.0, max_landmarks=64, fixed_size=fixed_size)
    make = lambda capturable: GraphPlanner(  # noqa: E731
        graph,
        distance,
        2,
        reach_radius=reach_radius,
        max_path_length=max_path_length,
        capturable=capturable,
        plan_on_demand=plan_on_demand,
    )
    return graph, make(False), make(True)


def _walk(gen, batch, steps):
    """Observations drifting in the maze, subgoals re-drawn where ``new_subgoal``."""
    obs = torch.rand(*batch, 4, generator=gen) * 12 - 2
    subgoal = torch.rand(*batch, 2, generator=gen) * 12 - 2
    for _ in range(steps):
        obs = obs + torch.randn(obs.shape, generator=gen) * 0.4
        new = torch.rand(*batch, 1, generator=gen) < 0.15
        subgoal = torch.where(new, torch.rand(*batch, 2, generator=gen) * 12 - 2, subgoal)
        yield obs.clone(), new, subgoal.clone()


def _step_td(td, obs, new, subgoal):
    td = td.clone()
    td["observation"], td["achieved_goal"] = obs, obs[..., :2].clone()
    td["new_subgoal"], td["subgoal"] = new, subgoal
    return td


def _assert_same_tracking(got, expected, planner, exact=True):
    for key in ("waypoint", *planner._state_keys.values()):
        if exact or not expected[key].is_floating_point():
            assert torch.equal(got[key], expected[key]), key
        else:  # compiled distances: float round-off in the budgets
            torch.testing.assert_close(got[key], expected[key], rtol=1e-5, atol=1e-5, msg=str(key))


@pytest.mark.parametrize("plan_on_demand", [True, False])
@pytest.mark.parametrize("fixed_size", [False, True])
@pytest.mark.parametrize("name", ["walled", "rounded"])
def test_capturable_tracking_equals_tracking_over_random_walks(name, fixed_size, plan_on_demand):
    """Waypoints and every tracking entry, step by step, ``[3, 2]`` envs: new subgoals, timeouts and radius
    advances, truncated paths used up, two rebuilds (other landmark counts) and a partial reset; on the
    graph's own buffers and on a fixed-size graph's padded copies; planning only in the calls where a replan
    is due, or at every call."""
    distance = DISTANCES[name]
    gen = torch.Generator().manual_seed(7)
    graph, planner, capturable = _planner_pair(
        distance, reach_radius=1.0, fixed_size=fixed_size, plan_on_demand=plan_on_demand
    )
    batch = (3, 2)
    td = TensorDict(batch_size=batch)
    mine = theirs = None
    replans = 0
    for step, (obs, new, subgoal) in enumerate(_walk(gen, batch, 80)):
        if step in (0, 30, 55):
            _set_random_landmarks(graph, distance, gen, num=(25, 40, 12)[(0, 30, 55).index(step)])
        if step == 45:  # a partial reset (env mode): only the active envs get a fresh plan
            reset = torch.rand(*batch, 1, generator=gen) < 0.5
            fresh = _step_td(td, obs, new, subgoal).exclude("planner")
            theirs = planner._reset(theirs.set("_reset", reset), fresh.clone())
            mine = capturable._reset(mine.set("_reset", reset), fresh.clone())
            _assert_same_tracking(mine, theirs, planner)
            continue
        theirs = planner(_step_td(td if theirs is None else theirs, obs, new, subgoal))
        mine = capturable(_step_td(td if mine is None else mine, obs, new, subgoal))
        _assert_same_tracking(mine, theirs, planner)
        replans += int((theirs["planner", "index"] == 0).sum())
    assert replans > 0 and bool(theirs["planner", "has_plan"].all())


@pytest.mark.parametrize("plan_on_demand", [True, False])
def test_capturable_planner_queries_the_distance_only_when_a_replan_is_due(plan_on_demand):
    """``plan_on_demand``: the distance is evaluated in exactly the calls where the host-branching planner plans
    (some env due for a replan); without it, at every call. The tracking agrees either way (test above)."""
    calls = {"host": 0, "capturable": 0}

    def counting(who):
        def distance(states, goals):
            calls[who] += 1
            return euclidean(states, goals)

        return distance

    gen = torch.Generator().manual_seed(5)
    graph, planner, capturable = _planner_pair(euclidean, reach_radius=1.0, plan_on_demand=plan_on_demand)
    _set_random_landmarks(graph, euclidean, gen, num=30)
    planner.distance, capturable.distance = counting("host"), counting("capturable")
    mine = theirs = TensorDict(batch_size=(3,))
    planned_calls = idle_calls = 0
    for obs, new, subgoal in _walk(gen, (3,), 40):
        before = dict(calls)
        theirs = planner(_step_td(theirs, obs, new, subgoal))
        mine = capturable(_step_td(mine, obs, new, subgoal))
        host_planned = calls["host"] > before["host"]
        capturable_planned = calls["capturable"] > before["capturable"]
        assert capturable_planned == (host_planned or not plan_on_demand)
        planned_calls += host_planned
        idle_calls += not host_planned
    assert planned_calls > 0 and idle_calls > 0  # both kinds of call happened


@pytest.mark.slow
@pytest.mark.parametrize("plan_on_demand", [True, False])
def test_compiled_planner_with_the_learned_distance_plans_inside_torch_cond(plan_on_demand):
    """Under ``torch.compile(fullgraph=True)`` with the recipe's learned distance (``GoalDistance.from_loss``:
    the networks evaluated with the loss's parameters): one graph with the planning in a ``torch.cond``
    (``plan_on_demand``) or without any (every call); the same waypoints and tracking state as eager over a
    walk with new subgoals and a rebuild; the distance's networks left as they were. Dynamo's graph is run
    as traced (no inductor: its kernels are covered by the slow tests)."""
    agent, _ = _agent(True)
    planner = agent.planner
    planner.plan_on_demand = plan_on_demand
    networks = [planner.distance.actor, planner.distance.critic]
    before = [dict(net.named_parameters()) for net in networks]
    graphs = []

    def traced_as_is(gm, example_inputs):
        graphs.append(gm)
        return gm.forward

    torch._dynamo.reset()
    compiled = torch.compile(planner, backend=traced_as_is, fullgraph=True)
    obs_dim = planner.distance.observation_dim
    gen = torch.Generator().manual_seed(3)
    eager_td = compiled_td = TensorDict(batch_size=(4,))
    idle = 0
    for step, (obs, new, subgoal) in enumerate(_walk(gen, (4,), 16)):
        if step == 8:
            points = torch.rand(50, obs_dim, generator=gen) * 12 - 2
            planner.build(points, points[:, :2].clone())
        obs = torch.cat([obs, torch.zeros(4, obs_dim - 4)], -1)
        idle += not bool(new.any())
        eager_td = planner(_step_td(eager_td, obs, new, subgoal))
        compiled_td = compiled(_step_td(compiled_td, obs, new, subgoal))
        _assert_same_tracking(compiled_td, eager_td, planner)
    torch._dynamo.reset()  # the frames traced for this backend stay out of later tests' compilations
    assert idle > 0
    conds = [node for gm in graphs for node in gm.graph.nodes if node.target is torch.ops.higher_order.cond]
    assert bool(conds) is plan_on_demand
    assert [dict(net.named_parameters()) for net in networks] == before


@pytest.mark.slow
def test_capturable_planner_compiles_whole_and_agrees():
    """``torch.compile(fullgraph=True)``: no graph break in the planner's call (would raise), the same
    waypoints and state as eager over a walk with a rebuild to another landmark count."""
    torch._dynamo.reset()  # nothing cached from another test's backend
    gen = torch.Generator().manual_seed(11)
    graph, _, capturable = _planner_pair(euclidean)
    compiled = torch.compile(capturable, fullgraph=True)
    batch = (4,)
    eager_td = compiled_td = TensorDict(batch_size=batch)
    for step, (obs, new, subgoal) in enumerate(_walk(gen, batch, 24)):
        if step in (0, 12):
            _set_random_landmarks(graph, euclidean, gen, num=(20, 33)[step // 12])
        eager_td = capturable(_step_td(eager_td, obs, new, subgoal))
        compiled_td = compiled(_step_td(compiled_td, obs, new, subgoal))
        _assert_same_tracking(compiled_td, eager_td, capturable, exact=False)
        compiled_td = eager_td.clone()  # keeps a budget's round-off from flipping a later timeout


@pytest.mark.slow
def test_fixed_size_planner_is_not_recompiled_by_rebuilds():
    """On a ``fixed_size`` graph the compiled planner survives rebuilds to other landmark counts and a clear
    without recompiling (``fail_on_recompile``) and agrees with eager; on a plain graph a rebuild recompiles."""
    for fixed_size in (True, False):
        torch._dynamo.reset()
        gen = torch.Generator().manual_seed(13)
        graph, _, capturable = _planner_pair(euclidean, fixed_size=fixed_size)
        compiled = torch.compile(capturable, fullgraph=True)
        eager_td = compiled_td = TensorDict(batch_size=(4,))
        recompiled = False
        for step, (obs, new, subgoal) in enumerate(_walk(gen, (4,), 16)):
            if step in (0, 5, 9, 13):  # 20 landmarks, then 33, none, 8
                _set_random_landmarks(graph, euclidean, gen, 20 + step) if step != 9 else graph.clear()
            stance = "fail_on_recompile" if step >= 2 else "default"  # two calls: without, then with state
            with torch.compiler.set_stance(stance):
                eager_td = capturable(_step_td(eager_td, obs, new, subgoal))
                try:
                    compiled_td = compiled(_step_td(compiled_td, obs, new, subgoal))
                except RuntimeError as err:
                    assert not fixed_size and "recompil" in str(err).lower(), err
                    recompiled = True
                    break
            _assert_same_tracking(compiled_td, eager_td, capturable, exact=False)
            compiled_td = eager_td.clone()
        assert recompiled is not fixed_size


@pytest.mark.slow
def test_planner_on_a_reserved_graph_is_not_recompiled_by_its_first_build():
    """Compiled before the graph has landmarks (a reserved ``fixed_size`` graph, as ``make_agent`` makes for a
    capturable planner): the first build, a rebuild and a clear change no guard (``fail_on_recompile``), and the
    compiled planner tracks like the eager one throughout."""
    torch._dynamo.reset()
    gen = torch.Generator().manual_seed(17)
    graph, _, capturable = _planner_pair(euclidean, fixed_size=True)
    graph.reserve(4, 2)
    compiled = torch.compile(capturable, fullgraph=True)
    eager_td = compiled_td = TensorDict(batch_size=(4,))
    for step, (obs, new, subgoal) in enumerate(_walk(gen, (4,), 16)):
        if step in (5, 9):  # the first landmarks, then others
            _set_random_landmarks(graph, euclidean, gen, 20 + step)
        if step == 13:
            graph.clear()
        with torch.compiler.set_stance("fail_on_recompile" if step >= 2 else "default"):
            eager_td = capturable(_step_td(eager_td, obs, new, subgoal))
            compiled_td = compiled(_step_td(compiled_td, obs, new, subgoal))
        _assert_same_tracking(compiled_td, eager_td, capturable, exact=False)
        compiled_td = eager_td.clone()
    assert bool(eager_td["planner", "has_plan"].all())


# ----------------------------------------------------------------------------- an agent of the recipe's builders
def assert_same_collection(got, expected):
    """Two collectors' batches: the same observations, actions, waypoints, subgoals (float round-off) and paths."""
    for key in (("next", "observation"), "action", "waypoint", "subgoal", ("planner", "path")):
        if expected[key].is_floating_point():
            torch.testing.assert_close(got[key], expected[key], rtol=1e-4, atol=1e-4, msg=str(key))
        else:
            assert torch.equal(got[key], expected[key]), key


def _agent(capturable_planner, num_cells=(16,)):
    from torchrl_dhrl.factory import make_agent, make_environment

    env = make_environment("PointMaze", num_envs=2, seed=0, max_episode_steps=30)
    agent = make_agent(
        env,
        goal_indices=[0, 1],
        high_policy={"subgoal_low": [-2.0, -2.0], "subgoal_high": [10.0, 10.0], "interval": 5, "num_cells": num_cells},
        high_critic={"num_cells": num_cells},
        low_actor={"num_cells": num_cells, "relative_goal": False},
        low_critic={"num_cells": num_cells},
        capturable_planner=capturable_planner,
    )
    points = torch.rand(
        60, env.observation_spec["observation"].shape[-1], generator=torch.Generator().manual_seed(0)
    )
    points = points * 12 - 2
    agent.planner.build(points, points[:, :2])
    return agent, make_environment("PointMaze", num_envs=2, seed=0, max_episode_steps=30, agent=agent)
