"""Every DHRL environment by name: the five mazes, then the two arm tasks."""

from __future__ import annotations

from .arms import ARMS
from .mazes import MAZES
from .task import TaskSpec, lookup_spec

__all__ = ["ENVS", "ENV_NAMES", "get_env_spec"]

#: Every environment spec by name (mazes first, in the paper's order, then the arms).
ENVS: dict[str, TaskSpec] = {**MAZES, **ARMS}
#: The valid environment names.
ENV_NAMES: tuple[str, ...] = tuple(ENVS)


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
