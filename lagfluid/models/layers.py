"""Model-neutral network pieces: activations by name, the shared MLP, the standardiser, a parameter count.

Any model of the zoo may build on them (FGN's networks do; a plugin takes them from :mod:`lagfluid.zoo`).
:class:`Standardizer` holds its statistics as buffers, so a network that standardises its inputs and
targets with it carries them in its ``state_dict`` and every checkpoint (``<name>.mean``, ``<name>.std``);
:func:`make_mlp` keeps the authors' ``build_shared_mlp`` layout, so its parameter names (``0.weight``,
``2.weight``, ...) match their weights.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from lagfluid.errors import ConfigError

__all__ = ["ACTIVATIONS", "Standardizer", "activation", "make_mlp", "parameter_count"]

ACTIVATIONS: dict[str, type[nn.Module]] = {
    "identity": nn.Identity,
    "relu": nn.ReLU,
    "silu": nn.SiLU,
    "gelu": nn.GELU,
    "tanh": nn.Tanh,
}


def activation(name: str) -> nn.Module:
    """The activation module called ``name`` (see :data:`ACTIVATIONS`)."""
    if name not in ACTIVATIONS:
        raise ConfigError(f"unknown activation '{name}'; available: {', '.join(ACTIVATIONS)}")
    return ACTIVATIONS[name]()


def make_mlp(
    sizes: Sequence[int], act: str, *, act_first: bool = False, layer_norm: bool = False
) -> nn.Sequential:
    """A shared MLP ``sizes[0] -> ... -> sizes[-1]``, laid out as the authors' ``build_shared_mlp``.

    ``act_first``: an activation before every linear layer (and none after the last); otherwise one between
    linear layers. ``layer_norm``: LayerNorm after every linear layer, whose bias is then dropped. Keeping
    their layout keeps the parameter names (``0.weight``, ``2.weight``, ...) loadable.
    """
    if len(sizes) < 2:
        raise ConfigError(f"an MLP needs at least an input and an output size, got {list(sizes)}")
    layers: list[nn.Module] = []
    for k in range(1, len(sizes)):
        if act_first:
            layers.append(activation(act))
        layers.append(nn.Linear(sizes[k - 1], sizes[k], bias=not layer_norm))
        if layer_norm:
            layers.append(nn.LayerNorm(sizes[k]))
        if not act_first and k != len(sizes) - 1:
            layers.append(activation(act))
    return nn.Sequential(*layers)


class Standardizer(nn.Module):
    """``(x - mean) / std`` with statistics as buffers (saved in every ``state_dict``).

    Args:
        size: number of channels F; statistics have shape (F,).
    """

    def __init__(self, size: int) -> None:
        super().__init__()
        self.register_buffer("mean", torch.zeros(size))
        self.register_buffer("std", torch.ones(size))

    def set(self, mean: Sequence[float] | Tensor, std: Sequence[float] | Tensor) -> None:
        """Set the statistics; a std below 1e-12 (a constant channel) is replaced by 1."""
        mean = torch.as_tensor(mean, dtype=self.mean.dtype).reshape(self.mean.shape)
        std = torch.as_tensor(std, dtype=self.std.dtype).reshape(self.std.shape)
        if not (torch.isfinite(mean).all() and torch.isfinite(std).all()):
            raise ValueError(f"statistics must be finite, got mean={mean.tolist()}, std={std.tolist()}")
        self.mean.copy_(mean)
        self.std.copy_(torch.where(std > 1e-12, std, torch.ones_like(std)))

    def forward(self, x: Tensor) -> Tensor:
        """(..., F) raw -> standardised."""
        return (x - self.mean) / self.std

    def inverse(self, y: Tensor) -> Tensor:
        """(..., F) standardised -> raw."""
        return y * self.std + self.mean


def parameter_count(module: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
