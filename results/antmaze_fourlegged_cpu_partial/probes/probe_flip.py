"""Deterministic evaluation rollouts: how many ants end upside down (``AntAgent.is_upside_down``)?"""

import sys

import torch
from dhrl_utils import agent_from_checkpoint, build_environment
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp
from torchrl_dhrl.envs import AntAgent

torch.manual_seed(0)
cfg, agent = agent_from_checkpoint(sys.argv[1])
env = build_environment(cfg, torch.device("cpu"), eval=True, agent=agent)


td = env.reset()
first_flip = torch.full((td.shape[0],), -1)
with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
    for t in range(600):
        td = agent.policy(td)
        new = AntAgent.is_upside_down(td["observation"]) & (first_flip < 0)
        first_flip[new] = t
        td = step_mdp(env.step(td))
print("ends upside down", AntAgent.is_upside_down(td["observation"]).tolist())
print("first upside-down step", first_flip.tolist())
print("final pos", [[round(v, 1) for v in p] for p in td["achieved_goal"].tolist()])
