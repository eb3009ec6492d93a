"""A rollout as an animation (GIF, or MP4 where ffmpeg exists): a side view (x-z) of the fluid over its walls.

:func:`animate` draws one panel per rollout, frames matched by time (the first rollout's stored times that
every other one stored too), at most ``max_frames`` of them evenly spread; the fluid is coloured by pressure
or speed on one colour scale for the whole animation (0 to the 99th percentile over the frames drawn), so
colours compare across frames and panels. Matplotlib's writers do the encoding (Pillow for GIF, ffmpeg for
MP4): no video code of our own.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lagfluid.data.store import open_lagfluid_file, read_array
from lagfluid.errors import ConfigError
from lagfluid.viz import FIELDS

COLORS = FIELDS  # what animation.color may name, and its colour bar's label


def _frame_indices(times: Sequence[np.ndarray], max_frames: int) -> list[list[int]]:
    """Per rollout, the indices of the frames drawn: times of the first that all stored (to 1e-9 s)."""
    common = []
    for k, t in enumerate(times[0]):
        found = [int(np.argmin(np.abs(other - t))) for other in times[1:]]
        if all(abs(other[i] - t) <= 1e-9 for other, i in zip(times[1:], found, strict=True)):
            common.append([k, *found])
    if not common:
        raise ConfigError("the rollouts share no stored time: nothing to draw side by side")
    keep = np.unique(np.linspace(0, len(common) - 1, min(max_frames, len(common))).round().astype(int))
    return [common[i] for i in keep]


def _walls_in_mid_plane(g) -> np.ndarray:
    """The wall particles (M, 3) of the lattice plane y = const nearest the fluid's middle.

    The tank's cross-section (floor and end walls), not the side walls that would cover the whole view.
    """
    walls = read_array(g, "boundary_position")[read_array(g, "boundary_type") == 2]
    if not len(walls):
        return walls
    fluid = read_array(g, "position", 0)
    middle = float(np.median(fluid[:, 1])) if len(fluid) else float(walls[:, 1].mean())
    nearest = walls[np.argmin(np.abs(walls[:, 1] - middle)), 1]
    return walls[np.abs(walls[:, 1] - nearest) < 0.25 * float(g.attrs.get("l0", 0.05))]


def animate(
    rollouts: Sequence[Path],
    out: Path,
    color: str = "pressure",
    fps: int = 20,
    max_frames: int = 100,
    titles: Sequence[str] | None = None,
) -> Path:
    """Write ``out`` (``.gif`` or ``.mp4``): the rollout files side by side, frames matched by time.

    Args:
        rollouts: rollout files (one panel each).
        out: the animation file; its suffix picks the writer.
        color: ``pressure`` or ``speed``.
        fps: frames per second of the animation.
        max_frames: at most this many frames, evenly spread over the common times.
        titles: one per panel (default: each file's model and scene).

    Raises:
        ConfigError: an unknown colour, fps or suffix, ``.mp4`` without ffmpeg, or no common time.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import animation

    if color not in COLORS:
        raise ConfigError(f"animation.color must be one of {', '.join(COLORS)}, got {color!r}")
    if fps < 1 or max_frames < 1:
        raise ConfigError(f"animation.fps and animation.max_frames must be >= 1, got {fps} and {max_frames}")
    if out.suffix == ".gif":
        writer: animation.AbstractMovieWriter = animation.PillowWriter(fps=fps)
    elif out.suffix == ".mp4":
        if not animation.writers.is_available("ffmpeg"):
            raise ConfigError(
                "format=mp4 needs ffmpeg on the PATH (not found here); format=gif works without it"
            )
        writer = animation.FFMpegWriter(fps=fps)
    else:
        raise ConfigError(f"an animation is a .gif or .mp4 file, got {out.name}")

    files = [open_lagfluid_file(path) for path in rollouts]
    try:
        groups = [f["00000"] for f in files]
        times = [read_array(g, "time") for g in groups]
        frames = _frame_indices(times, max_frames)
        titles = list(
            titles or [f"{g.attrs.get('model', '?')} on {g.attrs.get('scene', '?')}" for g in groups]
        )

        def field(g, k: int) -> np.ndarray:
            if color == "pressure":
                return read_array(g, "pressure", k)
            return np.linalg.norm(read_array(g, "velocity", k), axis=1)

        drawn = np.concatenate([field(g, row[i]) for row in frames for i, g in enumerate(groups)])
        high = float(np.percentile(drawn, 99)) if drawn.size else 1.0
        high = high if high > 0 else 1.0
        fig, axes = plt.subplots(1, len(groups), figsize=(5.2 * len(groups), 4.2), squeeze=False)
        dots = []
        for ax, g, title, first in zip(axes[0], groups, titles, frames[0], strict=True):
            walls = _walls_in_mid_plane(g)
            ax.scatter(walls[:, 0], walls[:, 2], s=2, c="0.55", linewidths=0)
            pos = read_array(g, "position", first)
            dot = ax.scatter(pos[:, 0], pos[:, 2], s=3, c=field(g, first), cmap="viridis", vmin=0, vmax=high)
            dots.append(dot)
            everything = np.concatenate([walls[:, [0, 2]], pos[:, [0, 2]]]) if len(walls) else pos[:, [0, 2]]
            low, top = everything.min(axis=0), everything.max(axis=0)
            ax.set_xlim(low[0] - 0.05, top[0] + 0.05)
            ax.set_ylim(low[1] - 0.05, max(top[1], low[1] + 0.2) + 0.05)
            ax.set_aspect("equal")
            ax.set_xlabel("x (m)")
            ax.set_ylabel("z (m)")
            ax.set_title(title, fontsize=10)
        fig.colorbar(dots[-1], ax=axes[0].tolist(), label=COLORS[color], shrink=0.8)
        clock = fig.suptitle("")

        def draw(row: list[int]) -> list:
            for dot, g, k in zip(dots, groups, row, strict=True):
                pos = read_array(g, "position", k)
                dot.set_offsets(pos[:, [0, 2]])
                dot.set_array(field(g, k))
            clock.set_text(f"t = {float(times[0][row[0]]):.3f} s")
            return [*dots, clock]

        movie = animation.FuncAnimation(fig, draw, frames=frames, blit=False)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(f"{out.stem}.part{out.suffix}")
        try:
            movie.save(tmp, writer=writer)
            tmp.replace(out)
        finally:
            tmp.unlink(missing_ok=True)  # a failed encoding leaves no half file
    finally:
        plt.close("all")
        for f in files:
            f.close()
    return out


def side_by_side(
    model: Path, reference: Path, out: Path, color: str = "pressure", max_frames: int = 60
) -> Path:
    """``task=evaluate``'s animation: the model beside the MPS reference, frames matched by time."""
    return animate([model, reference], out, color, max_frames=max_frames)
