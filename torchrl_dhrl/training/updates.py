"""One optimisation step of a DHRL loss: sample, loss, Adam steps, delayed Polyak averaging."""

from __future__ import annotations

import contextlib
import functools
import warnings
from collections.abc import Callable, Mapping

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import CudaGraphModule
from torchrl.data import ReplayBuffer
from torchrl.objectives import LossModule, SoftUpdate

from torchrl_dhrl.checks import checked, flag, integer, number

__all__ = ["AUTOCAST_DTYPES", "LossUpdater", "NonFiniteLossError", "compile_available"]

#: ``autocast_dtype`` values of :class:`LossUpdater` (``None``: full precision).
AUTOCAST_DTYPES = (None, torch.bfloat16)


class NonFiniteLossError(RuntimeError):
    """A loss became NaN or infinite; training must stop (the last good checkpoint is kept)."""


#: Inductor options of the compiled updates: random draws (TD3's target noise) through the eager
#: generator, so a compiled update draws exactly the noise an eager one would (same seed, same stream).
COMPILE_OPTIONS = {"fallback_random": True}


@functools.cache
def compile_available() -> str | None:
    """``None`` when ``torch.compile`` (inductor) works here, else the reason it does not (probed once).

    The probe compiles and runs a two-op function on the CPU, which needs inductor's C++ toolchain (and
    takes seconds the first time in a process); a machine without one gets the error's first line.
    """
    try:
        probe = torch.compile(lambda x: torch.relu(x) * 2.0 + 1.0, options=COMPILE_OPTIONS)
        out = probe(torch.linspace(-1.0, 1.0, 8))
        if not torch.allclose(out, torch.relu(torch.linspace(-1.0, 1.0, 8)) * 2.0 + 1.0):
            return "the compiled probe computed a wrong result"
    except Exception as err:  # noqa: BLE001 - any failure means: run eagerly
        return f"{type(err).__name__}: {str(err).strip().splitlines()[0] if str(err).strip() else ''}"
    return None


class LossUpdater:
    """Runs optimisation steps of a DHRL loss (:class:`SQGCLoss` or :class:`HighLevelLoss`) from a buffer.

    Each :meth:`step` samples a batch with ``replay_buffer.sample()`` (a
    :class:`~torchrl_dhrl.data.RelabelReplayBuffer` returns it relabelled: hindsight goals,
    rewards, subgoal tests), evaluates the loss, back-propagates the sum of its ``loss_*``
    entries, steps the critic optimiser, steps the actor optimiser only on every
    ``actor_update_interval``-th update (TD3's delayed actor: an Adam step on a zero gradient would
    still move the weights through its momentum), and applies Polyak averaging
    ``target <- polyak * target + (1 - polyak) * online`` every ``target_update_interval`` steps
    (reference: 0.995 every 10 steps). A non-finite loss raises
    :class:`NonFiniteLossError` before any parameter changes.

    With ``actor_after_critic_step=True`` (the reference implementation's order) the critic
    losses are back-propagated and the critic optimiser stepped first, and the actor loss of a
    delayed-actor step is then evaluated on the same sample with the *updated* critic and
    stepped separately. With ``False`` one backward pass of the sum of all ``loss_*`` entries
    (critic and actor losses from the same, pre-step critic) is followed by both optimiser
    steps, as TorchRL's TD3 recipes do. The two differ by one critic step in the critic the
    actor follows; both run the same forward and backward passes.

    **The delayed-actor schedule is the updater's**, as in TorchRL's TD3 recipe loop: the loss keeps no
    count. Update ``k`` (1-based, :attr:`num_updates` after it) trains the actor when
    ``k % actor_update_interval == 0``, and the updater tells the loss so with
    ``loss.loss_terms(sample, update_actor=...)`` (a loss without ``loss_terms``, e.g.
    :class:`~torchrl.objectives.TD3Loss`, is called as ``loss(sample)`` and only its actor step is
    skipped; it needs ``actor_after_critic_step=False``). The number of updates taken is the updater's only
    state (``state_dict``), so a resumed updater continues the schedule exactly; the optimisers and the loss
    (with its target parameters) are checkpointed by their owners.

    With ``cudagraphs=True`` (loss on a CUDA device) the loss, backward pass and Adam steps are captured
    in two CUDA graphs with :class:`tensordict.nn.CudaGraphModule`, one with and one without the actor
    step, and replayed: on an H100 this cuts an SQGC update at batch 1024 from about 9 ms to about 1 ms
    (``benchmarks/bench_losses.py --device cuda``). Where the buffer offers a capture-safe sampler
    (:meth:`RelabelReplayBuffer.capturable_sampler <torchrl_dhrl.data.RelabelReplayBuffer.capturable_sampler>`:
    uniform draws and relabel steps with a capture-safe form, such as the low-level buffer's
    :class:`~torchrl_dhrl.data.FutureGoalRelabel`, or the high-level buffer's
    :class:`~torchrl_dhrl.data.HindsightSubgoalRelabel` whose gradual penalty queries a ``fixed_size`` graph),
    sampling and relabelling are captured in the same graphs (``capture_sampling``): a replay is then the whole
    update from the storage on, with no host work but the replay itself. Otherwise (e.g. a gradual penalty on a
    graph that is not ``fixed_size``) the batch is sampled eagerly and copied into the graph's inputs. The delayed-actor schedule
    (decided on the host from :attr:`num_updates`) and Polyak averaging stay eager. The optimisers are
    switched to ``capturable`` Adam, and the graphs are captured after a few eager warm-up steps: load
    any state (``resume``) before the first step. The non-finite check then runs after the steps (once
    per :meth:`run`): the parameters have already taken the steps of that call when it raises (the recipe
    stops without saving them, keeping its last good checkpoint).

    With ``updates_per_graph=N`` (and ``cudagraphs=True``) :meth:`run` replays ``N`` consecutive updates as one
    graph: each samples itself (the capture-safe sampler, inside the graph), takes its loss, backward pass and Adam
    steps, and the Polyak averaging due after it runs inside the graph too, so ``N`` updates cost one replay and
    no host work between them. The pattern of delayed-actor and target updates over the ``N`` updates is decided
    on the host from :attr:`num_updates`; each pattern is its own graph (at most
    ``lcm(actor_update_interval, target_update_interval)`` of them). The updates are the same, in the same order,
    as ``N`` single ones (tested through CudaGraphModule's CPU pass-through). A call's remainder (fewer than ``N``
    updates left), :meth:`step`, and a buffer without a capture-safe sampler (whose batches are sampled on the
    host) take one update per replay.

    With ``autocast_dtype=torch.bfloat16`` the loss's forward pass runs under ``torch.autocast``
    on the loss's device (mixed precision): the hidden layers of every actor and critic multiply
    in bfloat16, their output layers, the TD targets, the losses, the backward pass's accumulated
    gradients and the Adam steps stay in float32 (the parameters' dtype). bfloat16 has float32's
    exponent range, so no loss scaling is needed. On a CPU with bfloat16 matrix instructions
    (AVX512-BF16 / AMX) an SQGC update at batch 1024 is about 1.7x faster
    (``benchmarks/bench_losses.py``); the price is 8-bit-mantissa hidden activations.

    With ``compile=True`` the loss's forward terms (``loss_terms`` and, with ``actor_after_critic_step``,
    ``actor_loss``) run through :func:`torch.compile` (inductor): AOTAutograd traces their backward too,
    so forward and backward become a few fused kernels around the matrix products (about 1.5x faster
    SQGC forward + backward at the quick preset's shape on a 2-core CPU, ``benchmarks/bench_losses.py``).
    Sampling, the optimiser steps (fused Adam), the delayed-actor schedule and Polyak averaging stay
    eager. Random draws go through the eager generator (``fallback_random``), so a compiled update takes
    the same noise as an eager one and the two agree to float round-off (fusion reorders sums). The first
    updates pay the compilation (tens of seconds on a small CPU; inductor's on-disk cache makes later runs
    start faster). Where ``torch.compile`` does not work (:func:`compile_available`), the updater warns
    once and runs eagerly. ``compile=True`` combines with ``cudagraphs=True`` (as TorchRL's and LeanRL's
    recipes do): the compiled functions (and the capture-safe sampler, compiled whole) run in the eager
    warm-up calls, where they compile, and their kernels are then captured in the graphs.

    Args:
        loss (LossModule): the loss, returning ``loss_*`` entries; a DHRL loss
            (:class:`~torchrl_dhrl.objectives.SQGCLoss`, :class:`~torchrl_dhrl.objectives.HighLevelLoss`)
            also takes the delayed-actor decision in ``loss_terms`` and reports it as ``actor_updated``.
        replay_buffer (ReplayBuffer): the buffer to sample from (its ``batch_size`` is used); its samples
            are fed to the loss as they are.
        optimizers (dict): ``{"actor": ..., "critic": ...}`` as made by
            :func:`~torchrl_dhrl.objectives.make_optimizers`.

    Keyword Args:
        polyak (float): Polyak coefficient of the target networks. Defaults to ``0.995``.
        target_update_interval (int): steps between target updates. Defaults to ``10``.
        actor_update_interval (int): TD3's actor delay: the actor is trained on every this-many-th
            update. Defaults to ``2`` (the reference's).
        cudagraphs (bool): replay the update as CUDA graphs (see above). Defaults to ``False``.
        autocast_dtype (torch.dtype, optional): ``torch.bfloat16`` for mixed-precision updates
            (see above); ``None`` (default) for full precision. With ``cudagraphs`` the captured forward
            runs autocast without its weight cache (``cache_enabled=False``): the same values.
        actor_after_critic_step (bool): evaluate and step the actor loss after the critic step
            (see above; needs a loss with ``loss_terms`` and ``actor_loss``). Defaults to ``True`` (the
            reference's order); ``False``: one backward of the summed losses, as TorchRL's TD3 recipes.
        compile (bool): run the loss's forward terms (and so their backward) through
            :func:`torch.compile` (see above). Defaults to ``False``.
        capture_sampling (bool, optional): draw batches with the buffer's capture-safe sampler
            (:meth:`~torchrl_dhrl.data.RelabelReplayBuffer.capturable_sampler`) instead of ``sample()``:
            with ``cudagraphs=True`` inside the update's graphs (see above), with ``compile=True`` compiled
            whole (``fullgraph=True``), else eagerly (no sampler object, no slicing of the storage: faster
            on a CPU too). ``None`` (default): inside the graphs when ``cudagraphs=True`` and the buffer
            can, otherwise ``sample()``; ``True``: always (the buffer's reason is raised at the first update
            if it cannot); ``False``: never. :attr:`sampling_captured` and :attr:`sampling_note` say what
            was chosen, once the first update ran. It draws other batches than ``sample()`` from the same
            seed (the same distribution: uniform over the written records).
        updates_per_graph (int): consecutive updates per CUDA-graph replay (see above; needs
            ``cudagraphs=True`` when above 1). Defaults to ``1``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage
        >>> from torchrl_dhrl.data import HindsightSubgoalRelabel, RelabelReplayBuffer
        >>> from torchrl_dhrl.modules import GoalConditionedCritic, HighLevelActor
        >>> from torchrl_dhrl.objectives import HighLevelLoss, make_optimizers
        >>> low, high = [-4.0, -4.0], [20.0, 20.0]
        >>> actor = HighLevelActor(6, 2, low, high, num_cells=(16,))
        >>> critic = GoalConditionedCritic(6, 2, action_low=low, action_high=high, goal_key="desired_goal",
        ...     action_key="subgoal", relative_goal=False, num_cells=(16,))
        >>> loss = HighLevelLoss(actor, critic)
        >>> rb = RelabelReplayBuffer(  # samples come out with HAC actions and rewards
        ...     storage=LazyTensorStorage(100), relabel=[HindsightSubgoalRelabel()], batch_size=8
        ... )
        >>> _ = rb.extend(TensorDict({"observation": torch.randn(20, 6), "desired_goal": torch.randn(20, 2),
        ...     "subgoal": torch.rand(20, 2) * 24 - 4, ("next", "observation"): torch.randn(20, 6),
        ...     ("next", "achieved_goal"): torch.randn(20, 2)}, [20]))
        >>> updater = LossUpdater(loss, rb, make_optimizers(loss))
        >>> metrics = updater.step()
        >>> updater.num_updates, bool(torch.isfinite(metrics["loss_qvalue"]))
        (1, True)
    """

    @checked(
        polyak=number(0.0, 1.0),
        target_update_interval=integer(1),
        actor_update_interval=integer(1),
        cudagraphs=flag(),
        actor_after_critic_step=flag(),
        compile=flag(),
        capture_sampling=flag(optional=True),
        updates_per_graph=integer(1, what="the updates per CUDA-graph replay"),
    )
    def __init__(
        self,
        loss: LossModule,
        replay_buffer: ReplayBuffer,
        optimizers: Mapping[str, torch.optim.Optimizer],
        *,
        polyak: float = 0.995,
        target_update_interval: int = 10,
        actor_update_interval: int = 2,
        cudagraphs: bool = False,
        autocast_dtype: torch.dtype | None = None,
        actor_after_critic_step: bool = True,
        compile: bool = False,  # noqa: A002 - the flag's name in TorchRL's recipes
        capture_sampling: bool | None = None,
        updates_per_graph: int = 1,
    ) -> None:
        if updates_per_graph > 1 and not cudagraphs:
            raise ValueError(
                f"`updates_per_graph` {updates_per_graph} > 1 needs cudagraphs=True (it sets how many updates one "
                "CUDA-graph replay runs); without graphs, updates run one by one."
            )
        if set(optimizers) != {"actor", "critic"}:
            raise ValueError(f"`optimizers` must have keys 'actor' and 'critic', got {sorted(optimizers)}.")
        if autocast_dtype not in AUTOCAST_DTYPES:
            raise ValueError(
                f"`autocast_dtype` must be None or torch.bfloat16, got {autocast_dtype!r} (float16 would "
                "need loss scaling)."
            )
        if actor_after_critic_step and not (hasattr(loss, "loss_terms") and hasattr(loss, "actor_loss")):
            raise TypeError(
                "`actor_after_critic_step=True` (the default) needs a loss with `loss_terms` and `actor_loss`, "
                f"got {type(loss).__name__}: pass actor_after_critic_step=False."
            )
        self.actor_after_critic_step = bool(actor_after_critic_step)
        self.loss = loss
        self.autocast_dtype = autocast_dtype
        self.replay_buffer = replay_buffer
        self.optimizers = dict(optimizers)
        self.target_update_interval = int(target_update_interval)
        self.actor_update_interval = actor_update_interval
        self.target_updater = SoftUpdate(loss, eps=polyak)
        self.num_updates = 0
        self.cudagraphs = bool(cudagraphs)
        self.capture_sampling = capture_sampling
        #: whether batches come from the capture-safe sampler (``None`` until the first update that decides)
        self.sampling_captured: bool | None = None
        #: why the graphs do (not) sample themselves, set with :attr:`sampling_captured`
        self.sampling_note = ""
        self._captured_sample: Callable[[], TensorDictBase] | None = None
        self._graphs: dict[bool, CudaGraphModule] = {}
        self.updates_per_graph = int(updates_per_graph)
        #: graphs of ``updates_per_graph`` updates, by their pattern of (actor due, target due) per update
        self._chunk_graphs: dict[tuple[tuple[bool, bool], ...], CudaGraphModule] = {}
        self.compile = bool(compile)
        if self.compile and (reason := compile_available()) is not None:
            warnings.warn(
                f"LossUpdater(compile=True): torch.compile does not work here ({reason}); running eagerly.",
                stacklevel=2,
            )
            self.compile = False
        self._terms_fn: Callable = self._loss_terms_eager
        self._actor_fn: Callable | None = getattr(loss, "actor_loss", None)
        if self.compile:
            self._terms_fn = torch.compile(self._loss_terms_eager, options=COMPILE_OPTIONS)
            if self._actor_fn is not None:
                self._actor_fn = torch.compile(self._actor_fn, options=COMPILE_OPTIONS)
        if self.cudagraphs:
            self._check_cuda()
            if not hasattr(loss, "loss_terms"):
                raise TypeError(
                    f"`cudagraphs=True` needs a loss with `loss_terms`, got {type(loss).__name__}."
                )
            for optimizer in self.optimizers.values():
                for group in optimizer.param_groups:
                    group["capturable"] = True  # Adam's step counts stay on the GPU

    def _check_cuda(self) -> None:
        devices = {p.device.type for p in self.loss.parameters()}
        if devices != {"cuda"}:
            raise ValueError(
                f"`cudagraphs=True` needs the loss on a CUDA device, its parameters are on {devices}."
            )

    def step(self) -> TensorDictBase:
        """One update; returns the loss's output (detached) as a TensorDict of scalars."""
        out = self._step()
        if self.cudagraphs:
            self._check_finite([out], first_update=self.num_updates)
        return out

    def _sample(self) -> TensorDictBase:
        if self.capture_sampling and not self.cudagraphs:  # the capture-safe sampler, outside any graph
            if self.sampling_captured is None:
                self._setup_sampling()
            return self._captured_sample()
        return self.replay_buffer.sample()

    def actor_update_due(self) -> bool:
        """Whether the next update (number ``num_updates + 1``) trains the actor (a host-side decision)."""
        return (self.num_updates + 1) % self.actor_update_interval == 0

    def _pattern(self, count: int) -> tuple[tuple[bool, bool], ...]:
        """(actor due, target update due) of the next ``count`` updates."""
        return tuple(
            (k % self.actor_update_interval == 0, k % self.target_update_interval == 0)
            for k in range(self.num_updates + 1, self.num_updates + count + 1)
        )

    def _loss_terms(self, sample: TensorDictBase, update_actor: bool) -> TensorDictBase:
        return self._terms_fn(sample, update_actor)

    def _loss_terms_eager(self, sample: TensorDictBase, update_actor: bool) -> TensorDictBase:
        if hasattr(self.loss, "loss_terms"):
            return self.loss.loss_terms(sample, update_actor=update_actor)
        return self.loss(sample)  # a loss without the switch computes its actor term anyway

    def _step(self) -> TensorDictBase:
        if self.cudagraphs:
            return self._graph_step()
        sample = self._sample()
        update_actor = self.actor_update_due()
        if self.actor_after_critic_step:
            out = self._sequential_update(sample, update_actor, check=True)
        else:
            with self._autocast():
                out = self._loss_terms(sample, update_actor)
            self._check_finite([out], first_update=self.num_updates + 1)  # before any parameter changes
            self._optimise(out, update_actor=update_actor)
        self._count_update()
        return out.detach()

    def _sequential_update(self, sample: TensorDictBase, update_actor: bool, check: bool) -> TensorDictBase:
        """Critic step, then (when due) the actor loss on the updated critic and the actor step.

        ``check``: raise :class:`NonFiniteLossError` before each optimiser step (eager path only; the captured
        path, ``check=False``, also runs autocast without its weight cache).
        """
        with self._autocast(cache_enabled=check):
            out = self._loss_terms(sample, False)
        if check:
            self._check_finite([out], first_update=self.num_updates + 1)
        self._optimise(out, update_actor=False)
        if update_actor:
            with self._autocast(cache_enabled=check):
                loss_actor = self._actor_fn(sample)[0]
            out.set("loss_actor", loss_actor)
            out.set("actor_updated", torch.ones_like(out.get("actor_updated")))
            if check:
                self._check_finite([out], first_update=self.num_updates + 1)
            self.optimizers["actor"].zero_grad(set_to_none=True)
            loss_actor.backward()
            self.optimizers["actor"].step()
        return out

    def _autocast(self, cache_enabled: bool = True):
        """``torch.autocast`` on the loss's device when ``autocast_dtype`` is set, else a no-op.

        ``cache_enabled=False`` inside a captured graph: autocast's cache of cast weights would be filled during
        the capture and replayed stale (PyTorch's CUDA-graph notes); the same values, the casts run every time."""
        if self.autocast_dtype is None:
            return contextlib.nullcontext()
        device = next(self.loss.parameters()).device
        return torch.autocast(device.type, dtype=self.autocast_dtype, cache_enabled=cache_enabled)

    def _optimise(self, out: TensorDictBase, update_actor: bool) -> None:
        """Back-propagates the sum of the ``loss_*`` entries and steps the optimisers."""
        total = torch.stack([value for key, value in out.items() if key.startswith("loss_")]).sum()
        for optimizer in self.optimizers.values():
            optimizer.zero_grad(set_to_none=True)
        total.backward()
        self.optimizers["critic"].step()
        if update_actor:
            self.optimizers["actor"].step()

    def _count_update(self) -> None:
        self.num_updates += 1
        if self.num_updates % self.target_update_interval == 0:
            self.target_updater.step()

    def _graph_update(self, update_actor: bool):
        """The captured part of a step: [sampling,] loss terms, backward, Adam steps (no host synchronisation)."""

        def update(sample: TensorDictBase) -> TensorDictBase:
            if self._captured_sample is not None:  # the input is empty: the graph samples itself
                sample = self._captured_sample()
            return self._captured_update(sample, update_actor)

        return update

    def _captured_update(self, sample: TensorDictBase, update_actor: bool) -> TensorDictBase:
        if self.actor_after_critic_step:
            return self._sequential_update(sample, update_actor, check=False).detach()
        with self._autocast(cache_enabled=False):
            out = self._loss_terms(sample, update_actor)
        self._optimise(out, update_actor)
        return out.detach()

    def _graph_chunk(self, pattern: tuple[tuple[bool, bool], ...]):
        """The captured part of ``len(pattern)`` consecutive updates that sample themselves, Polyak included."""

        def updates(_: TensorDictBase) -> TensorDictBase:
            outs = []
            for update_actor, update_target in pattern:
                outs.append(self._captured_update(self._captured_sample(), update_actor))
                if update_target:
                    self.target_updater.step()
            return torch.stack(outs)

        return updates

    def _chunk_step(self) -> list[TensorDictBase]:
        """``updates_per_graph`` updates in one replay (the graphs sample themselves)."""
        pattern = self._pattern(self.updates_per_graph)
        if pattern not in self._chunk_graphs:
            self._chunk_graphs[pattern] = CudaGraphModule(
                self._graph_chunk(pattern), warmup=3, in_keys=[], out_keys=[]
            )
        out = self._chunk_graphs[pattern](TensorDict()).clone()  # its buffers are reused by the next replay
        self.num_updates += len(pattern)
        return list(out.unbind(0))

    def _setup_sampling(self) -> None:
        """Decides (once, again after a restore) whether the capture-safe sampler is used, and builds it."""
        self._captured_sample = None
        self.sampling_captured = False
        self.sampling_note = "the buffer has no capture-safe sampler"
        if self.capture_sampling is False:
            self.sampling_note = "capture_sampling=False"
            return
        make = getattr(self.replay_buffer, "capturable_sampler", None)
        if make is None:
            if self.capture_sampling:
                raise RuntimeError(
                    f"capture_sampling=True: {type(self.replay_buffer).__name__} has no capturable_sampler()."
                )
            return
        try:
            self._captured_sample = make()
        except RuntimeError as err:
            if self.capture_sampling:
                raise
            self.sampling_note = str(err)
            return
        self.sampling_captured = True
        self.sampling_note = (
            "sampling and relabelling captured" if self.cudagraphs else "capture-safe sampler"
        )
        if self.compile:
            self._captured_sample = torch.compile(
                self._captured_sample, fullgraph=True, options=COMPILE_OPTIONS
            )
            self.sampling_note += ", compiled"

    def _graph_step(self) -> TensorDictBase:
        if self.sampling_captured is None:
            self._setup_sampling()
        due = self.actor_update_due()  # decided on the host: the graphs cannot branch
        if due not in self._graphs:
            self._graphs[due] = CudaGraphModule(self._graph_update(due), warmup=3, in_keys=[], out_keys=[])
        sample = TensorDict() if self.sampling_captured else self._sample()
        out = self._graphs[due](sample).clone()  # the graph's output buffers are reused by the next replay
        self._count_update()
        return out

    def _check_finite(self, outputs: list[TensorDictBase], first_update: int) -> None:
        """Raises :class:`NonFiniteLossError` if a ``loss_*`` entry of ``outputs`` is not finite (one sync)."""
        losses = torch.stack([v for out in outputs for k, v in out.items() if k.startswith("loss_")])
        if not bool(torch.isfinite(losses).all()):
            last = first_update + len(outputs) - 1
            updates = f"update {first_update}" if last == first_update else f"updates {first_update}-{last}"
            raise NonFiniteLossError(
                f"{type(self.loss).__name__} produced a non-finite loss in {updates}: "
                + ", ".join(f"{k}={v.item():.4g}" for k, v in outputs[-1].items() if k.startswith("loss_"))
            )

    def run(self, num_updates: int) -> TensorDictBase | None:
        """Runs ``num_updates`` steps; returns the mean of each output entry (``None`` when 0)."""
        if num_updates <= 0:
            return None
        if not self.cudagraphs:
            outputs = [self.step() for _ in range(num_updates)]
        else:  # checked once for the whole call: no host synchronisation between replays
            first, outputs = self.num_updates + 1, []
            if self.updates_per_graph > 1 and self.sampling_captured is None:
                self._setup_sampling()
            if self.updates_per_graph > 1 and self.sampling_captured:
                for _ in range(num_updates // self.updates_per_graph):
                    outputs += self._chunk_step()
            outputs += [self._step() for _ in range(num_updates - len(outputs))]
            self._check_finite(outputs, first_update=first)
        stacked = torch.stack([o.select(*(k for k, v in o.items() if v.numel() == 1)) for o in outputs])
        return TensorDict({key: value.float().mean() for key, value in stacked.items()}, batch_size=[])

    def state_dict(self) -> dict:
        return {
            "num_updates": self.num_updates,
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
        }

    def load_state_dict(self, state_dict: dict) -> None:
        self.num_updates = int(state_dict["num_updates"])
        for key, optimizer in self.optimizers.items():
            optimizer.load_state_dict(state_dict["optimizers"][key])
            if self.cudagraphs:  # the saved groups may come from an eager run
                for group in optimizer.param_groups:
                    group["capturable"] = True
                    for param in group["params"]:
                        state = optimizer.state.get(param, {})
                        if "step" in state:
                            state["step"] = state["step"].to(param.device, torch.float32)
        self._graphs = {}  # captured graphs point at the replaced optimiser state: capture again
        self._chunk_graphs = {}
        self.sampling_captured = None  # and the sampler at storage that a restore may have reallocated
