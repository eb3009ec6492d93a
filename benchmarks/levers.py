"""A model's rows before and after each lever of issue 35, on the 1 s dam, with and without exact stages.

Each lever is a folder of the model's weights (``model.weights``: GNS or CConv) and a line saying what made
it. For every lever the
rows of :mod:`benchmarks.exact_after` (the plain model, + exact collision, + MPS pressure, + both, and + both
with K = 3, w = 0.5 where one of those does not complete), each ``task=evaluate`` against the same MPS
reference: complete, or the step the guard stops it at, its Chamfer distance to MPS and density error.

Usage::

    python -m benchmarks.levers --model gns [--levers NAME=DIR=TEXT ...] [--runs-dir runs/gns_levers]

A lever's runs are in ``<runs-dir>/<name>`` (default ``runs/<model>_levers``); a row whose folder already
holds ``metrics.json`` is read, not run again. Writes ``benchmarks/results/<model>_levers.{md,csv}`` with
provenance and each row's command.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any

from benchmarks.exact_after import run_model, verdict
from benchmarks.provenance import provenance, write_results

RESULTS = Path(__file__).resolve().parent / "results"

LEVERS: dict[str, tuple[tuple[str, str, str], ...]] = {
    "gns": (
        (
            "shipped",
            "baselines/gns/weights",
            "the shipped weights (model=gns; their MODEL_CARD.md), trained before the window and statistics "
            "fixes",
        ),
        (
            "dagger",
            "baselines/gns/weights/dagger",
            "the fixed weights after 4 DAgger rounds (model=gns_dagger; their MODEL_CARD.md)",
        ),
    ),
    "cconv": (
        (
            "shipped",
            "baselines/cconv/weights",
            "the shipped weights (model=cconv; their MODEL_CARD.md), 500 iterations of batch 2 on data=cpu",
        ),
    ),
}
"""Per model, (name, weights folder, what made them): the levers always measured; ``--levers`` adds others."""
TITLES = {"gns": "GNS", "cconv": "CConv"}


def parse_lever(text: str) -> tuple[str, str, str]:
    """``NAME=DIR=TEXT`` as (name, folder, description).

    Raises:
        SystemExit: not three ``=``-separated parts, or ``DIR`` is not a folder.
    """
    parts = text.split("=", 2)
    if len(parts) != 3 or not all(parts):
        raise SystemExit(f"--levers: {text!r} is not NAME=DIR=TEXT")
    if not Path(parts[1]).is_dir():
        raise SystemExit(f"--levers: {parts[1]} (of {parts[0]}) is not a folder of the model's weights")
    return parts[0], parts[1], parts[2]


def lever_rows(name: str, weights: str, args: argparse.Namespace) -> list[dict[str, Any]]:
    """The rows of one lever: :func:`benchmarks.exact_after.run_model` on its weights, each with its name."""
    runs = str(Path(args.runs_dir) / name)
    here = argparse.Namespace(**{**vars(args), "runs_dir": runs, "weights": weights})
    return [{"lever": name, "weights": weights, **row} for row in run_model(args.model, here)]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", choices=sorted(LEVERS), default="gns")
    ap.add_argument("--levers", nargs="*", default=[], type=parse_lever, help="more levers: NAME=DIR=TEXT")
    ap.add_argument("--scene", default="dam")
    ap.add_argument("--duration", type=float, default=1.0, help="s of the scene")
    ap.add_argument("--runs-dir", default=None, help="default: runs/<model>_levers")
    ap.add_argument("--reference-dir", default="runs/reference", help="the MPS references' cache")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--results", default=str(RESULTS))
    args = ap.parse_args(argv)
    args.runs_dir = args.runs_dir or f"runs/{args.model}_levers"
    title, name = TITLES[args.model], f"{args.model}_levers"
    load = os.getloadavg()[0]
    rows, verdicts = [], []
    for lever, weights, about in (*LEVERS[args.model], *args.levers):
        these = lever_rows(lever, weights, args)
        rows += these
        verdicts.append(f"{verdict(lever, these)} Weights `{weights}`: {about}.")
    intro = (
        f"# {title} before and after each lever (issue 35)\n\n"
        f"`task=evaluate` of {title} on `{args.scene}` for {args.duration:g} s, frames every 40 ms, against "
        "one MPS reference at the scene's dt, for each set of weights (a lever) alone and with MPS's exact "
        "stages after each of its steps (`model.exact_after`, `benchmarks/exact_after.py`). A stopped run is "
        "compared over the frames it stored.\n\n" + "\n".join(f"- {v}" for v in verdicts)
    )
    prov = provenance("benchmarks.levers", load, runs=str(args.runs_dir))
    print(write_results(Path(args.results), name, rows, intro, prov))


if __name__ == "__main__":
    main()
