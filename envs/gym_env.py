"""Gymnasium goal-env front end of the DHRL mazes, and the registration of their ids."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from .arena import OVERVIEW_CAMERA
from .mazes import MAZES, MazeSpec, get_maze_spec
from .simulation import MazeSimulation

__all__ = ["MazeGoalEnv", "register_gym_envs"]


class MazeGoalEnv(gym.Env):
    """One DHRL maze as a Gymnasium goal-conditioned env (gymnasium-robotics convention).

    Observations are a ``Dict`` of float64 arrays: ``"observation"`` (``qpos ++ qvel``, 29-D for the ant,
    6-D for the point), ``"achieved_goal"`` (the agent's x, y) and ``"desired_goal"``. The reward is sparse,
    ``compute_reward(achieved_goal, desired_goal, info)`` (``-1``, or ``0`` within 0.5 of the goal),
    vectorised over leading dims so that HER implementations (e.g. Stable-Baselines3) can relabel;
    ``info["is_success"]`` tells whether the agent is within the evaluation threshold (2.5 or 5) of the goal.
    Episodes never terminate; they are truncated at ``max_episode_steps`` (the registered ids also carry
    the same time limit for Gymnasium's ``TimeLimit`` wrapper).

    Args:
        maze (str or MazeSpec): one of :data:`~torchrl_dhrl.envs.MAZE_NAMES`.

    Keyword Args:
        eval (bool): draw the fixed test goals instead of train goals (AntMazeComplex: one of its four per
            episode). Defaults to ``False``; ``reset(options={"eval": ...})`` overrides it per episode.
        max_episode_steps (int, optional): time limit; defaults to the maze's episode length.
        render_mode (str, optional): ``"rgb_array"`` renders the top-down view offscreen (needs
            ``MUJOCO_GL=egl`` or ``osmesa``).
        width (int): render width. Defaults to ``480``.
        height (int): render height. Defaults to ``480``.

    ``reset(options={"goal": (x, y)})`` sets the goal explicitly (it must lie inside the arena).

    Examples:
        >>> import gymnasium as gym
        >>> import torchrl_dhrl.envs  # registers the dhrl/ ids
        >>> env = gym.make("dhrl/AntMaze-v0", eval=True)
        >>> obs, info = env.reset(seed=0)
        >>> obs["observation"].shape, obs["desired_goal"].tolist()
        ((29,), [0.0, 16.0])
        >>> obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        >>> bool(reward == env.unwrapped.compute_reward(obs["achieved_goal"], obs["desired_goal"], info))
        True
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        maze: str | MazeSpec,
        *,
        eval: bool = False,  # noqa: A002 - the documented option name
        max_episode_steps: int | None = None,
        render_mode: str | None = None,
        width: int = 480,
        height: int = 480,
    ) -> None:
        spec = get_maze_spec(maze)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}."
            )
        self._sim = MazeSimulation(spec, 1, max_episode_steps=max_episode_steps, eval_goals=eval)
        self.render_mode = render_mode
        self.width, self.height = width, height
        self.metadata = {**self.metadata, "render_fps": int(round(1.0 / self._sim.dt))}
        agent = spec.agent
        low, high = spec.goal_bounds
        self.observation_space = spaces.Dict(
            {
                "observation": spaces.Box(-np.inf, np.inf, shape=(agent.obs_dim,), dtype=np.float64),
                "achieved_goal": spaces.Box(-np.inf, np.inf, shape=(2,), dtype=np.float64),
                "desired_goal": spaces.Box(low, high, shape=(2,), dtype=np.float64),
            }
        )
        self.action_space = spaces.Box(
            agent.action_low.astype(np.float32), agent.action_high.astype(np.float32), dtype=np.float32
        )

    @property
    def maze(self) -> MazeSpec:
        """The :class:`~torchrl_dhrl.envs.MazeSpec` of this environment."""
        return self._sim.spec

    @property
    def simulation(self) -> MazeSimulation:
        """The underlying simulation core (one env)."""
        return self._sim

    def _get_obs(self) -> dict[str, np.ndarray]:
        sim = self._sim
        return {
            "observation": sim.observation[0].copy(),
            "achieved_goal": sim.achieved_goal[0].copy(),
            "desired_goal": sim.desired_goal[0].copy(),
        }

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        options = {} if options is None else dict(options)
        unknown = set(options) - {"goal", "eval"}
        if unknown:
            raise ValueError(f"Unknown reset options {sorted(unknown)}; supported: 'goal', 'eval'.")
        self._sim.rngs[0] = self.np_random
        goal = options.get("goal")
        self._sim.reset(
            None,
            None if goal is None else np.asarray(goal, dtype=np.float64)[None],
            eval_goals=options.get("eval"),
        )
        _, success = self._sim.evaluate()
        return self._get_obs(), {"is_success": bool(success[0])}

    def step(self, action):
        action = np.asarray(action, dtype=np.float64)
        if action.shape != self.action_space.shape:
            raise ValueError(
                f"{self.maze.name} expects an action of shape {self.action_space.shape}, got {action.shape}."
            )
        reward, success, truncated = self._sim.step(action[None])
        return self._get_obs(), float(reward[0]), False, bool(truncated[0]), {"is_success": bool(success[0])}

    def compute_reward(self, achieved_goal, desired_goal, info=None) -> np.ndarray:
        """Sparse reward of goal pairs over leading dims: ``0`` within 0.5 of the goal, else ``-1``."""
        return self._sim.compute_reward(achieved_goal, desired_goal)

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        return self._sim.render(0, width=self.width, height=self.height, camera=OVERVIEW_CAMERA)

    def close(self) -> None:
        self._sim.close()


def register_gym_envs() -> list[str]:
    """Registers ``dhrl/<name>-v0`` for every maze (idempotent) and returns the ids.

    Each id carries the maze's episode length as ``max_episode_steps`` (Gymnasium's ``TimeLimit``).

    Examples:
        >>> from torchrl_dhrl.envs import register_gym_envs
        >>> register_gym_envs()[0]
        'dhrl/PointMaze-v0'
    """
    ids = []
    for name, spec in MAZES.items():
        if spec.gym_id not in gym.registry:
            gym.register(
                id=spec.gym_id,
                entry_point="torchrl_dhrl.envs.gym_env:MazeGoalEnv",
                kwargs={"maze": name},
                max_episode_steps=spec.episode_length,
            )
        ids.append(spec.gym_id)
    return ids
