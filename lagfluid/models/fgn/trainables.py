"""FGN's three networks as trainables (:class:`~lagfluid.models.trainable.Trainable`) for ``task=train``.

Each network learns from its own one-step samples (paper A.2) of a generated dataset
(:mod:`lagfluid.data.datasets`); its inputs come from :mod:`lagfluid.models.fgn.inputs`, the functions the
learned stages use at inference:

=============  ============================================  ==========================================
trainable      inputs (per node / edge)                      target (loss rows)
=============  ============================================  ==========================================
advection      v^n, particle type, g, nu; kernel graph        a = g + nu lap(v) (fluid rows)
               at ``model.advection.radius`` into the fluid
collision      v* differences and directions of pairs         v** - v* (fluid rows)
               within ``model.collision.radius``
pressure       v**, n / n0, type; kernel graph among the      PPE pressure (every node)
               PPE unknowns at ``model.pressure.radius``
=============  ============================================  ==========================================

Predictions and targets are standardised by the network's own statistics (its ``target`` buffer).

**Materials (advection).** With ``train.materials.resample`` each advection sample gets a fresh gravity
magnitude and viscosity every time it is drawn (``train.materials.gravity``, ``viscosity``, log-uniform or
uniform) and its label is recomputed exactly, ``a = g + nu lap(v)`` with the MPS Laplacian of the stored
velocities (the operator the solver applies). Labels stay exact; only the flow states come from water.
Why the range reaches down to water: ``docs/training.md``. Without it the labels are the
stored ones, which for water (nu = 1e-6) are ``g`` to 6 digits.

**Normalisation.** Statistics of inputs and targets are fitted here from training items and stored in the
network's buffers, hence in every checkpoint: the one source, since they depend on the network's radius,
features and material draws, which the dataset cannot know (``metadata.json``'s statistics only describe
the data; no network reads them).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf
from torch import Tensor, nn
from torch_geometric.data import Batch, Data

from lagfluid.data.datasets import AdvectionSamples, CollisionSamples, PressureSamples
from lagfluid.errors import ConfigError, LagfluidError
from lagfluid.models.fgn.inputs import advection_inputs, collision_inputs, pressure_inputs
from lagfluid.models.fgn.networks import build_network, owned_stages
from lagfluid.models.fgn.ppe_term import WithPPESystem, ppe_residual_rows
from lagfluid.neighbors import edge_vectors, radius_graph
from lagfluid.physics import operators as ops
from lagfluid.physics.settings import SolverSettings, lattice_constants
from lagfluid.state import ParticleType

__all__ = [
    "AdvectionTrainable",
    "CachedDataset",
    "CollisionTrainable",
    "FGNTrainable",
    "PressureTrainable",
    "ResampledMaterials",
    "build_trainables",
    "kernel_graph",
    "log_uniform_sample",
]


# ---------------------------------------------------------------------------------------------- data
def log_uniform_sample(
    low: float, high: float, size: int, generator: torch.Generator | None = None
) -> Tensor:
    """``size`` values log-uniform in ``[low, high]`` (float64)."""
    u = torch.rand(size, generator=generator, dtype=torch.float64)
    return torch.exp(math.log(low) + u * (math.log(high) - math.log(low)))


def kernel_graph(
    pos: Tensor, radius: float, batch: Tensor | None, receivers: Tensor | None
) -> tuple[Tensor, Tensor]:
    """Block-diagonal radius graph at ``radius`` (m): ``edge_index`` (2, E) and pair distances (E,)."""
    edge_index = radius_graph(pos, radius, batch=batch, receivers=receivers)
    _, dist = edge_vectors(pos, edge_index)
    return edge_index, dist


class ResampledMaterials:
    """Advection samples with a fresh gravity and viscosity at every draw, labels recomputed exactly.

    Wraps advection samples; the MPS Laplacian of each sample's velocities is computed once and cached
    (labels are ``g + nu lap(v)``, linear in both).

    Args:
        dataset: the advection samples (:class:`~lagfluid.data.datasets.AdvectionSamples` or a cache of them).
        gravity, viscosity: ``[low, high]`` ranges of ``|g|`` (m/s^2, pointing -z) and ``nu`` (m^2/s).
        log_uniform: draw log-uniformly (else uniformly).
        settings: solver coefficients (``re_laplacian``) and the lattice constants they imply.
        seed: seed of the draws.
        fixed: the same draw for an item every time (validation), instead of a fresh one (training).
    """

    def __init__(
        self,
        dataset: Any,
        gravity: tuple[float, float],
        viscosity: tuple[float, float],
        log_uniform: bool,
        settings: SolverSettings,
        seed: int,
        fixed: bool = False,
    ) -> None:
        self.dataset = dataset
        self.gravity, self.viscosity, self.log_uniform = gravity, viscosity, log_uniform
        self.settings = settings
        self.seed, self.fixed = seed, fixed
        self.generator = torch.Generator().manual_seed(seed)
        self._laplacians: dict[int, Tensor] = {}

    def __len__(self) -> int:
        return len(self.dataset)

    def _draw(self, low: float, high: float) -> float:
        if self.log_uniform:
            return float(log_uniform_sample(low, high, 1, self.generator)[0])
        return float(low + (high - low) * torch.rand(1, generator=self.generator, dtype=torch.float64)[0])

    def laplacian(self, idx: int, item: Data) -> Tensor:
        """MPS Laplacian of the sample's velocities at its fluid particles (Nf, 3), cached."""
        lap = self._laplacians.get(idx)
        if lap is None:
            l0 = float(item.l0[0])
            constants = lattice_constants(l0, self.settings)
            re = self.settings.re_laplacian * l0
            fluid = item.ptype == ParticleType.FLUID
            pos64, vel64 = item.pos.double(), item.vel.double()
            edge_index = radius_graph(pos64, re, receivers=fluid)
            lap = ops.laplacian(
                pos64, edge_index, vel64, re, constants.n0_lap, constants.lam, num_nodes=int(fluid.sum())
            ).float()
            self._laplacians[idx] = lap
        return lap

    def reseed(self, key: int) -> None:
        """Make the next item's draw a function of ``key`` (the trainer's ``epoch * len + index``)."""
        if not self.fixed:
            self.generator.manual_seed(self.seed * 1_000_003 + 500_009 + key)

    def __getitem__(self, idx: int) -> Data:
        item = self.dataset[idx]
        if self.fixed:
            self.generator.manual_seed(self.seed * 1_000_003 + idx)
        g = self._draw(*self.gravity)
        nu = self._draw(*self.viscosity)
        gravity = torch.tensor([[0.0, 0.0, -g]])
        item.laplacian = self.laplacian(idx, item)
        item.y = gravity + nu * item.laplacian
        item.gravity, item.viscosity = gravity, torch.tensor([nu], dtype=torch.float32)
        return item


class CachedDataset(torch.utils.data.Dataset):
    """Keeps items in memory after their first read (HDF5 reads, boundary pruning, graphs paid once).

    With ``graph=(radius_l0, fluid_receivers_only)`` each item also keeps its kernel graph
    (``edge_index``, ``edge_dist``), which PyG's batching offsets per sample: the radius search is a large
    share of an iteration (see ``docs/training.md``).

    ``max_bytes`` bounds the memory the cache holds: items are kept in their first-read order until the next
    would pass it; the others are read (and their graphs searched) again at every draw, giving the same
    item. Index tensors are kept as int32 (half the bytes; returned as int64). Why a bound: an item holds
    ~2 MB (advection, kernel graph) to ~10 MB (pressure with its PPE system) on the paper's scenes, so the
    4,000 training samples of ``data=paper`` would need 13-40 GB (``docs/training.md``).
    """

    _COMPACT = ("edge_index",)  # int64 index tensors kept as int32 while cached

    def __init__(
        self, dataset: Any, graph: tuple[float, bool] | None = None, max_bytes: float | None = None
    ) -> None:
        if max_bytes is not None and not max_bytes >= 0:
            raise ConfigError(f"a cache bound must be >= 0 bytes (train.cache_gb), got {max_bytes!r}")
        self.dataset = dataset
        self.graph = graph
        self.max_bytes = max_bytes
        self.cached_bytes = 0
        self._items: dict[int, Data] = {}

    def __len__(self) -> int:
        return len(self.dataset)

    def _read(self, idx: int) -> Data:
        item = self.dataset[idx]
        if self.graph is not None:
            radius, fluid_only = self.graph
            receivers = item.ptype == ParticleType.FLUID if fluid_only else None
            item.edge_index, item.edge_dist = kernel_graph(
                item.pos, radius * float(item.l0[0]), None, receivers
            )
        return item

    def __getitem__(self, idx: int) -> Data:
        cached = self._items.get(idx)
        if cached is not None:
            item = cached.clone()
            for key in self._COMPACT:
                if key in item:
                    item[key] = item[key].long()
            return item
        item = self._read(idx)
        compact = item.clone()
        for key in self._COMPACT:
            if key in compact and compact.num_nodes < 2**31:
                compact[key] = compact[key].int()
        size = sum(v.numel() * v.element_size() for _, v in compact.items() if torch.is_tensor(v))
        if self.max_bytes is None or self.cached_bytes + size <= self.max_bytes:
            self._items[idx] = compact
            self.cached_bytes += size
        return item


def _l0(batch: Data) -> float:
    l0 = batch.l0.unique()
    if l0.numel() != 1:
        raise LagfluidError(f"samples with different particle spacings in one batch: {l0.tolist()}")
    return float(l0[0])


def _dtype(net: nn.Module) -> torch.dtype:
    return next(net.parameters()).dtype


def _mean_std(x: Tensor) -> tuple[Tensor, Tensor]:
    x = x.double()
    return x.mean(dim=0), x.std(dim=0, unbiased=False)


def _fluid_speed(items: Sequence[Data]) -> Tensor:
    """(N, 1) ``|v| + eps`` of the items' fluid particles (the networks' ``speed`` input)."""
    fluid_vel = torch.cat([it.vel[it.ptype == ParticleType.FLUID] for it in items])
    return fluid_vel.norm(dim=1, keepdim=True) + 1e-8


# ------------------------------------------------------------------------------------------ trainables
class FGNTrainable:
    """One of FGN's networks as a trainable: its samples, statistics, inputs and target.

    Args:
        name: ``advection``, ``collision`` or ``pressure``.
        options: the network's options (``cfg.model.<name>``).
    """

    model = "fgn"
    loss = None  # train.loss.<name> (the profiles: mse, Huber for the pressure net)
    samples: type = AdvectionSamples
    graph_fluid_only: bool | None = None  # cache a kernel graph per item (into the fluid only), or none

    def __init__(self, name: str, options: dict[str, Any]) -> None:
        self.name = name
        self.options = options
        self.cache_bytes: float | None = None  # bound of each split's item cache (train.cache_gb); None: none

    def build_network(self) -> nn.Module:
        """A fresh network from :attr:`options`."""
        return build_network(self.name, self.options)

    def datasets(self, data_dir: Path) -> tuple[Any, Any]:
        """Cached ``train`` and ``valid`` samples (with their kernel graphs where the net has one)."""
        graph = (
            None if self.graph_fluid_only is None else (float(self.options["radius"]), self.graph_fluid_only)
        )
        train = CachedDataset(self.samples(data_dir, split="train"), graph, self.cache_bytes)
        valid = CachedDataset(self.samples(data_dir, split="valid"), graph, self.cache_bytes)
        return train, valid

    def identity(self) -> dict[str, Any]:
        """No settings beyond the network's options (``materials: None`` keeps older runs' fingerprints)."""
        return {"materials": None}

    @staticmethod
    def _graph(batch: Batch, radius: float, receivers: Tensor | None) -> tuple[Tensor, Tensor]:
        """The batch's kernel graph: from the items' cached graphs, or searched now."""
        if getattr(batch, "edge_index", None) is not None:
            return batch.edge_index, batch.edge_dist
        return kernel_graph(batch.pos, radius, batch.batch, receivers)


def _advection_label(net: nn.Module, item: Data) -> Tensor:
    """(Nf, 3) what ``net``'s de-standardised output is trained on.

    The acceleration ``y`` (m/s^2), or with ``linear_in_viscosity`` the MPS Laplacian of the velocities
    (1/(m s), :class:`ResampledMaterials`).
    """
    return item.laplacian if net.linear_in_viscosity else item.y


class AdvectionTrainable(FGNTrainable):
    """The advection net: ``[v^n, type, g, nu]`` on the kernel graph -> ``a`` (fluid rows).

    Args:
        name, options: as :class:`FGNTrainable`.
        materials: ``train.materials`` (``resample``, ``gravity``, ``viscosity``, ``log_uniform``).
        settings: solver settings (the Laplacian of resampled labels).
        seed: seed of the material draws (validation: ``seed + 1``, fixed per item).
    """

    samples = AdvectionSamples
    graph_fluid_only = True

    def __init__(
        self,
        name: str,
        options: dict[str, Any],
        materials: dict[str, Any],
        settings: SolverSettings,
        seed: int,
    ) -> None:
        super().__init__(name, options)
        self.materials, self.settings, self.seed = materials, settings, seed

    def identity(self) -> dict[str, Any]:
        """The material ranges (they change the labels)."""
        return {"materials": self.materials}

    def datasets(self, data_dir: Path) -> tuple[Any, Any]:
        """Cached samples; with ``materials.resample`` fresh g and nu per draw (fixed per item in valid)."""
        train, valid = super().datasets(data_dir)
        m = self.materials
        if self.options.get("linear_in_viscosity") and not m.get("resample"):
            raise ConfigError(
                "model.advection.linear_in_viscosity=true trains on the MPS Laplacian of each sample's "
                "velocities, which train.materials.resample=true computes; it is false"
            )
        if m.get("resample"):
            ranges = (m["gravity"], m["viscosity"], bool(m["log_uniform"]), self.settings)
            train = ResampledMaterials(train, *ranges, seed=self.seed)
            valid = ResampledMaterials(valid, *ranges, seed=self.seed + 1, fixed=True)
        return train, valid

    def fit_statistics(self, net: nn.Module, items: Sequence[Data]) -> dict[str, Any]:
        """Speed, target (per component) and log10 viscosity."""
        net.speed.set(*_mean_std(_fluid_speed(items)))
        net.target.set(*_mean_std(torch.cat([_advection_label(net, it) for it in items])))
        log_nu = torch.log10(torch.cat([it.viscosity for it in items]).double().clamp_min(1e-30))
        net.log_viscosity.set(*_mean_std(log_nu.unsqueeze(1)))
        return {
            "speed": [float(net.speed.mean), float(net.speed.std)],
            "target": [net.target.mean.tolist(), net.target.std.tolist()],
            "log_viscosity": [float(net.log_viscosity.mean), float(net.log_viscosity.std)],
        }

    def predict(self, net: nn.Module, batch: Batch) -> tuple[Tensor, Tensor]:
        """Standardised acceleration and target (Nf, 3) of the fluid rows."""
        fluid = batch.ptype == ParticleType.FLUID
        radius = net.radius * _l0(batch)
        edge_index, dist = self._graph(batch, radius, fluid)
        inputs = advection_inputs(
            batch.vel,
            fluid,
            batch.gravity,
            batch.viscosity,
            edge_index,
            dist,
            radius,
            _dtype(net),
            batch.batch,
        )
        return net(*inputs)[fluid], net.target(_advection_label(net, batch))


class CollisionTrainable(FGNTrainable):
    """The collision net: pairs within its radius -> ``v** - v*`` (fluid rows), scaled not centred."""

    samples = CollisionSamples

    range_quantities = ("dt", "l0")  # collision-only systems: no gravity, no viscosity

    def fit_statistics(self, net: nn.Module, items: Sequence[Data]) -> dict[str, Any]:
        """RMS relative velocity of the pairs and RMS velocity change of the moved particles."""
        # scales only: centring a velocity change would bias particles with no contact
        rel_sq, dv = [], []
        for it in items:
            ei = radius_graph(it.pos, net.radius * float(it.l0[0]), batch=None)
            rel_sq.append((it.vel[ei[0]] - it.vel[ei[1]]).double().square().sum(dim=1))
            y = it.y.double()
            dv.append(y[y.norm(dim=1) > 0])
        rms_v = float(torch.cat(rel_sq).mean().sqrt()) if rel_sq else 1.0
        moved = torch.cat(dv) if dv else torch.zeros(0, 3, dtype=torch.float64)
        rms_dv = float(moved.square().sum(dim=1).mean().sqrt()) if len(moved) else 1.0
        net.rel_vel.set([0.0], [rms_v])
        net.target.set([0.0], [rms_dv])
        return {"rel_vel_rms": rms_v, "delta_v_rms": rms_dv}

    def predict(self, net: nn.Module, batch: Batch) -> tuple[Tensor, Tensor]:
        """Velocity change and target (Nf, 3) of the fluid rows, in units of the target scale."""
        fluid = batch.ptype == ParticleType.FLUID
        edge_index = radius_graph(batch.pos, net.radius * _l0(batch), batch=batch.batch)
        rel, dist = edge_vectors(batch.pos, edge_index)
        out = net(*collision_inputs(batch.vel, rel, dist, edge_index, _dtype(net)))
        return out[fluid], batch.y / net.target.std


class PressureTrainable(FGNTrainable):
    """The pressure net: ``[v**, n / n0, type]`` on the PPE unknowns' kernel graph -> ``p`` (every node).

    Args:
        name, options: as :class:`FGNTrainable`.
        ppe_weight: ``train.ppe_weight``; > 0 adds the squared relative PPE residual of the prediction
            (paper eq. 31) at this weight (:mod:`lagfluid.models.fgn.ppe_term`): :meth:`predict` then returns
            the residual rows after the pressure rows (target 0), and the loss averages over both.
    """

    samples = PressureSamples
    graph_fluid_only = False

    def __init__(self, name: str, options: dict[str, Any], ppe_weight: float = 0.0) -> None:
        super().__init__(name, options)
        if not (math.isfinite(ppe_weight) and ppe_weight >= 0.0):
            raise ConfigError(f"train.ppe_weight must be a finite number >= 0, got {ppe_weight}")
        self.ppe_weight = ppe_weight

    def identity(self) -> dict[str, Any]:
        """The PPE term's weight when there is one (runs without it keep their fingerprints)."""
        return {"materials": None, **({"ppe_weight": self.ppe_weight} if self.ppe_weight else {})}

    def datasets(self, data_dir: Path) -> tuple[Any, Any]:
        """Cached samples, each with its step's PPE system when the PPE term is on."""
        if not self.ppe_weight:
            return super().datasets(data_dir)
        graph = (float(self.options["radius"]), False)
        return tuple(
            CachedDataset(WithPPESystem(self.samples(data_dir, split=split)), graph, self.cache_bytes)
            for split in ("train", "valid")
        )

    def fit_statistics(self, net: nn.Module, items: Sequence[Data]) -> dict[str, Any]:
        """Speed, density ratio and pressure."""
        net.speed.set(*_mean_std(_fluid_speed(items)))
        ratio = torch.cat([it.density / it.n0 for it in items]).unsqueeze(1)
        net.density.set(*_mean_std(ratio))
        net.target.set(*_mean_std(torch.cat([it.y for it in items]).unsqueeze(1)))
        return {
            "speed": [float(net.speed.mean), float(net.speed.std)],
            "density": [float(net.density.mean), float(net.density.std)],
            "target": [float(net.target.mean), float(net.target.std)],
        }

    def predict(self, net: nn.Module, batch: Batch) -> tuple[Tensor, Tensor]:
        """Standardised pressure and target (M,) of every node."""
        fluid = batch.ptype == ParticleType.FLUID
        radius = net.radius * _l0(batch)
        edge_index, dist = self._graph(batch, radius, None)
        inputs = pressure_inputs(
            batch.vel, batch.density, batch.n0, fluid, edge_index, dist, radius, _dtype(net), batch.batch
        )
        pred, target = net(*inputs), net.target(batch.y.unsqueeze(1)).squeeze(1)
        if not self.ppe_weight:
            return pred, target
        pressure = net.target.inverse(pred.unsqueeze(1)).squeeze(1)
        rows = math.sqrt(self.ppe_weight) * ppe_residual_rows(pressure, batch)
        return torch.cat([pred, rows]), torch.cat([target, torch.zeros_like(rows)])


def build_trainables(cfg: Any) -> dict[str, FGNTrainable]:
    """``model=fgn`` / ``hybrid`` / an ablation's trainables by name, from the composed config.

    Reads ``cfg.model.<name>`` (network options), ``cfg.model.trains`` (the stages the model owns; FGN all
    three, the Table 5 ablations advection and pressure), ``cfg.train.materials``, ``cfg.solver`` and
    ``cfg.seed``; ``cfg.train.ppe_weight`` (the pressure net's PPE term, 0 = none); ``cfg.train.cache_gb``
    (the bound of each split's item cache, GB; null or absent: none).
    """
    fmt = cfg.model.get("format", "lagfluid")
    if fmt != "lagfluid":
        raise ConfigError(f"task=train writes lagfluid checkpoints; model.format={fmt!r} cannot be trained")

    def plain(node: Any) -> dict[str, Any]:
        return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else dict(node)

    settings = SolverSettings.from_config(cfg.solver)
    materials = plain(cfg.train.materials)
    stages = {
        "advection": AdvectionTrainable(
            "advection", plain(cfg.model.advection), materials, settings, int(cfg.seed)
        ),
        "collision": CollisionTrainable("collision", plain(cfg.model.collision)),
        "pressure": PressureTrainable(
            "pressure", plain(cfg.model.pressure), float(cfg.train.get("ppe_weight") or 0.0)
        ),
    }
    cache_gb = cfg.train.get("cache_gb")
    if cache_gb is not None and not (isinstance(cache_gb, (int, float)) and cache_gb >= 0):
        raise ConfigError(f"train.cache_gb must be a number of GB >= 0 or null (no bound), got {cache_gb!r}")
    for trainable in stages.values():
        trainable.cache_bytes = None if cache_gb is None else float(cache_gb) * 1e9
    return {k: stages[k] for k in owned_stages(cfg.model)}
