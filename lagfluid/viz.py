"""Figures of rollouts (PNG via matplotlib's Agg backend; no display needed).

Matplotlib is loaded by the functions that draw, not on import: a task picks the field and title of its
figures (:func:`colour_field`, :func:`stopped_title`) before it has anything to draw.
"""

from __future__ import annotations

import os
import textwrap
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from matplotlib.figure import Figure

# What a picture can colour the fluid by, and its colour bar's label.
FIELDS = {"pressure": "pressure (Pa)", "speed": "speed (m/s)"}


def colour_field(simulator: object) -> str:
    """What pictures of ``simulator``'s rollouts colour the fluid by: ``pressure``, or ``speed`` without one.

    A simulator that predicts no pressure says so with ``predicts_pressure = False`` (GNS, CConv): its
    states carry zeros (or, during a warm start, the solver's pressure), which a pressure colour bar would
    show as a fluid at 0 Pa. Without the attribute a simulator is taken to predict pressure (MPS, FGN).
    """
    return "pressure" if getattr(simulator, "predicts_pressure", True) else "speed"


def field_values(field: str, velocity: np.ndarray, pressure: np.ndarray) -> np.ndarray:
    """What a picture colours by (N,): ``pressure`` (N,), or the speed ``|v|`` of ``velocity`` (N, 3)."""
    if field not in FIELDS:
        raise ValueError(f"a picture colours by one of {', '.join(FIELDS)}, not {field!r}")
    return pressure if field == "pressure" else np.linalg.norm(velocity, axis=1)


def stopped_title(title: str, stop_reason: str, by_guard: bool) -> str:
    """``title`` and a line saying why the run stopped early (``title`` alone when ``stop_reason`` is "").

    Args:
        title: the figure's title, e.g. ``gns on dam_small``.
        stop_reason: why the run ended before its last step ("" for a complete run); the guard's reasons
            start with the step, ``step 57: Courant number ...``.
        by_guard: the rollout guard stopped it (else an interruption or an error).
    """
    if not stop_reason:
        return title
    line = f"stopped by the guard: {stop_reason}" if by_guard else f"stopped: {stop_reason}"
    return "\n".join([title, *textwrap.wrap(line, 110)])


def preview_figure(
    frames: list[tuple[float, np.ndarray, np.ndarray]],
    boundary_position: np.ndarray,
    title: str,
    field: str = "pressure",
    axes: tuple[int, int] = (0, 2),
) -> Figure:
    """Side views of a few frames, fluid coloured by ``field`` on one shared colour scale from 0.

    Args:
        frames: ``(time, fluid_position (Nf, 3), values (Nf,))`` per panel, ``values`` the ``field``.
        boundary_position: (Nb, 3) static boundary, drawn light grey.
        title: figure title.
        field: what ``values`` are (a key of :data:`FIELDS`): names the colour bar.
        axes: the two coordinates shown (default x horizontal, z up).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    a, b = axes
    vmax = max(float(np.nanmax(v)) if v.size else 0.0 for _, _, v in frames) or 1.0
    fig, panels = plt.subplots(
        1, len(frames), figsize=(4.2 * len(frames), 3.6), squeeze=False, layout="constrained"
    )
    # Only the boundary within the fluid's depth range (floor, end walls, obstacles): the side walls
    # parallel to the view would otherwise cover the whole picture.
    depth = 3 - a - b
    lo, hi = float(frames[0][1][:, depth].min()), float(frames[0][1][:, depth].max())
    bnd = boundary_position[(boundary_position[:, depth] >= lo) & (boundary_position[:, depth] <= hi)]
    bnd = bnd[:: max(1, len(bnd) // 20000)]
    for ax, (t, pos, v) in zip(panels[0], frames, strict=True):
        ax.scatter(bnd[:, a], bnd[:, b], s=0.3, c="0.85", rasterized=True)
        order = np.argsort(-pos[:, depth])  # draw the far side first, the near side on top
        sc = ax.scatter(pos[order, a], pos[order, b], s=0.8, c=v[order], cmap="viridis", vmin=0, vmax=vmax)
        ax.set_title(f"t = {t:.3f} s")
        ax.set_aspect("equal")
        ax.set_xlabel("xyz"[a] + " (m)")
        ax.set_ylabel("xyz"[b] + " (m)")
    fig.colorbar(sc, ax=panels[0].tolist(), label=FIELDS[field], shrink=0.8)
    fig.suptitle(title)
    return fig


def preview(
    path: str | os.PathLike,
    frames: list[tuple[float, np.ndarray, np.ndarray]],
    boundary_position: np.ndarray,
    title: str,
    field: str = "pressure",
    axes: tuple[int, int] = (0, 2),
) -> Path:
    """Write :func:`preview_figure` of these frames to the PNG ``path``."""
    import matplotlib.pyplot as plt

    fig = preview_figure(frames, boundary_position, title, field, axes)
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
