"""Which observation entries of a DHRL run leave the range its networks were trained on?

Percentiles of ``|observation|`` per entry over the run's low-level replay buffer (every state the agent
visited, up to the buffer's size): an entry whose 99th percentile or maximum is far above the others is an
unbounded feature (e.g. Reacher3D's continuous roll joints, whose raw angles reach hundreds of radians: see
``angle_features``), which the critics extrapolate on.

    python recipes/diagnose_observations.py outputs/<date>/<time>       # the run directory
    python recipes/diagnose_observations.py run/checkpoint --quantiles 0.5 0.99
"""

from __future__ import annotations

import argparse

import torch
from dhrl_utils import agent_from_checkpoint, build_replay_buffers

from torchrl_dhrl.recipe import load_checkpoint

#: The most buffer rows the quantiles are taken over (a uniform subsample beyond; the maximum sees every row).
SAMPLE = 200_000


def observation_ranges(path, quantiles=(0.5, 0.99), device: str = "cpu") -> dict:
    """``{"entries": N, "quantiles": {q: tensor[obs_dim]}, "max": tensor[obs_dim]}`` of ``|observation|`` over the
    low-level buffer of the checkpoint at ``path`` (a checkpoint or its run directory)."""
    cfg, agent = agent_from_checkpoint(path, device)
    low_rb, _ = build_replay_buffers(cfg, agent, torch.device(device))
    low_rb.load_state_dict(load_checkpoint(path, map_location=device, components=("low_rb",))["low_rb"])
    if len(low_rb) == 0:
        raise ValueError(f"The low-level buffer of {path} is empty.")
    obs = low_rb[:]["observation"]
    obs = obs.reshape(-1, obs.shape[-1]).abs().float()
    # torch.quantile takes at most 2**24 elements: quantiles of up to SAMPLE rows drawn without replacement
    rows = obs[torch.randperm(obs.shape[0], generator=torch.Generator().manual_seed(0))[:SAMPLE]]
    return {
        "entries": obs.shape[0],
        "quantiles": {q: rows.quantile(q, dim=0) for q in quantiles},
        "max": obs.max(0).values,
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", help="a checkpoint or the run directory holding it")
    parser.add_argument("--quantiles", type=float, nargs="+", default=[0.5, 0.99])
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    ranges = observation_ranges(args.checkpoint, args.quantiles, args.device)
    qs = list(ranges["quantiles"])
    print(f"|observation| over {ranges['entries']} stored states")
    print(f"{'entry':>6} " + " ".join(f"{'p' + format(100 * q, 'g'):>9}" for q in qs) + f" {'max':>9}")
    for i in range(ranges["max"].numel()):
        print(
            f"{i:6d} "
            + " ".join(f"{ranges['quantiles'][q][i].item():9.3g}" for q in qs)
            + f" {ranges['max'][i].item():9.3g}"
        )
    return ranges


if __name__ == "__main__":
    main()
