"""Cost of one DHRL low-level (SQGC) update against a plain TD3 update of the same networks.

One update = forward + backward + optimiser steps: SQGC trains four critics (policy and graph
twins) every call and the actor every second call; TD3 trains one twin and the actor every
second call. Networks are 3 x 256 ReLU MLPs on AntMaze shapes (obs 29, goal 2, action 8).

Compared, per batch size:

* ``sqgc (fused)``  -- :class:`~torchrl_dhrl.objectives.SQGCLoss`, the four critics as one
  stacked ensemble (one batched matmul per layer, ``fuse_critics=True``);
* ``sqgc (separate)`` -- the same loss evaluating each twin (one stacked module each) on its
  own (``fuse_critics=False``, what the default ``None`` picks on CPU);
* ``td3 (ours)`` -- a plain twin-critic TD3 update with the same networks
  (:class:`~torchrl_dhrl.objectives.HighLevelLoss` on the low-level networks is exactly that);
* ``td3 (torchrl)`` -- :class:`torchrl.objectives.TD3Loss` (vmap over two ``nn.Linear`` MLPs).
* ``sqgc (generic)`` -- :class:`~torchrl_dhrl.objectives.SQGCLoss` with plain TorchRL critics
  (``ValueOperator(MLP)``, one member each; the loss stacks the twins' parameters and evaluates them
  with vmap, as TD3Loss): the price of the generic critic path against the fast path.

* ``sqgc (bf16)`` -- the default SQGC update with its forward pass under bfloat16 autocast, as
  ``LossUpdater(autocast_dtype=torch.bfloat16)`` / the recipe's ``update_dtype=bfloat16`` run it
  (hidden layers in bf16, output layers, targets, losses and Adam in float32);

With ``--device cuda`` a seventh variant runs too:

* ``sqgc (cudagraph)`` -- the fused SQGC update (critic step; critic + actor step every second call)
  captured in two CUDA graphs with :class:`tensordict.nn.CudaGraphModule` (capturable Adam). It shows
  how much of a GPU update is Python and kernel-launch overhead; the recipe does not use it yet.

The ratios use the device's default (``sqgc (separate)`` on CPU, ``sqgc (fused)`` on CUDA). Run::

    OMP_NUM_THREADS=2 python benchmarks/bench_losses.py            # batch 1024 and 256
    python benchmarks/bench_losses.py --batch-sizes 1024 --iters 50 --threads 1
    python benchmarks/bench_losses.py --device cuda

``--yardsticks`` prints a second table at the recipe's shapes (``--shape quick``: PointMaze, 2 x 256, batch
256; ``--shape paper``: AntMaze, 3 x 256, batch 1024) and ``--dtype`` (``float32`` or ``bfloat16``), with the
recipe's update path against two yardsticks (``reference_update.py``):

* ``recipe (eager)`` -- ``LossUpdater(SQGCLoss, actor_after_critic_step=True).step()`` on a fixed batch (the
  recipe's low-level update without sampling);
* ``recipe (compile)`` -- the same with ``compile=True`` (``torch.compile`` of the loss forward + backward);
* ``plain (eager)`` -- the same update written in plain PyTorch (``nn.Linear`` MLPs, no TensorDict);
* ``matmul floor`` -- the matrix products of one ``recipe (eager)`` update alone, replayed at their
  recorded shapes and dtype (forward and backward), in the same run.

    python benchmarks/bench_losses.py --yardsticks --shape quick --threads 1
    python benchmarks/bench_losses.py --yardsticks --shape paper --dtype bfloat16 --threads 2
"""

from __future__ import annotations

import argparse
import time
import warnings

import torch
from tensordict import TensorDict
from torch import nn
from torchrl.data import Bounded
from torchrl.modules import MLP, Actor, ValueOperator
from torchrl.objectives import SoftUpdate, TD3Loss

from torchrl_dhrl.modules import GoalConditionedCritic, LowLevelActor
from torchrl_dhrl.objectives import HighLevelLoss, SQGCLoss, make_optimizers
from torchrl_dhrl.training import LossUpdater

try:  # as a script (benchmarks/ on sys.path) or imported from the repository root
    from reference_update import PlainSQGCUpdate, count_flops, matmul_floor, plain_batch, record_matmuls
except ImportError:  # pragma: no cover
    from benchmarks.reference_update import (
        PlainSQGCUpdate,
        count_flops,
        matmul_floor,
        plain_batch,
        record_matmuls,
    )

OBS, GOAL, ACT, AMAX, GAMMA = 29, 2, 8, 30.0, 0.99
CELLS = (256, 256, 256)


def sqgc_batch(n: int, obs: int = OBS, goal: int = GOAL, act: int = ACT, amax: float = AMAX) -> TensorDict:
    """A random ``SQGCLoss`` input batch of ``n`` transitions (also used by ``bench_threads.py``)."""
    return TensorDict(
        {
            "observation": torch.randn(n, obs),
            "action": (torch.rand(n, act) * 2 - 1) * amax,
            "goal": torch.randn(n, goal),
            "graph_goal": torch.randn(n, goal),
            ("next", "observation"): torch.randn(n, obs),
            ("next", "reward"): -torch.ones(n, 1),
            ("next", "graph_reward"): -torch.ones(n, 1),
            ("next", "done"): torch.zeros(n, 1, dtype=torch.bool),
            ("next", "terminated"): torch.zeros(n, 1, dtype=torch.bool),
        },
        [n],
    )


def low_level_networks(obs=OBS, goal=GOAL, act=ACT, amax=AMAX, cells=CELLS, gamma=GAMMA):
    """The low level's actor and a factory of its critics, as the recipe builds them for an ant maze
    (also used by ``bench_threads.py``)."""
    actor = LowLevelActor(
        obs, goal, action_max=amax, action_dim=act, goal_key="goal", num_cells=cells, goal_indices=(0, 1)
    )

    def critic():
        return GoalConditionedCritic(
            obs,
            goal,
            action_max=amax,
            action_dim=act,
            num_cells=cells,
            gamma=gamma,
            relative_goal=True,
            goal_indices=(0, 1),
        )

    return actor, critic


def _ours(kind: str, device: torch.device):
    actor, dhrl_critic = low_level_networks()

    def critic():
        if kind == "generic":
            mlp = MLP(OBS + GOAL + ACT, 1, num_cells=list(CELLS), activation_class=nn.ReLU)
            return ValueOperator(mlp, in_keys=["observation", "goal", "action"])
        return dhrl_critic()

    if kind == "td3":
        loss = HighLevelLoss(actor, critic(), action_l2=0.01)
        loss.set_keys(goal="goal", action="action")
    else:
        fuse = None if kind in ("bf16", "generic") else kind in ("fused", "cudagraph")  # None: the default
        loss = SQGCLoss(actor, critic(), critic(), gamma=GAMMA, fuse_critics=fuse)
    loss = loss.to(device)
    optims = make_optimizers(loss)
    SoftUpdate(loss, eps=0.995)
    if kind == "cudagraph":
        return _captured_sqgc_update(loss, optims)

    step = [0]

    def update(data):  # the loop owns TD3's actor delay (as LossUpdater): the actor every second update
        step[0] += 1
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=kind == "bf16"):
            out = loss.loss_terms(data, update_actor=step[0] % 2 == 0)
        total = sum(v for k, v in out.items() if k.startswith("loss_"))
        for opt in optims.values():
            opt.zero_grad(set_to_none=True)
        total.backward()
        for opt in optims.values():
            opt.step()

    return update


def _captured_sqgc_update(loss: SQGCLoss, optims: dict):
    """The SQGC update as two CUDA graphs: critics only, and critics + actor (every second call)."""
    from tensordict.nn import CudaGraphModule

    for opt in optims.values():
        for group in opt.param_groups:
            group["capturable"] = True  # Adam's step counter stays on the GPU

    def critic_step(data):
        value, _ = loss.value_loss(data)
        optims["critic"].zero_grad(set_to_none=True)
        value.backward()
        optims["critic"].step()

    def critic_actor_step(data):
        value, _ = loss.value_loss(data)
        actor, _ = loss.actor_loss(data)
        for opt in optims.values():
            opt.zero_grad(set_to_none=True)
        (value + actor).backward()
        for opt in optims.values():
            opt.step()

    graphs = [CudaGraphModule(f, warmup=3, in_keys=[], out_keys=[]) for f in (critic_step, critic_actor_step)]
    calls = [0]

    def update(data):
        calls[0] += 1
        graphs[calls[0] % 2](data)

    return update


class _ConcatMLP(nn.Module):
    """``MLP(cat(inputs))``, optionally squashed to ``[-bound, bound]`` with tanh (the actor)."""

    def __init__(self, mlp: nn.Module, bound: float | None = None) -> None:
        super().__init__()
        self.mlp = mlp
        self.bound = bound

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        out = self.mlp(torch.cat(inputs, -1))
        return out if self.bound is None else self.bound * torch.tanh(out)


def _torchrl_td3(device: torch.device):
    spec = Bounded(-AMAX, AMAX, (ACT,), device=device)
    actor = Actor(
        _ConcatMLP(MLP(OBS + GOAL, ACT, num_cells=list(CELLS), activation_class=nn.ReLU), AMAX),
        in_keys=["observation", "goal"],
        spec=spec,
    )
    qvalue = ValueOperator(
        _ConcatMLP(MLP(OBS + GOAL + ACT, 1, num_cells=list(CELLS), activation_class=nn.ReLU)),
        in_keys=["observation", "goal", "action"],
    )
    loss = TD3Loss(actor, qvalue, action_spec=spec, policy_noise=0.05, noise_clip=1e9, loss_function="l2")
    loss.make_value_estimator(gamma=GAMMA)
    loss = loss.to(device)
    SoftUpdate(loss, eps=0.995)
    # The same (fused) Adam as make_optimizers, for a like-for-like comparison.
    actor_opt = torch.optim.Adam(list(loss.actor_network_params.values(True, True)), lr=1e-4, fused=True)
    critic_opt = torch.optim.Adam(list(loss.qvalue_network_params.values(True, True)), lr=1e-3, fused=True)
    step = [0]

    def update(data):
        step[0] += 1
        q_loss, _ = loss.value_loss(data)
        critic_opt.zero_grad(set_to_none=True)
        q_loss.backward()
        critic_opt.step()
        if step[0] % 2 == 0:
            a_loss, _ = loss.actor_loss(data)
            actor_opt.zero_grad(set_to_none=True)
            a_loss.backward()
            actor_opt.step()

    return update


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _time_interleaved(
    updates: dict, data: TensorDict, iters: int, repeats: int, device: torch.device
) -> dict[str, float]:
    """Milliseconds per update of each variant: the minimum over repeats, variants interleaved.

    Interleaving exposes every variant to the same background load, and the minimum is the
    least-disturbed estimate on a shared machine.
    """
    for update in updates.values():
        for _ in range(8):  # CUDA graphs: 3 warm-up calls per graph, then capture
            update(data)
    times = {name: [] for name in updates}
    for _ in range(repeats):
        for name, update in updates.items():
            _sync(device)
            start = time.perf_counter()
            for _ in range(iters):
                update(data)
            _sync(device)
            times[name].append((time.perf_counter() - start) / iters * 1e3)
    return {name: min(values) for name, values in times.items()}


#: ``--shape``: (obs, goal, action, action max, hidden widths, batch) of the recipe's presets.
SHAPES = {
    "quick": (6, 2, 2, 1.0, (256, 256), 256),  # PointMaze, preset=quick
    "paper": (29, 2, 8, 30.0, (256, 256, 256), 1024),  # AntMaze, the paper's networks and batch
}


class _FixedBatch:
    """A stand-in buffer whose ``sample()`` returns one fixed batch (the update without sampling)."""

    def __init__(self, data: TensorDict) -> None:
        self.data = data

    def sample(self) -> TensorDict:
        return self.data


def yardsticks(shape: str, dtype: str, device: torch.device, iters: int, repeats: int) -> None:
    """The recipe's SQGC update (eager and compiled) against a plain-PyTorch update and its matmul floor."""
    obs, goal, act, amax, cells, batch = SHAPES[shape]
    autocast = torch.bfloat16 if dtype == "bfloat16" else None
    data = sqgc_batch(batch, obs, goal, act, amax).to(device)

    def recipe_update(compile_: bool):
        torch.manual_seed(0)
        actor = LowLevelActor(
            obs, goal, action_max=amax, action_dim=act, goal_key="goal", num_cells=cells, goal_indices=(0, 1)
        )

        def critic():
            return GoalConditionedCritic(
                obs, goal, action_max=amax, action_dim=act, num_cells=cells, gamma=GAMMA, relative_goal=False
            )

        loss = SQGCLoss(actor, critic(), critic(), gamma=GAMMA).to(device)
        updater = LossUpdater(
            loss,
            _FixedBatch(data),
            make_optimizers(loss),
            actor_after_critic_step=True,
            autocast_dtype=autocast,
            compile=compile_,
        )
        return updater.step

    plain = PlainSQGCUpdate(obs, goal, act, cells, amax, autocast_dtype=autocast, device=device)
    tensors = plain_batch(data)
    updates = {"recipe (eager)": recipe_update(False), "recipe (compile)": recipe_update(True)}
    updates["plain (eager)"] = lambda _: plain(tensors)
    start = time.perf_counter()
    for _ in range(4):  # compile the compiled variant's graphs before anything is recorded or timed
        updates["recipe (compile)"]()
    compile_s = time.perf_counter() - start
    eager = updates["recipe (eager)"]
    calls = record_matmuls(lambda: [eager() for _ in range(2)])  # one critic-only and one actor update
    floor = matmul_floor(calls)
    timed = {
        "recipe (eager)": lambda _: eager(),
        "recipe (compile)": lambda _: updates["recipe (compile)"](),
        "plain (eager)": updates["plain (eager)"],
        "matmul floor": lambda _: floor(),  # two updates per call
    }
    ms = _time_interleaved(timed, data, iters, repeats, device)
    ms["matmul floor"] /= 2  # the floor replays two updates per call
    gflop = count_flops(calls) / 2 / 1e9
    print(
        f"\nyardsticks: --shape {shape} (obs {obs}, goal {goal}, act {act}, MLPs {cells}, batch {batch}), "
        f"{dtype}, {device} ({torch.get_num_threads()} threads); {gflop:.3f} GFLOP of matrix products per "
        f"update; compilation {compile_s:.1f} s; minimum of {repeats} interleaved repeats of {iters} updates"
    )
    print(
        " ".join(f"{name:>17}" for name in ms)
        + f" {'eager/plain':>12} {'eager/floor':>12} {'compile/plain':>14} {'compile/floor':>14}"
    )
    print(
        " ".join(f"{value:>14.2f} ms" for value in ms.values())
        + f" {ms['recipe (eager)'] / ms['plain (eager)']:>12.2f} {ms['recipe (eager)'] / ms['matmul floor']:>12.2f}"
        + f" {ms['recipe (compile)'] / ms['plain (eager)']:>14.2f} {ms['recipe (compile)'] / ms['matmul floor']:>14.2f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1024, 256])
    parser.add_argument(
        "--iters", type=int, default=20, help="updates per timed repeat (even: actor every 2nd)"
    )
    parser.add_argument("--repeats", type=int, default=7, help="timed repeats; the minimum is reported")
    parser.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's)")
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--yardsticks", action="store_true", help="only the recipe-vs-plain-vs-floor table")
    parser.add_argument("--shape", choices=sorted(SHAPES), default="quick", help="--yardsticks shapes")
    parser.add_argument("--dtype", choices=["float32", "bfloat16"], default="float32", help="--yardsticks")
    args = parser.parse_args()
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda needs a CUDA device")
    if args.threads:
        torch.set_num_threads(args.threads)
    warnings.filterwarnings("ignore")
    torch.manual_seed(0)
    if args.yardsticks:
        yardsticks(args.shape, args.dtype, device, args.iters, args.repeats)
        return
    variants = {
        "sqgc (fused)": lambda: _ours("fused", device),
        "sqgc (separate)": lambda: _ours("separate", device),
        "td3 (ours)": lambda: _ours("td3", device),
        "td3 (torchrl)": lambda: _torchrl_td3(device),
        "sqgc (bf16)": lambda: _ours("bf16", device),
        "sqgc (generic)": lambda: _ours("generic", device),
    }
    if device.type == "cuda":
        variants["sqgc (cudagraph)"] = lambda: _ours("cudagraph", device)
    default = "sqgc (fused)" if device.type == "cuda" else "sqgc (separate)"  # what fuse_critics=None picks
    print(
        f"torch {torch.__version__}, {device} ({torch.cuda.get_device_name(device) if device.type == 'cuda' else f'{torch.get_num_threads()} threads'}), "
        f"MLPs {CELLS}, obs {OBS} goal {GOAL} act {ACT}; ratios use {default}"
    )
    print(
        f"{'batch':>6} "
        + " ".join(f"{name:>16}" for name in variants)
        + f" {'sqgc/td3(ours)':>15} {'sqgc/td3(trl)':>14} {'sqgc/bf16':>10}"
        + (f" {'fused/cudagraph':>16}" if device.type == "cuda" else "")
    )
    for batch_size in args.batch_sizes:
        data = sqgc_batch(batch_size).to(device)
        ms = _time_interleaved(
            {name: make() for name, make in variants.items()}, data, args.iters, args.repeats, device
        )
        row = " ".join(f"{ms[name]:>13.2f} ms" for name in variants)
        sqgc = ms[default]
        r_ours, r_trl = sqgc / ms["td3 (ours)"], sqgc / ms["td3 (torchrl)"]
        graph = f" {sqgc / ms['sqgc (cudagraph)']:>16.2f}" if device.type == "cuda" else ""
        r_bf16 = sqgc / ms["sqgc (bf16)"]
        print(f"{batch_size:>6} {row} {r_ours:>15.2f} {r_trl:>14.2f} {r_bf16:>10.2f}{graph}")


if __name__ == "__main__":
    main()
