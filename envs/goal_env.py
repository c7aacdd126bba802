"""The goal-env key contract of torchrl-dhrl and :func:`check_goal_env`, which validates an env against it.

Every part of the library reads an environment through a handful of tensordict entries; any TorchRL
:class:`~torchrl.envs.EnvBase` that provides them (the seven built-in tasks, or an env of your own
registered with :func:`~torchrl_dhrl.envs.register_env`) can be trained by the recipe. See
``docs/goal_env.md`` for the contract with an example.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded
from torchrl.envs import EnvBase

__all__ = ["GOAL_ENV_KEYS", "GoalEnvError", "check_goal_env"]

#: The entries of the contract: key -> (where it lives, dtype kind, shape after the batch dims).
#: ``"obs_dim"`` / ``"goal_dim"`` / ``"action_dim"`` stand for sizes the env chooses (>= 1).
GOAL_ENV_KEYS: dict[str, tuple[str, str, tuple]] = {
    "observation": ("observation", "float32", ("obs_dim",)),
    "achieved_goal": ("observation", "float32", ("goal_dim",)),
    "desired_goal": ("observation", "float32", ("goal_dim",)),
    "is_success": ("observation", "bool", (1,)),
    "step_count": ("observation", "int", (1,)),
    "action": ("action", "float32", ("action_dim",)),
    "reward": ("reward", "float", (1,)),
    "done": ("done", "bool", (1,)),
    "terminated": ("done", "bool", (1,)),
    "truncated": ("done", "bool", (1,)),
}

_DOC = "see docs/goal_env.md"
_KINDS = {
    "float32": (
        "torch.float32, the networks' dtype (a float64 env: append torchrl's DoubleToFloat transform, or wrap a "
        "Gymnasium goal env with torchrl_dhrl.envs.GymnasiumGoalEnv, which converts)",
        lambda dtype: dtype == torch.float32,
    ),
    "float": ("a floating dtype", lambda dtype: dtype.is_floating_point),
    "bool": ("torch.bool", lambda dtype: dtype == torch.bool),
    "int": ("an integer dtype", lambda dtype: not dtype.is_floating_point and dtype != torch.bool),
}


#: What to add for each missing key.
_GYMNASIUM = "a Gymnasium goal env: wrap it with torchrl_dhrl.envs.GymnasiumGoalEnv (make_env('gymnasium:<id>')), which provides every key"
_MISSING_HINTS = {
    "observation": f"the state the policies read, float32 [*B, obs_dim] ({_GYMNASIUM})",
    "achieved_goal": f"the point of goal space the state reaches, float32 [*B, goal_dim] ({_GYMNASIUM})",
    "desired_goal": f"the episode's goal, float32 [*B, goal_dim] ({_GYMNASIUM})",
    "is_success": f"a bool [*B, 1] success flag, e.g. a transform renaming the env's own ({_GYMNASIUM})",
    "step_count": "add torchrl's StepCounter(max_steps=T) transform (and set max_episode_steps = T)",
    "action": "a Bounded float32 action spec under 'action'",
    "reward": "any float reward [*B, 1] (the library recomputes its own)",
    "done": "add torchrl's StepCounter(max_steps=T) transform for the truncation flags",
    "terminated": "add torchrl's StepCounter(max_steps=T) transform for the truncation flags",
    "truncated": "add torchrl's StepCounter(max_steps=T) transform, which writes it",
}


class GoalEnvError(ValueError):
    """An environment that does not meet the goal-env contract; the message names the key and what is accepted."""


def _fail(env: EnvBase, message: str) -> None:
    raise GoalEnvError(f"{type(env).__name__}: {message} ({_DOC}).")


def _specs(env: EnvBase) -> dict:
    return {
        "observation": env.full_observation_spec,
        "action": env.full_action_spec,
        "reward": env.full_reward_spec,
        "done": env.full_done_spec,
    }


def _check_spec(env: EnvBase, key: str, specs: dict, sizes: dict[str, int]) -> None:
    where, kind, feature = GOAL_ENV_KEYS[key]
    composite = specs[where]
    batch = env.batch_size
    if key not in composite.keys():
        listed = sorted(map(str, composite.keys(True, True)))
        _fail(env, f"its {where}_spec has no {key!r} entry (it holds {listed}); {_MISSING_HINTS[key]}")
    spec = composite[key]
    shape = tuple(spec.shape)
    if len(shape) != len(batch) + len(feature) or shape[: len(batch)] != tuple(batch):
        want = "[*batch_size, " + ", ".join(map(str, feature)) + "]"
        _fail(env, f"{where}_spec[{key!r}] has shape {shape}; expected {want} with batch_size {tuple(batch)}")
    for name, size in zip(feature, shape[len(batch) :], strict=True):
        if isinstance(name, str):
            if size < 1:
                _fail(env, f"{where}_spec[{key!r}] has an empty last dim ({name} = {size})")
            if sizes.setdefault(name, size) != size:
                _fail(
                    env,
                    f"{where}_spec[{key!r}] has {name} = {size} but an earlier entry has {sizes[name]}; "
                    "achieved_goal and desired_goal must have the same size",
                )
        elif size != name:
            _fail(env, f"{where}_spec[{key!r}] has shape {shape}; expected a trailing dim of {name}")
    text, accepts = _KINDS[kind]
    if not accepts(spec.dtype):
        _fail(env, f"{where}_spec[{key!r}] has dtype {spec.dtype}; expected {text}")


def _check_action_box(env: EnvBase) -> None:
    spec = env.full_action_spec["action"]
    if not isinstance(spec, Bounded):
        _fail(
            env, f"action_spec['action'] is a {type(spec).__name__}; expected a Bounded (continuous box) spec"
        )
    if not (torch.isfinite(spec.space.low).all() and torch.isfinite(spec.space.high).all()):
        _fail(
            env,
            "action_spec['action'] has infinite bounds; the actors scale their tanh output to a finite box",
        )
    if not (spec.space.low < spec.space.high).all():
        _fail(env, "action_spec['action'] must have low < high on every axis")


def _check_time_limit(env: EnvBase) -> int:
    steps = getattr(env, "max_episode_steps", None)
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        _fail(
            env,
            f"max_episode_steps is {steps!r}; expected the episode length as an int >= 1 (every episode "
            "truncates after exactly that many steps)",
        )
    return steps


def _check_data(env: EnvBase, data: TensorDictBase, prefix: tuple, keys: Sequence[str]) -> None:
    """The entries of a ``[*B, T]`` rollout: present, with the spec's shape (time inserted) and dtype."""
    specs, batch = _specs(env), len(env.batch_size)
    for key in keys:
        spec = specs[GOAL_ENV_KEYS[key][0]][key]
        name = "/".join((*prefix, key))
        value = data.get((*prefix, key), None)
        if value is None:
            _fail(env, f"a rollout has no {name!r} entry although the specs declare it")
        expected = (*spec.shape[:batch], data.shape[batch], *spec.shape[batch:])
        if tuple(value.shape) != expected or value.dtype != spec.dtype:
            _fail(
                env,
                f"a rollout's {name!r} is {value.dtype} {tuple(value.shape)}, but its spec says "
                f"{spec.dtype} {tuple(spec.shape)} (so {expected} over {data.shape[batch]} steps)",
            )


def _check_rollout(env: EnvBase, steps: int, goal_indices: Sequence[int] | None) -> None:
    box = env.full_action_spec["action"].space
    middle = (box.low + box.high) / 2

    def constant(td: TensorDictBase) -> TensorDictBase:  # no randomness: the global RNG is left alone
        return td.set("action", middle.clone())

    rollout = env.rollout(steps, constant, break_when_any_done=False)
    observations = [k for k, v in GOAL_ENV_KEYS.items() if v[0] == "observation"]
    _check_data(env, rollout, (), observations)
    _check_data(env, rollout, ("next",), [*observations, "reward", "done", "terminated", "truncated"])
    first = rollout[(slice(None),) * len(env.batch_size) + (0,)]
    if (first["step_count"] != 0).any():
        _fail(env, "step_count is not 0 right after reset; it must count the steps of the current episode")
    if (rollout["next", "step_count"] != rollout["step_count"] + 1).any():
        _fail(env, "('next', 'step_count') must be step_count + 1 within an episode")
    done = rollout["next", "done"]
    if not torch.equal(done, rollout["next", "terminated"] | rollout["next", "truncated"]):
        _fail(env, "done must equal terminated | truncated")
    _check_truncation(env, rollout, steps)
    if goal_indices is not None:
        indices = list(goal_indices)
        obs_dim = rollout["observation"].shape[-1]
        if any(not 0 <= i < obs_dim for i in indices):
            _fail(env, f"goal_indices {indices} fall outside the {obs_dim}-D observation")
        for prefix in ((), ("next",)):
            obs, achieved = rollout[(*prefix, "observation")], rollout[(*prefix, "achieved_goal")]
            if len(indices) != achieved.shape[-1] or not torch.allclose(obs[..., indices], achieved):
                _fail(
                    env,
                    f"observation[..., {indices}] is not the achieved_goal; goal_indices must say where the "
                    "achieved goal sits in the observation (null when it does not)",
                )


def _check_truncation(env: EnvBase, rollout: TensorDictBase, steps: int) -> None:
    """Every episode of the rollout ends by truncation after exactly ``max_episode_steps`` steps, never sooner and
    never by termination (the rollout resets the env after each end)."""
    length = env.max_episode_steps
    batch = len(env.batch_size)
    step = torch.arange(1, steps + 1).reshape((1,) * batch + (steps, 1))
    expected = (step % length == 0).expand_as(rollout["next", "truncated"]).to(rollout.device)
    terminated = rollout["next", "terminated"]
    if terminated.any():
        first = int(terminated.reshape(-1, steps).any(0).nonzero()[0]) + 1
        _fail(
            env,
            f"terminated is True at step {first}; every episode must end by truncation after max_episode_steps "
            f"({length}) steps, the collector yields whole episodes of that length (make the task continuing)",
        )
    truncated = rollout["next", "truncated"]
    if not torch.equal(truncated, expected):
        wrong = (truncated != expected).reshape(-1, steps).any(0).nonzero()
        first = int(wrong[0]) + 1
        actual = "truncated" if bool(truncated.reshape(-1, steps)[:, first - 1].any()) else "did not truncate"
        _fail(
            env,
            f"max_episode_steps is {length}, but the env {actual} at step {first} of the checking rollout "
            f"({steps} steps); max_episode_steps must be the step at which every episode truncates",
        )


def check_goal_env(env: EnvBase, *, goal_indices: Sequence[int] | None = None, steps: int = 2) -> None:
    """Checks that ``env`` meets the goal-env contract of torchrl-dhrl, raising one clear error if not.

    The contract (``docs/goal_env.md``) is what the planner, the relabelling, the evaluation and the
    recipe read from an environment; with ``B = env.batch_size``:

    ==================  =============  ==========================  ============================================
    key                 spec           shape, dtype                meaning
    ==================  =============  ==========================  ============================================
    ``observation``     observation    ``[*B, obs_dim]`` float     the state the policies and distances read
    ``achieved_goal``   observation    ``[*B, goal_dim]`` float    the point of goal space the state reaches
    ``desired_goal``    observation    ``[*B, goal_dim]`` float    the episode's goal (same shape and dtype)
    ``is_success``      observation    ``[*B, 1]`` bool            the state is within the success radius
    ``step_count``      observation    ``[*B, 1]`` integer         steps of the current episode, ``0`` at reset
    ``action``          action         ``[*B, action_dim]`` float  a :class:`~torchrl.data.Bounded` finite box
    ``reward``          reward         ``[*B, 1]`` float           any reward (the library recomputes its own)
    ``done``,           done           ``[*B, 1]`` bool            ``done == terminated | truncated``
    ``terminated``,
    ``truncated``
    ==================  =============  ==========================  ============================================

    and ``env.max_episode_steps``, an int: the recipe's collector yields whole episodes, so every episode
    must end by truncation after exactly that many steps. The checks read the specs, then (unless
    ``steps=0``) run a ``steps``-step rollout with the middle of the action box (no random numbers are
    drawn, so the global RNG is left as it was) and check that the data match the specs, that
    ``step_count`` counts from ``0``, that ``done == terminated | truncated``, and, with ``goal_indices``,
    that ``observation[..., goal_indices]`` is the achieved goal.

    Args:
        env (EnvBase): the environment to check (any batch size).

    Keyword Args:
        goal_indices (sequence of int, optional): where the achieved goal sits in the observation (the
            recipe's ``goal_indices``; relative goals and the oracle distance rely on it). Defaults to
            ``None`` (not checked).
        steps (int): length of the checking rollout; ``0`` checks the specs only. Defaults to ``2``.

    Raises:
        GoalEnvError: (a ``ValueError``) naming the env, the key and what is accepted.
        TypeError: when ``env`` is not a TorchRL ``EnvBase``.

    Examples:
        >>> from torchrl.testing.mocking_classes import ContinuousActionVecMockEnv
        >>> from torchrl_dhrl.envs import GoalEnvError, check_goal_env, make_env
        >>> check_goal_env(make_env("PointMaze", num_envs=2, seed=0), goal_indices=[0, 1])
        >>> try:
        ...     check_goal_env(ContinuousActionVecMockEnv())
        ... except GoalEnvError as err:
        ...     print(err)
        ContinuousActionVecMockEnv: its observation_spec has no 'achieved_goal' entry (it holds ['observation', 'observation_orig']); the point of goal space the state reaches, float32 [*B, goal_dim] (a Gymnasium goal env: wrap it with torchrl_dhrl.envs.GymnasiumGoalEnv (make_env('gymnasium:<id>')), which provides every key) (see docs/goal_env.md).
    """
    if not isinstance(env, EnvBase):
        raise TypeError(f"check_goal_env needs a TorchRL EnvBase, got {type(env).__name__}.")
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 0:
        raise ValueError(f"`steps` must be an int >= 0, got {steps!r}.")
    specs, sizes = _specs(env), {}
    for key in GOAL_ENV_KEYS:
        _check_spec(env, key, specs, sizes)
    _check_action_box(env)
    _check_time_limit(env)
    if steps:
        _check_rollout(env, steps, goal_indices)
