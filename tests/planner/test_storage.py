"""The landmark graph's planning storage, a strategy object: the graph's own buffers (DynamicStorage) or fixed-size
capture-safe copies (FixedSizeStorage), swapped with ``fixed_size`` and never part of the checkpoint."""

from __future__ import annotations

import pytest
import torch

from torchrl_dhrl.planner import DynamicStorage, FixedSizeStorage, LandmarkGraph


def _distance(states, goals):
    return (states[..., :2] - goals).norm(dim=-1) * 4.0


def _built(fixed_size: bool, seed: int = 0) -> LandmarkGraph:
    points = torch.rand(60, 3, generator=torch.Generator().manual_seed(seed)) * 10
    graph = LandmarkGraph(cutoff=12.0, max_landmarks=16, early_stop=0.0, fixed_size=fixed_size)
    return graph.build(points, points[:, :2], _distance)


def test_the_storage_follows_fixed_size_and_holds_the_graph_padded():
    graph = _built(False)
    assert isinstance(graph.storage, DynamicStorage) and graph.planning_tensors(capturable=True).valid is None
    graph.fixed_size = True  # a new fixed-size storage, filled from the graph at once
    assert isinstance(graph.storage, FixedSizeStorage)
    tensors, num = graph.planning_tensors(capturable=True), graph.num_landmarks
    assert tensors.states.shape[0] == 16 and tensors.valid.tolist() == [True] * num + [False] * (16 - num)
    torch.testing.assert_close(tensors.shortest[:num, :num], graph.shortest_distances)
    assert torch.isinf(tensors.distances[num:, :num]).all() and (tensors.next_hop[num:, :num] == -1).all()
    assert int(tensors.version) == int(graph.version)
    graph.fixed_size = False
    assert isinstance(graph.storage, DynamicStorage) and graph.planning_tensors(capturable=True).valid is None
    with pytest.raises(ValueError, match="fixed_size=False"):
        graph.reserve(3, 2)
    with pytest.raises(TypeError, match="`fixed_size` must be a bool"):
        graph.fixed_size = 1


def test_a_rebuild_writes_into_the_same_storage_and_the_checkpoint_does_not_hold_it():
    graph = _built(True)
    pointer = graph.planning_tensors(capturable=True).states.data_ptr()
    points = torch.rand(40, 3, generator=torch.Generator().manual_seed(1)) * 10
    graph.build(points, points[:, :2], _distance)
    assert graph.planning_tensors(capturable=True).states.data_ptr() == pointer
    state = graph.state_dict()
    assert not [key for key in state if key.startswith("storage")]
    # the same checkpoint loads into either storage and gives the same capture-safe plans as the own buffers
    for fixed in (False, True):
        other = LandmarkGraph(cutoff=12.0, max_landmarks=16, early_stop=0.0, fixed_size=fixed)
        other.load_state_dict(state)
        starts, subgoals = torch.rand(8, 3) * 10, torch.rand(8, 2) * 10
        captured = other.plan(starts, subgoals, _distance, 16, capturable=True)
        plain = graph.plan(starts, subgoals, _distance, 16)
        torch.testing.assert_close(captured.cost, plain.cost)
    graph.clear()
    assert not graph.planning_tensors(capturable=True).valid.any()
    assert graph.planning_tensors(capturable=True).states.data_ptr() == pointer
