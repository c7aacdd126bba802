"""Any Gymnasium goal environment as a batched env of the goal-env contract: :class:`GymnasiumGoalEnv`.

A Gymnasium goal env (a ``Dict`` observation with ``observation``, ``achieved_goal`` and ``desired_goal``, as
gymnasium-robotics' mazes, Fetch and hand tasks) is wrapped so that every part of torchrl-dhrl reads it: float32
tensors, ``is_success`` ``[B, 1]`` (from ``info["is_success"]`` or ``info["success"]``, or within a distance),
``step_count``, truncation after the env's own ``TimeLimit`` (``max_episode_steps``), the achieved goal put first
in the observation where the env's own leaves it out (gymnasium-robotics' ant mazes), and the simulator's state
in :meth:`~GymnasiumGoalEnv.state_dict` for exact resumes. ``make_env("gymnasium:<id>")`` builds one, so the
recipe trains it with ``env=gymnasium env_name=gymnasium:<id>`` (``docs/goal_env.md``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from torchrl_dhrl.checks import ArgumentCheck, checked, integer, number

from .agents import AntAgent, upright_pose
from .goal_env import GoalEnvError

__all__ = [
    "GYMNASIUM_PREFIX",
    "GymnasiumGoalEnv",
    "RightFlippedAnt",
    "goal_extent",
    "goal_indices_of",
    "gymnasium_id",
    "is_gymnasium_ant_maze",
]

#: ``make_env`` names of Gymnasium goal envs: ``"gymnasium:<id>"``.
GYMNASIUM_PREFIX = "gymnasium:"
_GOAL_KEYS = ("observation", "achieved_goal", "desired_goal")
_SUCCESS_KEYS = ("is_success", "success")


def gymnasium_id(name: str) -> str | None:
    """The Gymnasium id a ``make_env`` name designates (``"gymnasium:PointMaze_UMaze-v3"`` ->
    ``"PointMaze_UMaze-v3"``), or ``None`` for other names.

    Examples:
        >>> gymnasium_id("gymnasium:PointMaze_UMaze-v3"), gymnasium_id("AntMaze")
        ('PointMaze_UMaze-v3', None)
    """
    if isinstance(name, str) and name.startswith(GYMNASIUM_PREFIX):
        return name[len(GYMNASIUM_PREFIX) :]
    return None


def _import_gymnasium(env_id: str):
    import gymnasium as gym

    try:  # gymnasium-robotics registers its ids only once imported
        import gymnasium_robotics

        gym.register_envs(gymnasium_robotics)
    except ImportError:
        pass
    if env_id not in gym.registry:
        hint = " (gymnasium-robotics' envs need `pip install gymnasium-robotics`)" if "Maze" in env_id or "Fetch" in env_id else ""
        raise GoalEnvError(f"No Gymnasium env {env_id!r} is registered{hint}.")
    return gym


def is_gymnasium_ant_maze(env_id: str) -> bool:
    """Whether a registered Gymnasium id is one of gymnasium-robotics' ant mazes (``AntMaze_*``: its entry point
    is their ``AntMazeEnv``), whose ant can flip over (``right_flipped_after``).

    Raises:
        GoalEnvError: for an id that is not registered.
    """
    entry = _import_gymnasium(env_id).registry[env_id].entry_point
    name = entry if isinstance(entry, str) else f"{entry.__module__}:{entry.__qualname__}"
    return name.rsplit(":", 1)[-1].rsplit(".", 1)[-1] == "AntMazeEnv"


def _holds_an_ant(env: Any) -> bool:
    """Whether an unwrapped Gymnasium env drives an ant as gymnasium-robotics' ant mazes do (``env.ant_env``,
    a MuJoCo env whose ``qpos[:7]`` is the torso's position and quaternion)."""
    ant = getattr(env, "ant_env", None)
    return ant is not None and hasattr(ant, "data") and hasattr(ant, "set_state") and hasattr(env, "_get_obs")


def _ant_upside_down(env: Any) -> bool:
    """Whether the ant of an unwrapped gymnasium-robotics ant maze lies with its torso's up axis below the horizon."""
    return bool(AntAgent.is_upside_down(env.ant_env.data.qpos))


def _right_ant(env: Any) -> dict[str, np.ndarray]:
    """Puts the ant of an unwrapped gymnasium-robotics ant maze back on its feet and returns the maze's observation.

    The ant takes its reset pose at rest (``ant_env.init_qpos``: torso height, identity tilt, joints) at its
    (x, y) and heading (:func:`~torchrl_dhrl.envs.agents.upright_pose`), moved to the nearest place (0.1 steps,
    up to 2 away) where none of its geoms overlaps a wall (:func:`~torchrl_dhrl.envs.simulation.clear_of_walls`),
    as the built-in ant mazes' ``right_flipped_after``.
    """
    from .simulation import clear_of_walls

    ant = env.ant_env
    model, data = ant.model, ant.data
    data.qpos[:] = upright_pose(data.qpos, ant.init_qpos)
    data.qvel[:] = 0.0
    clear_of_walls(model, data, model.geom_bodyid != 0)  # the maze's walls and floor are the world's geoms
    ant.set_state(data.qpos.copy(), np.zeros(model.nv))
    return env._get_obs(ant._get_obs())


def _righted_step(env: Any) -> tuple[dict[str, np.ndarray], float, bool]:
    """:func:`_right_ant` on an unwrapped ant maze, and the observation, reward and success where the ant now
    stands: the env's own reward (``compute_reward`` on the new achieved goal, sparse or dense) and its success
    radius (0.45, as gymnasium-robotics' mazes' ``info["success"]``)."""
    obs = _right_ant(env)
    reward = float(np.asarray(env.compute_reward(obs["achieved_goal"], env.goal, {})).reshape(-1)[0])
    success = bool(np.linalg.norm(obs["achieved_goal"] - env.goal) <= 0.45)
    return obs, reward, success


class RightFlippedAnt(gymnasium.Wrapper):
    """A gymnasium-robotics ant maze whose flipped ant is put back on its feet after ``after`` consecutive steps
    upside down (the recipe's ``right_flipped_after``, for a Gymnasium pipeline such as the SAC + HER baseline).

    The ant takes its reset pose at rest at its (x, y) and heading, clear of the walls; the episode goes on.
    The step that rights it returns the new observation with its reward and ``info["success"]`` recomputed.

    Args:
        env (gymnasium.Env): an ant maze (``AntMaze_*``), wrapped or not.
        after (int): consecutive env steps upside down before the ant is righted (>= 1).

    Examples:
        >>> import gymnasium as gym, gymnasium_robotics  # doctest: +SKIP
        >>> gym.register_envs(gymnasium_robotics)  # doctest: +SKIP
        >>> env = RightFlippedAnt(gym.make("AntMaze_UMaze-v5"), after=10)  # doctest: +SKIP
    """

    def __init__(self, env: gymnasium.Env, after: int) -> None:
        super().__init__(env)
        if isinstance(after, bool) or not isinstance(after, (int, np.integer)) or after < 1:
            raise ValueError(f"`after` must be a positive number of env steps, got {after!r}.")
        if not _holds_an_ant(env.unwrapped):
            raise ValueError(
                f"RightFlippedAnt rights a flipped ant: it wraps gymnasium-robotics' ant mazes (AntMaze_*), not "
                f"{type(env.unwrapped).__name__}."
            )
        self.after = int(after)
        self.upside_down_steps = 0

    def reset(self, **kwargs):
        self.upside_down_steps = 0
        return self.env.reset(**kwargs)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        maze = self.env.unwrapped
        self.upside_down_steps = self.upside_down_steps + 1 if _ant_upside_down(maze) else 0
        if self.upside_down_steps >= self.after:
            obs, reward, success = _righted_step(maze)
            info = {**info, "success": success, "righted": True}
            self.upside_down_steps = 0
        return obs, reward, terminated, truncated, info


# ---- the simulator's state, for exact resumes ------------------------------------------------------------------


def _capture(obj: Any, depth: int = 2) -> dict[str, Any]:
    """The mutable state of a Gymnasium env object: its arrays, numbers, random generators and MuJoCo data, and
    those of the Gymnasium objects it holds (``depth`` levels)."""
    import mujoco

    state: dict[str, Any] = {}
    for name, value in vars(obj).items():
        if isinstance(value, np.ndarray):
            state[name] = ("array", value.copy())
        elif isinstance(value, np.random.Generator):
            state[name] = ("generator", value.bit_generator.state)
        elif isinstance(value, mujoco.MjData):
            spec = mujoco.mjtState.mjSTATE_INTEGRATION
            buffer = np.empty(mujoco.mj_stateSize(value.model, spec))
            mujoco.mj_getState(value.model, value, buffer, spec)
            state[name] = ("mujoco", buffer)
        elif isinstance(value, (bool, int, float)) and not isinstance(value, np.generic):
            state[name] = ("value", value)
        elif depth > 0 and type(value).__module__.startswith(("gymnasium", "gymnasium_robotics")):
            if hasattr(value, "__dict__") and not isinstance(value, type):
                state[name] = ("object", _capture(value, depth - 1))
    return state


def _restore(obj: Any, state: Mapping[str, Any]) -> None:
    import mujoco

    for name, (kind, value) in state.items():
        if kind == "array":
            setattr(obj, name, np.array(value))
        elif kind == "generator":
            generator = getattr(obj, name, None)
            if not isinstance(generator, np.random.Generator):
                generator = np.random.default_rng()
                setattr(obj, name, generator)
            generator.bit_generator.state = value
        elif kind == "mujoco":
            data = getattr(obj, name)
            mujoco.mj_setState(data.model, data, np.asarray(value), mujoco.mjtState.mjSTATE_INTEGRATION)
            mujoco.mj_forward(data.model, data)
        elif kind == "value":
            setattr(obj, name, value)
        elif kind == "object":
            _restore(getattr(obj, name), value)


def _goal_list(value: Any) -> bool:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return False
    return array.size > 0 and array.ndim in (1, 2) and np.isfinite(array).all()


def _holds_goal(env: Any, action_space: Any, options: Mapping[str, Any] | None = None, steps: int = 4) -> bool:
    """Whether every entry of ``env``'s achieved goal is an entry of its observation (a distinct one each), at a
    reset and after ``steps`` random actions (a fixed stream: a goal that equals some entry at one state only, e.g.
    ``0.0`` at a reset, does not count)."""
    rng = np.random.default_rng(0)
    obs, _ = env.reset(options=options)
    samples = [obs]
    for _ in range(steps):
        obs, _, terminated, truncated, _ = env.step(rng.uniform(action_space.low, action_space.high))
        samples.append(obs)
        if terminated or truncated:
            break
    observation = np.stack([np.asarray(o["observation"], dtype=np.float64).reshape(-1) for o in samples])
    goal = np.stack([np.asarray(o["achieved_goal"], dtype=np.float64).reshape(-1) for o in samples])
    used: set[int] = set()
    for j in range(goal.shape[1]):
        match = next(
            (i for i in range(observation.shape[1]) if i not in used and np.array_equal(observation[:, i], goal[:, j])),
            None,
        )
        if match is None:
            return False
        used.add(match)
    return True


def _options(value: Any) -> bool:
    return isinstance(value, Mapping) or (
        isinstance(value, Sequence) and not isinstance(value, str) and len(value) > 0
        and all(isinstance(v, Mapping) for v in value)
    )


class GymnasiumGoalEnv(EnvBase):
    """``num_envs`` copies of a Gymnasium goal env as one batched TorchRL env of the goal-env contract.

    The copies step in turn (``gym.make(env_id, **make_kwargs)``, stepped through ``env.unwrapped``: the
    adapter counts the steps and truncates every episode after exactly ``max_episode_steps``, the env's own
    ``TimeLimit`` unless given). Observations, goals and actions are float32 tensors on ``device``;
    ``is_success`` comes from ``info["is_success"]`` or ``info["success"]`` (whichever the env writes), or, with
    ``success_threshold``, from the distance between the achieved and the desired goal. Where the env's own
    observation leaves out the achieved goal (gymnasium-robotics' ant mazes observe the torso without its x, y),
    the adapter puts it first: ``observation[..., :goal_dim] == achieved_goal`` (``achieved_goal_in_observation``).

    Resets honour the ``"_reset"`` mask and, as the built-in envs', a ``"desired_goal"`` entry (``[num_envs,
    goal_dim]``): the goals of the envs being reset, set where ``goals`` sets its fixed goals (e.g. a reach test's
    goals around the start); TorchRL's automatic resets never pass it. A ``"start"`` entry is refused: a Gymnasium
    env starts where its reset options put it.

    An env that ends an episode itself (``terminated``) is refused: the recipe's collector needs episodes of one
    length (most goal envs have a continuing mode, e.g. the mazes' ``continuing_task=True``, their default). An
    env that says so beforehand (its unwrapped env's ``continuing_task`` is ``False``) is refused at construction.
    Any other is refused at the episode boundary after its first ``terminated`` step, so that a training loop can
    stop there with a checkpoint (an exception inside a TorchRL collector shuts the collector down, and a
    checkpoint in the middle of a batch would resume out of step with the episodes): the copy that terminated is
    held at its last state (the same observation, reward and success; ``terminated`` stays ``False``) until the
    episode truncates, :attr:`refusal` holds the message meanwhile, and the next step raises it.

    Args:
        env_id (str): a registered Gymnasium id (gymnasium-robotics' are registered on import), e.g.
            ``"PointMaze_UMaze-v3"``.
        num_envs (int): the batch size. Defaults to ``1``.

    Keyword Args:
        seed (int, optional): copy ``i`` is reset with seed ``seed + i`` the first time, then draws on. Defaults
            to ``None`` (Gymnasium's own seeding).
        device (torch.device, optional): where the tensors live. Defaults to the CPU.
        max_episode_steps (int, optional): the episode length. Defaults to the env's ``TimeLimit``.
        reset_options (dict or sequence of dict, optional): ``options`` of every reset (e.g. the mazes'
            ``{"goal_cell": ..., "reset_cell": ...}`` for fixed test goals), or one per episode in turn.
        success_threshold (float, optional): success is ``||achieved_goal - desired_goal|| <= threshold``;
            needed only when the env writes no success entry into ``info``.
        goals (goal or list of goals, optional): fixed goals, one per episode in turn (e.g. the test goals): after
            each reset the env's ``goal`` attribute (where gymnasium-robotics' envs keep it, and read it for their
            rewards and observations) and the observed ``desired_goal`` are set to it. Defaults to ``None`` (the
            env's own goals).
        make_kwargs (dict, optional): keyword arguments of ``gymnasium.make``.
        achieved_goal_in_observation (bool, optional): put the achieved goal first in the observation
            (``observation = [achieved_goal, env observation]``, so ``goal_indices`` are ``0 .. goal_dim - 1``):
            ``True`` always, ``False`` never, ``None`` (default) when the env's own observation does not hold it,
            as found at construction from a reset and a few random steps of the first copy (every achieved-goal
            entry equal to an observation entry at each of them).
        right_flipped_after (int, optional): gymnasium-robotics' ant mazes only: after this many consecutive env
            steps upside down (the torso's up axis below the horizon) the ant is put back on its feet in its
            reset pose at rest, at its (x, y) and heading, clear of the walls; the episode goes on (the built-in
            ant mazes' option of the same name; :class:`RightFlippedAnt` for a Gymnasium pipeline). Defaults
            to ``None``: a flipped ant stays flipped until its episode ends, as the env's own.

    Attributes:
        max_episode_steps (int): the episode length (the contract's attribute).
        env_id (str): the Gymnasium id.
        achieved_goal_in_observation (bool): whether the adapter puts the achieved goal first in the observation.
        upside_down_steps (np.ndarray): consecutive env steps each copy's ant has been upside down (counted with
            ``right_flipped_after`` only; part of :meth:`state_dict`).
        refusal (str or None): the message of an env that ended an episode itself, from that step until the next
            step after the episode's end raises it (``None`` otherwise): a training loop reads it at its batch
            boundaries to stop there.

    Examples:
        >>> env = GymnasiumGoalEnv("PointMaze_UMaze-v3", num_envs=2, seed=0)  # doctest: +SKIP
        >>> td = env.rollout(3)  # doctest: +SKIP
        >>> td["next", "observation"].dtype, td["next", "is_success"].shape, env.max_episode_steps  # doctest: +SKIP
        (torch.float32, torch.Size([2, 3, 1]), 300)
    """

    @checked(
        num_envs=integer(1),
        max_episode_steps=integer(1, optional=True),
        reset_options=ArgumentCheck(_options, "a dict of reset options or a non-empty list of them", optional=True),
        success_threshold=number(0.0, low_open=True, optional=True),
        goals=ArgumentCheck(_goal_list, "a goal (a list of numbers) or a non-empty list of goals", optional=True),
        make_kwargs=ArgumentCheck(lambda v: isinstance(v, Mapping), "a dict of gymnasium.make arguments", optional=True),
        achieved_goal_in_observation=ArgumentCheck(lambda v: isinstance(v, bool), "a bool", optional=True),
        right_flipped_after=integer(1, optional=True, what="env steps upside down before the ant is righted"),
    )
    def __init__(
        self,
        env_id: str,
        num_envs: int = 1,
        *,
        seed: int | None = None,
        device: torch.device | str | None = None,
        max_episode_steps: int | None = None,
        reset_options: Mapping[str, Any] | Sequence[Mapping[str, Any]] | None = None,
        success_threshold: float | None = None,
        goals: Sequence[float] | Sequence[Sequence[float]] | None = None,
        make_kwargs: Mapping[str, Any] | None = None,
        achieved_goal_in_observation: bool | None = None,
        right_flipped_after: int | None = None,
    ) -> None:
        gym = _import_gymnasium(env_id)
        super().__init__(device=device or "cpu", batch_size=torch.Size([num_envs]))
        self.env_id = env_id
        self._envs = [gym.make(env_id, **dict(make_kwargs or {})) for _ in range(num_envs)]
        first = self._envs[0]
        if getattr(first.unwrapped, "continuing_task", None) is False:  # it says so: refused before any step
            for env in self._envs:
                env.close()
            raise GoalEnvError(
                f"{env_id} has continuing_task=False (`make_kwargs`={dict(make_kwargs or {})}): it ends an episode "
                "itself when its goal is reached, and every episode must last max_episode_steps steps; accepted: "
                "continuing_task=True (the mazes' default: leave it out of `make_kwargs`, or set it there)."
            )
        if right_flipped_after is not None and not _holds_an_ant(first.unwrapped):
            for env in self._envs:
                env.close()
            raise GoalEnvError(
                f"right_flipped_after rights a flipped ant: it applies to gymnasium-robotics' ant mazes (AntMaze_*), "
                f"not to {env_id}; leave it None (null)."
            )
        self.right_flipped_after = None if right_flipped_after is None else int(right_flipped_after)
        space = first.observation_space
        if not isinstance(space, gym.spaces.Dict) or any(k not in space.spaces for k in _GOAL_KEYS):
            raise GoalEnvError(
                f"{env_id}: its observation space is {type(space).__name__}"
                f"{' with ' + str(sorted(space.spaces)) if isinstance(space, gym.spaces.Dict) else ''}; a goal env "
                f"has a Dict observation with {list(_GOAL_KEYS)}."
            )
        action = first.action_space
        if not isinstance(action, gym.spaces.Box) or not np.isfinite(action.low).all() or not np.isfinite(action.high).all():
            raise GoalEnvError(f"{env_id}: its action space {action} is not a finite Box.")
        steps = max_episode_steps or (first.spec.max_episode_steps if first.spec is not None else None)
        if steps is None:
            raise GoalEnvError(
                f"{env_id} has no TimeLimit (spec.max_episode_steps is None); pass max_episode_steps."
            )
        self.max_episode_steps = int(steps)
        self.success_threshold = None if success_threshold is None else float(success_threshold)
        if goals is not None:
            goals = np.asarray(goals, dtype=np.float64).reshape(-1, space.spaces["desired_goal"].shape[-1])
            if not hasattr(first.unwrapped, "goal") and not hasattr(first.unwrapped, "reset"):
                raise GoalEnvError(f"{env_id} keeps no `goal` attribute to set fixed goals on.")
        self.goals = goals
        if isinstance(reset_options, Mapping):
            reset_options = [reset_options]
        self.reset_options = [dict(o) for o in reset_options] if reset_options else None
        sizes = {key: int(np.prod(space.spaces[key].shape)) for key in _GOAL_KEYS}
        if sizes["achieved_goal"] != sizes["desired_goal"]:
            raise GoalEnvError(f"{env_id}: achieved_goal and desired_goal differ in size ({sizes}).")
        if achieved_goal_in_observation is None:
            options = self.reset_options[0] if self.reset_options else None
            achieved_goal_in_observation = not _holds_goal(first.unwrapped, action, options)
        self.achieved_goal_in_observation = bool(achieved_goal_in_observation)
        if self.achieved_goal_in_observation:
            sizes["observation"] += sizes["achieved_goal"]
        batch = self.batch_size
        self.observation_spec = Composite(
            observation=Unbounded((*batch, sizes["observation"]), dtype=torch.float32, device=self.device),
            achieved_goal=Unbounded((*batch, sizes["achieved_goal"]), dtype=torch.float32, device=self.device),
            desired_goal=Unbounded((*batch, sizes["desired_goal"]), dtype=torch.float32, device=self.device),
            is_success=Categorical(2, (*batch, 1), dtype=torch.bool, device=self.device),
            step_count=Unbounded((*batch, 1), dtype=torch.int64, device=self.device),
            shape=batch,
            device=self.device,
        )
        self.action_spec = Bounded(
            torch.as_tensor(action.low, dtype=torch.float32).expand(*batch, *action.shape),
            torch.as_tensor(action.high, dtype=torch.float32).expand(*batch, *action.shape),
            (*batch, *action.shape),
            dtype=torch.float32,
            device=self.device,
        )
        self.reward_spec = Unbounded((*batch, 1), dtype=torch.float32, device=self.device)
        self.done_spec = Composite(
            {k: Categorical(2, (*batch, 1), dtype=torch.bool, device=self.device) for k in ("done", "terminated", "truncated")},
            shape=batch,
            device=self.device,
        )
        self._seeds: list[int | None] = [None] * num_envs
        self._steps = np.zeros(num_envs, dtype=np.int64)
        self._episodes = np.zeros(num_envs, dtype=np.int64)
        self._last: list[dict[str, np.ndarray] | None] = [None] * num_envs
        self._success = np.zeros(num_envs, dtype=bool)
        self._held = np.zeros(num_envs, dtype=bool)  # ended its episode itself: held at its last state
        self._rewards = np.zeros(num_envs, dtype=np.float32)
        self.upside_down_steps = np.zeros(num_envs, dtype=np.int64)
        self.refusal: str | None = None
        if seed is not None:
            self.set_seed(seed)

    # ---- seeding, reset and step ----------------------------------------------------------------------------

    def _set_seed(self, seed: int | None) -> None:
        self._seeds = [None if seed is None else int(seed) + i for i in range(self.batch_size[0])]

    def _reset_one(self, i: int, goal: np.ndarray | None = None) -> None:
        options = None
        if self.reset_options:
            options = self.reset_options[int(self._episodes[i]) % len(self.reset_options)]
        env = self._envs[i].unwrapped
        obs, info = env.reset(seed=self._seeds[i], options=options)
        if goal is None and self.goals is not None:
            goal = self.goals[int(self._episodes[i]) % len(self.goals)]
        if goal is not None:  # a fixed goal: where the env reads it, and in what it observed
            env.goal = goal.astype(np.asarray(env.goal).dtype).reshape(np.shape(env.goal))
            obs = {**obs, "desired_goal": env.goal.copy()}
            radius = self.success_radius()  # the env's info was about its own goal
            distance = np.linalg.norm(np.asarray(obs["achieved_goal"]) - np.asarray(obs["desired_goal"]))
            info = {"is_success": radius is not None and bool(distance <= radius)}
        self._seeds[i] = None
        self._episodes[i] += 1
        self._steps[i] = 0
        self._held[i] = False
        self.upside_down_steps[i] = 0
        self._last[i] = obs
        self._success[i] = self._is_success(obs, info)

    def _reset_goals(self, tensordict: TensorDictBase) -> np.ndarray | None:
        """The ``"desired_goal"`` entry of a reset tensordict as ``[num_envs, goal_dim]`` float64, checked."""
        if "start" in tensordict.keys():
            raise GoalEnvError(
                f"{self.env_id}: a 'start' entry passed to reset moves the built-in mazes' agents only; a Gymnasium "
                "env starts where its reset options put it (the mazes' `reset_cell`)."
            )
        value = tensordict.get("desired_goal", None)
        if value is None:
            return None
        expected = (*self.batch_size, self.observation_spec["desired_goal"].shape[-1])
        if tuple(value.shape) != expected:
            raise GoalEnvError(
                f"A 'desired_goal' passed to reset must have shape {expected}, got {tuple(value.shape)}."
            )
        if not hasattr(self._envs[0].unwrapped, "goal"):
            raise GoalEnvError(f"{self.env_id} keeps no `goal` attribute to set the goals passed to reset on.")
        return value.detach().cpu().double().numpy()

    def _is_success(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any]) -> bool:
        if self.success_threshold is not None:
            distance = np.linalg.norm(np.asarray(obs["achieved_goal"]) - np.asarray(obs["desired_goal"]))
            return bool(distance <= self.success_threshold)
        for key in _SUCCESS_KEYS:
            if key in info:
                return bool(np.asarray(info[key]).reshape(-1)[0])
        return False

    def _output(self) -> TensorDict:
        def stack(key: str) -> torch.Tensor:
            values = np.stack([np.asarray(last[key], dtype=np.float32).reshape(-1) for last in self._last])
            return torch.as_tensor(values, device=self.device)

        out = {key: stack(key) for key in _GOAL_KEYS}
        if self.achieved_goal_in_observation:
            out["observation"] = torch.cat([out["achieved_goal"], out["observation"]], dim=-1)
        return TensorDict(
            out
            | {
                "is_success": torch.tensor(self._success, device=self.device).reshape(-1, 1),
                "step_count": torch.tensor(self._steps, device=self.device).reshape(-1, 1),
            },
            batch_size=self.batch_size,
            device=self.device,
        )

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = goals = None
        if tensordict is not None:
            if "_reset" in tensordict.keys():
                mask = tensordict.get("_reset").reshape(-1).cpu().numpy()
            goals = self._reset_goals(tensordict)
        for i in range(self.batch_size[0]):
            if mask is None or mask[i] or self._last[i] is None:
                self._reset_one(i, None if goals is None else goals[i])
        out = self._output()
        false = torch.zeros(*self.batch_size, 1, dtype=torch.bool, device=self.device)
        return out.update({"done": false, "terminated": false.clone(), "truncated": false.clone()})

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self.refusal is not None and not self._held.any():  # the episode it ended has ended: refused now
            raise GoalEnvError(self.refusal)
        actions = tensordict.get("action").detach().cpu().numpy().astype(np.float64)
        for i, env in enumerate(self._envs):
            self._steps[i] += 1
            if self._held[i]:  # ended its episode itself: its last state until the episode's end
                continue
            obs, reward, terminated, _, info = env.unwrapped.step(actions[i])
            success = self._is_success(obs, info)
            if self.right_flipped_after is not None:
                flipped = _ant_upside_down(env.unwrapped)
                self.upside_down_steps[i] = self.upside_down_steps[i] + 1 if flipped else 0
                if self.upside_down_steps[i] >= self.right_flipped_after:  # rare: no hot path
                    obs, reward, at_goal = _righted_step(env.unwrapped)
                    success = self._is_success(obs, {"success": at_goal})  # success_threshold, where given, decides
                    self.upside_down_steps[i] = 0
            self._last[i] = obs
            self._success[i] = success
            self._rewards[i] = float(reward)
            if terminated:
                self._held[i] = True
                if self.refusal is None:
                    self.refusal = (
                        f"{self.env_id} ended an episode itself (terminated) after {self._steps[i]} of "
                        f"{self.max_episode_steps} steps; every episode must last max_episode_steps steps (the "
                        "recipe's collector yields whole episodes of one length): make the env continuing, by a "
                        "`make_kwargs` option of its own (the mazes' continuing_task=True) or in its code or a "
                        "wrapper registered under its id, which never sets terminated."
                    )
        rewards = self._rewards.copy()
        out = self._output()
        truncated = torch.as_tensor(self._steps >= self.max_episode_steps, device=self.device).reshape(-1, 1)
        return out.update(
            {
                "reward": torch.as_tensor(rewards, device=self.device).reshape(-1, 1),
                "done": truncated.clone(),
                "terminated": torch.zeros_like(truncated),
                "truncated": truncated,
            }
        )

    # ---- the goal space --------------------------------------------------------------------------------------

    def maze_geometry(self, *, margin: float = 0.0, resolution: float | None = None):
        """The true geometry of the env's maze (:meth:`MazeGeometry.from_gymnasium_maze
        <torchrl_dhrl.envs.geometry.MazeGeometry.from_gymnasium_maze>`: gymnasium-robotics' ``PointMaze_*`` and
        ``AntMaze_*`` keep theirs as ``env.unwrapped.maze``), walls inflated by ``margin``, or ``None`` for an env
        without one. Progress is measured from the centre of the resets' ``reset_cell`` where every reset option
        gives the same one; elsewhere the geometry has no start (``start`` is ``None``)."""
        maze = getattr(self._envs[0].unwrapped, "maze", None)
        if maze is None or not hasattr(maze, "maze_map") or not hasattr(maze, "cell_rowcol_to_xy"):
            return None
        from .geometry import MazeGeometry

        cells = {tuple(np.asarray(o["reset_cell"]).tolist()) if "reset_cell" in o else None for o in self.reset_options or [{}]}
        start_cell = next(iter(cells)) if len(cells) == 1 else None
        return MazeGeometry.from_gymnasium_maze(maze, start_cell=start_cell, margin=margin, resolution=resolution)

    def reset_cell_at(self, point: Sequence[float]) -> tuple[int, int]:
        """The ``(row, col)`` of the free maze cell holding ``point`` (goal units), for the ``reset_cell`` of
        reset options (a gymnasium-robotics maze starts its agent at a cell's centre, with reset noise).

        Raises:
            ValueError: for an env without a gymnasium-robotics maze, or a point in a wall or outside the maze.
        """
        maze = getattr(self._envs[0].unwrapped, "maze", None)
        if maze is None or not hasattr(maze, "maze_map") or not hasattr(maze, "cell_xy_to_rowcol"):
            raise ValueError(f"{self.env_id} has no gymnasium-robotics maze to start from a point of.")
        row, col = (int(v) for v in maze.cell_xy_to_rowcol(np.asarray(point, dtype=np.float64)))
        cells = np.asarray(maze.maze_map)
        inside = 0 <= row < cells.shape[0] and 0 <= col < cells.shape[1]
        if not inside or cells[row, col] == 1:
            where = f"in cell ({row}, {col}), a wall," if inside else "outside the maze"
            raise ValueError(
                f"The start {list(point)} lies {where} of {self.env_id}; accepted: a point in a free cell."
            )
        return row, col

    def success_radius(self, *, tolerance: float = 1e-6) -> float | None:
        """The distance within which the env counts a goal as reached: ``success_threshold`` if given, else
        found from the env's ``compute_reward`` (the largest offset of the achieved goal that still earns the
        at-goal reward, by bisection); ``None`` when the env has no ``compute_reward`` or its reward does not
        step at a distance."""
        if self.success_threshold is not None:
            return self.success_threshold
        if getattr(self, "_radius", None) is not None:
            return self._radius
        env = self._envs[0].unwrapped
        compute = getattr(env, "compute_reward", None)
        if compute is None:
            return None
        size = self.observation_spec["desired_goal"].shape[-1]
        goal = np.zeros(size)
        direction = np.eye(size)[0]

        def reward(r: float) -> float:
            return float(np.asarray(compute(goal + r * direction, goal, {})).reshape(-1)[0])

        at_goal, low, high = reward(0.0), 0.0, 1.0
        while reward(high) == at_goal:
            high *= 2
            if high > 1e6:
                return None
        while high - low > tolerance:
            middle = (low + high) / 2
            low, high = (middle, high) if reward(middle) == at_goal else (low, middle)
        self._radius = low
        return low

    # ---- state, for exact resumes ----------------------------------------------------------------------------

    def state_dict(self, *args, **kwargs) -> dict[str, Any]:
        """The simulators' state (arrays, random generators and MuJoCo integration state of each copy and of the
        Gymnasium objects it holds), the step counts and the last observations: a resumed env steps on exactly
        as the saved one where the env keeps its state in those (gymnasium-robotics' MuJoCo envs do)."""
        return {
            "exact": True,
            "envs": [_capture(env.unwrapped) for env in self._envs],
            "steps": self._steps.copy(),
            "episodes": self._episodes.copy(),
            "success": self._success.copy(),
            "last": [None if last is None else {k: np.asarray(v).copy() for k, v in last.items()} for last in self._last],
            "seeds": list(self._seeds),
            "held": self._held.copy(),
            "rewards": self._rewards.copy(),
            "upside_down_steps": self.upside_down_steps.copy(),
        }

    def load_state_dict(self, state_dict: Mapping[str, Any], *args, **kwargs) -> None:
        if len(state_dict["envs"]) != len(self._envs):
            raise ValueError(
                f"The state holds {len(state_dict['envs'])} envs; this {type(self).__name__} has {len(self._envs)}."
            )
        for env, state in zip(self._envs, state_dict["envs"], strict=True):
            _restore(env.unwrapped, state)
        self._steps = np.array(state_dict["steps"])
        self._episodes = np.array(state_dict["episodes"])
        self._success = np.array(state_dict["success"])
        self._last = [None if last is None else dict(last) for last in state_dict["last"]]
        self._seeds = list(state_dict["seeds"])
        n = len(self._envs)  # (states saved before these entries: no copy held, no ant upside down)
        self._held = np.array(state_dict.get("held", np.zeros(n, dtype=bool)))
        self._rewards = np.array(state_dict.get("rewards", np.zeros(n, dtype=np.float32)))
        self.upside_down_steps = np.array(state_dict.get("upside_down_steps", np.zeros(n, dtype=np.int64)))

    def close(self, *args, **kwargs) -> None:
        for env in self._envs:
            env.close()
        super().close(*args, **kwargs)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}({self.env_id!r}, num_envs={self.batch_size[0]}, "
            f"max_episode_steps={self.max_episode_steps}"
            + (", achieved_goal_in_observation=True" if self.achieved_goal_in_observation else "")
            + (f", right_flipped_after={self.right_flipped_after}" if self.right_flipped_after is not None else "")
            + ")"
        )


def goal_extent(env: EnvBase, *, episodes: int = 32, seed: int = 0) -> tuple[list[float], list[float]]:
    """The box of the goal space an env uses: the smallest box holding the desired goals of ``episodes``
    resets and the achieved goals of their first steps under uniform random actions, widened by a tenth of its
    size on every side (at least ``1e-3``).

    Returns:
        ``(low, high)``, lists of floats of the goal size.
    """
    generator = torch.Generator().manual_seed(seed)
    spec = env.full_action_spec["action"]
    points = []
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        env.set_seed(seed)
        td = env.reset()
        for _ in range(math.ceil(episodes / env.batch_size.numel())):
            points += [td["desired_goal"].reshape(-1, td["desired_goal"].shape[-1]), td["achieved_goal"].reshape(-1, td["achieved_goal"].shape[-1])]
            for _ in range(min(env.max_episode_steps, 50)):
                low, high = spec.space.low, spec.space.high
                action = low + (high - low) * torch.rand(low.shape, generator=generator)
                td = env.step(td.set("action", action.to(td.device)))["next"]
                points.append(td["achieved_goal"].reshape(-1, td["achieved_goal"].shape[-1]))
            td = env.reset()
    cloud = torch.cat(points).float()
    low, high = cloud.min(0).values, cloud.max(0).values
    pad = ((high - low) / 10).clamp_min(1e-3)
    return (low - pad).tolist(), (high + pad).tolist()


def goal_speed(env: EnvBase, *, episodes: int = 32, steps: int = 50, seed: int = 0) -> float:
    """The agent's top speed in goal units per env step, from short rollouts: the larger of

    - the fastest 5 steps in a row (mean per-step move of the achieved goal) while one action entry is held at
      either end of its range for ``steps`` steps (the others at the box's centre), from a reset each, over those
      pushes: a body that a constant action speeds up (gymnasium-robotics' point, 0.052; the built-in PointMaze's,
      0.2);
    - the 95th percentile of its per-step moves under uniform random actions (``episodes`` resets of ``steps``
      steps): a legged body that a constant action does not carry, but whose random steps do (the ants, about 0.1).

    Checked against the built-in env files' hand-set ``planner.oracle_speed`` (tests/envs/test_gymnasium_goal_env.py).
    Deterministic for a given ``seed``; the global torch random state is left as it was.

    Examples:
        >>> from torchrl_dhrl.envs import make_env
        >>> round(goal_speed(make_env("PointMaze", seed=0)), 2)
        0.2
    """
    generator = torch.Generator().manual_seed(seed)
    box = env.full_action_spec["action"].space
    low, high = box.low, box.high
    size = low.shape[-1]
    moves = []
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        env.set_seed(seed)

        def rollout(action_of) -> torch.Tensor:  # [steps, envs] per-step moves of the achieved goal
            td = env.reset()
            goal, out = td["achieved_goal"], []
            for _ in range(min(env.max_episode_steps, steps)):
                td = env.step(td.set("action", action_of().to(td.device)))["next"]
                out.append((td["achieved_goal"] - goal).norm(dim=-1).reshape(-1))
                goal = td["achieved_goal"]
            return torch.stack(out)

        pushed = []
        try:  # an env that ends an episode itself is refused at its next episode (GymnasiumGoalEnv): measured so far
            for i in range(size):
                for end in (low, high):
                    action = (low + high) / 2
                    action[..., i] = end[..., i]
                    held = rollout(lambda a=action: a)
                    window = min(5, held.shape[0])
                    pushed.append(held.unfold(0, window, 1).mean(-1).max())  # its fastest 5 steps in a row
            for _ in range(math.ceil(episodes / env.batch_size.numel())):
                moves.append(rollout(lambda: low + (high - low) * torch.rand(low.shape, generator=generator)))
        except GoalEnvError:
            if not pushed:
                raise
    top = torch.stack(pushed).max().float()
    return float(torch.maximum(top, torch.quantile(torch.cat(moves).flatten().float(), 0.95)) if moves else top)


def goal_indices_of(env: EnvBase, *, steps: int = 20, seed: int = 0) -> list[int] | None:
    """Where the achieved goal sits in the observation, read from a short random rollout: for each goal entry,
    the first observation entry equal to it at every step; ``None`` when some goal entry has none.

    Examples:
        >>> from torchrl_dhrl.envs import make_env
        >>> goal_indices_of(make_env("PointMaze", seed=0))
        [0, 1]
    """
    generator = torch.Generator().manual_seed(seed)
    box = env.full_action_spec["action"].space
    with torch.random.fork_rng():
        env.set_seed(seed)
        td = env.reset()
        observations, goals = [td["observation"]], [td["achieved_goal"]]
        for _ in range(steps):
            action = box.low + (box.high - box.low) * torch.rand(box.low.shape, generator=generator)
            td = env.step(td.set("action", action.to(td.device)))["next"]
            observations.append(td["observation"])
            goals.append(td["achieved_goal"])
            if td["done"].any():
                td = env.reset()
    obs = torch.stack(observations).reshape(-1, observations[0].shape[-1])
    goal = torch.stack(goals).reshape(-1, goals[0].shape[-1])
    indices = []
    for j in range(goal.shape[-1]):
        matches = [i for i in range(obs.shape[-1]) if i not in indices and torch.equal(obs[:, i], goal[:, j])]
        if not matches:
            return None
        indices.append(matches[0])
    return indices
