"""One trainer for FGN's networks: ``python -m lagfluid.run task=train model=fgn stage=...``.

``stage`` is ``advection``, ``collision``, ``pressure`` or ``all`` (the three, one after another).

Each network is trained on its own one-step samples (paper A.2) from a generated dataset (``data=...``,
:mod:`lagfluid.data.datasets`): mini-batches of whole scenes as block-diagonal graphs (PyG ``Batch``; no
edge joins two samples), a loss on standardised targets (``train.loss``: mean-squared error as eq. 23,
or Huber), Adam, learning rate decayed exponentially from ``train.lr_start`` to ``train.lr_end`` over
``train.iterations`` (the paper: 1e-3 -> 6.25e-5 over 100k iterations).

**Loss.** ``train.loss.<stage>`` is ``mse`` (the paper) or ``huber`` (``train.huber_delta`` in target
standard deviations). The pressure labels are heavy-tailed: impact pressures of the falling blocks reach
50-140 standard deviations (99.9th percentile 20-176 kPa per scene against a median of ~0.8 kPa in
``data=cpu``). Under MSE those few particles set the gradient: on ``data=cpu`` the validation MSE of the
pressure net stalled at 1.0-2.0 (no better than the mean) by iteration 1000 while its bulk error grew and
it predicted 14 kPa peaks in 4.7 kPa scenes. ``train=cpu`` therefore trains the pressure net with Huber.

=============  ============================================  ==========================================
stage          inputs (per node / edge)                      target (loss rows)
=============  ============================================  ==========================================
advection      v^n, particle type, g, nu; kernel graph        a = g + nu lap(v) (fluid rows)
               at ``model.advection.radius`` into the fluid
collision      v* differences and directions of pairs         v** - v* (fluid rows)
               within ``model.collision.radius``
pressure       v**, n / n0, type; kernel graph among the      PPE pressure (every node)
               PPE unknowns at ``model.pressure.radius``
=============  ============================================  ==========================================

**Materials (advection).** With ``train.materials.resample`` each advection sample gets a fresh gravity
magnitude and viscosity every time it is drawn (g 1-100 m/s^2 as the paper's Table 4; nu log-uniform from
water's 1e-6 to 0.1 m^2/s, wider than Table 4's 1e-4 to 0.1: trained on Table 4's range, the net's error at
water was 84 % (normalised MAE, eq. 32, on the test split, against 7 % median on held-out Table 4
materials), because water's log nu lay 3.9 standard deviations outside its inputs) and its label is
recomputed exactly, ``a = g + nu lap(v)`` with the MPS Laplacian
of the stored velocities (:func:`lagfluid.physics.operators.laplacian`, the same operator the solver
applies). Labels stay exact; only the flow states come from water. Without it the labels are the stored
ones, which for water (nu = 1e-6) are ``g`` to 6 digits.

**Normalisation.** Statistics of inputs and targets come from the training split (``train.stat_samples``
samples) and live in the network's buffers, hence in every checkpoint.

**Outputs** in ``out_dir`` (default ``runs/train/<model>-<data>``): ``<stage>.pt`` (network, statistics,
options, optimizer, step; :mod:`lagfluid.models.checkpoint`), ``<stage>_loss.csv`` (iteration, lr, train
loss, valid loss, seconds). ``model.weights=<out_dir>`` then loads them into ``model=fgn``/``hybrid``.

**Resume.** A checkpoint is written every ``train.checkpoint_every`` iterations and at the end (atomic
rename). A rerun with the same command continues from it (weights, optimizer, RNG state and CSV rows after
the checkpoint dropped); a finished stage is skipped; a checkpoint from other network options or another
dataset is an error, never silently mixed.
"""

from __future__ import annotations

import csv
import hashlib
import json
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from torch import Tensor, nn
from torch_geometric.data import Batch, Data
from torch_geometric.loader import DataLoader
from tqdm import tqdm

import lagfluid
from lagfluid.data.datasets import AdvectionSamples, CollisionSamples, PressureSamples, load_metadata
from lagfluid.errors import ConfigError, LagfluidError
from lagfluid.models.checkpoint import (
    KINDS,
    build_network,
    network_payload,
    read_checkpoint,
    save_checkpoint,
)
from lagfluid.models.fgn import log_uniform_sample
from lagfluid.neighbors import edge_vectors, kernel_adjacency, radius_graph
from lagfluid.physics import operators as ops
from lagfluid.physics.stages import SolverSettings, lattice_constants
from lagfluid.state import ParticleType

log = logging.getLogger(__name__)

DATASETS = {"advection": AdvectionSamples, "collision": CollisionSamples, "pressure": PressureSamples}


# ---------------------------------------------------------------------------------------------- batches
def _l0(batch: Data) -> float:
    l0 = batch.l0.unique()
    if l0.numel() != 1:
        raise LagfluidError(f"samples with different particle spacings in one batch: {l0.tolist()}")
    return float(l0[0])


def kernel_graph(
    pos: Tensor, radius: float, batch: Tensor | None, receivers: Tensor | None
) -> tuple[Tensor, Tensor]:
    """Block-diagonal radius graph and its MPS kernel weights: ``edge_index`` (2, E), ``w`` (E,)."""
    edge_index = radius_graph(pos, radius, batch=batch, receivers=receivers)
    _, dist = edge_vectors(pos, edge_index)
    return edge_index, ops.kernel(dist, radius)


class ResampledMaterials:
    """Advection samples with a fresh gravity and viscosity at every draw, labels recomputed exactly.

    Wraps :class:`AdvectionSamples`; the MPS Laplacian of each sample's velocities is computed once and
    cached (labels are ``g + nu lap(v)``, linear in both).

    Args:
        dataset: the advection samples.
        gravity, viscosity: ``[low, high]`` ranges of ``|g|`` (m/s^2, pointing -z) and ``nu`` (m^2/s).
        log_uniform: draw log-uniformly (else uniformly).
        settings: solver coefficients (``re_laplacian``) and the lattice constants they imply.
        seed: seed of the draws.
        fixed: the same draw for an item every time (validation), instead of a fresh one (training).
    """

    def __init__(
        self,
        dataset: AdvectionSamples,
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

    def __getitem__(self, idx: int) -> Data:
        item = self.dataset[idx]
        if self.fixed:
            self.generator.manual_seed(self.seed * 1_000_003 + idx)
        g = self._draw(*self.gravity)
        nu = self._draw(*self.viscosity)
        gravity = torch.tensor([[0.0, 0.0, -g]])
        item.y = gravity + nu * self.laplacian(idx, item)
        item.gravity, item.viscosity = gravity, torch.tensor([nu], dtype=torch.float32)
        return item


class CachedDataset(torch.utils.data.Dataset):
    """Keeps every item in memory after its first read (HDF5 reads and boundary pruning paid once).

    With ``graph=(radius_l0, fluid_receivers_only)`` each item also keeps its kernel graph
    (``edge_index``, ``edge_weight``), which PyG's batching offsets per sample: the radius search was a
    quarter of a training iteration (0.09 of 0.37 s for 4 advection samples of 6k fluid particles), for
    ~3 MB of memory per sample.
    """

    def __init__(self, dataset: Any, graph: tuple[float, bool] | None = None) -> None:
        self.dataset = dataset
        self.graph = graph
        self._items: dict[int, Data] = {}

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, idx: int) -> Data:
        item = self._items.get(idx)
        if item is None:
            item = self.dataset[idx]
            if self.graph is not None:
                radius, fluid_only = self.graph
                receivers = item.ptype == ParticleType.FLUID if fluid_only else None
                item.edge_index, item.edge_weight = kernel_graph(
                    item.pos, radius * float(item.l0[0]), None, receivers
                )
            self._items[idx] = item
        return item.clone()


# ---------------------------------------------------------------------------------------------- stages
@dataclass
class StageTask:
    """How one network is fed and scored; :func:`stage_task` builds it."""

    kind: str

    @staticmethod
    def _adjacency(batch: Batch, radius: float, receivers: Tensor | None) -> Tensor:
        """Kernel adjacency of the batch: from the items' cached graphs, or searched now."""
        if getattr(batch, "edge_index", None) is not None:
            edge_index, w = batch.edge_index, batch.edge_weight
        else:
            edge_index, w = kernel_graph(batch.pos, radius, batch.batch, receivers)
        return kernel_adjacency(edge_index, w, batch.num_nodes)

    def predict(self, net: nn.Module, batch: Batch) -> tuple[Tensor, Tensor]:
        """``(prediction, target)``, both standardised, on the loss rows."""
        l0 = _l0(batch)
        fluid = batch.ptype == ParticleType.FLUID
        if self.kind == "advection":
            adj = self._adjacency(batch, net.radius * l0, fluid)
            gravity = batch.gravity.index_select(0, batch.batch)
            viscosity = batch.viscosity.index_select(0, batch.batch)
            out = net(batch.vel, fluid, gravity, viscosity, adj)
            return out[fluid], net.target(batch.y)
        if self.kind == "pressure":
            adj = self._adjacency(batch, net.radius * l0, None)
            ratio = batch.density / batch.n0.index_select(0, batch.batch)
            out = net(batch.vel, ratio, fluid, adj)
            return out, net.target(batch.y.unsqueeze(1)).squeeze(1)
        r = net.radius * l0
        edge_index = radius_graph(batch.pos, r, batch=batch.batch)
        rel, dist = edge_vectors(batch.pos, edge_index)
        out = net(batch.vel, rel, dist, edge_index)
        return out[fluid], batch.y / net.target.std


def fit_statistics(kind: str, net: nn.Module, items: list[Data]) -> dict[str, Any]:
    """Set ``net``'s input and target statistics from training ``items``; returns them (for the log)."""

    def mean_std(x: Tensor) -> tuple[Tensor, Tensor]:
        x = x.double()
        return x.mean(dim=0), x.std(dim=0, unbiased=False)

    fluid_vel = torch.cat([it.vel[it.ptype == ParticleType.FLUID] for it in items])
    speed = fluid_vel.norm(dim=1, keepdim=True) + 1e-8
    stats: dict[str, Any] = {}
    if kind in ("advection", "pressure"):
        net.speed.set(*mean_std(speed))
        stats["speed"] = [float(net.speed.mean), float(net.speed.std)]
    if kind == "advection":
        y = torch.cat([it.y for it in items])
        net.target.set(*mean_std(y))
        log_nu = torch.log10(torch.cat([it.viscosity for it in items]).double().clamp_min(1e-30))
        net.log_viscosity.set(*mean_std(log_nu.unsqueeze(1)))
        stats.update(
            target=[net.target.mean.tolist(), net.target.std.tolist()],
            log_viscosity=[float(net.log_viscosity.mean), float(net.log_viscosity.std)],
        )
    elif kind == "pressure":
        ratio = torch.cat([it.density / it.n0 for it in items]).unsqueeze(1)
        net.density.set(*mean_std(ratio))
        net.target.set(*mean_std(torch.cat([it.y for it in items]).unsqueeze(1)))
        stats.update(
            density=[float(net.density.mean), float(net.density.std)],
            target=[float(net.target.mean), float(net.target.std)],
        )
    else:  # collision: scales only (centring a velocity change would bias particles with no contact)
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
        stats.update(rel_vel_rms=rms_v, delta_v_rms=rms_dv)
    return stats


# ---------------------------------------------------------------------------------------------- trainer
def learning_rate(iteration: int, iterations: int, lr_start: float, lr_end: float) -> float:
    """Exponential decay from ``lr_start`` (iteration 0) to ``lr_end`` (the last iteration)."""
    frac = iteration / max(iterations - 1, 1)
    return lr_start * math.exp(frac * math.log(lr_end / lr_start))


def _fingerprint(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _truncate_csv(path: Path, step: int) -> None:
    """Drop log rows written after the checkpoint we resume from (they will be recomputed)."""
    if not path.is_file():
        return
    with path.open() as f:
        rows = list(csv.reader(f))
    keep = [rows[0]] + [r for r in rows[1:] if r and int(r[0]) <= step] if rows else []
    tmp = path.with_name(path.name + ".part")
    with tmp.open("w", newline="") as f:
        csv.writer(f).writerows(keep)
    os.replace(tmp, path)


LOSSES = ("mse", "huber")


def stage_loss(pred: Tensor, target: Tensor, loss: str, delta: float = 1.0) -> Tensor:
    """Mean loss of standardised ``pred`` vs ``target`` (same shape): ``mse``, or ``huber`` at ``delta``."""
    if loss == "mse":
        return torch.mean((pred - target) ** 2)
    if loss == "huber":
        return torch.nn.functional.huber_loss(pred, target, delta=delta)
    raise ConfigError(f"unknown train.loss {loss!r}; choose from {', '.join(LOSSES)}")


def _valid_loss(
    task: StageTask,
    net: nn.Module,
    loader: DataLoader | None,
    batches: int,
    loss: str = "mse",
    delta: float = 1.0,
) -> float:
    if loader is None:
        return float("nan")
    net.eval()
    losses = []
    with torch.no_grad():
        for k, batch in enumerate(loader):
            if k >= batches:
                break
            pred, target = task.predict(net, batch.to(next(net.parameters()).device))
            losses.append(float(stage_loss(pred, target, loss, delta)))
    net.train()
    return sum(losses) / len(losses) if losses else float("nan")


def train_stage(cfg: DictConfig, kind: str, out_dir: Path) -> dict[str, Any]:
    """Train (or resume, or skip when finished) the ``kind`` network; returns its summary."""
    tcfg = cfg.train
    options = OmegaConf.to_container(cfg.model[kind], resolve=True)
    iterations = int(tcfg.iterations[kind])
    batch_size = int(tcfg.batch_size[kind])
    loss_name = str(tcfg.get("loss", {}).get(kind, "mse"))
    delta = float(tcfg.get("huber_delta", 1.0))
    stage_loss(torch.zeros(1), torch.zeros(1), loss_name, delta)  # an unknown loss fails before any work
    data_dir = Path(str(cfg.data.out_dir))
    metadata = load_metadata(data_dir)
    materials = OmegaConf.to_container(tcfg.materials, resolve=True) if kind == "advection" else None
    identity = {
        "options": options,
        "data": {"dir": str(data_dir.resolve()), "scenes": metadata.get("splits", {}).get("train")},
        "materials": materials,
        "batch_size": batch_size,
        "lr": [float(tcfg.lr_start), float(tcfg.lr_end)],
        "iterations": iterations,
    }
    if loss_name != "mse":  # only then: checkpoints trained before the option existed keep their fingerprint
        identity["loss"] = {"name": loss_name, "delta": delta}
    fingerprint = _fingerprint(identity)
    ckpt_path, csv_path = out_dir / f"{kind}.pt", out_dir / f"{kind}_loss.csv"

    torch.manual_seed(int(cfg.seed))
    device = torch.device(str(cfg.device))
    net = build_network(kind, options)
    optimizer = torch.optim.Adam(net.parameters(), lr=float(tcfg.lr_start))
    start_step, elapsed, stats = 0, 0.0, None
    if ckpt_path.is_file():
        ckpt = read_checkpoint(ckpt_path, kind)
        meta = ckpt.get("meta", {})
        if meta.get("fingerprint") != fingerprint:
            raise ConfigError(
                f"{ckpt_path} was trained with other settings (network options, data, batch size, schedule); "
                "use another out_dir or delete it to start afresh"
            )
        net.load_state_dict(ckpt["state_dict"])
        start_step, elapsed, stats = (
            int(ckpt["step"]),
            float(meta.get("train_seconds", 0.0)),
            meta.get("stats"),
        )
        if start_step >= iterations:
            log.info("%s: already trained (%d iterations) in %s, skipped", kind, start_step, ckpt_path)
            return {"kind": kind, "step": start_step, "skipped": True, **meta}
        optimizer.load_state_dict(ckpt["optimizer"])
        torch.set_rng_state(ckpt["rng"])
        log.info("%s: resuming at iteration %d from %s", kind, start_step, ckpt_path)
        _truncate_csv(csv_path, start_step)

    base = DATASETS[kind](data_dir, split="train")
    valid_base = DATASETS[kind](data_dir, split="valid")
    settings = SolverSettings.from_config(cfg.solver)
    graph = {"advection": (float(options["radius"]), True), "pressure": (float(options["radius"]), False)}
    train_items: Any = CachedDataset(base, graph.get(kind))
    valid_items: Any = CachedDataset(valid_base, graph.get(kind))
    if kind == "advection" and materials.get("resample"):
        ranges = (materials["gravity"], materials["viscosity"], bool(materials["log_uniform"]), settings)
        train_items = ResampledMaterials(train_items, *ranges, seed=int(cfg.seed))
        valid_items = ResampledMaterials(valid_items, *ranges, seed=int(cfg.seed) + 1, fixed=True)
    if len(train_items) == 0:
        raise LagfluidError(f"no {kind} training samples in {data_dir}")
    generator = torch.Generator().manual_seed(int(cfg.seed) + start_step)
    loader = DataLoader(
        train_items, batch_size=batch_size, shuffle=True, generator=generator, drop_last=False
    )
    valid_loader = DataLoader(valid_items, batch_size=batch_size, shuffle=False) if len(valid_items) else None

    if stats is None:
        n_stat = min(len(train_items), int(tcfg.stat_samples))
        pick = torch.randperm(len(train_items), generator=torch.Generator().manual_seed(int(cfg.seed)))[
            :n_stat
        ]
        stats = fit_statistics(kind, net, [train_items[int(i)] for i in pick])
        log.info("%s statistics from %d training samples: %s", kind, n_stat, stats)
    net.to(device)
    for state in optimizer.state.values():  # a resumed optimizer's moments follow the weights
        for key, value in state.items():
            if isinstance(value, Tensor) and key != "step":
                state[key] = value.to(device)

    task = StageTask(kind)
    net.train()
    new_file = not csv_path.is_file()
    csv_file = csv_path.open("a", newline="")
    writer = csv.writer(csv_file)
    if new_file:
        writer.writerow(["iteration", "lr", "train_loss", "valid_loss", "seconds"])

    def save(step: int) -> None:
        meta = {
            "fingerprint": fingerprint,
            "identity": json.dumps(identity, default=str),
            "stats": stats,
            "train_seconds": elapsed,
            "profile": str(tcfg.name),
            "version": lagfluid.__version__,
            "data_dir": str(data_dir),
        }
        payload = network_payload(net, kind, options, step, meta)
        payload.update(optimizer=optimizer.state_dict(), rng=torch.get_rng_state())
        save_checkpoint(ckpt_path, payload)

    step, window, t_last = start_step, [], time.perf_counter()
    bar = tqdm(total=iterations, initial=start_step, desc=f"train {kind}", disable=not cfg.progress)
    try:
        while step < iterations:
            for batch in loader:
                if step >= iterations:
                    break
                batch = batch.to(device)
                lr = learning_rate(step, iterations, float(tcfg.lr_start), float(tcfg.lr_end))
                for group in optimizer.param_groups:
                    group["lr"] = lr
                pred, target = task.predict(net, batch)
                loss = stage_loss(pred, target, loss_name, delta)
                if not torch.isfinite(loss):
                    raise LagfluidError(
                        f"{kind}: loss is {float(loss)} at iteration {step}; lower train.lr_start"
                    )
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
                step += 1
                window.append(loss.item())
                bar.update(1)
                now = time.perf_counter()
                elapsed += now - t_last
                t_last = now
                last = step == iterations
                if step % int(tcfg.log_every) == 0 or last:
                    valid = (
                        _valid_loss(task, net, valid_loader, int(tcfg.valid_batches), loss_name, delta)
                        if step % int(tcfg.valid_every) == 0 or last
                        else float("nan")
                    )
                    writer.writerow(
                        [
                            step,
                            f"{lr:.6g}",
                            f"{sum(window) / len(window):.6g}",
                            f"{valid:.6g}",
                            f"{elapsed:.1f}",
                        ]
                    )
                    csv_file.flush()
                    bar.set_postfix(loss=f"{sum(window) / len(window):.4g}", valid=f"{valid:.4g}")
                    window = []
                    t_last = time.perf_counter()
                if step % int(tcfg.checkpoint_every) == 0 or last:
                    save(step)
                    t_last = time.perf_counter()
    finally:
        bar.close()
        csv_file.close()
    log.info("%s: %d iterations in %.0f s -> %s", kind, step, elapsed, ckpt_path)
    return {"kind": kind, "step": step, "train_seconds": elapsed, "checkpoint": str(ckpt_path)}


def train(cfg: DictConfig) -> list[dict[str, Any]]:
    """``task=train``: train ``cfg.stage`` (one of advection, collision, pressure, or ``all``)."""
    if cfg.model.get("format", "lagfluid") != "lagfluid" or "advection" not in cfg.model:
        raise ConfigError(f"task=train trains FGN networks: use model=fgn (got model={cfg.model.name})")
    stage = str(cfg.stage)
    kinds = list(KINDS) if stage == "all" else [stage]
    if any(k not in KINDS for k in kinds):
        raise ConfigError(f"unknown stage '{stage}'; available: {', '.join(KINDS)}, all")
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    out_dir = Path(str(cfg.out_dir))
    out_dir.mkdir(parents=True, exist_ok=True)
    return [train_stage(cfg, kind, out_dir) for kind in kinds]
