"""Figures of rollouts (PNG via matplotlib's Agg backend; no display needed)."""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np


def preview(
    path: str | os.PathLike,
    frames: list[tuple[float, np.ndarray, np.ndarray]],
    boundary_position: np.ndarray,
    title: str,
    axes: tuple[int, int] = (0, 2),
) -> Path:
    """Side views of a few frames, fluid coloured by pressure on one shared colour scale.

    Args:
        path: output PNG.
        frames: ``(time, fluid_position (Nf, 3), fluid_pressure (Nf,))`` per panel.
        boundary_position: (Nb, 3) static boundary, drawn light grey.
        title: figure title.
        axes: the two coordinates shown (default x horizontal, z up).
    """
    a, b = axes
    pmax = max(float(np.nanmax(p)) if p.size else 0.0 for _, _, p in frames) or 1.0
    fig, panels = plt.subplots(
        1, len(frames), figsize=(4.2 * len(frames), 3.6), squeeze=False, layout="constrained"
    )
    # Only the boundary within the fluid's depth range (floor, end walls, obstacles): the side walls
    # parallel to the view would otherwise cover the whole picture.
    depth = 3 - a - b
    lo, hi = float(frames[0][1][:, depth].min()), float(frames[0][1][:, depth].max())
    bnd = boundary_position[(boundary_position[:, depth] >= lo) & (boundary_position[:, depth] <= hi)]
    bnd = bnd[:: max(1, len(bnd) // 20000)]
    for ax, (t, pos, p) in zip(panels[0], frames, strict=True):
        ax.scatter(bnd[:, a], bnd[:, b], s=0.3, c="0.85", rasterized=True)
        order = np.argsort(-pos[:, depth])  # draw the far side first, the near side on top
        sc = ax.scatter(pos[order, a], pos[order, b], s=0.8, c=p[order], cmap="viridis", vmin=0, vmax=pmax)
        ax.set_title(f"t = {t:.3f} s")
        ax.set_aspect("equal")
        ax.set_xlabel("xyz"[a] + " (m)")
        ax.set_ylabel("xyz"[b] + " (m)")
    fig.colorbar(sc, ax=panels[0].tolist(), label="pressure (Pa)", shrink=0.8)
    fig.suptitle(title)
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
