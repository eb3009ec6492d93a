"""Each DAgger round's dam rollout against the MPS reference: complete or stopped, Chamfer, density error.

A ``train.dagger`` run (``lagfluid/tasks/dagger_rounds.py``) rolls each round's weights out on the dam
(``<run>/dagger/round<k>/dam/rollout.h5``; round 0: the starting weights) and its ``dam.csv`` says whether
it completed. This compares those rollouts, as stored, with one MPS reference rollout of the same scene
(``lagfluid.tasks.evaluate.compare.compare``, the metrics of ``task=evaluate``), so that a round is judged
by how close it stays to MPS, not only by whether it runs to the end.

Usage::

    python -m benchmarks.dagger_rounds RUN_DIR --reference REFERENCE_ROLLOUT --name NAME --about TEXT

(``REFERENCE_ROLLOUT``: e.g. the tables' cached MPS dam, ``runs/tables/reference/dam-<key>/rollout.h5``.)

Writes ``benchmarks/results/<name>.{md,csv}`` with provenance; the rollouts are read, not run again.
"""

from __future__ import annotations

import argparse
import csv
import os
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.provenance import provenance, write_results
from benchmarks.tables.config import compose_config
from lagfluid.physics.settings import SolverSettings
from lagfluid.tasks.evaluate.compare import Trajectory, compare

RESULTS = Path(__file__).resolve().parent / "results"


def round_rows(run: Path, reference: Path, settings: SolverSettings) -> list[dict[str, Any]]:
    """One row per round of ``run``'s ``dagger/dam.csv`` whose rollout is there, compared with ``reference``.

    Raises:
        SystemExit: ``run`` has no ``dagger/dam.csv``.
    """
    summary = run / "dagger" / "dam.csv"
    if not summary.is_file():
        raise SystemExit(f"{run} holds no dagger/dam.csv: not a train.dagger run with dam_steps > 0")
    rows = []
    with summary.open() as f:
        for line in csv.DictReader(f):
            k = int(line["round"])
            rollout = run / "dagger" / f"round{k}" / "dam" / "rollout.h5"
            if not rollout.is_file():
                continue
            frames = compare(rollout, reference, settings)
            chamfer = np.array(frames["chamfer_mm"])
            density = np.array(frames["density_error"]["model"])
            rows.append(
                {
                    "round": k,
                    "rollout": "complete" if line["complete"] == "True" else f"stops at step {line['steps']}",
                    "frames_compared": len(chamfer),
                    "chamfer_mean_mm": round(float(chamfer.mean()), 1),
                    "chamfer_max_mm": round(float(chamfer.max()), 1),
                    "density_error_mean": round(float(density.mean()), 4),
                    "density_error_mps": round(float(np.mean(frames["density_error"]["reference"])), 4),
                    "weights": line["weights"],
                }
            )
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="the train.dagger run's out_dir")
    ap.add_argument("--reference", type=Path, required=True, help="the MPS reference's rollout.h5")
    ap.add_argument("--name", required=True, help="results file name (<name>.md, <name>.csv)")
    ap.add_argument("--about", required=True, help="one paragraph: what the run is and its command")
    ap.add_argument("--results", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    load = os.getloadavg()[0]
    Trajectory.open(args.reference).file.close()  # a missing or unreadable reference fails here, named
    settings = SolverSettings.from_config(compose_config([]).solver)  # as Hydra composes it
    rows = round_rows(args.run, args.reference, settings)
    intro = (
        f"# DAgger rounds of `{args.run}` on the dam\n\n{args.about}\n\n"
        "Each round's dam rollout (`dagger/round<k>/dam`, round 0: the starting weights) against one MPS "
        f"reference (`{args.reference}`), frames matched by time: Chamfer distance to MPS's fluid and "
        "density error (mean over the frames; MPS's own over the same frames beside it)."
    )
    prov = provenance("benchmarks.dagger_rounds", load, run=str(args.run))
    print(write_results(args.results, args.name, rows, intro, prov))


if __name__ == "__main__":
    main()
