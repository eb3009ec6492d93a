"""FGN's three networks (paper section 3, A.1) as PyTorch Geometric modules.

* :class:`AdvectionNet` and :class:`PressureNet` are *node-focused*: an encoder MLP, ``L`` message-passing
  layers :class:`KernelConv` and a decoder MLP. Each layer aggregates the neighbours' embeddings weighted
  by the MPS kernel ``w_ij = re / r_ij - 1`` (eq. 19) as one sparse product with the CSR kernel adjacency
  (:func:`lagfluid.neighbors.kernel_adjacency`), then updates every node with an MLP and a residual.
* :class:`CollisionNet` is *edge-focused* (eqs. 21-22): an MLP encodes each edge's relative velocity and
  direction, one message layer mixes in the summed edges at the source, a decoder MLP maps each edge to a
  velocity change, summed over the edges into each particle.

Inputs are relative or per-particle quantities only (velocity, its direction and magnitude, number
density, particle type, the scene's gravity and viscosity), never absolute positions, so the networks are
translation invariant; they are permutation invariant and batch block-diagonally because every neighbour
sum is a sparse product over a radius graph. Inputs and targets are standardised with statistics held as
buffers (:class:`Standardizer`), so a checkpoint's ``state_dict`` carries them.

The layout mirrors the authors' released code so that their weights load by name (see
:mod:`lagfluid.models.fgn.original`); what differs is configuration:

============================ ============================ =====================================
choice                        authors' release             ``conf/model/fgn.yaml`` (ours)
============================ ============================ =====================================
activation                    identity (``LeakyReLU(True)``) SiLU
advection inputs              vel_dir, speed, is_fluid     + vel, gravity, viscosity (paper eq. 11)
aggregation                   kernel-weighted sum          kernel-weighted sum (eq. 19's mean: config)
============================ ============================ =====================================

The paper's Table 5 ablations swap the node-focused nets' two :class:`KernelConv` layers, nothing else, for
PyG's ``GCNConv`` (``aggregation: gcn``), ``SAGEConv`` with mean aggregation (``sage``) or no aggregation at
all (``none``, a per-node MLP layer): ``model=fgn_gcn``, ``fgn_sage``, ``fgn_mlp`` (:func:`node_layer`).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor, nn
from torch_geometric.nn import GCNConv, MessagePassing, SAGEConv
from torch_geometric.utils import scatter

from lagfluid.errors import ConfigError
from lagfluid.models.checkpoint import CheckpointError, read_checkpoint
from lagfluid.models.layers import Standardizer, activation, make_mlp, parameter_count

__all__ = [
    "ADVECTION_FEATURES",
    "KINDS",
    "PRESSURE_FEATURES",
    "AdvectionNet",
    "CollisionNet",
    "KernelConv",
    "NodeNet",
    "PressureNet",
    "Standardizer",
    "build_network",
    "load_network",
    "make_mlp",
    "node_layer",
    "owned_stages",
    "parameter_count",
]

KINDS = ("advection", "collision", "pressure")
"""FGN's networks, one per learned stage (each a trainable of ``model=fgn``)."""
_NODE_NET_KEYS = ("width", "layers", "act", "aggregation", "encoder_hidden", "decoder_hidden")
KERNEL_AGGREGATIONS = ("sum", "mean")
"""FGN's own aggregations (:class:`KernelConv`): the MPS kernel weights the neighbours."""
ABLATION_AGGREGATIONS = ("gcn", "sage", "none")
"""The paper's Table 5 replacements (:class:`GraphConvLayer`, :class:`PointwiseLayer`)."""

# Per-node input features a node-focused net can take, with their widths.
ADVECTION_FEATURES: dict[str, int] = {
    "vel_dir": 3,  # v / |v|
    "speed": 1,  # standardised |v|
    "vel": 3,  # v / std(|v|): the velocity itself, which the viscous term is linear in
    "is_fluid": 1,  # 1 for fluid, 0 for boundary particles
    "gravity": 3,  # g / gravity_scale (the scene's body force, paper eq. 11)
    "viscosity": 1,  # standardised log10(nu)
}
PRESSURE_FEATURES: dict[str, int] = {
    "vel_dir": 3,
    "speed": 1,
    "vel": 3,
    "density": 1,  # standardised n / n0
    "is_fluid": 1,
}
_EPS_SPEED = 1e-8  # the authors add it to |v| before dividing: walls (v = 0) get vel_dir = 0


def owned_stages(model_cfg: Any) -> tuple[str, ...]:
    """The stages whose networks ``model_cfg`` trains and loads from ``model.weights`` (``model.trains``).

    The others (an ablation's collision net) are another model's, always loaded from the shipped weights.
    """
    trains = model_cfg.get("trains")
    owned = tuple(KINDS) if trains is None else tuple(str(k) for k in trains)
    unknown = [k for k in owned if k not in KINDS]
    if unknown or not owned:
        raise ConfigError(f"model.trains {list(owned)}: unknown {unknown}; available: {', '.join(KINDS)}")
    return tuple(k for k in KINDS if k in owned)


class KernelConv(MessagePassing):
    r"""One node-focused message-passing layer (paper eqs. 19-20, the authors' ``SmoothGCN``).

    .. math::
        m_i = \sum_j w_{ij} f_j \quad(\text{``sum''}) \qquad\text{or}\qquad
        m_i = \frac{\sum_j w_{ij} f_j}{\sum_j w_{ij}} \quad(\text{``mean'', eq. 19}),
        \qquad f_i' = \mathrm{MLP}(W_n f_i + W_m m_i)

    where ``w_ij`` is the MPS kernel of the pair's distance. The self term of eq. 19 enters through
    ``W_n f_i``. The sum is ``A @ f`` with the (N, N) CSR kernel adjacency ``A`` (rows = targets), computed
    in :meth:`message_and_aggregate` as one sparse product.

    Args:
        width: embedding size F (input and output).
        act: activation inside the update MLP.
        aggregation: ``"sum"`` (authors) or ``"mean"`` (paper eq. 19).

    Shapes: ``x`` (N, F), ``adj`` (N, N) sparse CSR -> (N, F).
    """

    def __init__(self, width: int, act: str, aggregation: str = "sum") -> None:
        super().__init__(aggr="add", flow="source_to_target")
        if aggregation not in KERNEL_AGGREGATIONS:
            raise ConfigError(f"KernelConv aggregation must be 'sum' or 'mean', got {aggregation!r}")
        if width % 2:
            raise ConfigError(f"width must be even (the update works at width/2), got {width}")
        self.aggregation = aggregation
        self.mlp = make_mlp([width // 2, width], act, act_first=True)
        self.node_linear = nn.Linear(width, width // 2)
        self.edge_linear = nn.Linear(width, width // 2)

    def reset_parameters(self) -> None:
        """Re-initialise the linear layers."""
        for module in self.modules():
            if isinstance(module, nn.Linear):
                module.reset_parameters()

    def forward(self, x: Tensor, adj: Tensor, weight_sum: Tensor | None = None) -> Tensor:
        """Update (N, F) node embeddings over the (N, N) kernel adjacency ``adj``.

        ``weight_sum`` (N, 1): ``sum_j w_ij`` per node, needed for ``aggregation="mean"``.
        """
        # W_e (A x) = A (x W_e^T): both linear maps as one (N, F) x (F, F) product, then the sparse product
        # at width F/2 instead of F (half its cost; the profile in benchmarks/results/fgn_speed.md).
        half = self.node_linear.out_features
        both = nn.functional.linear(x, torch.cat([self.node_linear.weight, self.edge_linear.weight]))
        msg = self.propagate(adj, x=both[:, half:].contiguous())
        if self.aggregation == "mean":
            msg = msg / weight_sum.clamp_min(1e-12)
        return self.mlp(both[:, :half] + msg + (self.node_linear.bias + self.edge_linear.bias))

    def message_and_aggregate(self, adj_t: Tensor, x: Tensor) -> Tensor:
        """``sum_j w_ij x_j`` as a CSR sparse-dense product (rows of ``adj_t`` are targets)."""
        return adj_t @ x


class GraphConvLayer(nn.Module):
    r"""An ablation layer (paper Table 5): PyG's ``GCNConv`` or ``SAGEConv`` (mean), then the activation.

    .. math::
        \text{gcn:}\quad f_i' = \sigma\Big(\sum_{j \in N(i) \cup \{i\}} \frac{W f_j}{\sqrt{d_i d_j}} + b\Big)
        \qquad
        \text{sage:}\quad f_i' = \sigma\Big(W_1 f_i + W_2 \frac{1}{|N(i)|}\sum_{j \in N(i)} f_j\Big)

    with ``d_i = |N(i)| + 1``: the neighbours count equally, by degree (Kipf and Welling 2016; Hamilton et al.
    2017), where :class:`KernelConv` weights them by the MPS kernel of their distance, the contrast the
    paper draws (A.1). The radius graph has no self-loops (the kernel is infinite at r = 0); GCN adds its own.
    The graph changes every step, so nothing is cached.

    Args:
        width: embedding size F (input and output).
        act: activation after the convolution.
        aggregation: ``"gcn"`` or ``"sage"``.

    Shapes: ``x`` (N, F), ``structure`` (N, N) sparse CSR with unit values -> (N, F).
    """

    def __init__(self, width: int, act: str, aggregation: str) -> None:
        super().__init__()
        if aggregation == "gcn":
            self.conv: MessagePassing = GCNConv(width, width, cached=False, add_self_loops=True)
        elif aggregation == "sage":
            self.conv = SAGEConv(width, width, aggr="mean")
        else:
            raise ConfigError(f"GraphConvLayer aggregation must be 'gcn' or 'sage', got {aggregation!r}")
        self.act = activation(act)

    def forward(self, x: Tensor, structure: Tensor) -> Tensor:
        """Update (N, F) node embeddings over the unweighted adjacency ``structure`` (rows = targets)."""
        return self.act(self.conv(x, structure))


class PointwiseLayer(nn.Module):
    """The ``none`` ablation (paper Table 5's MLP): ``f_i' = act(W f_i + b)``, no neighbour enters.

    Shapes: ``x`` (N, F) -> (N, F).
    """

    def __init__(self, width: int, act: str) -> None:
        super().__init__()
        self.linear = nn.Linear(width, width)
        self.act = activation(act)

    def forward(self, x: Tensor) -> Tensor:
        """Update every node from itself alone."""
        return self.act(self.linear(x))


def node_layer(width: int, act: str, aggregation: str) -> nn.Module:
    """One message-passing layer of a node-focused net: FGN's kernel or a Table 5 ablation."""
    if aggregation in KERNEL_AGGREGATIONS:
        return KernelConv(width, act, aggregation)
    if aggregation in ("gcn", "sage"):
        return GraphConvLayer(width, act, aggregation)
    if aggregation == "none":
        return PointwiseLayer(width, act)
    raise ConfigError(
        f"unknown aggregation {aggregation!r}; available: "
        f"{', '.join(KERNEL_AGGREGATIONS + ABLATION_AGGREGATIONS)}"
    )


def unit_adjacency(adj: Tensor) -> Tensor:
    """(N, N) CSR ``adj`` with every stored value set to 1: who neighbours whom, not how much."""
    crow, col, ones = adj.crow_indices(), adj.col_indices(), torch.ones_like(adj.values())
    return torch.sparse_csr_tensor(crow, col, ones, adj.shape, check_invariants=False)  # adj's valid indices


class NodeNet(nn.Module):
    """Encoder MLP -> ``layers`` x [``h = LN(h); h = layer(h) + h``] -> decoder MLP.

    ``layer`` is :class:`KernelConv` (FGN) or an ablation (:func:`node_layer`); encoder, decoder, norms and
    residuals are the same for all.

    Args:
        in_features, out_features: input and output channels.
        width: embedding size (authors: 64).
        encoder_hidden, decoder_hidden: hidden sizes of the encoder and decoder MLPs (authors: 8x the input
            and output sizes).
        layers: message-passing layers (authors: 2).
        act: activation name.
        aggregation: ``"sum"`` or ``"mean"`` (:class:`KernelConv`), or an ablation: ``"gcn"``, ``"sage"``,
            ``"none"`` (:func:`node_layer`).

    Shapes: ``x`` (N, in_features), ``adj`` (N, N) CSR -> (N, out_features).
    """

    def __init__(
        self,
        in_features: int,
        out_features: int,
        width: int = 64,
        encoder_hidden: int | None = None,
        decoder_hidden: int | None = None,
        layers: int = 2,
        act: str = "silu",
        aggregation: str = "sum",
    ) -> None:
        super().__init__()
        encoder_hidden = encoder_hidden or 8 * in_features
        decoder_hidden = decoder_hidden or 8 * out_features
        self.aggregation = aggregation
        self.node_encoder = make_mlp([in_features, encoder_hidden, width], act)
        self.node_decoder = make_mlp([width, decoder_hidden, out_features], act)
        self.mp_layers = nn.ModuleList(
            nn.ModuleList([nn.LayerNorm(width), node_layer(width, act, aggregation)]) for _ in range(layers)
        )

    def forward(self, x: Tensor, adj: Tensor) -> Tensor:
        """Run the network on (N, in_features) inputs over the kernel adjacency ``adj``."""
        if self.aggregation in KERNEL_AGGREGATIONS:
            weight_sum = None
            if self.aggregation == "mean":
                weight_sum = adj @ torch.ones(adj.shape[1], 1, dtype=x.dtype, device=x.device)
            layer_inputs: tuple[Tensor | None, ...] = (adj, weight_sum)
        elif self.aggregation == "none":
            layer_inputs = ()
        else:
            layer_inputs = (unit_adjacency(adj),)
        h = self.node_encoder(x)
        for norm, layer in self.mp_layers:
            h = norm(h)  # the residual carries the normalised embedding, as in the authors' NodeNetwork
            h = layer(h, *layer_inputs) + h
        return self.node_decoder(h)


def _speed_and_direction(vel: Tensor) -> tuple[Tensor, Tensor]:
    """(N, 1) ``|v| + eps`` and (N, 3) ``v / (|v| + eps)``, as the authors compute them."""
    speed = vel.norm(dim=1, keepdim=True) + _EPS_SPEED
    return speed, vel / speed


def _check_features(features: Sequence[str], allowed: dict[str, int], net: str) -> tuple[str, ...]:
    unknown = [f for f in features if f not in allowed]
    if unknown or not features:
        raise ConfigError(
            f"{net} features {list(features)}: unknown {unknown}; available: {', '.join(allowed)}"
        )
    return tuple(features)


class AdvectionNet(nn.Module):
    """Advection net ``a = G_adv(x^n, v^n, g, nu)`` (paper eq. 11): body force and viscosity.

    Nodes are the fluid particles and their neighbours within ``radius``; only fluid rows are used.

    With ``linear_in_viscosity`` the network learns only the viscous term's operator, as the MPS rule
    ``a = g + nu lap(v)`` (paper eq. 3) has it: :meth:`predict` returns ``g + nu * L`` with ``L`` the
    network's de-standardised output (1/(m s), trained on the MPS Laplacian of the velocities), so gravity
    is exact and the viscous part is linear in ``nu``. Why: one network over ``g`` in [1, 100] m/s^2 and
    ``nu`` in [1e-6, 0.1] m^2/s standardises its output by the whole range (std ~5-20 m/s^2), so at water
    (``nu`` = 1e-6, viscous term ~1e-4 m/s^2) its error was 7% of ``g`` where the authors' water-only net's
    is 2e-5 (``benchmarks/results/fgn_recipe.md``, "adv. nMAE water"); linear in ``nu`` it is exact in the
    limit of no viscosity.

    Args:
        features: per-node inputs, names from :data:`ADVECTION_FEATURES`.
        radius: graph radius in l0 (authors: 0.6 x 3.1 = 1.86).
        gravity_scale: m/s^2 dividing ``g`` for the ``gravity`` input.
        linear_in_viscosity: learn ``L`` in ``a = g + nu L`` (above) instead of ``a`` itself (paper eq. 11).
        **net: :class:`NodeNet` options (width, layers, act, aggregation, hidden sizes).

    Buffers: ``speed`` (|v|), ``vel_scale`` (std of |v|), ``log_viscosity``, ``target`` (3 components of
    the acceleration, m/s^2; with ``linear_in_viscosity`` of ``L``, 1/(m s)).
    """

    kind = "advection"

    def __init__(
        self,
        features: Sequence[str] = ("vel_dir", "speed", "vel", "is_fluid", "gravity", "viscosity"),
        radius: float = 1.86,
        gravity_scale: float = 9.8065,
        linear_in_viscosity: bool = False,
        **net: Any,
    ) -> None:
        super().__init__()
        if not isinstance(linear_in_viscosity, bool):
            raise CheckpointError(
                f"advection network: linear_in_viscosity must be true or false, got {linear_in_viscosity!r}"
            )
        self.linear_in_viscosity = linear_in_viscosity
        self.features = _check_features(features, ADVECTION_FEATURES, "advection")
        self.radius = float(radius)
        self.gravity_scale = float(gravity_scale)
        self.speed = Standardizer(1)
        self.log_viscosity = Standardizer(1)
        self.target = Standardizer(3)
        width = sum(ADVECTION_FEATURES[f] for f in self.features)
        self.net = NodeNet(width, 3, **net)

    def node_features(self, vel: Tensor, is_fluid: Tensor, gravity: Tensor, viscosity: Tensor) -> Tensor:
        """(N, F) inputs: ``vel`` (N, 3), ``is_fluid`` (N,) bool, ``gravity`` (N, 3), ``viscosity`` (N,)."""
        speed, direction = _speed_and_direction(vel)
        parts = {
            "vel_dir": lambda: direction,
            "speed": lambda: self.speed(speed),
            "vel": lambda: vel / self.speed.std,
            "is_fluid": lambda: is_fluid.to(vel.dtype).unsqueeze(1),
            "gravity": lambda: gravity.to(vel.dtype) / self.gravity_scale,
            "viscosity": lambda: self.log_viscosity(
                torch.log10(viscosity.to(vel.dtype).clamp_min(1e-30))[:, None]
            ),
        }
        return torch.cat([parts[f]() for f in self.features], dim=1)

    def forward(
        self, vel: Tensor, is_fluid: Tensor, gravity: Tensor, viscosity: Tensor, adj: Tensor
    ) -> Tensor:
        """Standardised acceleration (N, 3) of every node (the loss is taken on fluid rows)."""
        return self.net(self.node_features(vel, is_fluid, gravity, viscosity), adj)

    def predict(
        self, vel: Tensor, is_fluid: Tensor, gravity: Tensor, viscosity: Tensor, adj: Tensor
    ) -> Tensor:
        """Acceleration in m/s^2 (N, 3); same arguments as :meth:`forward`."""
        out = self.target.inverse(self.forward(vel, is_fluid, gravity, viscosity, adj))
        if self.linear_in_viscosity:
            return gravity.to(out.dtype) + viscosity.to(out.dtype).unsqueeze(1) * out
        return out


class PressureNet(nn.Module):
    """Pressure net ``p = G_pres(x*, v**, n)`` (paper eq. 16) on the non-free-surface particles.

    Args:
        features: per-node inputs, names from :data:`PRESSURE_FEATURES`.
        radius: graph radius in l0 (authors: 0.55 x 3.1 = 1.705).
        **net: :class:`NodeNet` options.

    Buffers: ``speed``, ``density`` (n / n0), ``target`` (pressure, Pa).
    """

    kind = "pressure"

    def __init__(
        self,
        features: Sequence[str] = ("vel_dir", "speed", "vel", "density", "is_fluid"),
        radius: float = 1.705,
        **net: Any,
    ) -> None:
        super().__init__()
        self.features = _check_features(features, PRESSURE_FEATURES, "pressure")
        self.radius = float(radius)
        self.speed = Standardizer(1)
        self.density = Standardizer(1)
        self.target = Standardizer(1)
        width = sum(PRESSURE_FEATURES[f] for f in self.features)
        self.net = NodeNet(width, 1, **net)

    def node_features(self, vel: Tensor, density_ratio: Tensor, is_fluid: Tensor) -> Tensor:
        """(N, F) inputs from ``vel`` (N, 3), ``density_ratio`` n / n0 (N,), ``is_fluid`` (N,) bool."""
        speed, direction = _speed_and_direction(vel)
        parts = {
            "vel_dir": lambda: direction,
            "speed": lambda: self.speed(speed),
            "vel": lambda: vel / self.speed.std,
            "density": lambda: self.density(density_ratio.to(vel.dtype).unsqueeze(1)),
            "is_fluid": lambda: is_fluid.to(vel.dtype).unsqueeze(1),
        }
        return torch.cat([parts[f]() for f in self.features], dim=1)

    def forward(self, vel: Tensor, density_ratio: Tensor, is_fluid: Tensor, adj: Tensor) -> Tensor:
        """Standardised pressure (N,)."""
        return self.net(self.node_features(vel, density_ratio, is_fluid), adj).squeeze(1)

    def predict(self, *args: Tensor) -> Tensor:
        """Pressure in Pa (N,); same arguments as :meth:`forward`."""
        return self.target.inverse(self.forward(*args).unsqueeze(1)).squeeze(1)


class EdgeMessage(nn.Module):
    """The collision net's edge update: ``e_ji <- MLP(W_h h_j + W_e e_ji)``, ``h_j = sum_k e_kj``.

    ``h_j`` sums the edges arriving at the source particle ``j``: what else is pressing on the neighbour.
    (The authors' module also computes a node update that their network never uses; it is left out here
    and its weights are skipped when loading theirs.)

    Shapes: ``e`` (E, F), ``edge_index`` (2, E) -> (E, F).
    """

    def __init__(self, width: int, act: str) -> None:
        super().__init__()
        self.mlp = make_mlp([width // 2, width // 2, width], act, act_first=True)
        self.node_linear = nn.Linear(width, width // 2)
        self.edge_linear = nn.Linear(width, width // 2)

    def forward(self, e: Tensor, edge_index: Tensor, num_nodes: int) -> Tensor:
        """Updated edge embeddings (E, F)."""
        src, dst = edge_index
        h = scatter(e, dst, dim=0, dim_size=num_nodes, reduce="sum")
        return self.mlp(self.node_linear(h.index_select(0, src)) + self.edge_linear(e))


class CollisionNet(MessagePassing):
    r"""Collision net ``dv = G_col(x*_r, v*_r)`` (paper eqs. 14, 21-22).

    .. math::
        e_{ji} = \mathrm{Enc}\big[(v_j - v_i)/s_v,\ (x_j - x_i)/|x_j - x_i|\big], \quad
        e_{ji} \leftarrow \mathrm{EdgeMessage}(\mathrm{LN}(e_{ji})), \quad
        \Delta v_i = s_{\Delta v} \sum_j \mathrm{Dec}(e_{ji})

    over the pairs closer than ``radius`` (no self loops). The relative velocity and direction are all the
    elastic-collision rule depends on. ``s_v``, ``s_dv`` are the ``rel_vel`` and ``target`` scales (1 for
    the authors' weights, which take raw m/s).

    With ``homogeneous`` the encoder sees each pair's relative-velocity *direction* and the decoded change is
    multiplied by that pair's relative speed ``|v_j - v_i| / s_v``: scaling every velocity by ``c`` scales
    ``dv`` by ``c`` exactly, as the MPS rule does (it is linear in the velocities). Without it the
    encoder's LayerNorm divides the speed out, so the change saturates beyond the training speeds (the
    collision data reach ~4 m/s; the water fall hits its far wall at 7-9 m/s: docs/training.md).

    Args:
        radius: graph radius in l0 (authors: 0.92).
        width: edge embedding size (authors: 64).
        encoder_hidden, decoder_hidden: hidden sizes (authors: 24, 24).
        layers: edge message layers (authors: 1).
        act: activation of the encoder and decoder (authors: ReLU).
        message_act: activation inside the edge messages (authors: identity).
        homogeneous: per-pair output scaled by the pair's relative speed (above; authors: false).

    Shapes: ``vel`` (N, 3), ``rel`` (E, 3) ``x_j - x_i``, ``dist`` (E,), ``edge_index`` (2, E) -> (N, 3).
    """

    kind = "collision"

    def __init__(
        self,
        radius: float = 0.92,
        width: int = 64,
        encoder_hidden: int = 24,
        decoder_hidden: int = 24,
        layers: int = 1,
        act: str = "relu",
        message_act: str = "silu",
        homogeneous: bool = False,
    ) -> None:
        super().__init__(aggr="add", flow="source_to_target")
        if not isinstance(homogeneous, bool):
            raise CheckpointError(
                f"collision network: homogeneous must be true or false, got {homogeneous!r}"
            )
        self.radius = float(radius)
        self.homogeneous = homogeneous
        self.rel_vel = Standardizer(1)  # only the scale is used: relative velocities stay centred
        self.target = Standardizer(1)
        self.edge_encoder = make_mlp([6, encoder_hidden, width, width], act, layer_norm=True)
        self.edge_decoder = make_mlp([width, decoder_hidden, 3], act)
        self.mp_layers = nn.ModuleList(
            nn.ModuleList([nn.LayerNorm(width), EdgeMessage(width, message_act)]) for _ in range(layers)
        )

    def forward(self, vel: Tensor, rel: Tensor, dist: Tensor, edge_index: Tensor) -> Tensor:
        """Velocity change (N, 3) of every node, in units of ``target.std``."""
        n = vel.shape[0]
        if edge_index.shape[1] == 0:  # nothing within the collision radius: no work, no change
            return vel.new_zeros(n, 3)
        src, dst = edge_index
        rel_vel = (vel.index_select(0, src) - vel.index_select(0, dst)) / self.rel_vel.std
        if self.homogeneous:
            speed = torch.linalg.vector_norm(rel_vel, dim=1, keepdim=True)  # (E, 1)
            rel_vel = rel_vel / speed.clamp_min(torch.finfo(rel_vel.dtype).tiny)  # at rest: 0, not NaN
        direction = rel / dist.clamp_min(1e-12).unsqueeze(1)
        e = self.edge_encoder(torch.cat([rel_vel, direction], dim=1))
        for norm, layer in self.mp_layers:
            e = layer(norm(e), edge_index, n)
        change = self.edge_decoder(e)
        if self.homogeneous:
            change = change * speed
        return self.propagate(edge_index, e=change, size=(n, n))

    def message(self, e: Tensor) -> Tensor:
        """Each edge's decoded velocity change."""
        return e

    def predict(self, vel: Tensor, rel: Tensor, dist: Tensor, edge_index: Tensor) -> Tensor:
        """Velocity change in m/s (N, 3)."""
        return self.forward(vel, rel, dist, edge_index) * self.target.std


_SIZE_KEYS = frozenset({"width", "layers", "encoder_hidden", "decoder_hidden"})
_LENGTH_KEYS = frozenset({"radius", "gravity_scale"})


def build_network(kind: str, options: dict[str, Any]) -> nn.Module:
    """A fresh network of ``kind`` from its options (the ``model.<kind>`` config node as a dict).

    Raises:
        CheckpointError: an unknown kind or option name, or a size or radius that is no positive number
            (from a config or from a checkpoint's own options), named before torch sees it.
    """
    opts = {k: v for k, v in dict(options).items() if v is not None}
    for key in _SIZE_KEYS & opts.keys():
        value = opts[key]
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise CheckpointError(
                f"invalid options for the {kind} network: {key} must be a whole number >= 1, got {value!r}"
            )
    for key in _LENGTH_KEYS & opts.keys():
        value = opts[key]
        if (
            isinstance(value, bool)
            or not isinstance(value, int | float)
            or not math.isfinite(value)
            or value <= 0
        ):
            raise CheckpointError(
                f"invalid options for the {kind} network: {key} must be a number > 0, got {value!r}"
            )
    try:
        if kind == "collision":
            return CollisionNet(**opts)
        net_opts = {k: opts.pop(k) for k in _NODE_NET_KEYS if k in opts}
        if kind == "advection":
            return AdvectionNet(**opts, **net_opts)
        if kind == "pressure":
            return PressureNet(**opts, **net_opts)
    except TypeError as err:  # an unknown option name
        raise CheckpointError(f"invalid options for the {kind} network: {err}") from err
    raise CheckpointError(f"unknown network kind '{kind}'; available: {', '.join(KINDS)}")


def load_network(path: str | os.PathLike, kind: str | None = None) -> tuple[nn.Module, dict[str, Any]]:
    """Rebuild the FGN network saved in ``path`` with its own options and weights.

    Returns:
        The network (CPU, eval mode) and the checkpoint dict.

    Raises:
        CheckpointError: see :func:`lagfluid.models.checkpoint.read_checkpoint`; weights that do not fit
            the checkpoint's own options.
    """
    ckpt = read_checkpoint(path, kind, model="fgn")
    net = build_network(ckpt["kind"], ckpt["options"])
    try:
        net.load_state_dict(ckpt["state_dict"])
    except RuntimeError as err:
        raise CheckpointError(f"{path}: weights do not fit its own options: {err}") from err
    return net.eval(), ckpt
