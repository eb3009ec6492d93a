"""The PPE residual (paper eq. 31) as an auxiliary training term of FGN's pressure net.

With ``train.ppe_weight = w > 0`` each pressure sample also carries the MPS pressure Poisson system
of its step, ``A p = b``, rebuilt by the solver's own assembly (:func:`lagfluid.physics.mps.pressure_system`)
from the full scene at ``(x**, v**)`` with the generating run's settings and constants (the scene file's
``config``, ``n0``, ``n0_lap``, ``lambda``). The loss then also asks the predicted pressure to satisfy it:
:func:`ppe_residual_rows` times ``sqrt(w)`` join the pressure rows, target 0, in the pressure net's loss
(``train.loss.pressure``). Under ``mse`` that adds ``w ||A p - b||^2 / ||b||^2`` per sample (averaged with
the data term over both sets of rows); under ``huber`` (``train=cpu``) rows beyond ``huber_delta`` count
linearly, as the pressure rows do. The label
solves the same system to the solver's tolerance; :class:`WithPPESystem` refuses a sample whose label does
not (data made with other settings than the file says).

Why a physics term: the one-step data loss weighs every pressure error alike, while the scheme only feels
``grad p`` and the PPE is the relation between ``p`` and the velocity field the correction has to fix.
Measured in ``benchmarks/results/fgn_recipe.md``.
"""

from __future__ import annotations

import logging
from typing import Any

import torch
from omegaconf import OmegaConf
from torch import Tensor
from torch_geometric.data import Batch, Data
from torch_geometric.utils import scatter

from lagfluid.errors import LagfluidError
from lagfluid.physics.mps import pressure_system
from lagfluid.physics.reference import exact_context
from lagfluid.physics.settings import MPSConstants, SolverSettings

__all__ = ["BORDERLINE", "LABEL_TOLERANCE", "WithPPESystem", "ppe_residual_rows"]

log = logging.getLogger(__name__)

LABEL_TOLERANCE = 1e-2
"""Largest relative PPE residual of a stored label (float32 storage and the solver's own tolerance)."""

BORDERLINE = 5
"""Unknowns that may differ from the stored ones (particles at the free-surface threshold to rounding):
``max(BORDERLINE, 0.1 % of the nodes)``; more, and the sample is refused. Such a sample gets no PPE term."""


class WithPPESystem:
    """Pressure samples, each with its step's PPE on its nodes (``ppe_index``, ``ppe_value``, ``ppe_b``).

    ``ppe_index`` (2, E) int32 are (row, column) node indices of the item (PyG offsets them per sample in a
    batch, as any ``*index`` attribute), ``ppe_value`` (E,) the matrix entries ``A = -(1/rho) L``, ``ppe_b``
    (M,) the source of every node and ``ppe_label_residual`` (1,) the stored label's relative residual.
    The boundary is pruned beyond the reach of the unknowns' rows before the assembly (exact: the rebuilt
    unknowns are checked against the stored ones).

    Args:
        samples: :class:`~lagfluid.data.datasets.PressureSamples` (their :meth:`scene_state`).

    Raises:
        LagfluidError: a sample's PPE unknowns differ from its stored nodes, or its label does not solve the
            rebuilt system (residual above :data:`LABEL_TOLERANCE`): the file's settings are not the ones
            that made it.
    """

    def __init__(self, samples: Any) -> None:
        self.samples = samples
        self._settings: dict[str, tuple[SolverSettings, torch.dtype]] = {}

    def _solver_settings(self, config: str) -> tuple[SolverSettings, torch.dtype]:
        """The generating run's solver settings and dtype (parsed once per distinct config)."""
        found = self._settings.get(config)
        if found is None:
            cfg = OmegaConf.create(config)
            found = SolverSettings.from_config(cfg.solver), getattr(torch, str(cfg.get("dtype", "float32")))
            self._settings[config] = found
        return found

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, idx: int) -> Data:
        item = self.samples[idx]
        attrs = self.samples.scene_attributes(idx)
        settings, dtype = self._solver_settings(str(attrs["config"]))
        # Boundary beyond the reach of the unknowns' rows (their Laplacian neighbours and those neighbours'
        # number density) changes nothing; pruning it makes the assembly ~10x cheaper on data=cpu's tanks.
        reach = 2 * (settings.re_laplacian + settings.re_density) + 1.0
        # In the generating run's dtype: a particle with n at beta n0 to float32 rounding must fall on the
        # same side of the free-surface test as it did for the solver.
        state, rows = self.samples.scene_state(idx, boundary_radius=reach * float(item.l0[0]), dtype=dtype)
        constants = MPSConstants(float(attrs["n0"]), float(attrs["n0_lap"]), float(attrs["lambda"]))
        built = pressure_system(exact_context(state, settings, constants), state.pos, state.vel)
        system = built.system
        unknowns = rows[system.index.cpu()]
        if not torch.equal(unknowns, item.particle_id):
            differ = int(torch.isin(unknowns, item.particle_id, invert=True).sum())
            differ += int(torch.isin(item.particle_id, unknowns, invert=True).sum())
            if differ == 0 or differ > max(BORDERLINE, 1e-3 * item.particle_id.numel()):
                raise LagfluidError(
                    f"pressure sample {idx}: the rebuilt PPE has {system.num_unknowns} unknowns, the sample "
                    f"{item.particle_id.numel()} nodes ({differ} differ); was it generated with other "
                    "solver settings?"
                )
            # a particle at the free-surface threshold to rounding: no PPE term for this sample
            log.warning("pressure sample %d: %d unknowns differ at the threshold, no PPE term", idx, differ)
            return self._without_system(item)
        crow, col = system.matrix.crow_indices(), system.matrix.col_indices().long()
        row = torch.repeat_interleave(torch.arange(system.num_unknowns), torch.diff(crow))
        value, b = system.matrix.values().double(), system.gather(built.source).double()
        label = item.y.double()
        residual = torch.zeros_like(b).index_add_(0, row, value * label[col]) - b
        rel = float(residual.norm() / b.norm().clamp_min(1e-30))
        if rel > LABEL_TOLERANCE:
            raise LagfluidError(
                f"pressure sample {idx}: its label leaves a relative PPE residual of {rel:.3g} in the "
                f"rebuilt system (> {LABEL_TOLERANCE}): the scene file's settings did not make it"
            )
        item.ppe_index = torch.stack([row, col]).int()  # int32: ~600k entries per data=cpu sample, cached
        item.ppe_value = value.float()
        item.ppe_b = b.float()
        item.ppe_label_residual = torch.tensor([rel])
        return item

    @staticmethod
    def _without_system(item: Data) -> Data:
        """The sample with an empty system (its residual rows are 0: it adds nothing to the PPE term)."""
        item.ppe_index = torch.zeros(2, 0, dtype=torch.int32)
        item.ppe_value = torch.zeros(0)
        item.ppe_b = torch.zeros(item.num_nodes)
        item.ppe_label_residual = torch.tensor([float("nan")])
        return item


def ppe_residual_rows(pressure: Tensor, batch: Batch) -> Tensor:
    """Rows whose mean square over a sample is its squared relative PPE residual ``||A p - b||^2 / ||b||^2``.

    Args:
        pressure: (M,) predicted pressure (Pa) of the batch's nodes.
        batch: a batch of :class:`WithPPESystem` items (``ppe_index``, ``ppe_value``, ``ppe_b``, ``batch``).

    Returns:
        (M,) ``r_i sqrt(M_g) / ||b||_g`` with ``r = A p - b`` and ``g`` the node's sample.
    """
    row, col = batch.ppe_index.long()
    r = torch.zeros_like(pressure).index_add(0, row, batch.ppe_value * pressure[col]) - batch.ppe_b
    graph = batch.batch
    b_sq = scatter(batch.ppe_b.square(), graph, dim=0, dim_size=batch.num_graphs, reduce="sum")
    count = scatter(torch.ones_like(pressure), graph, dim=0, dim_size=batch.num_graphs, reduce="sum")
    return r * (count / b_sq.clamp_min(1e-30)).sqrt()[graph]
