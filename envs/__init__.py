"""The DHRL paper's MuJoCo mazes (installed as ``torchrl_dhrl.envs``).

Five environments, each fully described by a :class:`MazeSpec` in :data:`MAZES`: ``PointMaze``,
``AntMazeSmall``, ``AntMaze``, ``AntMazeBottleneck`` and ``AntMazeComplex``. The arenas are built
programmatically from their grids with :mod:`dm_control.mjcf`; one batched simulation core
(:class:`MazeSimulation`) serves two front ends:

* TorchRL: :func:`make_env` / :class:`MazeEnv`, a native batched ``EnvBase`` (float32 tensors);
* Gymnasium: ids ``dhrl/<name>-v0`` (registered on import) / :class:`MazeGoalEnv`, goal-env convention
  (float64 ``Dict`` observations, vectorised ``compute_reward``, ``info["is_success"]``).

:func:`plot_maze` draws a maze from above with matplotlib (walls, start, test goals, trajectories,
landmarks, edges and paths).
"""

from .agents import AntAgent, PointAgent
from .arena import build_maze_mjcf, compile_maze_model
from .goals import BoxGoalSampler, FixedGoalSampler, FreeCellGoalSampler, GoalSampler
from .gym_env import MazeGoalEnv, register_gym_envs
from .layouts import COMPLEX_MAZE, U_MAZE, MazeLayout, WallBox, bottleneck_walls
from .mazes import MAZE_NAMES, MAZES, MazeSpec, get_maze_spec
from .plotting import plot_maze
from .simulation import MazeSimulation, sparse_reward
from .torchrl_env import MazeEnv, make_env

#: The registered Gymnasium ids, ``dhrl/<name>-v0``.
GYM_IDS: tuple[str, ...] = tuple(register_gym_envs())

__all__ = [
    "AntAgent",
    "BoxGoalSampler",
    "COMPLEX_MAZE",
    "FixedGoalSampler",
    "FreeCellGoalSampler",
    "GYM_IDS",
    "GoalSampler",
    "MAZES",
    "MAZE_NAMES",
    "MazeEnv",
    "MazeGoalEnv",
    "MazeLayout",
    "MazeSimulation",
    "MazeSpec",
    "PointAgent",
    "U_MAZE",
    "WallBox",
    "bottleneck_walls",
    "build_maze_mjcf",
    "compile_maze_model",
    "get_maze_spec",
    "make_env",
    "plot_maze",
    "register_gym_envs",
    "sparse_reward",
]
