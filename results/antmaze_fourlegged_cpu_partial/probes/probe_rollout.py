"""Deterministic rollout of the trained hierarchy towards a chosen goal; prints the subgoal and position every 40 steps."""

import sys

import torch
from dhrl_utils import agent_from_checkpoint, build_environment
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

torch.manual_seed(0)
cfg, agent = agent_from_checkpoint(sys.argv[1])
env = build_environment(cfg, torch.device("cpu"), eval=True, agent=agent)
goal = torch.tensor([float(v) for v in sys.argv[2].split(",")])
td = env.reset()
td["desired_goal"] = goal.expand_as(td["desired_goal"]).clone()
with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
    for t in range(600):
        td = agent.policy(td)
        if t % 20 == 0 or t < 5:
            pl = td["planner"][0]
            print(
                t,
                "pos",
                [round(v, 2) for v in td["achieved_goal"][0].tolist()],
                "z",
                round(td["observation"][0, 2].item(), 2),
                "subgoal",
                [round(v, 1) for v in td["subgoal"][0].tolist()],
                "wp",
                [round(v, 2) for v in td["waypoint"][0].tolist()],
                "idx",
                pl["index"].item(),
                "len",
                pl["path_length"].item(),
                "steps",
                pl["steps"].item(),
                "budget",
                [round(b, 1) for b in pl["budgets"][:4].tolist()],
                "act",
                round(td["action"][0].abs().mean().item(), 1),
            )
        td = env.step(td)
        nxt = step_mdp(td)
        nxt["desired_goal"] = goal.expand_as(nxt["desired_goal"]).clone()
        td = nxt
print("end", [round(v, 1) for v in td["achieved_goal"].reshape(-1, 2)[0].tolist()])
