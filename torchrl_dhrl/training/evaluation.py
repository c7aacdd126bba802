"""Deterministic evaluation episodes on the fixed test goals, with what the pictures need."""

from __future__ import annotations

import time
from pathlib import Path
from typing import NamedTuple

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from tensordict.utils import NestedKey
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

__all__ = [
    "EvaluationResult",
    "ModuleTimer",
    "evaluate",
    "goal_as_subgoal",
    "goal_as_waypoint",
    "record_video",
]


class EvaluationResult(NamedTuple):
    """Outcome of :func:`evaluate`.

    Attributes:
        success (float): fraction of episodes whose FINAL state is within the env's success
            threshold (the paper's and the reference's measure).
        any_success (float): fraction of episodes within the threshold at any step.
        final_distance (float): mean final distance between the achieved and the desired goal.
        last_steps_success (float): fraction of the last ``last_steps`` steps (all episodes) whose
            state is within the threshold: tells "passes through the goal" from "stays there".
        final_speed (float): mean distance the achieved goal moved in the last step (goal units per
            env step): an agent still moving at the end overshoots or coasts.
        rollout (TensorDictBase): the ``[num_envs, T]`` rollout (achieved goals, subgoals, waypoints).
    """

    success: float
    any_success: float
    final_distance: float
    last_steps_success: float
    final_speed: float
    rollout: TensorDictBase


@torch.no_grad()
def evaluate(
    env: EnvBase, policy: TensorDictModuleBase, max_steps: int, *, last_steps: int = 10
) -> EvaluationResult:
    """Runs one episode in each of ``env``'s envs with exploration off and measures success.

    The env should be built with its test goals (``make_env(..., eval=True)``) and the policy's
    primers; every env runs exactly ``max_steps`` steps (episodes only truncate). ``last_steps``
    sets the window of :attr:`EvaluationResult.last_steps_success`.

    Examples:
        >>> import torch
        >>> from torchrl_dhrl.envs import make_env
        >>> env = make_env("PointMaze", num_envs=2, seed=0, eval=True, max_episode_steps=5)
        >>> still = lambda td: td.set("action", torch.zeros(*td.batch_size, 2))
        >>> result = evaluate(env, still, max_steps=5)
        >>> result.success, result.rollout.shape
        (0.0, torch.Size([2, 5]))
    """
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = env.rollout(max_steps, policy, break_when_any_done=False)
    success = rollout["next", "is_success"].reshape(*rollout.shape, -1).any(-1)
    final = rollout[..., -1]
    distance = (final["next", "achieved_goal"] - final["next", "desired_goal"]).norm(dim=-1)
    speed = (final["next", "achieved_goal"] - final["achieved_goal"]).norm(dim=-1)
    return EvaluationResult(
        success=success[..., -1].float().mean().item(),
        any_success=success.any(-1).float().mean().item(),
        final_distance=distance.mean().item(),
        last_steps_success=success[..., -last_steps:].float().mean().item(),
        final_speed=speed.mean().item(),
        rollout=rollout,
    )


def goal_as_waypoint(
    low_actor: TensorDictModuleBase, goal_key: NestedKey = "desired_goal"
) -> TensorDictSequential:
    """The low level alone, chasing the final goal: a flat policy for diagnosis.

    Copies ``goal_key`` into the low-level actor's goal entry (its second in-key, ``"waypoint"`` for
    :class:`~torchrl_dhrl.modules.LowLevelActor`) and acts. Evaluated next to the full agent, it tells a
    high level (or a graph) that leads the low level astray from a low level that cannot reach the goal
    itself; on a maze with walls between the start and the goal it is expected to fail.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_dhrl.modules import LowLevelActor
        >>> actor = LowLevelActor(6, 2, action_max=1.0, action_dim=2, goal_indices=[0, 1], num_cells=(8,))
        >>> flat = goal_as_waypoint(actor)
        >>> td = flat(TensorDict(observation=torch.zeros(3, 6), desired_goal=torch.ones(3, 2), batch_size=[3]))
        >>> torch.equal(td["waypoint"], td["desired_goal"]), td["action"].shape
        (True, torch.Size([3, 2]))
    """
    if len(low_actor.in_keys) < 2:
        raise ValueError(
            f"goal_as_waypoint: the low-level actor must read (observation, goal); its in_keys are {low_actor.in_keys}."
        )
    waypoint_key = low_actor.in_keys[1]
    copy = TensorDictModule(lambda goal: goal.clone(), in_keys=[goal_key], out_keys=[waypoint_key])
    return TensorDictSequential(copy, low_actor)


def goal_as_subgoal(
    policy: TensorDictSequential, planner: TensorDictModuleBase, goal_key: NestedKey = "desired_goal"
) -> TensorDictSequential:
    """The acting policy with the high level's subgoal replaced by the final goal: the graph plans to the goal.

    ``policy`` is an acting policy ``TensorDictSequential(high_policy, planner, low_policy)`` (as
    :func:`~torchrl_dhrl.factory.make_agent` builds it); a module copying ``goal_key`` into the planner's
    ``subgoal_key`` is inserted right before ``planner``, so the high level keeps its cadence (its
    ``new_subgoal`` flags still trigger a replan every ``c_h`` steps) but the planner routes to the goal
    itself. Evaluated next to the full agent, it tells a high level whose subgoals lead astray from a
    graph that cannot route to the goal (e.g. a goal beyond the explored region, where the planner falls
    back to the landmark it estimates nearest).

    Examples:
        >>> import torch
        >>> from torchrl_dhrl.factory import make_agent, make_environment
        >>> spec_env = make_environment("PointMaze", "cpu", num_envs=1, max_episode_steps=20)
        >>> agent = make_agent(spec_env, "cpu", goal_indices=[0, 1], high_policy={"subgoal_low": [-2.0, -2.0], "subgoal_high": [10.0, 10.0], "interval": 5,
        ...     "num_cells": (16,)}, high_critic={"num_cells": (16,)}, low_actor={"num_cells": (16,)},
        ...     low_critic={"num_cells": (16,)}, graph={"max_landmarks": 8})
        >>> env = make_environment("PointMaze", "cpu", num_envs=2, seed=0, eval=True, max_episode_steps=20,
        ...     agent=agent)
        >>> policy = goal_as_subgoal(agent.policy, agent.planner)
        >>> td = policy(env.reset())
        >>> torch.equal(td["subgoal"], td["desired_goal"]), torch.equal(td["waypoint"], td["desired_goal"])
        (True, True)
    """
    modules = list(policy.module)
    positions = [i for i, module in enumerate(modules) if module is planner]
    if len(positions) != 1:
        raise ValueError(
            "goal_as_subgoal: `planner` must be one of the modules of `policy` (found "
            f"{len(positions)} times among {[type(m).__name__ for m in modules]})."
        )
    copy = TensorDictModule(lambda goal: goal.clone(), in_keys=[goal_key], out_keys=[planner.subgoal_key])
    modules.insert(positions[0], copy)
    return TensorDictSequential(*modules)


class ModuleTimer:
    """Accumulates the wall-clock time spent in a module's forward calls (e.g. the planner's share of acting).

    Installs forward pre/post hooks; :meth:`pop` returns the seconds and calls since the last pop.

    Examples:
        >>> import torch
        >>> timer = ModuleTimer(torch.nn.Linear(2, 2))
        >>> _ = timer.module(torch.zeros(1, 2))
        >>> seconds, calls = timer.pop()
        >>> calls, seconds >= 0
        (1, True)
    """

    def __init__(self, module: torch.nn.Module) -> None:
        self.module = module
        self.seconds, self.calls, self._start = 0.0, 0, 0.0
        module.register_forward_pre_hook(self._before)
        module.register_forward_hook(self._after)

    def _before(self, module, args) -> None:
        self._start = time.perf_counter()

    def _after(self, module, args, output) -> None:
        self.seconds += time.perf_counter() - self._start
        self.calls += 1

    def pop(self) -> tuple[float, int]:
        out = (self.seconds, self.calls)
        self.seconds, self.calls = 0.0, 0
        return out


@torch.no_grad()
def record_video(
    env: EnvBase,
    policy: TensorDictModuleBase,
    max_steps: int,
    path: str | Path,
    *,
    every: int = 4,
    size: int = 320,
) -> Path:
    """Renders the first env of a deterministic episode with MuJoCo (every ``every``-th step) to a GIF.

    Needs an OpenGL back end for MuJoCo (e.g. ``MUJOCO_GL=egl``); raises the renderer's error otherwise.
    """
    from PIL import Image

    frames, steps = [], [0]

    def grab(env_, td) -> None:
        if steps[0] % every == 0:
            frames.append(Image.fromarray(env.base_env.render(0, width=size, height=size).numpy()))
        steps[0] += 1

    with set_exploration_type(ExplorationType.DETERMINISTIC):
        env.rollout(max_steps, policy, break_when_any_done=False, callback=grab)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=40 * every, loop=0)
    return path
