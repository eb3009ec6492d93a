"""Frame-by-frame comparison of a model's rollout file with the reference's (:mod:`lagfluid.metrics`)."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch

from lagfluid.data.store import open_lagfluid_file
from lagfluid.metrics import (
    FieldMetrics,
    chamfer_distance,
    field_metrics,
    kinetic_energy,
    kinetic_energy_error,
    mse_horizons,
    position_mse,
    summarize,
)
from lagfluid.physics.settings import SolverSettings, lattice_constants
from lagfluid.state import ParticleType

log = logging.getLogger(__name__)


@dataclass
class Trajectory:
    """An open rollout file, read frame by frame (a long run need not fit in memory)."""

    file: h5py.File
    steps: list[int]
    times: list[float]
    boundary_position: np.ndarray
    boundary_type: np.ndarray
    attrs: dict[str, Any]

    @classmethod
    def open(cls, path: Path) -> Trajectory:
        """Open the rollout file at ``path`` (closed by the caller through ``.file``)."""
        f = open_lagfluid_file(path)
        g = f["00000"]
        dt = float(g.attrs["dt"])
        times = [float(t) for t in g["time"][()]]
        return cls(
            f,
            [round(t / dt) for t in times],
            times,
            g["boundary_position"][()],
            g["boundary_type"][()],
            dict(g.attrs),
        )

    @property
    def l0(self) -> float:
        """Particle spacing (m)."""
        return float(self.attrs["l0"])

    @property
    def surface_offset(self) -> float:
        """Where the boundary surface lies in the built scenes' coordinates: half a spacing inside (m)."""
        return 0.5 * self.l0

    def frame(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Fluid position (Nf, 3), velocity (Nf, 3) and pressure (Nf,) of stored frame ``index``."""
        g = self.file["00000"]
        return g["position"][index], g["velocity"][index], g["pressure"][index]


def _field(
    traj: Trajectory, pos: np.ndarray, vel: np.ndarray, settings: SolverSettings, n0: float
) -> FieldMetrics:
    """Density error and divergence of a stored frame (fluid + static boundary), in float64."""
    nf = pos.shape[0]
    all_pos = torch.from_numpy(np.concatenate([pos, traj.boundary_position]).astype(np.float64))
    all_vel = torch.zeros_like(all_pos)
    all_vel[:nf] = torch.from_numpy(vel.astype(np.float64))
    ptype = torch.cat(
        [torch.full((nf,), int(ParticleType.FLUID)), torch.from_numpy(traj.boundary_type.astype(np.int64))]
    )
    l0, dim = float(traj.attrs["l0"]), int(traj.attrs.get("dim", 3))
    return field_metrics(
        all_pos,
        all_vel,
        ptype,
        n0,
        settings.re_density * l0,
        settings.re_gradient * l0,
        settings.surface_beta,
        dim,
        settings.neighbor_backend,
    )


def common_frames(model: Trajectory, ref: Trajectory) -> list[tuple[int, int]]:
    """``(model frame, reference frame)`` index pairs stored at the same time (the model's dt may differ).

    A model frame matches when its time lies on the reference's step grid and the reference stored that
    step. The tolerance is 1e-6 of a reference step or of the time, whichever is larger: a model's dt read
    from float32 (0.016000001 s) drifts off the grid by 1e-9 s a frame, far less than a step.
    """
    dt_ref = float(ref.attrs["dt"])
    ref_index = {s: i for i, s in enumerate(ref.steps)}
    pairs = []
    for i, t in enumerate(model.times):
        s = round(t / dt_ref)
        if abs(t - s * dt_ref) <= 1e-6 * max(dt_ref, abs(t)) and s in ref_index:
            pairs.append((i, ref_index[s]))
    return pairs


def compare(model_path: Path, reference_path: Path, settings: SolverSettings) -> dict[str, Any]:
    """Per-frame metrics of the model's rollout against the reference's, at the times both stored.

    The model may run at another dt or particle spacing than the reference (``evaluate.reference``): frames
    are matched by time, each rollout's density error uses its own spacing's ``n0``, its kinetic energy its
    own particle mass, and the Chamfer distance is taken in the boundary surface's frame (see the module
    doc); the position MSE is NaN when the particle counts differ (no correspondence).

    Returns:
        ``{"step", "time_s", "chamfer_mm", "position_mse_m2", "kinetic_energy_error_rel_peak"}`` lists
        (the last: ``|E_model(t) - E_ref(t)| / max_s E_ref(s)``,
        :func:`~lagfluid.metrics.kinetic_energy_error`) and ``density_error``,
        ``velocity_divergence_per_s``, ``kinetic_energy_J`` as ``{"model", "reference"}``.
    """
    model, ref = Trajectory.open(model_path), Trajectory.open(reference_path)
    try:
        dim = int(ref.attrs.get("dim", 3))
        n0 = {id(t): lattice_constants(t.l0, settings, dim).n0 for t in (model, ref)}
        mass = {id(t): float(t.attrs["density"]) * t.l0**dim for t in (model, ref)}
        # zero when the spacings agree: then positions are compared exactly as stored
        shift = np.float32(model.surface_offset - ref.surface_offset)
        out: dict[str, Any] = {k: [] for k in ("step", "time_s", "chamfer_mm", "position_mse_m2")}
        pairs = {k: {"model": [], "reference": []} for k in ("density_error", "velocity_divergence_per_s")}
        pairs["kinetic_energy_J"] = {"model": [], "reference": []}
        common = common_frames(model, ref)
        if len(model.times) > 1 and len(common) <= 1:  # a mean over frame 0 alone reads as a perfect model
            log.warning(
                "%s: %d stored frames, but %d at a time %s stored: the metrics are of that frame alone; "
                "choose write_every so that the frames meet the reference's",
                model_path,
                len(model.times),
                len(common),
                reference_path,
            )
        for i, j in common:
            mp, mv, _ = model.frame(i)
            rp, rv, _ = ref.frame(j)
            out["step"].append(model.steps[i])
            out["time_s"].append(model.times[i])
            out["chamfer_mm"].append(1e3 * chamfer_distance(mp - shift if shift else mp, rp))
            out["position_mse_m2"].append(position_mse(mp, rp) if mp.shape == rp.shape else math.nan)
            e_model, e_ref = kinetic_energy(mv, mass[id(model)]), kinetic_energy(rv, mass[id(ref)])
            pairs["kinetic_energy_J"]["model"].append(e_model)
            pairs["kinetic_energy_J"]["reference"].append(e_ref)
            for who, traj, p, v in (("model", model, mp, mv), ("reference", ref, rp, rv)):
                m = _field(traj, p, v, settings, n0[id(traj)])
                pairs["density_error"][who].append(m.density_error)
                pairs["velocity_divergence_per_s"][who].append(m.velocity_divergence)
        energy = pairs["kinetic_energy_J"]
        out["kinetic_energy_error_rel_peak"] = kinetic_energy_error(energy["model"], energy["reference"])
        return {**out, **pairs}
    finally:
        model.file.close()
        ref.file.close()


def summaries(frames: dict[str, Any], horizons: tuple[int, ...]) -> dict[str, Any]:
    """Mean and max of every per-frame metric over the run, and the position MSE at ``horizons``."""
    out: dict[str, Any] = {}
    for key, value in frames.items():
        if key in ("step", "time_s"):
            continue
        if isinstance(value, dict):
            out[key] = {who: summarize(v, finite_only=True) for who, v in value.items()}
        else:
            out[key] = summarize(value, finite_only=True)
    out["position_mse_horizons_m2"] = mse_horizons(frames["step"], frames["position_mse_m2"], horizons)
    return out
