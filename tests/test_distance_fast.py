"""GoalDistance speed options: reduced-precision autocast, the CPU chunk default, the actor fast path."""

import pytest
import torch
from tensordict import TensorDict

from torchrl_dhrl.modules import GoalConditionedCritic, LowLevelActor
from torchrl_dhrl.planner import GoalDistance
from torchrl_dhrl.planner.distances import DEFAULT_CPU_CHUNK_SIZE

OBS, GOAL, ACT = 9, 2, 4
#: Tolerances of the reduced-precision path against float32 on the network below: the error is about
#: absolute (bfloat16 rounding of the hidden activations, times the output weights), up to 0.28 steps
#: (measured, both twin members; p99 0.16-0.17), so relative to the distance it is small for the
#: pessimistic member (median 0.06%, max 0.7%) and larger for the optimistic one, whose distances reach
#: below 1 step here (median 0.12%, max 11% at a distance of 0.5). float16 is about 8x more accurate.
BF16_MEDIAN_REL, BF16_ABS, BF16_REL = 0.005, 0.3, 0.02


def trained_like(seed=0, width=64):
    """Actor and twin critic whose distances spread over ~[5, 120] steps, like a trained critic.

    Random weights of the default initialisation give distances of about 0.7 for every pair; the
    output layer is rescaled so that the distance depends strongly on the inputs.
    """
    torch.manual_seed(seed)
    actor = LowLevelActor(OBS, GOAL, action_max=2.0, action_dim=ACT, num_cells=(width, width))
    critic = GoalConditionedCritic(OBS, GOAL, action_max=2.0, action_dim=ACT, num_cells=(width, width))
    last = critic.module.ensemble.layers[-1]
    with torch.no_grad():
        last.weight.mul_(60.0)
        last.bias.fill_(40.0)
    return actor, critic


def pairs(num, seed=1):
    gen = torch.Generator().manual_seed(seed)
    return torch.randn(num, OBS, generator=gen) * 3, torch.randn(num, GOAL, generator=gen) * 3


def relative_error(value, reference):
    return (value - reference).abs() / reference.abs().clamp_min(1.0)


@pytest.mark.parametrize("twin", ["optimistic", "pessimistic"])
@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_autocast_is_close_to_float32_and_really_reduced(dtype, twin):
    actor, critic = trained_like()
    states, goals = pairs(4000)
    ref = GoalDistance(actor, critic, twin=twin)(states, goals)
    assert 5.0 < ref.median() < 120.0 and ref.std() > 5.0  # a spread of distances, as trained
    fast = GoalDistance(actor, critic, autocast_dtype=dtype, twin=twin)(states, goals)
    assert fast.dtype == torch.float32 and fast.shape == ref.shape
    assert relative_error(fast, ref).median() < BF16_MEDIAN_REL
    assert ((fast - ref).abs() <= BF16_ABS + BF16_REL * ref).all()
    assert (fast != ref).float().mean() > 0.5  # the networks really ran in reduced precision


def test_bfloat16_output_layer_is_not_rounded():
    # The raw output is the distance (distance parameterisation): were it computed by a bfloat16
    # matmul, (almost) every distance above 20 steps would sit on the bfloat16 grid.
    actor, critic = trained_like()
    states, goals = pairs(2000)
    fast = GoalDistance(actor, critic, autocast_dtype=torch.bfloat16)(states, goals)
    large = fast[fast > 20.0]
    assert large.numel() > 200
    on_grid = (large == large.bfloat16().float()).float().mean()
    assert on_grid < 0.2


def test_default_path_ignores_an_enclosing_autocast():
    actor, critic = trained_like()
    states, goals = pairs(500)
    distance = GoalDistance(actor, critic)
    ref = distance(states, goals)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        inside = distance(states, goals)
    assert torch.equal(inside, ref)


def test_with_autocast_copies_and_shares_the_networks():
    actor, critic = trained_like()
    distance = GoalDistance(actor, critic, max_distance=100.0)
    fast = distance.with_autocast(torch.bfloat16)
    assert fast is not distance and fast.autocast_dtype is torch.bfloat16 and distance.autocast_dtype is None
    assert fast.actor is actor and fast.critic is critic and fast.max_distance == 100.0
    assert fast.with_autocast(None).autocast_dtype is None
    states, goals = pairs(300)
    torch.testing.assert_close(fast(states, goals), distance(states, goals), rtol=BF16_REL, atol=BF16_ABS)
    # it follows training: an in-place update of the shared critic changes both
    with torch.no_grad():
        critic.module.ensemble.layers[-1].bias.add_(5.0)
    torch.testing.assert_close(fast(states, goals), distance(states, goals), rtol=BF16_REL, atol=BF16_ABS)


@pytest.mark.parametrize("bad", [torch.float32, torch.float64, torch.int8, "bfloat16"])
def test_autocast_dtype_is_validated(bad):
    actor, critic = trained_like()
    with pytest.raises(ValueError, match="autocast_dtype"):
        GoalDistance(actor, critic, autocast_dtype=bad)
    with pytest.raises(ValueError, match="autocast_dtype"):
        GoalDistance(actor, critic).with_autocast(bad)


@pytest.mark.parametrize("bad", [0, -3, 2.5, True])
def test_chunk_size_is_validated(bad):
    actor, critic = trained_like()
    with pytest.raises(ValueError, match="chunk_size"):
        GoalDistance(actor, critic, chunk_size=bad)


@pytest.mark.parametrize("dtype", [None, torch.bfloat16])
def test_results_do_not_depend_on_the_chunk_size(dtype):
    actor, critic = trained_like()
    states, goals = pairs(37)
    grid = GoalDistance(actor, critic, autocast_dtype=dtype)(states[:, None], goals[None])  # 1369 pairs
    for chunk in (64, 500, 100_000):
        chunked = GoalDistance(actor, critic, chunk_size=chunk, autocast_dtype=dtype)(
            states[:, None], goals[None]
        )
        # matmul kernels may differ in the last bits between batch sizes
        tol = 1e-5 if dtype is None else 2e-3
        torch.testing.assert_close(chunked, grid, rtol=tol, atol=tol * 10)


def test_default_chunk_on_cpu_and_explicit_chunk():
    actor, critic = trained_like(width=16)
    sizes = []
    handle = actor.module.register_forward_hook(lambda mod, args, out: sizes.append(args[0].shape[0]))
    states, goals = pairs(2 * DEFAULT_CPU_CHUNK_SIZE + 5)
    GoalDistance(actor, critic)(states, goals)
    assert sizes == [DEFAULT_CPU_CHUNK_SIZE, DEFAULT_CPU_CHUNK_SIZE, 5]
    sizes.clear()
    GoalDistance(actor, critic, chunk_size=65536)(states, goals)
    assert sizes == [states.shape[0]]
    handle.remove()


def test_actor_fast_path_equals_the_tensordict_path():
    actor, critic = trained_like()
    states, goals = pairs(700)
    fast = GoalDistance(actor, critic)(states, goals)
    # a hook on the TensorDictModule sends the call through the TensorDict path
    calls = []
    handle = actor.register_forward_pre_hook(lambda mod, args: calls.append(1))
    slow = GoalDistance(actor, critic)(states, goals)
    handle.remove()
    assert calls and torch.equal(fast, slow)


def test_autocast_with_swapped_parameters():
    actor, critic = trained_like(seed=0)
    other_actor, other_critic = trained_like(seed=3)
    states, goals = pairs(400)
    swapped = GoalDistance(
        actor,
        critic,
        actor_params=TensorDict.from_module(other_actor),
        critic_params=TensorDict.from_module(other_critic),
        autocast_dtype=torch.bfloat16,
    )
    expected = GoalDistance(other_actor, other_critic, autocast_dtype=torch.bfloat16)(states, goals)
    torch.testing.assert_close(swapped(states, goals), expected)
    assert not torch.allclose(expected, GoalDistance(actor, critic)(states, goals), rtol=0.05)


def test_autocast_keeps_float64_parameters_in_float64():
    actor, critic = trained_like()
    actor.double()
    critic.double()
    states, goals = pairs(200)
    ref = GoalDistance(actor, critic)(states, goals)
    out = GoalDistance(actor, critic, autocast_dtype=torch.bfloat16)(states, goals)
    assert out.dtype == torch.float64
    torch.testing.assert_close(out, ref)  # autocast leaves float64 alone


@pytest.mark.parametrize("num_cells", [(), (32,)])
def test_autocast_with_shallow_critics(num_cells):
    torch.manual_seed(0)
    actor = LowLevelActor(OBS, GOAL, action_max=2.0, action_dim=ACT, num_cells=(16,))
    critic = GoalConditionedCritic(OBS, GOAL, action_max=2.0, action_dim=ACT, num_cells=num_cells)
    states, goals = pairs(300)
    ref = GoalDistance(actor, critic)(states, goals)
    fast = GoalDistance(actor, critic, autocast_dtype=torch.bfloat16)(states, goals)
    torch.testing.assert_close(fast, ref, rtol=0.02, atol=0.02)
