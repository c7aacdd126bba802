"""Stacked ensembles: ``EnsembleLinear`` and ``EnsembleMLP`` against per-member layers."""

import torch

from torchrl_dhrl.modules import EnsembleLinear, EnsembleMLP


def test_ensemble_linear_matches_per_member_linear():
    torch.manual_seed(5)
    layer = EnsembleLinear(6, 4, ensemble_size=3)
    x = torch.randn(10, 6)
    out = layer(x)
    for k in range(3):
        torch.testing.assert_close(out[k], x @ layer.weight[k] + layer.bias[k, 0])
    xs = torch.randn(3, 10, 6)
    out = layer(xs)
    for k in range(3):
        torch.testing.assert_close(out[k], xs[k] @ layer.weight[k] + layer.bias[k, 0])


def test_ensemble_mlp_members_are_independent_mlps():
    torch.manual_seed(6)
    mlp = EnsembleMLP(5, 1, ensemble_size=2, num_cells=(8, 8))
    x = torch.randn(4, 3, 5)
    out = mlp(x)
    assert out.shape == (2, 4, 3, 1)
    for k in range(2):
        h = x
        for i, layer in enumerate(mlp.layers):
            h = h @ layer.weight[k] + layer.bias[k, 0]
            if i < len(mlp.layers) - 1:
                h = torch.relu(h)
        torch.testing.assert_close(out[k], h)
    # Members differ (independent initialisation).
    assert not torch.allclose(out[0], out[1])
