"""The DHRL paper's MuJoCo environments (installed as ``torchrl_dhrl.envs``).

Seven environments, each fully described by a task spec (:class:`TaskSpec`) in :data:`ENVS`:

* five mazes (:class:`MazeSpec` in :data:`MAZES`): ``PointMaze``, ``AntMazeSmall``, ``AntMaze``,
  ``AntMazeBottleneck`` and ``AntMazeComplex``, whose arenas are built from their grids;
* two robot-arm tasks (:class:`ArmSpec` in :data:`ARMS`): ``Reacher3D`` (a 7-DoF PR2-like arm) and
  ``UR3Obstacle`` (a UR3 reaching behind thin boards), with 3-D end-effector goals.

All models are built programmatically with :mod:`dm_control.mjcf`. One batched simulation core
(:class:`GoalSimulation`) serves two front ends:

* TorchRL: :func:`make_env` / :class:`GoalEnv`, a native batched ``EnvBase`` (float32 tensors);
* Gymnasium: ids ``dhrl/<name>-v0`` (registered on import) / :class:`GymGoalEnv`, goal-env convention
  (float64 ``Dict`` observations, vectorised ``compute_reward``, ``info["is_success"]``).

Any other TorchRL env can join them: :func:`check_goal_env` validates the key contract the library reads
(``observation``, ``achieved_goal``, ``desired_goal``, ``is_success``, ``step_count``, the done flags and
``max_episode_steps``; ``docs/goal_env.md``) and :func:`register_env` makes it available by name to
:func:`make_env` and the training recipe.

:func:`plot_env` draws any environment with matplotlib (:func:`plot_maze` from above with walls, start
and test goals; :func:`plot_arm` as a top, front or side projection with the arm, the boards and the goal
region), with trajectories, landmarks, edges and paths in goal space.
"""

from .agents import AntAgent, MotorControl, PointAgent
from .arms import ARM_NAMES, ARMS, ArmSpec, build_arm_mjcf, get_arm_spec, ur3_boards
from .goal_env import GOAL_ENV_KEYS, GoalEnvError, check_goal_env
from .goals import BoxGoalSampler, FixedGoalSampler, FreeCellGoalSampler, GaussianGoalSampler, GoalSampler
from .gym_env import GymGoalEnv, register_gym_envs
from .gymnasium_goal_env import (
    GYMNASIUM_PREFIX,
    GymnasiumGoalEnv,
    RightFlippedAnt,
    goal_extent,
    goal_indices_of,
    goal_speed,
    gymnasium_id,
    is_gymnasium_ant_maze,
)
from .layouts import COMPLEX_MAZE, U_MAZE, MazeLayout, WallBox, bottleneck_walls
from .mazes import MAZE_NAMES, MAZES, MazeSpec, build_maze_mjcf, compile_maze_model, get_maze_spec
from .plotting import plot_arm, plot_env, plot_maze
from .registry import (
    ENV_NAMES,
    ENVS,
    EnvFactory,
    get_env_factory,
    get_env_spec,
    register_env,
    registered_env_names,
    unregister_env,
)
from .robots import UR3_DH, PR2Arm, UR3Arm
from .simulation import GoalSimulation, sparse_reward
from .task import TaskSpec, lookup_spec
from .torchrl_env import GoalEnv, make_env

#: Every registered Gymnasium id, ``dhrl/<name>-v0``, mazes first.
ALL_GYM_IDS: tuple[str, ...] = tuple(register_gym_envs())
#: The mazes' Gymnasium ids.
GYM_IDS: tuple[str, ...] = tuple(MAZES[name].gym_id for name in MAZE_NAMES)
#: The arm tasks' Gymnasium ids.
ARM_GYM_IDS: tuple[str, ...] = tuple(ARMS[name].gym_id for name in ARM_NAMES)

__all__ = [
    "ALL_GYM_IDS",
    "AntAgent",
    "ARM_GYM_IDS",
    "ARM_NAMES",
    "ARMS",
    "ArmSpec",
    "bottleneck_walls",
    "BoxGoalSampler",
    "build_arm_mjcf",
    "build_maze_mjcf",
    "check_goal_env",
    "compile_maze_model",
    "COMPLEX_MAZE",
    "ENV_NAMES",
    "EnvFactory",
    "ENVS",
    "FixedGoalSampler",
    "FreeCellGoalSampler",
    "GaussianGoalSampler",
    "get_arm_spec",
    "get_env_factory",
    "get_env_spec",
    "get_maze_spec",
    "GOAL_ENV_KEYS",
    "goal_extent",
    "goal_speed",
    "goal_indices_of",
    "GoalEnv",
    "GoalEnvError",
    "GoalSampler",
    "GoalSimulation",
    "GYM_IDS",
    "GymGoalEnv",
    "gymnasium_id",
    "is_gymnasium_ant_maze",
    "GYMNASIUM_PREFIX",
    "GymnasiumGoalEnv",
    "RightFlippedAnt",
    "lookup_spec",
    "make_env",
    "MAZE_NAMES",
    "MazeLayout",
    "MAZES",
    "MazeSpec",
    "MotorControl",
    "plot_arm",
    "plot_env",
    "plot_maze",
    "PointAgent",
    "PR2Arm",
    "register_env",
    "register_gym_envs",
    "registered_env_names",
    "sparse_reward",
    "TaskSpec",
    "U_MAZE",
    "unregister_env",
    "ur3_boards",
    "UR3_DH",
    "UR3Arm",
    "WallBox",
]
