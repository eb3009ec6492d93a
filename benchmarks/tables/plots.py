"""The figures of the tables: paper Fig. 5 (FGN at other time steps) and the speed/accuracy trade-off."""

from __future__ import annotations

import math
import textwrap
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.tables.bench import Run
from benchmarks.tables.simulators import GROUND_TRUTH

KEY_WIDTH = 36
"""Characters of a trade-off key line (8 pt monospace in the figure's right fifth); longer names wrap."""


def plot_fig5(path: Path, runs: list[Run], verdict: str, title: str) -> None:
    """Paper Fig. 5: FGN's Chamfer distance to MPS against time, one line per dt (dotted: stopped)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    fig.subplots_adjust(left=0.1, right=0.97, bottom=0.12, top=0.88)
    shown = [r for r in runs if r.ok]
    cmap = plt.get_cmap("viridis")
    for i, run in enumerate(shown):
        frames = run.metrics["frames"]
        t = np.asarray(frames["time_s"], dtype=float)
        y = np.asarray([np.nan if v is None else v for v in frames["chamfer_mm"]], dtype=float)
        label = f"dt = {1e3 * run.info['dt']:g} ms" + ("" if run.complete else " (stopped)")
        colour = cmap(i / max(1, len(shown) - 1))
        ax.plot(
            t, y, "-" if run.complete else ":", color=colour, label=label, marker="." if len(t) < 30 else None
        )
    ax.set_xlabel("time (s)")
    ax.set_ylabel("Chamfer distance to MPS (mm)")
    ax.set_title(f"{title}\n{textwrap.fill(verdict, 90)}", fontsize=10)  # a stop reason can be long
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# The colours of the simulators in the trade-off plot, in the order their rows come (the ground truth is
# black; C3, red, is the Pareto front's).
# matplotlib's cycle without red (the Pareto front) and black (the ground truth), then darker hues: 14 apart
_PALETTE = ("C0", "C1", "C2", "C4", "C5", "C6", "C8", "C9", "C7", "#6a3d9a", "#01665e", "#b15928", "#c51b7d",
            "#1a237e")  # fmt: skip


def simulator_colours(rows: list[dict[str, Any]]) -> dict[str, str]:
    """One colour per simulator key (``simulator_key``), in the order of the rows; the ground truth black.

    A simulator's variants (another dt, PPE tolerance or spacing) are its rows too and share its colour.
    """
    keys = [k for k in dict.fromkeys(r["simulator_key"] for r in rows) if k != GROUND_TRUTH]
    colours = {k: _PALETTE[i % len(_PALETTE)] for i, k in enumerate(keys)}
    return {GROUND_TRUTH: "k", **colours}


def plot_tradeoff(path: Path, rows: list[dict[str, Any]], title: str) -> None:
    """Wall seconds per simulated second (log x) against the Chamfer distance and the density error.

    Points are numbered (the key beside the panels names them), the Pareto front is a staircase: at any
    cost on the x axis, the front's height is the smallest error a run at most that expensive achieved.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    done = [r for r in rows if r["status"] == "complete" and math.isfinite(r["s_per_simulated_s"])]
    done.sort(key=lambda r: r["s_per_simulated_s"])
    stopped_lines = len(textwrap.wrap(", ".join(r["simulator"] for r in rows if r not in done), 180))
    fig, axes = plt.subplots(1, 2, figsize=(15, 6.2 + 0.15 * stopped_lines))
    axes_top = 0.86 - 0.02 * stopped_lines  # room for the title's list of rows not shown
    fig.subplots_adjust(left=0.05, right=0.8, bottom=0.1, top=axes_top, wspace=0.2)
    panels = (
        ("chamfer_mean_mm", "Chamfer distance to the reference MPS, mean over frames (mm)", "symlog"),
        ("density_error_mean", "density error, mean over frames", "log"),
    )
    x_max = max((r["s_per_simulated_s"] for r in done), default=1.0)
    colours = simulator_colours(rows)
    for ax, (metric, ylabel, yscale) in zip(axes, panels, strict=True):
        for number, r in enumerate(done, start=1):
            colour = colours[r["simulator_key"]]
            hollow = math.isfinite(r["chamfer_t0_mm"]) and r["chamfer_t0_mm"] > 0
            x, y = r["s_per_simulated_s"], r[metric]
            ax.scatter(x, y, s=36, facecolors="none" if hollow else colour, edgecolors=colour, zorder=3)
            ax.annotate(str(number), (x, y), fontsize=8, xytext=(4, 3), textcoords="offset points")
        front = [r for r in done if r[f"pareto_{metric}"]]
        if front:
            # a staircase carried on to the right: no budget beyond the last point buys more accuracy
            xs = [r["s_per_simulated_s"] for r in front] + [1.3 * x_max]
            ys = [r[metric] for r in front] + [front[-1][metric]]
            ax.step(xs, ys, where="post", color="C3", lw=1.5, label="Pareto front", zorder=2)
            ax.legend(loc="upper right", fontsize=8)
        ax.set_xscale("log")
        values = [r[metric] for r in done if math.isfinite(r[metric])]
        positive = [v for v in values if v > 0]
        if yscale == "symlog":  # MPS against itself is exactly 0: linear below the smallest positive error
            ax.set_yscale("symlog", linthresh=min(positive, default=1e-3))
            ax.set_ylim(0.0, 2.0 * max(values, default=1.0))
        elif positive:
            ax.set_yscale("log")
            ax.set_ylim(0.7 * min(positive), 1.5 * max(positive))
        ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("wall seconds per simulated second (log)")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3, which="both")
    # the key, each entry in its simulator's colour (one text per entry: a text has one colour), long
    # names wrapped onto indented lines so that they stay inside the figure
    line = 8 * 1.35 / 72 / fig.get_figheight()  # 8 pt lines in figure coordinates
    top = axes_top
    for i, r in enumerate(done, start=1):
        wrapped = textwrap.wrap(r["simulator"], KEY_WIDTH)
        text = "\n".join([f"{i:2d}  {wrapped[0]}", *(f"    {part}" for part in wrapped[1:])])
        colour = colours[r["simulator_key"]]
        fig.text(0.815, top, text, fontsize=8, va="top", family="monospace", color=colour)
        top -= line * len(wrapped)
    sub = "colour: one per simulator as in the key (black: the ground truth), its variants (dt, tolerance, "
    sub += "spacing) share it; hollow: coarser spacing (its Chamfer includes the lattice offset at t = 0)"
    stopped = [r["simulator"] for r in rows if r not in done]
    if stopped:
        sub += "\n" + "\n".join(textwrap.wrap("not shown (stopped or failed): " + ", ".join(stopped), 180))
    fig.suptitle(f"{title}\n{sub}", fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)
