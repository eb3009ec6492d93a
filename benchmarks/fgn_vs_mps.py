"""FGN against its MPS ground truth on one scene: accuracy and wall time per step, measured in one run.

Rolls out every model on the same scene for the same steps with the same threads (one after another, so
the timings share the machine's conditions) through the package's rollout
(``lagfluid.tasks.simulate.simulate``), then compares each rollout with MPS's:

* density error and velocity divergence (mean and max over the run; ``lagfluid.metrics`` definitions);
* Chamfer distance to MPS (paper eq. 29, asymmetric, model -> MPS, mean over the stored frames), in l0;
* wall time per step, median (a typical step) and mean (the whole run: the Verlet rebuilds of a flowing
  scene included), and their ratios to MPS's (the speed-up).

Usage::

    python -m benchmarks.fgn_vs_mps --scene dam --steps 500 --threads 2 --models mps fgn hybrid fgn_original


Writes ``benchmarks/results/fgn_vs_mps_<scene>.md`` and ``.csv`` (with the provenance block); the
rollouts go to ``runs/bench/fgn_vs_mps/<model>-<scene>`` (not committed).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir

from benchmarks.provenance import provenance, results_markdown, write_results
from lagfluid.data.store import read_trajectory
from lagfluid.memory import keep_freed_memory
from lagfluid.metrics import chamfer_distance
from lagfluid.run import CONF_DIR
from lagfluid.tasks.simulate import simulate

RESULTS = Path(__file__).resolve().parent / "results"


def run_model(model: str, args: argparse.Namespace) -> tuple[dict, Path]:
    out = Path(args.out_root) / f"{model}-{args.scene}"
    overrides = [
        f"model={model}",
        f"scene={args.scene}",
        f"steps={args.steps}",
        f"out_dir={out}",
        f"device={args.device}",
        f"write_every={args.write_every}",
        "progress=false",
        *args.override,
    ]
    if args.threads:
        overrides.append(f"threads={args.threads}")
    if model in ("fgn", "hybrid") and args.weights:
        overrides.append(f"model.weights={args.weights}")
    if model == "fgn_original" and args.weights_original:
        overrides.append(f"model.weights={args.weights_original}")
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    return simulate(cfg), out / "rollout.h5"


def main(argv: list[str] | None = None) -> None:
    keep_freed_memory()  # as the CLI does: the timings are a user's
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="dam")
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--models", nargs="+", default=["mps", "fgn", "hybrid"])
    ap.add_argument("--weights", default=None, help="FGN checkpoint directory (default: shipped weights)")
    ap.add_argument(
        "--weights-original",
        default=None,
        help="the authors' arrays (default: the copy shipped in the package)",
    )
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--write-every", type=int, default=10)
    ap.add_argument("--out-root", default="runs/bench/fgn_vs_mps")
    ap.add_argument("--override", nargs="*", default=[], help="extra Hydra overrides for every model")
    ap.add_argument("--no-save", action="store_true")
    ap.add_argument("--results", default=str(RESULTS), help="folder of the .md/.csv (default: results/)")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    load = os.getloadavg()[0]
    if "mps" not in args.models:
        args.models = ["mps", *args.models]

    runs = {m: run_model(m, args) for m in args.models}
    reference = read_trajectory(runs["mps"][1])
    dt = float(reference["attrs"]["dt"])
    ref_frames = {round(t / dt): p for t, p in zip(reference["time"], reference["position"], strict=True)}
    mps_step = runs["mps"][0]["time_per_step_median_s"]
    mps_mean = runs["mps"][0]["time_per_step_mean_s"]
    rows = []
    for model, (metrics, path) in runs.items():
        traj = read_trajectory(path)
        l0 = float(traj["attrs"]["l0"])
        dists = [
            chamfer_distance(p, ref_frames[round(t / dt)])
            for t, p in zip(traj["time"], traj["position"], strict=True)
            if round(t / dt) in ref_frames
        ]
        step, mean = metrics["time_per_step_median_s"], metrics["time_per_step_mean_s"]
        rows.append(
            {
                "model": model,
                "complete": metrics["complete"],
                "steps": metrics["steps"],
                "ms_per_step": round(1e3 * step, 1),
                "speedup_vs_mps": round(mps_step / step, 2),
                "ms_per_step_mean": round(1e3 * mean, 1),
                "speedup_vs_mps_mean": round(mps_mean / mean, 2),
                "density_error_mean": round(metrics["density_error"]["mean"], 5),
                "density_error_max": round(metrics["density_error"]["max"], 5),
                "divergence_mean_per_s": round(metrics["velocity_divergence_per_s"]["mean"], 3),
                "divergence_max_per_s": round(metrics["velocity_divergence_per_s"]["max"], 3),
                "chamfer_to_mps_l0": round(float(np.nanmean(dists)) / l0, 3) if dists else float("nan"),
                "stages_ms": " ".join(f"{k}={1e3 * v:.1f}" for k, v in metrics["stage_median_s"].items()),
                "stages_ms_mean": " ".join(f"{k}={1e3 * v:.1f}" for k, v in metrics["stage_mean_s"].items()),
                "list_rebuilds": metrics.get("list_rebuilds", ""),
            }
        )
    prov = provenance(
        "benchmarks.fgn_vs_mps",
        load,
        args.device,
        scene=args.scene,
        steps=str(args.steps),
        particles=str(runs["mps"][0]["particles"]),
    )
    intro = (
        f"# FGN vs MPS on `{args.scene}` ({args.steps} steps)\n\n"
        "Same scene, steps and threads for every model, run one after another in one process. Time per "
        "step: median (`ms_per_step`, a typical step) and mean (`ms_per_step_mean`, the whole run with its "
        "neighbour-list rebuilds); each speed-up is MPS's time over the model's; the stages' median and "
        "mean ms (`stages_ms`, `stages_ms_mean`) and the neighbour-list searches of the run "
        "(`list_rebuilds`). Chamfer: "
        "paper eq. 29 from the model's fluid to MPS's at the same step, mean over stored frames, in l0. "
        "Density error and divergence: `lagfluid.metrics` (README, Metrics)."
    )
    if args.no_save:
        print(results_markdown(rows, intro, prov))
    else:
        print(write_results(Path(args.results), f"fgn_vs_mps_{args.scene}", rows, intro, prov))


if __name__ == "__main__":
    main()
