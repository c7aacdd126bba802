"""The batched simulation core shared by the Gymnasium and the TorchRL environments.

:class:`MazeSimulation` holds one :class:`mujoco.MjModel` and ``num_envs`` :class:`mujoco.MjData`, with
preallocated float64 numpy buffers for the observations and goals. Both front ends
(:class:`~torchrl_dhrl.envs.MazeGoalEnv` and :class:`~torchrl_dhrl.envs.MazeEnv`) only convert inputs
and outputs; every rule of the task (reset noise, goal sampling, reward, success, time limit) lives here.
"""

from __future__ import annotations

import mujoco
import numpy as np

from .arena import GOAL_BODY, OVERVIEW_CAMERA, compile_maze_model
from .mazes import MazeSpec, get_maze_spec

__all__ = ["MazeSimulation", "sparse_reward"]

# Goals set explicitly may sit this far outside the arena bounds (float round-off of user inputs).
_GOAL_BOUNDS_TOLERANCE = 1e-6


def sparse_reward(achieved_goal, desired_goal, threshold: float = 0.5) -> np.ndarray:
    """The DHRL sparse reward: ``0`` within ``threshold`` of the goal, else ``-1``, over leading dims.

    Args:
        achieved_goal (array-like): ``[..., goal_dim]``.
        desired_goal (array-like): ``[..., goal_dim]`` (broadcasts with ``achieved_goal``).
        threshold (float): success radius of the reward. Defaults to ``0.5``.

    Examples:
        >>> import numpy as np
        >>> from torchrl_dhrl.envs import sparse_reward
        >>> sparse_reward(np.array([[0.0, 0.0], [0.0, 0.6]]), np.array([0.0, 1.0])).tolist()
        [-1.0, 0.0]
    """
    distance = np.linalg.norm(np.asarray(achieved_goal) - np.asarray(desired_goal), axis=-1)
    return np.where(distance > threshold, -1.0, 0.0)


class MazeSimulation:
    """Batched MuJoCo simulation of one maze: ``num_envs`` independent episodes on one model.

    Observations are simulated and stored in float64: ``observation`` is ``qpos ++ qvel``
    (29-D for the ant, 6-D for the point), ``achieved_goal`` is its first two entries (the agent's x, y).
    Each env has its own :class:`numpy.random.Generator` (``rngs[i]``, spawned from one
    :class:`numpy.random.SeedSequence` by :meth:`seed`), used for its reset noise and goals, so an env's
    episodes do not depend on which other envs reset at the same time. The RNG state lives in this object.

    Args:
        maze (str or MazeSpec): the maze name (see :data:`~torchrl_dhrl.envs.MAZE_NAMES`) or spec.
        num_envs (int): number of parallel episodes. Defaults to ``1``.

    Keyword Args:
        max_episode_steps (int, optional): time limit in env steps; defaults to the maze's episode length.
        eval_goals (bool): if ``True``, resets draw the fixed test goals instead of train goals.
            Defaults to ``False``.
        seed (int, optional): seed of the per-env RNG streams (``None``: fresh OS entropy).

    Examples:
        >>> import numpy as np
        >>> from torchrl_dhrl.envs import MazeSimulation
        >>> sim = MazeSimulation("AntMazeSmall", num_envs=2, seed=0)
        >>> sim.reset()
        >>> sim.observation.shape, sim.desired_goal.shape
        ((2, 29), (2, 2))
        >>> reward, success, truncated = sim.step(np.zeros((2, 8)))
        >>> reward.shape, sim.step_count.tolist()
        ((2,), [1, 1])
    """

    def __init__(
        self,
        maze: str | MazeSpec,
        num_envs: int = 1,
        *,
        max_episode_steps: int | None = None,
        eval_goals: bool = False,
        seed: int | None = None,
    ) -> None:
        self.spec = get_maze_spec(maze)
        if not isinstance(num_envs, int) or isinstance(num_envs, bool) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}.")
        if max_episode_steps is None:
            max_episode_steps = self.spec.episode_length
        if not isinstance(max_episode_steps, int) or max_episode_steps < 1:
            raise ValueError(f"max_episode_steps must be a positive integer, got {max_episode_steps!r}.")
        self.num_envs = num_envs
        self.max_episode_steps = max_episode_steps
        self.eval_goals = bool(eval_goals)
        self.agent = self.spec.agent

        self.model = compile_maze_model(self.spec)
        self.datas = [mujoco.MjData(self.model) for _ in range(num_envs)]
        self._nq, self._nv = self.model.nq, self.model.nv
        if self._nq + self._nv != self.agent.obs_dim:
            raise RuntimeError(f"Model has nq + nv = {self._nq + self._nv}, expected {self.agent.obs_dim}.")
        self._goal_mocap = int(self.model.body(GOAL_BODY).mocapid[0])
        self._init_qpos = np.asarray(self.agent.init_qpos, dtype=np.float64)
        self._goal_low, self._goal_high = self.spec.goal_bounds
        self._renderer: mujoco.Renderer | None = None

        self.observation = np.zeros((num_envs, self.agent.obs_dim), dtype=np.float64)
        self.desired_goal = np.zeros((num_envs, 2), dtype=np.float64)
        self.step_count = np.zeros(num_envs, dtype=np.int64)
        self.rngs: list[np.random.Generator] = []
        self.seed(seed)
        # A valid, noise-free state until the first reset (it consumes no randomness).
        for i, data in enumerate(self.datas):
            data.qpos[:] = self._init_qpos
            mujoco.mj_forward(self.model, data)
            self._read_state(i, data)
        self.desired_goal[:] = np.asarray(self.spec.test_goals[0])

    # ------------------------------------------------------------------ properties
    @property
    def obs_dim(self) -> int:
        """Size of ``observation``."""
        return self.agent.obs_dim

    @property
    def action_dim(self) -> int:
        """Size of an action."""
        return self.agent.action_dim

    @property
    def achieved_goal(self) -> np.ndarray:
        """``[num_envs, 2]`` view of the agents' (x, y)."""
        return self.observation[:, :2]

    @property
    def dt(self) -> float:
        """Simulated seconds per env step."""
        return self.model.opt.timestep * self.agent.frame_skip

    # ------------------------------------------------------------------ seeding and checks
    def seed(self, seed: int | None) -> None:
        """Re-creates the per-env RNG streams from ``seed`` (``None``: fresh OS entropy)."""
        children = np.random.SeedSequence(seed).spawn(self.num_envs)
        self.rngs = [np.random.default_rng(child) for child in children]

    def check_goals(self, goals, count: int) -> np.ndarray:
        """Validates explicit goals: ``[count, 2]`` (or one ``[2]`` goal for all), finite, inside the arena."""
        goals = np.asarray(goals, dtype=np.float64)
        if goals.shape == (2,):
            goals = np.broadcast_to(goals, (count, 2))
        if goals.shape != (count, 2):
            raise ValueError(f"Expected goals of shape ({count}, 2) or (2,), got {tuple(goals.shape)}.")
        if not np.isfinite(goals).all():
            raise ValueError("Goals must be finite.")
        outside = (
            (goals < self._goal_low - _GOAL_BOUNDS_TOLERANCE)
            | (goals > self._goal_high + _GOAL_BOUNDS_TOLERANCE)
        ).any(axis=-1)
        if outside.any():
            raise ValueError(
                f"Goal {goals[outside][0].tolist()} lies outside the {self.spec.name} arena: goals must be in "
                f"x in [{self._goal_low[0]}, {self._goal_high[0]}], y in [{self._goal_low[1]}, {self._goal_high[1]}]."
            )
        return goals

    def check_actions(self, actions) -> np.ndarray:
        """Validates a batch of actions: shape ``[num_envs, action_dim]``, finite."""
        actions = np.asarray(actions, dtype=np.float64)
        expected = (self.num_envs, self.action_dim)
        if actions.shape != expected:
            raise ValueError(
                f"{self.spec.name} expects actions of shape {expected} (num_envs, action_dim), "
                f"got {tuple(actions.shape)}."
            )
        if not np.isfinite(actions).all():
            raise ValueError("Actions must be finite (got NaN or inf).")
        return actions

    # ------------------------------------------------------------------ dynamics
    def _read_state(self, i: int, data: mujoco.MjData) -> None:
        self.observation[i, : self._nq] = data.qpos
        self.observation[i, self._nq :] = data.qvel

    def reset(self, mask=None, goals=None, *, eval_goals: bool | None = None) -> None:
        """Starts new episodes in the envs selected by ``mask`` (all by default).

        Args:
            mask (array-like of bool, optional): ``[num_envs]``, ``True`` for the envs to reset.
            goals (array-like, optional): explicit goals, ``[k, 2]`` for the ``k`` reset envs or one ``[2]``
                goal for all of them; they must lie inside the arena. By default goals are drawn from the
                train (or test) distribution with each env's RNG.
            eval_goals (bool, optional): overrides :attr:`eval_goals` for this reset.
        """
        if mask is None:
            indices = np.arange(self.num_envs)
        else:
            mask = np.asarray(mask, dtype=bool).reshape(-1)
            if mask.shape != (self.num_envs,):
                raise ValueError(f"Expected a reset mask of shape ({self.num_envs},), got {mask.shape}.")
            indices = np.flatnonzero(mask)
        if goals is not None:
            goals = self.check_goals(goals, len(indices))
        use_test = self.eval_goals if eval_goals is None else bool(eval_goals)
        sampler = self.spec.test_goal_sampler if use_test else self.spec.train_goals
        agent, model = self.agent, self.model
        for k, i in enumerate(indices):
            rng = self.rngs[i]
            data = self.datas[i]
            mujoco.mj_resetData(model, data)
            qpos = self._init_qpos + rng.uniform(-agent.qpos_noise, agent.qpos_noise, size=self._nq)
            agent.normalize_qpos(qpos)
            data.qpos[:] = qpos
            data.qvel[:] = agent.qvel_noise * rng.standard_normal(self._nv)
            goal = sampler.sample(rng, 1)[0] if goals is None else goals[k]
            self.desired_goal[i] = goal
            data.mocap_pos[self._goal_mocap, :2] = goal
            mujoco.mj_forward(model, data)
            self._read_state(i, data)
            self.step_count[i] = 0

    def step(self, actions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Advances every env by one env step (``frame_skip`` physics steps).

        Args:
            actions (array-like): ``[num_envs, action_dim]``; clipped to the action box.

        Returns:
            ``(reward, is_success, truncated)``, freshly allocated ``[num_envs]`` arrays (float64, bool,
            bool) for the new states.
        """
        actions = self.check_actions(actions)
        command = self.agent.command(actions, self.observation[:, : self._nq])
        field = self.agent.control_field
        model, nstep, nq = self.model, self.agent.frame_skip, self._nq
        observation = self.observation
        for i, data in enumerate(self.datas):
            getattr(data, field)[:] = command[i]
            mujoco.mj_step(model, data, nstep)
            observation[i, :nq] = data.qpos
            observation[i, nq:] = data.qvel
        self.step_count += 1
        reward, success = self.evaluate()
        return reward, success, self.step_count >= self.max_episode_steps

    def evaluate(self) -> tuple[np.ndarray, np.ndarray]:
        """Sparse reward (``-1``/``0`` at the reward threshold) and success (within the evaluation threshold)
        of the current states against the desired goals."""
        distance = np.linalg.norm(self.achieved_goal - self.desired_goal, axis=-1)
        reward = np.where(distance > self.spec.reward_threshold, -1.0, 0.0)
        return reward, distance <= self.spec.success_threshold

    def compute_reward(self, achieved_goal, desired_goal) -> np.ndarray:
        """Vectorised sparse reward of arbitrary goal pairs (see :func:`sparse_reward`)."""
        return sparse_reward(achieved_goal, desired_goal, self.spec.reward_threshold)

    # ------------------------------------------------------------------ rendering
    def render(
        self, index: int = 0, *, width: int = 480, height: int = 480, camera: str | int = OVERVIEW_CAMERA
    ) -> np.ndarray:
        """Offscreen RGB render ``[height, width, 3]`` (uint8) of env ``index``.

        Needs an OpenGL backend (``MUJOCO_GL=egl`` or ``osmesa``). The default camera looks straight down on
        the whole maze; ``"ant/track"`` / ``"point/track"`` follow the agent.
        """
        if not 0 <= index < self.num_envs:
            raise ValueError(f"index must be in [0, {self.num_envs}), got {index}.")
        limit = self.model.vis.global_.offwidth
        if not (0 < width <= limit and 0 < height <= self.model.vis.global_.offheight):
            raise ValueError(f"width and height must be in (0, {limit}], got {width} x {height}.")
        if self._renderer is None or (self._renderer.width, self._renderer.height) != (width, height):
            self.close()
            self._renderer = mujoco.Renderer(self.model, height=height, width=width)
        self._renderer.update_scene(self.datas[index], camera=camera)
        return self._renderer.render()

    def close(self) -> None:
        """Frees the renderer, if any."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
