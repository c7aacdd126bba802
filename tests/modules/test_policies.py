"""The high-level policy: subgoal noise and the c_h cadence inside envs and Collectors."""

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.collectors import Collector
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase, StepCounter, TransformedEnv
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type, step_mdp
from torchrl.modules.utils import get_primers_from_module

from torchrl_dhrl.modules import NO_SUBGOAL, HighLevelPolicy, SubgoalScheduler

OBS, GOAL = 4, 2
LOW, HIGH = [-4.0, -4.0], [20.0, 20.0]


class _GoalMockEnv(EnvBase):
    """A batched point env with goal keys whose episodes end after a per-env number of steps."""

    def __init__(self, lengths):
        super().__init__(batch_size=[len(lengths)])
        n = len(lengths)
        self.lengths = torch.as_tensor(lengths)
        self.observation_spec = Composite(
            observation=Unbounded((n, OBS)),
            achieved_goal=Unbounded((n, GOAL)),
            desired_goal=Unbounded((n, GOAL)),
            shape=(n,),
        )
        self.action_spec = Bounded(-1.0, 1.0, (n, 2))
        self.reward_spec = Unbounded((n, 1))
        self.done_spec = Composite(
            {k: Categorical(2, (n, 1), dtype=torch.bool) for k in ("done", "terminated", "truncated")},
            shape=(n,),
        )
        self.t = torch.zeros(n, dtype=torch.long)
        self.obs = torch.zeros(n, OBS)

    def _obs_td(self, done):
        n = self.batch_size[0]
        return TensorDict(
            observation=self.obs.clone(),
            achieved_goal=self.obs[:, :GOAL].clone(),
            desired_goal=torch.full((n, GOAL), 8.0),
            done=done,
            terminated=torch.zeros_like(done),
            truncated=done.clone(),
            batch_size=self.batch_size,
        )

    def _reset(self, tensordict):
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict["_reset"].reshape(-1)
        else:
            mask = torch.ones(self.batch_size, dtype=torch.bool)
        self.t[mask] = 0
        self.obs[mask] = 0.0
        return self._obs_td(torch.zeros(*self.batch_size, 1, dtype=torch.bool))

    def _step(self, tensordict):
        self.t += 1
        self.obs[:, :2] += tensordict["action"]
        self.obs[:, 2:] = torch.randn(self.batch_size[0], OBS - 2)
        done = (self.t >= self.lengths).unsqueeze(-1)
        out = self._obs_td(done)
        out["reward"] = torch.zeros(*self.batch_size, 1)
        return out

    def _set_seed(self, seed):
        torch.manual_seed(seed)


def _make(lengths, interval, with_step_counter=True, noise=2.0, append_primer=True):
    policy = HighLevelPolicy(OBS, GOAL, LOW, HIGH, interval, noise_sigma=noise, num_cells=(16,))
    env = TransformedEnv(_GoalMockEnv(lengths))
    if with_step_counter:
        env.append_transform(StepCounter())
    if append_primer:
        env.append_transform(policy.make_primer())
    act = TensorDictModule(
        lambda sg, obs: torch.tanh(sg - obs[..., :2]), in_keys=["subgoal", "observation"], out_keys=["action"]
    )
    return env, policy, TensorDictSequential(policy, act)


def _episode_steps(done):
    """Step index within the episode for a [T] done trajectory (done marks the last step)."""
    steps = torch.zeros(done.shape[0], dtype=torch.long)
    for t in range(1, done.shape[0]):
        steps[t] = 0 if done[t - 1] else steps[t - 1] + 1
    return steps


@pytest.mark.parametrize(
    "with_step_counter,primer_by_collector", [(True, False), (False, False), (True, True)]
)
def test_cadence_with_collector_per_env_and_at_reset(with_step_counter, primer_by_collector):
    """c_h cadence per env in a Collector; the primer is appended by hand or found by the Collector."""
    torch.manual_seed(0)
    interval, lengths = 3, [7, 11, 4]
    env, policy, full_policy = _make(
        lengths, interval, with_step_counter, append_primer=not primer_by_collector
    )
    if not primer_by_collector:
        check_env_specs(env)
    collector = Collector(
        env,
        full_policy,
        frames_per_batch=3 * 40,
        total_frames=3 * 40,
        auto_register_policy_transforms=primer_by_collector,
    )
    batch = next(iter(collector))
    collector.shutdown()
    assert batch.shape == (3, 40)
    for e in range(3):
        done = batch["next", "done"][e].reshape(-1)
        steps = _episode_steps(done)
        if with_step_counter:
            assert torch.equal(batch["step_count"][e].reshape(-1), steps)
        expected_new = steps % interval == 0
        new = batch["new_subgoal"][e].reshape(-1)
        assert torch.equal(new, expected_new), (e, new.int().tolist(), expected_new.int().tolist())
        counter = batch["subgoal_step"][e].reshape(-1)
        assert torch.equal(counter, steps % interval)
        sg = batch["subgoal"][e]
        changed = (sg[1:] != sg[:-1]).any(-1)
        # The subgoal changes exactly when a new one is issued (noise makes every issue differ).
        assert torch.equal(changed, expected_new[1:])
        # The held subgoal is the one carried into "next" (primer) and issued subgoals lie in the box.
        torch.testing.assert_close(batch["next", "subgoal"][e], sg)
        assert ((sg >= torch.tensor(LOW)) & (sg <= torch.tensor(HIGH))).all()
    # Envs end episodes at different times: their cadences are not in phase.
    assert not torch.equal(batch["new_subgoal"][0], batch["new_subgoal"][1])


def test_held_subgoal_survives_step_mdp_and_resets_to_primer_default():
    torch.manual_seed(1)
    env, policy, full_policy = _make([5, 5], interval=4)
    td = env.reset()
    assert (td["subgoal_step"] == NO_SUBGOAL).all()
    td = full_policy(td)
    issued = td["subgoal"].clone()
    assert td["new_subgoal"].all()
    td = env.step(td)
    nxt = step_mdp(td)
    torch.testing.assert_close(nxt["subgoal"], issued)
    assert (nxt["subgoal_step"] == 0).all()
    nxt = full_policy(nxt)
    torch.testing.assert_close(nxt["subgoal"], issued)
    assert not nxt["new_subgoal"].any() and (nxt["subgoal_step"] == 1).all()
    # A partial reset restores the primer default only for the reset env.
    nxt["_reset"] = torch.tensor([[True], [False]])
    after = env.reset(nxt)
    assert after["subgoal_step"].reshape(-1).tolist() == [NO_SUBGOAL, 1]


def test_rollout_noise_only_on_issue_and_off_when_deterministic():
    torch.manual_seed(2)
    env, policy, full_policy = _make([30], interval=5)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        roll = env.rollout(12, full_policy)[0]
    proposal = roll["subgoal_proposal"]
    sg = roll["subgoal"]
    new = roll["new_subgoal"].reshape(-1)
    # Deterministic: the issued subgoal is the network output.
    torch.testing.assert_close(sg[new], proposal[new])
    with set_exploration_type(ExplorationType.RANDOM):
        roll = env.rollout(12, full_policy)[0]
    new = roll["new_subgoal"].reshape(-1)
    assert new.nonzero().reshape(-1).tolist() == [0, 5, 10]
    noise = roll["subgoal"][new] - policy.actor(roll[new].clone())["subgoal_proposal"]
    assert noise.abs().max() > 0.1  # absolute noise with std 2 goal units


def test_scheduler_offline_batches_and_missing_state():
    sched = SubgoalScheduler(2, step_count_key=None)
    td = TensorDict({"subgoal_proposal": torch.randn(3, 4, GOAL)}, [3, 4])
    td = sched(td)  # no counter and no held subgoal: a fresh start everywhere
    assert td["new_subgoal"].all() and (td["subgoal_step"] == 0).all()
    first = td["subgoal"].clone()
    td["subgoal_proposal"] = torch.randn(3, 4, GOAL)
    td = sched(td)
    torch.testing.assert_close(td["subgoal"], first)
    td["subgoal_proposal"] = torch.randn(3, 4, GOAL)
    td = sched(td)
    torch.testing.assert_close(td["subgoal"], td["subgoal_proposal"])


def test_scheduler_step_count_forces_issue_and_errors():
    sched = SubgoalScheduler(10)
    td = TensorDict(
        {
            "subgoal_proposal": torch.ones(2, GOAL),
            "subgoal": torch.zeros(2, GOAL),
            "subgoal_step": torch.tensor([[3], [3]]),
            "step_count": torch.tensor([[0], [7]]),
        },
        [2],
    )
    td = sched(td)
    assert td["new_subgoal"].reshape(-1).tolist() == [True, False]
    assert td["subgoal"][:, 0].tolist() == [1.0, 0.0]
    assert td["subgoal_step"].reshape(-1).tolist() == [0, 4]
    with pytest.raises(ValueError, match=r"`interval` \(the high-level interval\) must be an integer >= 1"):
        SubgoalScheduler(0)
    with pytest.raises(ValueError, match="shape"):
        sched(TensorDict({"subgoal_proposal": torch.ones(2, GOAL), "subgoal_step": torch.zeros(2)}, [2]))


def test_primer_found_by_torchrl_module_walk():
    policy = HighLevelPolicy(OBS, GOAL, LOW, HIGH, 3, num_cells=(8,))
    primer = get_primers_from_module(policy)
    assert set(primer.primers.keys()) == {"subgoal", "new_subgoal", "subgoal_step"}
    with pytest.raises(ValueError, match="goal_dim"):
        SubgoalScheduler(3).make_primer()
