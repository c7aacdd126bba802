"""The batched simulation core shared by the Gymnasium and the TorchRL environments.

:class:`GoalSimulation` holds one :class:`mujoco.MjModel` and ``num_envs`` :class:`mujoco.MjData` of any
task (:class:`~torchrl_dhrl.envs.TaskSpec`: the mazes and the arms), with preallocated float64 numpy
buffers for the observations and goals. Both front ends (:class:`~torchrl_dhrl.envs.GymGoalEnv` and
:class:`~torchrl_dhrl.envs.GoalEnv`) only convert inputs and outputs; every rule of the task (reset noise,
goal sampling, observation, achieved goal, reward, success, time limit) lives here and in the task spec.
"""

from __future__ import annotations

import dataclasses
from concurrent.futures import ThreadPoolExecutor

import mujoco
import numpy as np
from mujoco import mjtState

from .registry import get_env_spec
from .task import GOAL_BODY, OVERVIEW_CAMERA, TaskSpec

__all__ = ["GoalSimulation", "reference_engine_spec", "sparse_reward"]

# Goals set explicitly may sit this far outside the goal bounds (float round-off of user inputs).
_GOAL_BOUNDS_TOLERANCE = 1e-6
_AXES = "xyz"
# Where a righted ant may be moved to get clear of walls: no move, then rings of 16 directions, 0.1 to 2 away.
_SEPARATION_OFFSETS = np.concatenate(
    [
        np.zeros((1, 2)),
        *(
            radius * np.stack([np.cos(angles), np.sin(angles)], axis=-1)
            for radius in np.arange(1, 21) / 10.0
            for angles in [np.arange(16) * (2.0 * np.pi / 16)]
        ),
    ]
)


def overlaps_wall(model: mujoco.MjModel, data: mujoco.MjData, agent_geoms: np.ndarray) -> bool:
    """Whether, at ``data``'s forwarded state, a geom of the agent (``agent_geoms``, a boolean mask over the model's
    geoms) penetrates another geom other than a floor plane (a wall)."""
    planes = model.geom_type == mujoco.mjtGeom.mjGEOM_PLANE
    for contact in data.contact[: data.ncon]:
        g1, g2 = contact.geom
        if contact.dist < 0.0 and agent_geoms[g1] != agent_geoms[g2] and not (planes[g1] or planes[g2]):
            return True
    return False


def clear_of_walls(model: mujoco.MjModel, data: mujoco.MjData, agent_geoms: np.ndarray) -> None:
    """Moves an agent whose root's (x, y) is ``data.qpos[:2]`` to the nearest place in the floor plane where none
    of its geoms (``agent_geoms``, a boolean mask over the model's geoms) penetrates another geom other than a
    floor plane (a wall).

    Candidates are the current (x, y), then rings of 16 directions at radii 0.1, 0.2, ..., 2 around it; the first
    one clear is kept (none clear: the agent stays put and the contacts push it out). ``data`` is left forwarded
    (``mj_forward``) at the pose kept. Used to right a flipped ant (the built-in ant mazes and gymnasium-robotics').
    """
    xy = data.qpos[:2].copy()
    for offset in _SEPARATION_OFFSETS:
        data.qpos[:2] = xy + offset
        mujoco.mj_forward(model, data)
        if not overlaps_wall(model, data, agent_geoms):
            return
    data.qpos[:2] = xy
    mujoco.mj_forward(model, data)


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


def reference_engine_spec(task: str | TaskSpec) -> TaskSpec:
    """The spec of an ant maze with its agent emulating MuJoCo 2.0 (``AntAgent(reference_engine=True)``).

    The returned spec is a copy of ``task``'s with ``agent=dataclasses.replace(agent, reference_engine=True)``
    (same name, layout, goals and thresholds); its model has the reference's 0.01 margin per contact and
    MuJoCo 2.0's capsule masses and inertias (see :class:`~torchrl_dhrl.envs.AntAgent`).

    Raises:
        ValueError: naming the option and the env, for an env whose agent is not the ant.

    Examples:
        >>> from torchrl_dhrl.envs.simulation import reference_engine_spec
        >>> spec = reference_engine_spec("AntMaze")
        >>> spec.name, spec.agent.reference_engine, round(spec.agent.geom_margin, 3)
        ('AntMaze', True, 0.005)
    """
    spec = get_env_spec(task)
    agent = getattr(spec, "agent", None)
    if not (
        dataclasses.is_dataclass(spec)
        and dataclasses.is_dataclass(agent)
        and "reference_engine" in {field.name for field in dataclasses.fields(agent)}
    ):
        raise ValueError(
            f"reference_engine emulates MuJoCo 2.0's contact margins and capsule inertias of the ant: it applies "
            f"to the ant mazes only, not to {spec.name} (agent {type(agent).__name__}). Leave it False."
        )
    return dataclasses.replace(spec, agent=dataclasses.replace(agent, reference_engine=True))


class GoalSimulation:
    """Batched MuJoCo simulation of one task: ``num_envs`` independent episodes on one model.

    Observations are simulated and stored in float64. ``observation`` concatenates the parts of the task's
    :attr:`~torchrl_dhrl.envs.TaskSpec.observation_layout` (mazes: ``qpos ++ qvel``, 29-D for the ant and
    6-D for the point; Reacher3D: ``qpos ++ goal ++ qvel``, 17-D; UR3Obstacle: ``achieved ++ qpos ++ qvel``,
    15-D). ``achieved_goal`` is the maze agent's (x, y) (``qpos[:2]``) or the arm's end-effector site
    position, recomputed from the new joint angles after every step (``mj_kinematics``), so it always
    matches ``qpos``. Each env has its own :class:`numpy.random.Generator` (``rngs[i]``, spawned from one
    :class:`numpy.random.SeedSequence` by :meth:`seed`), used for its reset noise and goals, so an env's
    episodes do not depend on which other envs reset at the same time. The RNG state lives in this object.

    Args:
        task (str or TaskSpec): the environment name (see :data:`~torchrl_dhrl.envs.ENV_NAMES`) or spec.
        num_envs (int): number of parallel episodes. Defaults to ``1``.

    Keyword Args:
        max_episode_steps (int, optional): time limit in env steps; defaults to the task's episode length.
        eval_goals (bool): if ``True``, resets draw test goals instead of train goals. Defaults to ``False``.
        seed (int, optional): seed of the per-env RNG streams (``None``: fresh OS entropy).
        right_flipped_after (int, optional): ant mazes only: after this many consecutive env steps upside
            down (:meth:`~torchrl_dhrl.envs.AntAgent.is_upside_down`), the ant is put back on its feet at its
            (x, y) and heading, in the reset pose at rest (:meth:`~torchrl_dhrl.envs.AntAgent.upright_qpos`),
            pushed clear of any wall it would overlap; the episode goes on. ``None`` (the default, as the
            reference): a flipped ant stays flipped until the episode ends. The count of consecutive steps
            upside down (:attr:`upside_down_steps`) is part of :meth:`get_state`.
        reference_engine (bool): ant mazes only: emulate MuJoCo 2.0 where MuJoCo 3 differs (the reference's
            0.01 margin per contact and MuJoCo 2.0's capsule masses and inertias; see
            :class:`~torchrl_dhrl.envs.AntAgent` and :func:`reference_engine_spec`). Defaults to ``False``:
            the spec's own agent (MuJoCo 3's sum of margins, exact capsules).
        step_threads (int): threads that step the envs in :meth:`step`, each a contiguous group of them
            (MuJoCo releases the GIL while it integrates, so the groups run on several cores). Every env has its
            own ``MjData``, observation row and random stream, so the transitions are those of stepping them one
            by one, bit for bit. At most ``num_envs`` are used. Defaults to ``1`` (no thread pool).

    Examples:
        >>> import numpy as np
        >>> from torchrl_dhrl.envs import GoalSimulation
        >>> sim = GoalSimulation("AntMazeSmall", num_envs=2, seed=0)
        >>> sim.reset()
        >>> sim.observation.shape, sim.desired_goal.shape
        ((2, 29), (2, 2))
        >>> reward, success, truncated = sim.step(np.zeros((2, 8)))
        >>> reward.shape, sim.step_count.tolist()
        ((2,), [1, 1])
        >>> arm = GoalSimulation("Reacher3D", seed=0)
        >>> arm.reset()
        >>> arm.observation.shape, bool((arm.observation[0, 7:10] == arm.desired_goal[0]).all())
        ((1, 17), True)
    """

    def __init__(
        self,
        task: str | TaskSpec,
        num_envs: int = 1,
        *,
        max_episode_steps: int | None = None,
        eval_goals: bool = False,
        seed: int | None = None,
        right_flipped_after: int | None = None,
        reference_engine: bool = False,
        step_threads: int = 1,
    ) -> None:
        if isinstance(step_threads, bool) or not isinstance(step_threads, (int, np.integer)) or step_threads < 1:
            raise ValueError(f"step_threads must be a positive integer, got {step_threads!r}.")
        if not isinstance(reference_engine, (bool, np.bool_)):
            raise ValueError(f"reference_engine must be True or False, got {reference_engine!r}.")
        self.spec = spec = reference_engine_spec(task) if reference_engine else get_env_spec(task)
        if not isinstance(num_envs, int) or isinstance(num_envs, bool) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}.")
        if max_episode_steps is None:
            max_episode_steps = spec.episode_length
        if not isinstance(max_episode_steps, int) or max_episode_steps < 1:
            raise ValueError(f"max_episode_steps must be a positive integer, got {max_episode_steps!r}.")
        if right_flipped_after is not None:
            if (
                isinstance(right_flipped_after, bool)
                or not isinstance(right_flipped_after, (int, np.integer))
                or right_flipped_after < 1
            ):
                raise ValueError(
                    f"right_flipped_after must be None or a positive number of env steps, got {right_flipped_after!r}."
                )
            if not hasattr(spec.agent, "upright_qpos"):
                raise ValueError(
                    f"right_flipped_after is for the ant mazes (an agent that can flip over); {spec.name}'s "
                    f"{type(spec.agent).__name__} cannot. Leave it None."
                )
            right_flipped_after = int(right_flipped_after)
        self.right_flipped_after = right_flipped_after
        self.num_envs = num_envs
        #: threads stepping the envs (see ``step_threads``); the pool itself starts at the first step
        self.step_threads = min(int(step_threads), num_envs)
        self._groups = [g.tolist() for g in np.array_split(np.arange(num_envs), self.step_threads)]
        self._pool: ThreadPoolExecutor | None = None
        self.max_episode_steps = max_episode_steps
        self.eval_goals = bool(eval_goals)
        self.agent = spec.agent

        self.model = model = spec.compile_model()
        self.datas = [mujoco.MjData(model) for _ in range(num_envs)]
        self._nq, self._nv = model.nq, model.nv
        self._make_layout()
        self._site = None if spec.achieved_goal_site is None else model.site(spec.achieved_goal_site).id
        self._goal_mocap = int(model.body(GOAL_BODY).mocapid[0])
        self._init_qpos = np.asarray(self.agent.init_qpos, dtype=np.float64)
        self._goal_low, self._goal_high = spec.goal_bounds
        self._renderer: mujoco.Renderer | None = None

        goal_dim = spec.goal_dim
        self.observation = np.zeros((num_envs, spec.obs_dim), dtype=np.float64)
        self.achieved_goal = np.zeros((num_envs, goal_dim), dtype=np.float64)
        self.desired_goal = np.zeros((num_envs, goal_dim), dtype=np.float64)
        self.step_count = np.zeros(num_envs, dtype=np.int64)
        #: Consecutive env steps each ant has been upside down (counted with ``right_flipped_after`` only).
        self.upside_down_steps = np.zeros(num_envs, dtype=np.int64)
        self._agent_geoms = self._geoms_of_agent()
        self.rngs: list[np.random.Generator] = []
        self.seed(seed)
        # A valid, noise-free state until the first reset (it consumes no randomness).
        self.desired_goal[:] = spec.reference_goal
        for i in range(num_envs):
            self.set_state(i, self._init_qpos)

    def _make_layout(self) -> None:
        """Slices of the observation parts, checked against the model and the task's ``obs_dim``."""
        sizes = {
            "qpos": self._nq,
            "qvel": self._nv,
            "goal": self.spec.goal_dim,
            "achieved": self.spec.goal_dim,
        }
        self._parts: list[tuple[slice, str]] = []
        offset = 0
        for part in self.spec.observation_layout:
            if part not in sizes:
                raise ValueError(f"Unknown observation part {part!r}; valid parts: {', '.join(sizes)}.")
            self._parts.append((slice(offset, offset + sizes[part]), part))
            offset += sizes[part]
        if offset != self.spec.obs_dim or "qpos" not in self.spec.observation_layout:
            raise RuntimeError(
                f"{self.spec.name}: the layout {self.spec.observation_layout} gives {offset} entries for "
                f"nq = {self._nq}, nv = {self._nv}, expected obs_dim = {self.spec.obs_dim} including qpos."
            )
        self._qpos_slice = dict((part, sl) for sl, part in self._parts)["qpos"]

    # ------------------------------------------------------------------ properties
    @property
    def obs_dim(self) -> int:
        """Size of ``observation``."""
        return self.spec.obs_dim

    @property
    def action_dim(self) -> int:
        """Size of an action."""
        return self.agent.action_dim

    @property
    def goal_dim(self) -> int:
        """Size of a goal (2 for the mazes, 3 for the arms)."""
        return self.spec.goal_dim

    @property
    def dt(self) -> float:
        """Simulated seconds per env step."""
        return self.model.opt.timestep * self.agent.frame_skip

    # ------------------------------------------------------------------ seeding and checks
    def seed(self, seed: int | None) -> None:
        """Re-creates the per-env RNG streams from ``seed`` (``None``: fresh OS entropy)."""
        children = np.random.SeedSequence(seed).spawn(self.num_envs)
        self.rngs = [np.random.default_rng(child) for child in children]

    def check_goals(self, goals, count: int, *, what: str = "goal") -> np.ndarray:
        """Validates explicit goals: ``[count, goal_dim]`` (or one goal for all), finite, inside the bounds.

        ``what`` names them in the errors (``"start"`` for start positions)."""
        dim = self.goal_dim
        goals = np.asarray(goals, dtype=np.float64)
        if goals.shape == (dim,):
            goals = np.broadcast_to(goals, (count, dim))
        if goals.shape != (count, dim):
            raise ValueError(
                f"Expected {what}s of shape ({count}, {dim}) or ({dim},), got {tuple(goals.shape)}."
            )
        if not np.isfinite(goals).all():
            raise ValueError(f"{what.capitalize()}s must be finite.")
        outside = (
            (goals < self._goal_low - _GOAL_BOUNDS_TOLERANCE)
            | (goals > self._goal_high + _GOAL_BOUNDS_TOLERANCE)
        ).any(axis=-1)
        if outside.any():
            ranges = ", ".join(
                f"{_AXES[k]} in [{self._goal_low[k]}, {self._goal_high[k]}]" for k in range(dim)
            )
            raise ValueError(
                f"{what.capitalize()} {goals[outside][0].tolist()} lies outside the {self.spec.name} arena: "
                f"{what}s must be in {ranges}."
            )
        return goals

    def _check_starts(self, starts, count: int) -> np.ndarray:
        """Validates explicit start positions like goals; only for agents whose achieved goal is ``qpos[:goal_dim]``."""
        if self._site is not None:
            raise ValueError(
                f"starts is for the mazes, whose achieved goal is the agent's position; {self.spec.name}'s is an "
                "end-effector site (set joint angles with set_state instead)."
            )
        return self.check_goals(starts, count, what="start")

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
    def _observe(self, i: int, data: mujoco.MjData) -> None:
        """Fills row ``i`` of ``achieved_goal`` and ``observation`` from ``data`` (positions already set)."""
        achieved = self.achieved_goal[i]
        if self._site is None:
            achieved[:] = data.qpos[: achieved.shape[0]]
        else:
            mujoco.mj_kinematics(self.model, data)  # site positions of the new joint angles
            achieved[:] = data.site_xpos[self._site]
        observation = self.observation[i]
        for sl, part in self._parts:
            if part == "qpos":
                observation[sl] = data.qpos
            elif part == "qvel":
                observation[sl] = data.qvel
            elif part == "goal":
                observation[sl] = self.desired_goal[i]
            else:
                observation[sl] = achieved

    def set_state(self, index: int, qpos, qvel=None) -> None:
        """Puts env ``index`` in the state ``(qpos, qvel)`` (zero velocities by default) and observes it.

        The goal and the step count are left as they are; handy for scripted tests and demonstrations.
        """
        if not 0 <= index < self.num_envs:
            raise ValueError(f"index must be in [0, {self.num_envs}), got {index}.")
        data = self.datas[index]
        data.qpos[:] = qpos
        data.qvel[:] = 0.0 if qvel is None else qvel
        data.mocap_pos[self._goal_mocap, : self.goal_dim] = self.desired_goal[index]
        mujoco.mj_forward(self.model, data)
        self._observe(index, data)

    def get_state(self) -> dict:
        """The exact state of every env: MuJoCo's integration state, goals, step counts and RNG streams.

        With :meth:`set_full_state` this makes checkpoints resume bit-for-bit (episodes in progress included).
        The integration state holds the constraint solver's warm start too: without it the first steps after
        a restore start the solver from another guess and can differ in the last bits.
        """
        spec = mjtState.mjSTATE_INTEGRATION
        physics = np.zeros((self.num_envs, mujoco.mj_stateSize(self.model, spec)), dtype=np.float64)
        for i, data in enumerate(self.datas):
            mujoco.mj_getState(self.model, data, physics[i], spec)
        return {
            "physics": physics,
            "desired_goal": self.desired_goal.copy(),
            "step_count": self.step_count.copy(),
            "upside_down_steps": self.upside_down_steps.copy(),
            "rngs": [rng.bit_generator.state for rng in self.rngs],
            "eval_goals": self.eval_goals,
        }

    def set_full_state(self, state: dict) -> None:
        """Restores a state returned by :meth:`get_state` (same task and number of envs)."""
        physics = np.asarray(state["physics"], dtype=np.float64)
        # states saved before the warm start was included hold the full physics state only
        specs = {
            mujoco.mj_stateSize(self.model, s): s
            for s in (mjtState.mjSTATE_FULLPHYSICS, mjtState.mjSTATE_INTEGRATION)
        }
        expected = (self.num_envs, mujoco.mj_stateSize(self.model, mjtState.mjSTATE_INTEGRATION))
        spec = specs.get(physics.shape[-1]) if physics.ndim == 2 and len(physics) == self.num_envs else None
        if spec is None or len(state["rngs"]) != self.num_envs:
            raise ValueError(
                f"State of shape {physics.shape} with {len(state['rngs'])} RNG streams does not fit "
                f"{self.num_envs} {self.spec.name} envs (expected {expected})."
            )
        self.desired_goal[:] = state["desired_goal"]
        self.step_count[:] = state["step_count"]
        # states saved before the righting switch existed: no ant was being counted
        self.upside_down_steps[:] = state.get("upside_down_steps", 0)
        self.eval_goals = bool(state["eval_goals"])
        for i, data in enumerate(self.datas):
            mujoco.mj_setState(self.model, data, physics[i], spec)
            data.mocap_pos[self._goal_mocap, : self.goal_dim] = self.desired_goal[i]
            mujoco.mj_forward(self.model, data)
            self._observe(i, data)
            self.rngs[i].bit_generator.state = state["rngs"][i]

    def reset(self, mask=None, goals=None, *, eval_goals: bool | None = None, starts=None) -> None:
        """Starts new episodes in the envs selected by ``mask`` (all by default).

        Args:
            mask (array-like of bool, optional): ``[num_envs]``, ``True`` for the envs to reset.
            goals (array-like, optional): explicit goals, ``[k, goal_dim]`` for the ``k`` reset envs or one
                ``[goal_dim]`` goal for all of them; they must lie inside the goal bounds. By default goals
                are drawn from the train (or test) distribution with each env's RNG.
            eval_goals (bool, optional): overrides :attr:`eval_goals` for this reset.
            starts (array-like, optional): where the agents start, in goal space (``[k, goal_dim]`` or one
                ``[goal_dim]``): the reset pose and its noise moved to this position (the mazes only, whose
                achieved goal is the agent's position; no agent geom may overlap a wall there). By default the
                task's start. The reset draws the same random numbers either way.
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
        if starts is not None:
            starts = self._check_starts(starts, len(indices))
        use_test = self.eval_goals if eval_goals is None else bool(eval_goals)
        sampler = self.spec.test_goal_sampler if use_test else self.spec.train_goals
        agent, model = self.agent, self.model
        for k, i in enumerate(indices):
            rng = self.rngs[i]
            data = self.datas[i]
            mujoco.mj_resetData(model, data)
            qpos = self._init_qpos + rng.uniform(-agent.qpos_noise, agent.qpos_noise, size=self._nq)
            agent.normalize_qpos(qpos)
            qvel = agent.qvel_noise * rng.standard_normal(self._nv)
            self.desired_goal[i] = sampler.sample(rng, 1)[0] if goals is None else goals[k]
            if not self.spec.start_position_noise:
                qpos[: self.goal_dim] = self._init_qpos[: self.goal_dim]
            if starts is not None:
                qpos[: self.goal_dim] += starts[k] - self._init_qpos[: self.goal_dim]
            self.set_state(i, qpos, qvel)
            if starts is not None and self._overlaps_wall(data):
                raise ValueError(
                    f"Start {starts[k].tolist()} puts the {self.spec.name} agent inside a wall (env {i}): "
                    "starts must leave room for the agent's body in free space."
                )
            self.step_count[i] = 0
            self.upside_down_steps[i] = 0

    def step(self, actions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Advances every env by one env step (``frame_skip`` physics steps).

        Args:
            actions (array-like): ``[num_envs, action_dim]``; clipped to the action box.

        Returns:
            ``(reward, is_success, truncated)``, freshly allocated ``[num_envs]`` arrays (float64, bool,
            bool) for the new states.
        """
        actions = self.check_actions(actions)
        command = self.agent.command(actions, self.observation[:, self._qpos_slice])
        field = self.agent.control_field
        model, nstep, observe, datas = self.model, self.agent.frame_skip, self._observe, self.datas

        def advance(indices) -> None:  # each env's own MjData and rows: groups may run at once
            for i in indices:
                data = datas[i]
                getattr(data, field)[:] = command[i]
                mujoco.mj_step(model, data, nstep)
                observe(i, data)

        if self.step_threads == 1:
            advance(range(self.num_envs))
        else:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(self.step_threads, thread_name_prefix="mujoco-step")
            list(self._pool.map(advance, self._groups))  # waits for every group; re-raises a group's error
        self.step_count += 1
        if self.right_flipped_after is not None:
            self._right_flipped()
        reward, success = self.evaluate()
        return reward, success, self.step_count >= self.max_episode_steps

    def _geoms_of_agent(self) -> np.ndarray:
        """Boolean mask over the model's geoms: those of the agent (every body below the world's child that
        holds the agent's root joint)."""
        model = self.model
        root = model.body_rootid[model.jnt_bodyid[0]]
        return model.body_rootid[model.geom_bodyid] == root

    def _right_flipped(self) -> None:
        """Counts the consecutive steps each ant has been upside down and rights those at the limit."""
        flipped = self.agent.is_upside_down(self.observation[:, self._qpos_slice])
        self.upside_down_steps = np.where(flipped, self.upside_down_steps + 1, 0)
        for i in np.flatnonzero(self.upside_down_steps >= self.right_flipped_after):  # rare: no hot path
            data = self.datas[i]
            data.qpos[:] = self.agent.upright_qpos(data.qpos)
            self._separate_from_walls(i)  # sets the velocities to zero and observes the new state
            self.upside_down_steps[i] = 0

    def _separate_from_walls(self, index: int) -> None:
        """Moves agent ``index`` to the nearest place in the floor plane where none of its geoms overlaps a wall
        (:func:`clear_of_walls`), at rest, and observes it."""
        data = self.datas[index]
        clear_of_walls(self.model, data, self._agent_geoms)
        self.set_state(index, data.qpos.copy())

    def _overlaps_wall(self, data: mujoco.MjData) -> bool:
        """Whether a geom of the agent penetrates a static geom other than the floor plane (:func:`overlaps_wall`)."""
        return overlaps_wall(self.model, data, self._agent_geoms)

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

        Needs an OpenGL backend (``MUJOCO_GL=egl`` or ``osmesa``). The default camera shows the whole scene
        (straight down on a maze, obliquely on an arm); ``"ant/track"`` / ``"point/track"`` follow a maze
        agent.
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
        """Frees the renderer and stops the stepping threads, if any (a later step starts them again)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_pool"] = None  # threads do not travel: a copy starts its own at its first step
        return state
