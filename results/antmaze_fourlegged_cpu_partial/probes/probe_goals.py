"""For goals around the frontier: the high level's subgoal at the start, the plan, and the learned distances."""

import sys

import torch
from dhrl_utils import agent_from_checkpoint, build_environment
from tensordict import TensorDict

torch.manual_seed(0)
cfg, agent = agent_from_checkpoint(sys.argv[1])
env = build_environment(cfg, torch.device("cpu"), eval=True, agent=agent)
td = env.reset()
obs = td["observation"].reshape(-1, td["observation"].shape[-1])[:1]
p = agent.planner
goals = torch.tensor([[float(x) for x in g.split(",")] for g in sys.argv[2:]])
n = goals.shape[0]
o = obs.expand(n, -1)
with torch.no_grad():
    sg = agent.high_policy.actor(TensorDict({"observation": o, "desired_goal": goals}, [n]))[
        "subgoal_proposal"
    ]
    lg = p.landmark_goals
    d_lm_goal = p.distance(
        p.landmark_states.unsqueeze(0).expand(n, -1, -1).reshape(-1, 29),
        goals.repeat_interleave(lg.shape[0], 0),
    ).reshape(n, -1)
    plan_g = p.plan(o, goals)
    plan_s = p.plan(o, sg)
for i in range(n):
    k = d_lm_goal[i].argmin()
    e = (lg - goals[i]).norm(dim=-1)
    ke = e.argmin()
    L = int(plan_g.length[i])
    Ls = int(plan_s.length[i])
    last_g = lg[plan_g.path[i, L - 1]].tolist() if L else None
    last_s = lg[plan_s.path[i, Ls - 1]].tolist() if Ls else None
    print(
        f"goal {goals[i].tolist()} subgoal {[round(v, 1) for v in sg[i].tolist()]} | "
        f"min learned d(lm->goal) {d_lm_goal[i].min():.0f} at {[round(v, 1) for v in lg[k].tolist()]}; "
        f"euclid-nearest lm {[round(v, 1) for v in lg[ke].tolist()]} d={d_lm_goal[i, ke]:.0f}; d range {d_lm_goal[i].min():.0f}-{d_lm_goal[i].max():.0f} | "
        f"plan->goal reach {bool(plan_g.reachable[i])} last {None if last_g is None else [round(v, 1) for v in last_g]} | "
        f"plan->subgoal reach {bool(plan_s.reachable[i])} last {None if last_s is None else [round(v, 1) for v in last_s]}"
    )
