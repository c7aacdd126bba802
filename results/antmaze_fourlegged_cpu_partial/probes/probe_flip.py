"""Deterministic evaluation rollouts: how many ants end upside down (torso up-axis z < 0)?"""

import sys

import torch
from dhrl_utils import agent_from_checkpoint, build_environment
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

torch.manual_seed(0)
cfg, agent = agent_from_checkpoint(sys.argv[1])
env = build_environment(cfg, torch.device("cpu"), eval=True, agent=agent)


def upz(obs):  # z component of the torso's local z axis from quaternion (w, x, y, z)
    x, y = obs[:, 4], obs[:, 5]
    return 1 - 2 * (x * x + y * y)


td = env.reset()
first_flip = torch.full((td.shape[0],), -1)
with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
    for t in range(600):
        td = agent.policy(td)
        u = upz(td["observation"])
        new = (u < 0) & (first_flip < 0)
        first_flip[new] = t
        td = step_mdp(env.step(td))
u = upz(td["observation"])
print("final up_z", [round(v, 2) for v in u.tolist()])
print("first upside-down step", first_flip.tolist())
print("final pos", [[round(v, 1) for v in p] for p in td["achieved_goal"].tolist()])
