"""Every DHRL environment by name: the five mazes, the two arm tasks, and the envs registered by users."""

from __future__ import annotations

from collections.abc import Callable

from torchrl.envs import EnvBase

from .arms import ARMS
from .mazes import MAZES
from .task import TaskSpec, lookup_spec

__all__ = [
    "ENVS",
    "ENV_NAMES",
    "EnvFactory",
    "get_env_factory",
    "get_env_spec",
    "register_env",
    "registered_env_names",
    "unregister_env",
]

#: Every environment spec by name (mazes first, in the paper's order, then the arms).
ENVS: dict[str, TaskSpec] = {**MAZES, **ARMS}
#: The valid environment names.
ENV_NAMES: tuple[str, ...] = tuple(ENVS)

#: A user environment's factory, called by :func:`~torchrl_dhrl.envs.make_env` as
#: ``factory(num_envs=..., seed=..., device=..., eval=..., max_episode_steps=...)``.
EnvFactory = Callable[..., EnvBase]

#: The environments registered with :func:`register_env`: name -> factory.
_USER_ENVS: dict[str, EnvFactory] = {}


def get_env_spec(name: str | TaskSpec) -> TaskSpec:
    """Returns the spec of any environment, given a name (``"UR3Obstacle"``, ``"dhrl/AntMaze-v0"``) or a spec.

    Raises:
        ValueError: for an unknown name (the message lists the valid ones).
        TypeError: for anything else than a string or a :class:`~torchrl_dhrl.envs.TaskSpec`.

    Examples:
        >>> from torchrl_dhrl.envs import get_env_spec
        >>> get_env_spec("UR3Obstacle").episode_length, get_env_spec("dhrl/AntMaze-v0").goal_dim
        (100, 2)
    """
    return lookup_spec(name, ENVS, TaskSpec, "environment")


def register_env(name: str, factory: EnvFactory, *, overwrite: bool = False) -> None:
    """Makes a user environment available by name to :func:`~torchrl_dhrl.envs.make_env` and the recipe.

    ``factory`` builds the env; :func:`~torchrl_dhrl.envs.make_env` calls it with the keywords
    ``num_envs`` (the env's batch size must be ``[num_envs]``), ``seed`` (``int`` or ``None``),
    ``device``, ``eval`` (``True``: the test goals of evaluation episodes) and ``max_episode_steps``
    (``None``: the env's own episode length), and checks the result against the goal-env contract
    (:func:`~torchrl_dhrl.envs.check_goal_env`, ``docs/goal_env.md``). The training recipe then runs on
    it with ``env_name=<name>`` and the env's hyperparameters as overrides (``high.subgoal_low``,
    ``high.subgoal_high``, ``goal_indices``, ...). Registrations live in the current process.

    Args:
        name (str): the name; not one of the built-in :data:`~torchrl_dhrl.envs.ENV_NAMES`.
        factory (callable): ``factory(*, num_envs, seed, device, eval, max_episode_steps) -> EnvBase``.

    Keyword Args:
        overwrite (bool): replace an earlier registration of ``name``. Defaults to ``False``.

    Raises:
        ValueError: for a built-in name, an empty name, or a name already registered (without
            ``overwrite``).
        TypeError: when ``factory`` is not callable.

    Examples:
        >>> from torchrl_dhrl.envs import make_env, register_env, registered_env_names, unregister_env
        >>> def small_point_maze(*, num_envs, seed, device, eval, max_episode_steps):
        ...     return make_env("PointMaze", num_envs=num_envs, seed=seed, device=device, eval=eval,
        ...                     max_episode_steps=max_episode_steps or 50)
        >>> register_env("ShortPointMaze", small_point_maze)
        >>> registered_env_names()
        ('ShortPointMaze',)
        >>> make_env("ShortPointMaze", num_envs=2, seed=0).max_episode_steps
        50
        >>> unregister_env("ShortPointMaze")
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"An environment name must be a non-empty string, got {name!r}.")
    if name in ENVS:
        raise ValueError(f"{name!r} is a built-in environment; register yours under another name.")
    if not callable(factory):
        raise TypeError(
            f"`factory` must be callable (num_envs=..., ...) -> EnvBase, got {type(factory).__name__}."
        )
    if name in _USER_ENVS and not overwrite:
        raise ValueError(f"An environment {name!r} is already registered; pass overwrite=True to replace it.")
    _USER_ENVS[name] = factory


def unregister_env(name: str) -> None:
    """Removes an environment registered with :func:`register_env`.

    Raises:
        ValueError: when ``name`` was not registered (built-in environments cannot be removed).
    """
    if name not in _USER_ENVS:
        raise ValueError(f"No environment {name!r} was registered with register_env.")
    del _USER_ENVS[name]


def registered_env_names() -> tuple[str, ...]:
    """The names registered with :func:`register_env`, in registration order (built-ins excluded)."""
    return tuple(_USER_ENVS)


def get_env_factory(name: str) -> EnvFactory | None:
    """The factory registered under ``name`` with :func:`register_env`, or ``None``."""
    return _USER_ENVS.get(name) if isinstance(name, str) else None
