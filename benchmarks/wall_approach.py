"""How close the fluid comes to the boundary particles: in the training data, and in a model's rollouts.

A learned model can only have learned the wall's push for the distances its training data shows it. MPS
keeps the fluid about one particle spacing from the wall and floor particles (its pressure and collision
rule push back hard below that); a rollout whose particles drift closer than the data ever came is
extrapolating, and a particle that reaches the wall plane stops the rollout guard. For the train split of
a dataset and for any rollout files (``rollout.h5`` of ``task=simulate`` or ``task=evaluate``) this reports
the distance from each fluid particle to its nearest boundary particle, in ``l0``, over every stored frame:
low percentiles, the smallest, and the fraction of particle-frames closer than 0.5, 0.7 and 0.8 l0.

Usage::

    python -m benchmarks.wall_approach --data data/cpu --rollouts runs/check/gns/rollout.h5 [...]

Writes ``benchmarks/results/wall_approach.{md,csv}`` with provenance.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from benchmarks.provenance import provenance, write_results
from lagfluid.data.datasets import load_metadata
from lagfluid.data.store import read_trajectory

RESULTS = Path(__file__).resolve().parent / "results"
THRESHOLDS_L0 = (0.5, 0.7, 0.8)
PERCENTILES = (0.01, 0.1, 1.0)


def boundary_distances(trajectory: dict, l0: float, every: int = 1) -> np.ndarray:
    """Distances (l0) from every fluid particle of every ``every``-th frame to its nearest boundary particle.

    Args:
        trajectory: :func:`lagfluid.data.store.read_trajectory`'s dict (``position`` (T, Nf, 3) and
            ``boundary_position`` (Nb, 3), m).
        l0: particle spacing, m.
        every: frame stride.

    Returns:
        (T' * Nf,) distances in units of ``l0``.
    """
    tree = cKDTree(trajectory["boundary_position"])
    frames = trajectory["position"][::every]
    return np.concatenate([tree.query(x, k=1)[0] for x in frames]) / l0


def summary(name: str, distances: np.ndarray, frames: int) -> dict[str, object]:
    """One row: percentiles, minimum and the fractions below each threshold of ``distances`` (l0)."""
    row: dict[str, object] = {"source": name, "frames": frames, "particle-frames": distances.size}
    row["min"] = round(float(distances.min()), 3)
    for p, value in zip(PERCENTILES, np.percentile(distances, PERCENTILES), strict=True):
        row[f"p{p:g}%"] = round(float(value), 3)
    for t in THRESHOLDS_L0:
        row[f"< {t} l0"] = f"{(distances < t).mean():.2e}"
    return row


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="data/cpu", help="a generated dataset (its train split)")
    ap.add_argument("--every", type=int, default=2, help="every k-th stored frame of the data")
    ap.add_argument("--rollouts", nargs="*", default=[], help="rollout.h5 files of models")
    ap.add_argument("--labels", nargs="*", default=None, help="a name per rollout (default: its path)")
    ap.add_argument("--results", default=str(RESULTS))
    args = ap.parse_args(argv)
    labels = args.labels or args.rollouts
    if len(labels) != len(args.rollouts):
        ap.error(f"--labels gives {len(labels)} names for {len(args.rollouts)} rollouts")
    start, load = time.perf_counter(), os.getloadavg()[0]
    meta = load_metadata(args.data)
    l0 = float(meta["l0"])
    data = [read_trajectory(Path(args.data) / f) for f in meta["splits"]["train"]]
    rows = [
        summary(
            f"{args.data}, train split ({len(data)} scenes)",
            np.concatenate([boundary_distances(t, l0, args.every) for t in data]),
            sum(len(t["position"][:: args.every]) for t in data),
        )
    ]
    for label, path in zip(labels, args.rollouts, strict=True):
        trajectory = read_trajectory(path)
        rows.append(summary(label, boundary_distances(trajectory, l0), len(trajectory["position"])))
    command = f"python -m benchmarks.wall_approach --data {args.data} --every {args.every}"
    if args.rollouts:
        command += " --rollouts " + " ".join(args.rollouts)
        command += " --labels " + " ".join(f"'{x}'" for x in labels)
    prov = provenance(
        "benchmarks.wall_approach", load, command=command, runtime_s=f"{time.perf_counter() - start:.0f}"
    )
    intro = (
        "# How close the fluid comes to the boundary particles\n\n"
        "Distance from each fluid particle to its nearest boundary (wall or dummy) particle, in l0, over the "
        "stored frames: the smallest, low percentiles and the fraction of particle-frames below 0.5, 0.7 "
        "and 0.8 l0. A learned model has seen the wall's push only down to the distances its training data "
        "reaches; closer than that it extrapolates (`benchmarks/wall_approach.py`)."
    )
    print(write_results(Path(args.results), "wall_approach", rows, intro, prov))


if __name__ == "__main__":
    main()
