"""A user's ``nn.Module`` as the distance (and other callables) of the planner, FGS and the relabellers.

Such a module must work end to end, stay out of the owner's ``state_dict()`` / ``parameters()``, and be
replaceable by assignment: the attributes of ``torchrl_dhrl._unregistered.UnregisteredAttributes``.
"""

import copy
import functools
import io
import math

import pytest
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.envs import TransformedEnv
from torchrl_dhrl.envs import make_env

from torchrl_dhrl.data import FutureGoalRelabel, HighLevelTransitionBuilder, HindsightSubgoalRelabel
from torchrl_dhrl.planner import FrontierGoalShifting, GoalShiftOnReset, GraphPlanner, LandmarkGraph


class ScaledEuclidean(nn.Module):
    """A user-made distance: ``exp(log_scale) * ||goal - state[..., :2]||`` with a learnable-looking scale."""

    def __init__(self, scale=1.0):
        super().__init__()
        self.log_scale = nn.Parameter(torch.tensor(math.log(scale)))

    def forward(self, states, goals):
        return self.log_scale.exp() * (goals - states[..., :2]).norm(dim=-1)


class GoalNorm(nn.Module):
    """A module taking goals only (a ``distance_from_graph`` / proxy-like callable)."""

    def __init__(self, scale=10.0):
        super().__init__()
        self.scale = nn.Parameter(torch.tensor(scale))

    def forward(self, goals, other=None):
        if other is not None:  # fps proxy: (goals_a, goals_b) -> distances
            return (goals - other).norm(dim=-1)
        return self.scale * goals.norm(dim=-1)


class ModuleReward(nn.Module):
    def __init__(self):
        super().__init__()
        self.threshold = nn.Parameter(torch.tensor(0.5))

    def forward(self, achieved, goal):
        return -((achieved - goal).norm(dim=-1, keepdim=True) > self.threshold).float()


def line_points():
    xs = torch.linspace(0, 5, 51)
    return torch.stack([xs, torch.zeros_like(xs)], -1)


def query(batch=3, subgoal=(5.0, 0.0)):
    return TensorDict(
        observation=torch.zeros(batch, 2),
        achieved_goal=torch.zeros(batch, 2),
        subgoal=torch.tensor([subgoal]).expand(batch, 2),
        new_subgoal=torch.ones(batch, 1, dtype=torch.bool),
        batch_size=[batch],
    )


def assert_no_distance_state(owner):
    names = list(owner.state_dict())
    assert not any("scale" in name or "threshold" in name for name in names), names
    assert not list(owner.parameters())


def test_module_distance_builds_and_plans_through_the_transform():
    distance = ScaledEuclidean(1.0)
    planner = GraphPlanner(LandmarkGraph(cutoff=1.5, max_landmarks=20, early_stop=0.9), distance, goal_dim=2)
    assert planner.distance is distance
    points = line_points()
    planner.build(points, points.clone())
    assert planner.num_landmarks == 5
    td = planner(query())
    assert td["planner", "path_length"][0].item() == 5
    assert [round(x, 1) for x in planner.planned_path(td, 0)[:, 0].tolist()] == [0.0, 1.2, 2.5, 3.7, 5.0, 5.0]
    # not part of the planner's state: the learner owns (and checkpoints) its parameters
    assert_no_distance_state(planner)
    assert "distance" not in planner._modules and list(planner._modules) == ["graph"]
    assert all(name.startswith("graph.") for name in planner.state_dict())
    # .to() and train/eval leave it alone; a clone shares it; a checkpoint round-trips without it
    distance.eval()
    planner.to("cpu").train()
    assert not distance.training and planner.distance is distance
    assert planner.clone().distance is distance
    buffer = io.BytesIO()
    torch.save(planner.state_dict(), buffer)
    buffer.seek(0)
    other = GraphPlanner(LandmarkGraph(cutoff=1.5), ScaledEuclidean(1.0), goal_dim=2)
    other.load_state_dict(torch.load(buffer))
    assert torch.equal(other(query())["planner", "path"], planner(query())["planner", "path"])
    assert isinstance(copy.deepcopy(planner).distance, ScaledEuclidean)


def test_reassigning_the_distance_takes_effect():
    planner = GraphPlanner(LandmarkGraph(cutoff=10.0), ScaledEuclidean(1.0), goal_dim=2, max_path_length=8)
    points = torch.stack([torch.arange(6.0), torch.zeros(6)], -1)
    planner.graph.set_landmarks(points, points.clone(), planner.distance)
    goal = torch.tensor([[7.0, 0.0]])  # 2 units past the last landmark
    assert planner.distance_from_graph(goal).item() == pytest.approx(2.0)
    planner.distance = ScaledEuclidean(1.5)  # module -> module
    assert planner.distance.log_scale.item() == pytest.approx(math.log(1.5))
    assert planner.distance_from_graph(goal).item() == pytest.approx(3.0)
    planner.distance = lambda s, g: 3.0 * (g - s[..., :2]).norm(dim=-1)  # module -> plain callable
    assert planner.distance_from_graph(goal).item() == pytest.approx(6.0)
    planner.distance = ScaledEuclidean(2.0)  # plain callable -> module
    assert planner.distance_from_graph(goal).item() == pytest.approx(4.0)
    assert planner.plan(torch.zeros(1, 2), goal).cost.item() == pytest.approx(5.0 + 4.0)
    planner.build(points, points.clone())  # builds with the current distance
    expected = 2.0 * torch.cdist(planner.landmark_goals, planner.landmark_goals)
    torch.testing.assert_close(planner.graph.landmark_distances, expected)
    assert_no_distance_state(planner)
    with pytest.raises(TypeError, match="callable"):
        planner.distance = 3.0


def test_module_distance_in_env_mode():
    # PointMaze: obs[..., :2] is the position; the desired goal serves as the subgoal (no new_subgoal flag)
    distance = ScaledEuclidean(10.0)
    planner = GraphPlanner(
        LandmarkGraph(cutoff=30.0), distance, goal_dim=2, subgoal_key="desired_goal", max_path_length=8
    )
    env = TransformedEnv(make_env("PointMaze", num_envs=1, seed=0), planner)
    grid = torch.cartesian_prod(torch.arange(0.0, 8.5, 2.0), torch.arange(0.0, 8.5, 2.0))
    planner.graph.set_landmarks(torch.cat([grid, torch.zeros(grid.shape[0], 4)], -1), grid, distance)
    rollout = env.rollout(4, break_when_any_done=False)
    assert rollout["next", "waypoint"].shape == (1, 4, 2)
    assert rollout["planner", "has_plan"].all() and (rollout["planner", "graph_version"] == 1).all()
    assert_no_distance_state(planner)
    assert env.transform.distance is distance


def test_fgs_and_goal_shift_with_a_module_distance():
    distance = ScaledEuclidean(1.0)
    planner = GraphPlanner(LandmarkGraph(cutoff=1.5), distance, goal_dim=2)
    points = torch.tensor([[float(x), 0.0] for x in range(6)])
    planner.graph.set_landmarks(points, points.clone(), distance)
    fgs = FrontierGoalShifting(planner, noise=0.0, generator=torch.Generator().manual_seed(0))
    td = TensorDict(
        observation=torch.zeros(2, 2), desired_goal=torch.tensor([[2.2, 0.3], [20.0, 20.0]]), batch_size=[2]
    )
    out = fgs(td.clone())
    assert out["goal_shifted"].squeeze(-1).tolist() == [True, False]
    assert (torch.cdist(out["desired_goal"][:1], points).min() < 1e-6).item()
    assert fgs.planner is planner and not list(fgs.state_dict()) and not list(fgs.parameters())
    # the planner can be replaced: an empty one shifts nothing
    fgs.planner = GraphPlanner(LandmarkGraph(cutoff=1.5), ScaledEuclidean(1.0), goal_dim=2)
    assert not fgs(td.clone())["goal_shifted"].any()
    assert "planner" not in fgs._modules
    with pytest.raises(TypeError, match="GraphPlanner"):
        fgs.planner = distance
    shift = GoalShiftOnReset(fgs)
    assert shift.fgs is fgs and not list(shift.state_dict()) and "fgs" not in shift._modules
    other = FrontierGoalShifting(planner, noise=0.0)
    shift.fgs = other
    assert shift.fgs is other and "fgs" not in shift._modules


def test_gradual_penalty_with_a_module_distance():
    torch.manual_seed(0)
    planner = GraphPlanner(LandmarkGraph(cutoff=30.0), ScaledEuclidean(10.0), goal_dim=2)
    points = torch.tensor([[float(x), 0.0] for x in range(6)])
    planner.graph.set_landmarks(points, points.clone(), planner.distance)
    sample = TensorDict(
        {
            "subgoal": torch.tensor([[5.0, 30.0]]).expand(500, 2),  # 300 steps from the graph: far
            "desired_goal": torch.zeros(500, 2),
            ("next", "achieved_goal"): torch.zeros(500, 2),
        },
        batch_size=[500],
    )
    relabel = HindsightSubgoalRelabel(
        distance_from_graph=functools.partial(planner.distance_from_graph, at_most=90.0),
        reward_fn=ModuleReward(),
    )
    out = relabel(sample.clone())
    tested = out["subgoal_test"].squeeze(-1)
    assert tested.any() and (out["next", "reward"][tested] == -5.0).all()
    assert_no_distance_state(relabel)
    # distance_from_graph and reward_fn may be modules themselves, and be replaced by plain callables
    relabel.distance_from_graph = GoalNorm(1.0)  # 30.4 < 90: not far, missed
    out = relabel(sample.clone())
    assert (out["next", "reward"][out["subgoal_test"].squeeze(-1)] == -1.3).all()
    relabel.reward_fn = lambda achieved, goal: torch.full((achieved.shape[0], 1), 7.0)
    out = relabel(sample.clone())
    assert (out["next", "reward"][~out["subgoal_test"].squeeze(-1)] == 7.0).all()
    relabel.reward_fn = ModuleReward()
    assert_no_distance_state(relabel)
    assert not relabel._modules


def test_other_callables_stay_plain_attributes():
    future = FutureGoalRelabel(reward_fn=ModuleReward())
    for owner in (future, HighLevelTransitionBuilder(reward_fn=ModuleReward())):
        assert_no_distance_state(owner)
        owner.reward_fn = lambda achieved, goal: achieved[..., :1]  # was: TypeError (child module)
        owner.reward_fn = ModuleReward()
        assert isinstance(owner.reward_fn, ModuleReward) and not owner._modules
    proxy = GoalNorm()
    graph = LandmarkGraph(cutoff=1.5, max_landmarks=20, early_stop=0.9, fps_proxy=proxy)
    points = line_points()
    graph.build(points, points.clone(), ScaledEuclidean(1.0))
    assert graph.num_landmarks == 5 and graph.fps_proxy is proxy
    assert_no_distance_state(graph)
    graph.fps_proxy = None
    assert graph.fps_proxy is None and list(graph._modules) == ["storage"]  # its planning storage only
