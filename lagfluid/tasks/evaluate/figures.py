"""The figures of an evaluation: errors against time (paper Fig. 4) and a pressure slice (Fig. 6).

The slice shows speed instead for a model that predicts no pressure (:func:`lagfluid.viz.colour_field`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from lagfluid.errors import RolloutError
from lagfluid.state import ParticleType
from lagfluid.tasks.evaluate.compare import Trajectory, common_frames
from lagfluid.tasks.evaluate.options import SLICE_AXES, EvaluateOptions
from lagfluid.viz import FIELDS, field_values


def plot_errors(path: Path, frames: dict[str, Any], title: str) -> Path:
    """Paper Fig. 4: every per-frame metric against time, model (and MPS where both have one)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(frames["time_s"])
    # Fixed margins rather than a layout engine: the constrained layout dominated the time per figure.
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5))
    top = 0.93 - 0.035 * title.count("\n")  # room for a stopped run's reason under the title
    fig.subplots_adjust(left=0.06, right=0.99, bottom=0.08, top=top, wspace=0.28, hspace=0.3)
    model_style, ref_style = {"color": "C0", "label": "model"}, {"color": "k", "ls": "--", "label": "MPS"}

    def both(ax: Any, key: str, ylabel: str) -> None:
        ax.plot(t, frames[key]["model"], **model_style)
        ax.plot(t, frames[key]["reference"], **ref_style)
        ax.set_ylabel(ylabel)
        ax.legend()

    def single(ax: Any, values: list[float], ylabel: str, label: str, log_scale: bool = False) -> None:
        y = np.asarray(values, dtype=float)
        ax.plot(t, y, marker="." if len(t) < 30 else None, label=label)
        ax.set_ylabel(ylabel)
        if log_scale and np.any(np.isfinite(y) & (y > 0)):
            ax.set_yscale("log")

    single(axes[0, 0], frames["chamfer_mm"], "Chamfer distance to MPS (mm)", "model -> MPS")
    both(axes[0, 1], "density_error", "density error")
    both(axes[0, 2], "velocity_divergence_per_s", "velocity divergence (1/s)")
    single(axes[1, 0], frames["position_mse_m2"], "position MSE to MPS (m$^2$)", "model", log_scale=True)
    both(axes[1, 1], "kinetic_energy_J", "fluid kinetic energy (J)")
    ax = axes[1, 2]
    single(ax, frames["advection_nmae"], "one-step error", "advection nMAE (eq. 32)", log_scale=True)
    single(ax, frames["ppe_relative_residual"], "one-step error", "PPE residual (eq. 31)", log_scale=True)
    ax.legend()
    for ax in axes.flat:
        ax.set_xlabel("time (s)")
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_pressure_slice(
    path: Path,
    model_path: Path,
    reference_path: Path,
    options: EvaluateOptions,
    title: str,
    field: str = "pressure",
) -> dict[str, Any]:
    """Paper Fig. 6: pressure on a vertical slab through the tank, model and MPS, one colour scale.

    The frame is the common stored frame nearest ``options.slice_time`` (the middle one when None); the slab
    holds the particles within ``slice_width / 2`` l0 of the plane ``slice_axis = slice_position``.
    ``field="speed"`` colours both panels by speed (a model that predicts no pressure).

    Returns:
        Where the slice is and what it shows: ``time_s``, ``axis``, ``position_m``, ``width_l0``,
        ``field``, ``particles`` per panel.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    model, ref = Trajectory.open(model_path), Trajectory.open(reference_path)
    try:
        l0 = max(model.l0, ref.l0)  # the coarser spacing: a slab that holds a layer of both rollouts
        common = common_frames(model, ref)
        if not common:
            raise RolloutError(f"{model_path} and {reference_path} store no frame at the same time")
        if options.slice_time is None:
            i_model, i_ref = common[len(common) // 2]
        else:
            i_model, i_ref = min(common, key=lambda ij: abs(model.times[ij[0]] - options.slice_time))
        time_s = model.times[i_model]
        axis = SLICE_AXES[options.slice_axis]
        across = 1 - axis  # the other horizontal axis is drawn left to right, z up
        if options.slice_position is None:
            first = model.frame(0)[0][:, axis].astype(np.float64)
            centre = first[np.argmin(np.abs(first - first.mean()))]  # a particle layer, not between two
        else:
            centre = options.slice_position
        half = 0.5 * options.slice_width * l0
        panels = []
        for name, traj, index in (("model", model, i_model), ("MPS", ref, i_ref)):
            pos, vel, p = traj.frame(index)
            inside = np.abs(pos[:, axis] - centre) < half
            panels.append((name, pos[inside], field_values(field, vel[inside], p[inside])))
        bnd = ref.boundary_position
        walls = bnd[(np.abs(bnd[:, axis] - centre) < half) & (ref.boundary_type == int(ParticleType.WALL))]
        pmax = max((float(p.max()) for _, _, p in panels if p.size), default=0.0) or 1.0
        fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharex=True, sharey=True)
        top = 0.8 - 0.05 * title.count("\n")  # the title, its stop reason and the slab's line
        fig.subplots_adjust(left=0.07, right=0.88, bottom=0.12, top=top, wspace=0.08)
        sc = None
        for ax, (name, pos, p) in zip(axes, panels, strict=True):
            ax.scatter(walls[:, across], walls[:, 2], s=6, c="0.8", marker="s", linewidths=0)
            sc = ax.scatter(pos[:, across], pos[:, 2], s=10, c=p, cmap="jet", vmin=0.0, vmax=pmax, marker="s")
            ax.set_title(f"{name}, t = {time_s:.3f} s ({len(p)} particles)")
            ax.set_aspect("equal")
            ax.set_xlabel("xyz"[across] + " (m)")
        axes[0].set_ylabel("z (m)")
        fig.colorbar(sc, cax=fig.add_axes((0.9, 0.15, 0.015, top - 0.18)), label=FIELDS[field])
        slab = f"|{options.slice_axis} - {centre:.3f} m| < {half:.3f} m"
        fig.suptitle(f"{title}\n{field} on the slab {slab}")
        fig.savefig(path, dpi=110)
        plt.close(fig)
        return {
            "time_s": time_s,
            "step": model.steps[i_model],
            "axis": options.slice_axis,
            "position_m": float(centre),
            "width_l0": options.slice_width,
            "field": field,
            "particles": {name: len(p) for name, _, p in panels},
        }
    finally:
        model.file.close()
        ref.file.close()
