"""GNS's network: encoder, processor of interaction-network blocks, decoder (Sanchez-Gonzalez et al. 2020).

Per particle graph (nodes: the fluid and the boundary particles within reach of it; edges: every ordered
pair closer than the connectivity radius ``R``; :mod:`baselines.gns.graph`)::

    encode     v = phi_v(node features)      e = phi_e(edge features)           latent L each
    process    M blocks, unshared weights (Battaglia et al. 2018, paper A.5 eqs. 33-35):
                 e'_k = phi_e([e_k, v_receiver, v_sender]);  v'_i = phi_v([v_i, sum_{k -> i} e'_k])
                 v <- v + v',  e <- e + e'      (residuals on nodes *and* edges)
    decode     a = phi_d(v)                                   standardised acceleration, (N, 3)

Every MLP has ``mlp_layers`` hidden layers of ``hidden`` units with ReLU and a LayerNorm on its output,
except the decoder's. The statistics that standardise the inputs and the output live in buffers (their
:class:`~lagfluid.zoo.Standardizer`), so a checkpoint's ``state_dict`` carries them.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn
from torch.nn import functional as F
from torch_geometric.nn import MessagePassing

from lagfluid.zoo import ConfigError, Standardizer

__all__ = ["GNSNet", "InteractionNetwork", "mlp", "node_feature_count"]

EDGE_FEATURES = 4
"""Edge inputs: ``(x_sender - x_receiver) / R`` (3) and its norm (1)."""
BOUNDS_FEATURES = 6
"""Distances to the lower and upper domain bounds per axis, over ``R``, clipped to [-1, 1]."""
PARTICLE_TYPES = 2
"""Node classes: 0 fluid, 1 boundary (paper A.5: "simple zero and one")."""


def node_feature_count(history: int, type_embedding: int) -> int:
    """Width of a node's input: ``3 history`` velocities, the bounds features and the particle type.

    ``type_embedding`` 0 is the paper's one 0/1 channel; ``k > 0`` a learned embedding of ``k`` channels.
    """
    return 3 * history + BOUNDS_FEATURES + (type_embedding if type_embedding > 0 else 1)


def mlp(sizes: Sequence[int], *, layer_norm: bool) -> nn.Sequential:
    """``sizes[0] -> ... -> sizes[-1]`` with ReLU between linear layers and optionally a LayerNorm last."""
    layers: list[nn.Module] = []
    for k in range(1, len(sizes)):
        layers.append(nn.Linear(sizes[k - 1], sizes[k]))
        if k != len(sizes) - 1:
            # in place on the linear layer's fresh output: one (E, hidden) array less
            layers.append(nn.ReLU(inplace=True))
    if layer_norm:
        layers.append(nn.LayerNorm(sizes[-1]))
    return nn.Sequential(*layers)


class InteractionNetwork(MessagePassing):
    r"""One GN block without globals: an edge update, a sum over incoming edges, a node update.

    .. math::
        e'_k = \phi^e([e_k, v_{r_k}, v_{s_k}]), \qquad
        v'_i = \phi^v([v_i, \textstyle\sum_{k: r_k = i} e'_k])

    and the block returns ``(v + v', e + e')`` (residual on both). The first linear layer of
    :math:`\phi^e` is applied by parts, ``W [e, v_r, v_s] = W_e e + (W_r v)_r + (W_s v)_s``: the node
    projections are computed once per node instead of once per edge (same parameters, same function).

    Args:
        latent: width L of node and edge latents.
        hidden: width of the MLPs' hidden layers.
        mlp_layers: hidden layers per MLP.

    Shapes:
        x (N, L), edge_index (2, E) (row 0 sender j, row 1 receiver i), e (E, L) -> (N, L), (E, L).
    """

    def __init__(self, latent: int, hidden: int, mlp_layers: int) -> None:
        super().__init__(aggr="sum", flow="source_to_target")
        self.latent = latent
        self.edge_mlp = mlp([3 * latent, *[hidden] * mlp_layers, latent], layer_norm=True)
        self.node_mlp = mlp([2 * latent, *[hidden] * mlp_layers, latent], layer_norm=True)

    def reset_parameters(self) -> None:
        """Re-initialise both MLPs."""
        for module in (*self.edge_mlp, *self.node_mlp):
            if hasattr(module, "reset_parameters"):
                module.reset_parameters()

    def forward(self, x: Tensor, edge_index: Tensor, e: Tensor) -> tuple[Tensor, Tensor]:
        """Updated ``(x, e)``, (N, L) and (E, L)."""
        e_new = self.edge_updater(edge_index, x=x, e=e)
        aggregated = self.propagate(edge_index, e_new=e_new, size=(x.shape[0], x.shape[0]))
        x_new = self.node_mlp(torch.cat([x, aggregated], dim=1))
        return x + x_new, e_new.add_(e)  # in place: the LayerNorm's output is not saved for backward

    def edge_update(self, e: Tensor, edge_index: Tensor, x: Tensor) -> Tensor:  # type: ignore[override]
        """``phi_e([e, x_receiver, x_sender])`` with the first layer applied by parts, (E, L)."""
        first, L = self.edge_mlp[0], self.latent
        w = first.weight  # (hidden, 3L): columns for e, receiver, sender
        receiver = F.linear(x, w[:, L : 2 * L]).index_select(0, edge_index[1])
        sender = F.linear(x, w[:, 2 * L :]).index_select(0, edge_index[0])
        # summed in place into the linear layer's output (autograd does not need it): each (E, hidden) array
        # is fresh memory, ~250 MB at 40k particles (benchmarks/results/fgn_step_speed.md)
        return self.edge_mlp[1:](F.linear(e, w[:, :L], first.bias).add_(receiver).add_(sender))

    def message(self, e_new: Tensor) -> Tensor:  # type: ignore[override]
        """The updated edge latent is the message, (E, L)."""
        return e_new


class GNSNet(nn.Module):
    """Encoder, ``blocks`` :class:`InteractionNetwork` blocks, decoder; statistics in buffers.

    Args:
        latent: latent width L (paper size 128).
        hidden: hidden width of every MLP (128).
        mlp_layers: hidden layers per MLP (2).
        blocks: message-passing blocks, unshared (10).
        history: previous velocities per node (5).
        radius: connectivity radius in units of ``l0`` (2.1).
        type_embedding: 0 for the paper's 0/1 type channel, ``k`` for a learned embedding of ``k`` channels.

    Buffers: ``velocity`` and ``acceleration`` :class:`Standardizer` (3,) in m/s and m/s^2 (std combined
    with the training noise's), ``frame_dt`` (s, the spacing of the training frames: the model's time step)
    and ``solver_dt`` (s, the MPS step of the training data: the warm start's step); ``trained_batches``.
    """

    def __init__(
        self,
        latent: int = 128,
        hidden: int = 128,
        mlp_layers: int = 2,
        blocks: int = 10,
        history: int = 5,
        radius: float = 2.1,
        type_embedding: int = 0,
    ) -> None:
        super().__init__()
        for name, value in (("latent", latent), ("hidden", hidden), ("blocks", blocks), ("history", history)):
            if not (isinstance(value, int) and value >= 1):
                raise ConfigError(f"model.gns.{name} must be an integer >= 1, got {value!r}")
        if not (isinstance(mlp_layers, int) and mlp_layers >= 0):
            raise ConfigError(f"model.gns.mlp_layers must be an integer >= 0, got {mlp_layers!r}")
        if not (isinstance(type_embedding, int) and type_embedding >= 0):
            raise ConfigError(f"model.gns.type_embedding must be an integer >= 0, got {type_embedding!r}")
        if not float(radius) > 0:
            raise ConfigError(f"model.gns.radius must be > 0 (in l0), got {radius!r}")
        self.history, self.radius = history, float(radius)
        self.type_embedding = nn.Embedding(PARTICLE_TYPES, type_embedding) if type_embedding > 0 else None
        hidden_sizes = [hidden] * mlp_layers
        self.node_encoder = mlp(
            [node_feature_count(history, type_embedding), *hidden_sizes, latent], layer_norm=True
        )
        self.edge_encoder = mlp([EDGE_FEATURES, *hidden_sizes, latent], layer_norm=True)
        self.processor = nn.ModuleList(InteractionNetwork(latent, hidden, mlp_layers) for _ in range(blocks))
        self.decoder = mlp([latent, *hidden_sizes, 3], layer_norm=False)
        self.velocity = Standardizer(3)
        self.acceleration = Standardizer(3)
        self.register_buffer("frame_dt", torch.zeros((), dtype=torch.float64))
        self.register_buffer("solver_dt", torch.zeros((), dtype=torch.float64))
        # training batches seen (resumes with the weights: the pushforward schedule counts them)
        self.register_buffer("trained_batches", torch.zeros((), dtype=torch.long))

    def type_features(self, boundary: Tensor) -> Tensor:
        """(N, 1) 0/1 channel, or (N, k) learned embedding, of the boolean ``boundary`` (N,)."""
        if self.type_embedding is None:
            return boundary.to(self.velocity.mean.dtype).unsqueeze(1)
        return self.type_embedding(boundary.long())

    def forward(self, nodes: Tensor, edge_index: Tensor, edges: Tensor) -> Tensor:
        """Standardised accelerations (N, 3) of node inputs (N, F), edges (2, E) and edge inputs (E, 4)."""
        x, e = self.node_encoder(nodes), self.edge_encoder(edges)
        for block in self.processor:
            x, e = block(x, edge_index, e)
        return self.decoder(x)
