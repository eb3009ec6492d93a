"""How much of the MPS training targets is a smooth field, and how much is particle-level noise.

Every learned model of the zoo is fitted to MPS's motion: CConv to the positions of the next solver steps
(2 ms), GNS to the acceleration between stored frames (8 ms apart), FGN's stages to the solver's own
intermediates. MPS's pressure is known to oscillate from particle to particle and step to step; a network
that sees a neighbourhood (a smooth function of it) can only learn the part of the target that its
neighbourhood shares. This splits the fluid's acceleration ``a`` of a window into

* the **smooth part**: the mean of ``a`` over the particle's neighbourhood (every fluid particle within
  ``--radius`` l0, itself included), and
* the **residual**: ``a`` minus that mean,

and reports the RMS of each over the fluid, at the solver step (``(x_{n+1} - x_n) / dt - v_n`` over dt, from
the ``next_steps`` a dataset stores) and at the frame spacing (``(x_{t+1} - 2 x_t + x_{t-1}) / dt_f^2``),
grouped by the solver step the window starts at. A residual several times the smooth part is a target that
no smooth model fits: its loss stalls near the trivial predictor's.

Usage::

    python -m benchmarks.studies.acceleration_noise --data data/cpu [--every 5]

Writes ``benchmarks/results/acceleration_noise.{md,csv}`` with provenance.
"""

from __future__ import annotations

import argparse
import os
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from benchmarks.provenance import provenance, write_results
from lagfluid.data.datasets import StepWindows, TrajectoryWindows, load_metadata
from lagfluid.state import ParticleType

RESULTS = Path(__file__).resolve().parents[1] / "results"  # benchmarks/results, where its results are cited
PHASES = ((0, 40), (40, 160), (160, 10**9))
"""Solver-step ranges of the window starts: the start (at rest or falling), the first impact, the rest."""


def smooth_and_residual(pos: np.ndarray, acc: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The neighbourhood mean (N, 3) of ``acc`` (N, 3) and the residual ``acc - mean``.

    The neighbourhood of a point of ``pos`` (N, 3) is every point within ``radius``, itself included.
    """
    pairs = cKDTree(pos).query_pairs(radius, output_type="ndarray")
    n = pos.shape[0]
    rows = np.concatenate([pairs[:, 0], pairs[:, 1], np.arange(n)])
    cols = np.concatenate([pairs[:, 1], pairs[:, 0], np.arange(n)])
    adjacency = sparse.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n))
    mean = (adjacency @ acc) / np.asarray(adjacency.sum(axis=1))
    return mean, acc - mean


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt((values**2).sum(axis=1).mean()))


def _phase(step: int) -> str:
    for lo, hi in PHASES:
        if lo <= step < hi:
            return f"{lo}-{hi - 1}" if hi < 10**9 else f">= {lo}"
    raise ValueError(step)


def measure(data: str, every: int, radius_l0: float) -> list[dict[str, object]]:
    """Rows per (spacing, phase): RMS of the acceleration, its smooth part and its residual (m/s^2)."""
    meta = load_metadata(data)
    l0, dt = float(meta["l0"]), float(meta["dt"])
    radius = radius_l0 * l0
    sums: dict[tuple[str, str], list[tuple[float, float, float]]] = defaultdict(list)
    steps = StepWindows(data, "train", steps=1) if int(meta.get("next_steps", 0)) >= 1 else None
    frames = TrajectoryWindows(data, "train", history=1)
    if steps is not None:
        for i in range(0, len(steps), every):
            item = steps[i]
            fluid = (item.ptype == ParticleType.FLUID).numpy()
            x = item.pos.numpy()[fluid].astype(np.float64)
            v = item.vel.numpy()[fluid].astype(np.float64)
            acc = ((item.y[:, 0].numpy().astype(np.float64) - x) / dt - v) / dt
            mean, resid = smooth_and_residual(x, acc, radius)
            sums[(f"solver step ({dt * 1e3:g} ms)", _phase(int(item.step)))].append(
                (_rms(acc), _rms(mean), _rms(resid))
            )
    for i in range(0, len(frames), every):
        item = frames[i]
        fluid = (item.ptype == ParticleType.FLUID).numpy()
        x = item.pos.numpy()[fluid].astype(np.float64)
        before = item.history[:, -1].numpy().astype(np.float64)
        after = item.y.numpy().astype(np.float64)
        frame_dt = float(item.frame_dt)
        acc = (after - 2 * x + before) / frame_dt**2
        mean, resid = smooth_and_residual(x, acc, radius)
        sums[(f"frame ({frame_dt * 1e3:g} ms)", _phase(int(item.step)))].append(
            (_rms(acc), _rms(mean), _rms(resid))
        )
    rows = []
    for (spacing, phase), values in sorted(sums.items()):
        arr = np.array(values)
        med = np.median(arr, axis=0)
        rows.append(
            {
                "spacing": spacing,
                "window start (solver steps)": phase,
                "windows": len(values),
                "acceleration rms": round(float(med[0]), 2),
                "smooth part rms": round(float(med[1]), 2),
                "residual rms": round(float(med[2]), 2),
                "residual / smooth": round(float(med[2] / med[1]), 2),
            }
        )
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="data/cpu", help="a generated dataset (its train split)")
    ap.add_argument("--every", type=int, default=5, help="every k-th window")
    ap.add_argument("--radius", type=float, default=2.1, help="neighbourhood radius, l0 (GNS's)")
    ap.add_argument("--results", default=str(RESULTS))
    args = ap.parse_args(argv)
    start, load = time.perf_counter(), os.getloadavg()[0]
    rows = measure(args.data, args.every, args.radius)
    prov = provenance(
        "benchmarks.studies.acceleration_noise",
        load,
        command=f"python -m benchmarks.studies.acceleration_noise --data {args.data} --every {args.every} "
        f"--radius {args.radius}",
        runtime_s=f"{time.perf_counter() - start:.0f}",
    )
    intro = (
        "# MPS training targets: smooth field and particle-level noise\n\n"
        f"The fluid's acceleration in the train split of `{args.data}`, split into its mean over each "
        f"particle's neighbourhood ({args.radius} l0, the particle included) and the residual; medians over "
        "the windows of each group of the RMS over the fluid (m/s^2). A network sees a neighbourhood, so "
        "it can fit the smooth part; a residual several times it is a target whose loss stalls near that "
        "of a trivial predictor (`baselines/cconv/weights/MODEL_CARD.md`). Before the first impact "
        "(steps 0-39) the blocks fall freely or rest before any pressure builds: gravity alone."
    )
    print(write_results(Path(args.results), "acceleration_noise", rows, intro, prov))


if __name__ == "__main__":
    main()
