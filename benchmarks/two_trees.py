r"""One benchmark in two checkouts, alternated in one sitting: ``python -m benchmarks.two_trees``.

    python -m benchmarks.two_trees --before /path/to/old/checkout --after . \\
        --scenes dam dam_medium dam_large --repeats 2 --threads 2 --name fgn_vs_mps_search

Runs ``python -m benchmarks.fgn_vs_mps --scene S --steps N --models mps fgn`` in each checkout (its own
``lagfluid`` and configs: the command runs with the checkout as its working folder, first on ``sys.path``),
before, after, before, after, ... per scene, so both see the machine's conditions of the same minutes.
Each checkout's rows go to a scratch folder; this script reads them back and writes one table: per scene,
model and checkout, the median over repeats of the mean and median ms per step, the neighbour stage's mean,
the list's searches, and the metrics; then after / before ratios. The rollouts of the two checkouts are
compared frame by frame (largest position difference: 0 means bit-identical).

A checkout needs ``benchmarks.fgn_vs_mps`` with ``--results`` and ``stages_ms_mean`` (commit 1a6904c): for
an older one, cherry-pick that commit. Compiled kernels are warmed in each checkout first (a 2-step run),
so no timed step pays a compilation.
"""

from __future__ import annotations

import argparse
import csv
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from statistics import median

import numpy as np

from benchmarks.provenance import provenance, write_results
from lagfluid.data.store import read_trajectory

RESULTS = Path(__file__).resolve().parent / "results"
TREES = ("before", "after")


def run_tree(tree: Path, scene: str, steps: int, threads: int, results: Path, runs: Path) -> list[dict]:
    """``benchmarks.fgn_vs_mps`` in ``tree``; its CSV rows (strings)."""
    cmd = [
        sys.executable, "-m", "benchmarks.fgn_vs_mps", "--scene", scene, "--steps", str(steps),
        "--threads", str(threads), "--models", "mps", "fgn", "--results", str(results),
        "--out-root", str(runs),
    ]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(tree)}
    subprocess.run(cmd, cwd=tree, env=env, check=True, stdout=subprocess.DEVNULL)
    with open(results / f"fgn_vs_mps_{scene}.csv", newline="") as f:
        return list(csv.DictReader(f))


def stage_ms(field: str, stage: str) -> float:
    """The ms of ``stage`` in a ``stages_ms`` field (``"neighbors=12.3 network=4.5"``); nan if absent."""
    for part in field.split():
        name, _, value = part.partition("=")
        if name == stage:
            return float(value)
    return float("nan")


def largest_difference(a: Path, b: Path) -> float:
    """The largest |position difference| (m) between two rollouts over their common frames (inf if none)."""
    ta, tb = read_trajectory(a), read_trajectory(b)
    n = min(len(ta["position"]), len(tb["position"]))
    if n == 0 or ta["position"][0].shape != tb["position"][0].shape:
        return float("inf")
    return float(max(np.abs(ta["position"][k] - tb["position"][k]).max() for k in range(n)))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", type=Path, required=True)
    ap.add_argument("--after", type=Path, default=Path("."))
    ap.add_argument("--scenes", nargs="+", default=["dam", "dam_medium", "dam_large"])
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--name", default="fgn_vs_mps_two_trees")
    ap.add_argument("--about", default="", help="a paragraph: what the two checkouts are")
    args = ap.parse_args(argv)
    trees = {"before": args.before.resolve(), "after": args.after.resolve()}
    for label, tree in trees.items():
        if not (tree / "benchmarks" / "fgn_vs_mps.py").is_file():
            raise SystemExit(f"--{label} {tree}: no benchmarks/fgn_vs_mps.py there")
    load = os.getloadavg()[0]
    scratch = Path(tempfile.mkdtemp(prefix="two_trees-"))
    for label, tree in trees.items():  # compile the kernels once per checkout, untimed
        run_tree(
            tree, "dam_small", 2, args.threads, scratch / f"warm-{label}", scratch / f"warm-runs-{label}"
        )
    found: dict[tuple[str, str, str], list[dict]] = {}
    for scene in args.scenes:
        for r in range(args.repeats):
            for label, tree in trees.items():
                rows = run_tree(
                    tree, scene, args.steps, args.threads, scratch / f"{label}-{r}", scratch / f"runs-{label}"
                )
                for row in rows:
                    found.setdefault((scene, row["model"], label), []).append(row)
                print(f"two_trees: {scene} repeat {r} {label} done", file=sys.stderr, flush=True)
    out = []
    for scene in args.scenes:
        for model in ("mps", "fgn"):
            means = {}
            for label in TREES:
                rows = found[(scene, model, label)]
                mean = median(float(x["ms_per_step_mean"]) for x in rows)
                means[label] = mean
                mps_mean = median(float(x["ms_per_step_mean"]) for x in found[(scene, "mps", label)])
                first = rows[0]
                out.append(
                    {
                        "scene": scene,
                        "model": model,
                        "code": label,
                        "ms_per_step_mean": round(mean, 1),
                        "ms_per_step_mean_each": " ".join(x["ms_per_step_mean"] for x in rows),
                        "ms_per_step_median": round(median(float(x["ms_per_step"]) for x in rows), 1),
                        "neighbors_ms_mean": round(
                            median(stage_ms(x["stages_ms_mean"], "neighbors") for x in rows), 1
                        ),
                        "list_rebuilds": first["list_rebuilds"],
                        "mps_over_model_mean": round(mps_mean / mean, 2),
                        "complete": first["complete"],
                        "density_error_mean": first["density_error_mean"],
                        "divergence_mean_per_s": first["divergence_mean_per_s"],
                        "chamfer_to_mps_l0": first["chamfer_to_mps_l0"],
                        "after_over_before": "",
                        "largest_position_difference_m": "",
                    }
                )
            runs = {label: scratch / f"runs-{label}" / f"{model}-{scene}" / "rollout.h5" for label in TREES}
            out[-1]["after_over_before"] = round(means["after"] / means["before"], 3)
            out[-1]["largest_position_difference_m"] = (
                f"{largest_difference(runs['before'], runs['after']):.3g}"
            )
    intro = (
        f"# {args.name}: `benchmarks.fgn_vs_mps` in two checkouts, alternated\n\n"
        f"{args.about}\n\n"
        f"Each scene {args.steps} steps, `--models mps fgn`, {args.threads} threads, {args.repeats} repeats "
        "per checkout in the order before, after, before, after (scene by scene). `ms_per_step_mean`: the "
        "median over repeats of the whole run's mean step (each repeat in `ms_per_step_mean_each`); "
        "`neighbors_ms_mean`: the neighbour stage's mean; `list_rebuilds`: the Verlet list's searches in the "
        "run; `mps_over_model_mean`: MPS's mean step over the model's, same checkout. Metrics of the first "
        "repeat. `largest_position_difference_m`: the last repeat's rollouts of the two checkouts, frame by "
        "frame (0: bit-identical)."
    )
    prov = provenance(
        "benchmarks.two_trees",
        load,
        "cpu",
        before=str(trees["before"]),
        after=str(trees["after"]),
        scratch=str(scratch),
    )
    print(write_results(RESULTS, args.name, out, intro, prov))


if __name__ == "__main__":
    main()
