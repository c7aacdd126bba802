"""Fraction of training time the ant spends upside down, for every other 9000-step block of the low-level
buffer (``AntAgent.is_upside_down``)."""

import sys

import torch
from dhrl_utils import agent_from_checkpoint, build_replay_buffers
from torchrl_dhrl.envs import AntAgent

from torchrl_dhrl.training import load_checkpoint

cfg, agent = agent_from_checkpoint(sys.argv[1])
low_rb, _ = build_replay_buffers(cfg, agent, torch.device("cpu"))
low_rb.load_state_dict(load_checkpoint(sys.argv[1], components=("low_rb",))["low_rb"])
st = low_rb.storage
n = len(st)
rec = st[:n]
print(rec.batch_size, list(rec.keys())[:12])
obs = rec["observation"].reshape(-1, 29) if rec["observation"].ndim > 2 else rec["observation"]
flipped = AntAgent.is_upside_down(obs).float()
T = obs.shape[0]
chunk = 9000
for s in range(0, T, chunk * 2):
    print(
        f"steps {s:>7}-{min(s + chunk, T):>7}: upside down {flipped[s : s + chunk].mean():.1%}, torso z<0.35 {(obs[s : s + chunk, 2] < 0.35).float().mean():.1%}"
    )
print("overall upside down", f"{flipped.mean():.1%}")
