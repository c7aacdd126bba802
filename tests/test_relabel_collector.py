"""FutureGoalRelabel on real TorchRL collector output: batched envs with desynchronised episodes."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.data import Bounded, Composite, LazyTensorStorage, Unbounded
from torchrl.envs import EnvBase, SerialEnv, StepCounter, TransformedEnv

from torchrl_dhrl.data import FutureGoalRelabel, RelabelReplayBuffer


class TraceableGoalEnv(EnvBase):
    """Episodes of random length whose achieved goal is ``(episode uid, step)``; uids are unique."""

    def __init__(self, env_index: int, num_envs: int, min_len: int, max_len: int, seed: int) -> None:
        super().__init__()
        self.env_index, self.num_envs = env_index, num_envs
        self.min_len, self.max_len = min_len, max_len
        self.rng = torch.Generator().manual_seed(seed)
        self.episode = -1
        self.observation_spec = Composite(
            observation=Unbounded((3,)), achieved_goal=Unbounded((2,)), desired_goal=Unbounded((2,))
        )
        self.action_spec = Bounded(-1.0, 1.0, (1,))
        self.reward_spec = Unbounded((1,))

    def _observation(self) -> TensorDict:
        achieved = torch.tensor([self.env_index + self.num_envs * self.episode, self.t], dtype=torch.float32)
        return TensorDict(
            observation=torch.cat([achieved, torch.tensor([float(self.env_index)])]),
            achieved_goal=achieved,
            desired_goal=torch.full((2,), -1000.0),
        )

    def _reset(self, tensordict=None, **kwargs) -> TensorDict:
        self.episode += 1
        self.t = 0
        self.length = int(torch.randint(self.min_len, self.max_len + 1, (), generator=self.rng))
        out = self._observation()
        out["done"] = out["terminated"] = torch.zeros(1, dtype=torch.bool)
        return out

    def _step(self, tensordict) -> TensorDict:
        self.t += 1
        out = self._observation()
        out["reward"] = torch.zeros(1)
        out["done"] = torch.tensor([self.t >= self.length])
        out["terminated"] = torch.zeros(1, dtype=torch.bool)
        return out

    def _set_seed(self, seed):
        self.rng.manual_seed(seed)


@pytest.mark.parametrize("layout", ["ndim2", "flat_with_traj_ids"])
def test_collector_batches_never_cross_episodes(layout):
    torch.manual_seed(0)
    num_envs, horizon, window = 3, 16, 10
    env = TransformedEnv(
        SerialEnv(
            num_envs, [lambda i=i: TraceableGoalEnv(i, num_envs, 5, 30, seed=i) for i in range(num_envs)]
        ),
        StepCounter(),
    )
    collector = Collector(
        env, None, frames_per_batch=num_envs * horizon, total_frames=num_envs * horizon * 10
    )
    relabel = FutureGoalRelabel(window=window)
    storage = LazyTensorStorage(num_envs * 64, ndim=2 if layout == "ndim2" else 1)
    rb = RelabelReplayBuffer(storage=storage, relabel=[relabel], batch_size=2048)
    last_step: dict[int, int] = {}
    try:
        for batch in collector:
            assert batch.batch_size == torch.Size([num_envs, horizon])
            for uid, step in batch["next", "achieved_goal"].reshape(-1, 2).long().tolist():
                last_step[uid] = max(step, last_step.get(uid, 0))
            rb.extend(batch if layout == "ndim2" else batch.reshape(-1))
            sample = rb.sample()
            for key in ("goal", "graph_goal"):
                goal, achieved = sample[key], sample["achieved_goal"]
                relabelled = goal[:, 0] != -1000.0
                assert (goal[relabelled, 0] == achieved[relabelled, 0]).all()
                ahead = (goal[:, 1] - achieved[:, 1])[relabelled]
                assert (ahead >= 1).all() and (ahead <= window).all()
                stored = torch.tensor([last_step[int(u)] for u in achieved[relabelled, 0]])
                assert (goal[relabelled, 1] <= stored).all()
            if layout == "ndim2":  # episode-contiguous lanes: the full window is used
                uid, step = sample["achieved_goal"].long().unbind(-1)
                expected = (torch.tensor([last_step[int(u)] for u in uid]) - step).clamp(max=window)
                assert torch.equal(
                    relabel.window_lengths(sample["index"], rb.storage, rb.newest_index), expected
                )
    finally:
        collector.shutdown()
