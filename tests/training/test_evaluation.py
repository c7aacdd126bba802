"""Evaluation: final and any-time success, the last steps and the final speed, video recording."""

import os

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv
from torchrl_dhrl.envs import make_env

from torchrl_dhrl.training import evaluate


def test_evaluate_final_vs_any_time_success():
    env = make_env("PointMaze", num_envs=2, seed=0, eval=True, max_episode_steps=4)
    goal = torch.tensor([0.0, 0.4])  # within the 2.5 success radius of the start
    td = env.reset(TensorDict({"desired_goal": goal.expand(2, 2)}, [2]))
    assert td["is_success"].all()
    still = lambda td: td.set("action", torch.zeros(*td.batch_size, 2))  # noqa: E731
    result = evaluate(env, still, max_steps=4)  # evaluate resets to the test goal (0, 8): never reached
    assert result.success == 0.0 and result.any_success == 0.0
    assert result.final_distance == pytest.approx(8.0, abs=0.5)
    assert result.rollout.shape == (2, 4)


def test_evaluate_last_steps_and_final_speed_on_a_crafted_rollout():
    """Two 12-step episodes: one passes through the goal ball and leaves it, one arrives and stays."""

    class Recorded:
        def __init__(self, rollout):
            self.recorded = rollout

        def rollout(self, max_steps, policy, break_when_any_done=False):
            return self.recorded

    t = torch.arange(12.0)
    ag = torch.stack(
        [torch.stack([t * 0.5, torch.zeros(12)], -1), torch.stack([t.clamp(max=6.0), t * 0], -1)], 0
    )
    nxt = torch.cat([ag[:, 1:], ag[:, -1:] + torch.tensor([[[0.5, 0.0]], [[0.0, 0.0]]])], 1)
    inside = torch.zeros(2, 12, 1, dtype=torch.bool)
    inside[0, 3:6] = True  # passes through the ball at steps 3-5
    inside[1, 5:] = True  # arrives at step 5 and stays
    rollout = TensorDict(
        {
            "achieved_goal": ag,
            ("next", "achieved_goal"): nxt,
            ("next", "desired_goal"): torch.full((2, 12, 2), 6.0),
            ("next", "is_success"): inside,
        },
        [2, 12],
    )
    result = evaluate(Recorded(rollout), None, max_steps=12)
    assert result.success == 0.5 and result.any_success == 1.0
    assert result.last_steps_success == pytest.approx(
        (3 + 7) / 20
    )  # of steps 2-11: 3-5 (ep. 0), 5-11 (ep. 1)
    assert result.final_speed == pytest.approx((0.5 + 0.0) / 2)
    assert evaluate(Recorded(rollout), None, 12, last_steps=3).last_steps_success == pytest.approx(3 / 6)


@pytest.mark.skipif(
    os.environ.get("MUJOCO_GL", "").lower() not in ("egl", "osmesa"),
    reason="offscreen rendering needs MUJOCO_GL=egl or osmesa (an OpenGL backend)",
)
def test_record_video(tmp_path):
    from PIL import Image

    from torchrl_dhrl.training import record_video

    env = make_env("PointMaze", num_envs=2, seed=0, eval=True, max_episode_steps=9)
    still = lambda td: td.set("action", torch.zeros(*td.batch_size, 2))  # noqa: E731
    path = record_video(TransformedEnv(env), still, 9, tmp_path / "episode.gif", every=4, size=64)
    with Image.open(path) as gif:
        assert gif.n_frames == 3 and gif.size == (64, 64)
