"""Ensembles of MLPs with stacked weights, evaluated in one batched matmul per layer."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from ._utils import autocast_enabled


class EnsembleLinear(nn.Module):
    """A stack of ``ensemble_size`` independent linear layers evaluated with one batched matmul.

    The weight has shape ``[ensemble_size, in_features, out_features]`` and the bias
    ``[ensemble_size, 1, out_features]`` (ensemble dimension first, like the stacked
    parameters of :class:`~torchrl.objectives.TD3Loss`). Each member is initialised like
    :class:`torch.nn.Linear`. The number of members used in :meth:`forward` is read from
    the weight, so parameters of several ensembles can be concatenated along dim 0 and
    evaluated together (``TensorDict.to_module``).

    Args:
        in_features (int): input features.
        out_features (int): output features.
        ensemble_size (int): number of members.

    Keyword Args:
        device (torch.device, optional): where the parameters live.
        dtype (torch.dtype, optional): parameter dtype.

    Examples:
        >>> import torch
        >>> layer = EnsembleLinear(3, 4, ensemble_size=2)
        >>> layer(torch.randn(10, 3)).shape  # one input shared by both members
        torch.Size([2, 10, 4])
        >>> layer(torch.randn(2, 10, 3)).shape  # one input per member
        torch.Size([2, 10, 4])
    """

    def __init__(
        self,
        in_features: int,
        out_features: int,
        ensemble_size: int,
        *,
        device: torch.device | None = None,
        dtype: torch.dtype | None = None,
    ) -> None:
        super().__init__()
        if min(in_features, out_features, ensemble_size) < 1:
            raise ValueError(
                f"EnsembleLinear needs positive sizes, got in={in_features}, out={out_features}, "
                f"ensemble_size={ensemble_size}."
            )
        self.in_features = in_features
        self.out_features = out_features
        kwargs = {"device": device, "dtype": dtype}
        self.weight = nn.Parameter(torch.empty(ensemble_size, in_features, out_features, **kwargs))
        self.bias = nn.Parameter(torch.empty(ensemble_size, 1, out_features, **kwargs))
        self.reset_parameters()

    @property
    def ensemble_size(self) -> int:
        return self.weight.shape[0]

    def reset_parameters(self) -> None:
        # nn.Linear's default: kaiming_uniform(a=sqrt(5)) == U(-1/sqrt(fan_in), 1/sqrt(fan_in)), same for bias.
        bound = 1.0 / math.sqrt(self.in_features)
        with torch.no_grad():
            self.weight.uniform_(-bound, bound)
            self.bias.uniform_(-bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Maps ``[N, in]`` (shared by all members) or ``[E, N, in]`` (one per member) to ``[E, N, out]``."""
        weight, bias = self.weight, self.bias
        if x.ndim == 2:
            # A stride-0 view: no copy of the shared input.
            x = x.expand(weight.shape[0], *x.shape)
        if x.ndim == 3:
            return torch.baddbmm(bias, x, weight)
        raise ValueError(f"EnsembleLinear expects [N, in] or [E, N, in] inputs, got shape {tuple(x.shape)}.")

    def full_precision(self, x: torch.Tensor) -> torch.Tensor:
        """:meth:`forward` in the parameters' dtype, also inside ``torch.autocast``.

        For an output layer fed reduced-precision activations: the result is not rounded to the
        reduced dtype. A single output unit (a critic's) is an elementwise product summed, which on
        CPUs is several times faster than a batched matmul with one column.
        """
        x = x.to(self.weight.dtype)
        with torch.autocast(x.device.type, enabled=False):
            if self.weight.shape[-1] == 1 and x.ndim in (2, 3):  # [E, N, in] * [E, 1, in] -> [E, N, 1]
                product = (x if x.ndim == 3 else x.unsqueeze(0)) * self.weight.transpose(-1, -2)
                return product.sum(-1, keepdim=True) + self.bias
            return self(x)

    def extra_repr(self) -> str:
        return f"in_features={self.in_features}, out_features={self.out_features}, ensemble_size={self.ensemble_size}"


class EnsembleMLP(nn.Module):
    """An ensemble of identical MLPs with stacked weights (one batched matmul per layer).

    Inside ``torch.autocast`` the hidden layers run in the autocast dtype and the output
    layer in the parameters' dtype, so the outputs are not rounded to the reduced precision.

    Args:
        in_features (int): input features.
        out_features (int): output features per member.
        ensemble_size (int): number of members (2 for a TD3 twin critic).

    Keyword Args:
        num_cells (sequence of int): hidden widths. Defaults to ``(256, 256, 256)``.
        activation_class (type): hidden activation. Defaults to :class:`torch.nn.ReLU`.
        device (torch.device, optional): where the parameters live.

    Examples:
        >>> import torch
        >>> mlp = EnsembleMLP(5, 1, ensemble_size=2, num_cells=(32, 32))
        >>> mlp(torch.randn(4, 7, 5)).shape  # shared input with batch [4, 7]
        torch.Size([2, 4, 7, 1])
        >>> mlp(torch.randn(2, 4, 5), per_member=True).shape
        torch.Size([2, 4, 1])
    """

    def __init__(
        self,
        in_features: int,
        out_features: int,
        ensemble_size: int,
        *,
        num_cells: Sequence[int] = (256, 256, 256),
        activation_class: type[nn.Module] = nn.ReLU,
        device: torch.device | None = None,
    ) -> None:
        super().__init__()
        widths = [in_features, *num_cells, out_features]
        self.layers = nn.ModuleList(
            EnsembleLinear(w_in, w_out, ensemble_size, device=device)
            for w_in, w_out in zip(widths[:-1], widths[1:], strict=True)
        )
        self.activation = activation_class()
        self.in_features = in_features
        self.out_features = out_features

    @property
    def ensemble_size(self) -> int:
        return self.layers[0].ensemble_size

    def forward(self, x: torch.Tensor, per_member: bool = False) -> torch.Tensor:
        """Evaluates every member.

        Args:
            x (Tensor): ``[*batch, in]`` shared by all members, or ``[E, *batch, in]`` when
                ``per_member=True``.
            per_member (bool): whether the leading dim of ``x`` indexes the members.

        Returns:
            ``[E, *batch, out]``.
        """
        n_members = self.layers[0].weight.shape[0]
        if per_member:
            if x.ndim < 2 or x.shape[0] != n_members:
                raise ValueError(
                    f"per-member inputs need a leading dim of {n_members} members, got {tuple(x.shape)}."
                )
            lead = x.shape[1:-1]
            h = x.reshape(n_members, -1, x.shape[-1])
        else:
            lead = x.shape[:-1]
            h = x.reshape(-1, x.shape[-1])
        *hidden, last = self.layers
        for layer in hidden:
            h = self.activation(layer(h))
        # under autocast: hidden layers reduced, the output layer in the parameters' dtype
        h = last.full_precision(h) if autocast_enabled(h) else last(h)
        return h.reshape(n_members, *lead, self.out_features)
