"""A user-made goal env for the tests: a point mass in an open square, a plain TorchRL ``EnvBase`` (not taken from
``torchrl_dhrl.envs``), registered by the tests only."""

import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase


class PointSquare(EnvBase):
    """A point mass in the open square ``[-4, 4]^2`` moving ``0.3 * action`` per step from ``U(-0.1, 0.1)^2``.

    Train goals are uniform in the square, the test goal is ``(3, 3)``.
    """

    goal_dim = 2

    def __init__(
        self, num_envs=1, *, seed=None, device=None, eval=False, max_episode_steps=None, dtype=torch.float32  # noqa: A002
    ):
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        self.length = max_episode_steps or 50
        self.max_episode_steps = self.length
        self.dtype = dtype
        self.eval_goals = eval
        self.rng = torch.Generator()
        shape, dim = self.batch_size, self.goal_dim
        self.observation_spec = Composite(
            observation=Unbounded((*shape, 2), dtype=dtype),
            achieved_goal=Unbounded((*shape, 2), dtype=dtype),
            desired_goal=Unbounded((*shape, dim), dtype=dtype),
            is_success=Categorical(2, (*shape, 1), dtype=torch.bool),
            step_count=Unbounded((*shape, 1), dtype=torch.int64),
            shape=shape,
        )
        self.action_spec = Bounded(-1.0, 1.0, (*shape, 2))
        self.reward_spec = Unbounded((*shape, 1))
        flags = ("done", "terminated", "truncated")
        self.done_spec = Composite(
            {k: Categorical(2, (*shape, 1), dtype=torch.bool) for k in flags}, shape=shape
        )
        self.pos, self.goal = torch.zeros(*shape, 2), torch.zeros(*shape, dim)
        self.steps = torch.zeros(*shape, 1, dtype=torch.int64)
        if seed is not None:
            self.set_seed(seed)

    def _set_seed(self, seed):
        self.rng.manual_seed(seed)

    def _out(self, **extra):
        success = (self.pos - self.goal[..., :2]).norm(dim=-1, keepdim=True) <= 0.5
        return TensorDict(
            observation=self.pos.clone().to(self.dtype),
            achieved_goal=self.pos.clone().to(self.dtype),
            desired_goal=self.goal.clone().to(self.dtype),
            is_success=success,
            step_count=self.steps.clone(),
            **extra,
            batch_size=self.batch_size,
        )

    def _reset(self, tensordict=None, **kwargs):
        mask = None if tensordict is None else tensordict.get("_reset", None)
        mask = (
            torch.ones(self.batch_size, dtype=torch.bool) if mask is None else mask.reshape(self.batch_size)
        )
        num = int(mask.sum())
        if self.eval_goals:
            goals = torch.full((num, self.goal_dim), 3.0)
        else:
            goals = torch.rand(num, self.goal_dim, generator=self.rng) * 8 - 4
        self.pos[mask] = torch.rand(num, 2, generator=self.rng) * 0.2 - 0.1
        self.goal[mask], self.steps[mask] = goals, 0
        done = torch.zeros(*self.batch_size, 1, dtype=torch.bool)
        return self._out(done=done, terminated=done.clone(), truncated=done.clone())

    def _step(self, tensordict):
        self.pos = (self.pos + 0.3 * tensordict["action"].clamp(-1, 1)).clamp(-4, 4)
        self.steps += 1
        truncated = self.steps >= self.length
        out = self._out(done=truncated.clone(), terminated=torch.zeros_like(truncated), truncated=truncated)
        return out.set("reward", out["is_success"].float() - 1.0)


def make_point_square(*, num_envs, seed, device, eval, max_episode_steps, cls=PointSquare):  # noqa: A002
    return cls(num_envs, seed=seed, device=device, eval=eval, max_episode_steps=max_episode_steps)
