"""Median wall time per MPS step, split by stage, at ~10k and ~40k fluid particles.

    python -m benchmarks.mps_speed [--scenes dam_medium dam_large] [--warmup 10] [--steps 20]

Each scene starts from rest and is first advanced ``--warmup`` steps (neighbour list built, PPE warm
started, the column already moving); then ``--steps`` steps are timed. Reported: median ms per step and
per stage, steps per second (from the median), the mean ms per step (which carries the steps that rebuilt
the Verlet list: run ``--warmup 100 --steps 100`` for the flowing dam, where it rebuilds every ~3-4
steps), PPE iterations, neighbour-list rebuilds. Results go to
``benchmarks/results/mps_speed.{md,csv}`` with provenance. Timings on shared machines are noisy: compare
medians from one run only.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from statistics import median

import torch
from hydra import compose, initialize_config_dir

from benchmarks.provenance import markdown, markdown_table, provenance, write_results
from lagfluid.memory import keep_freed_memory
from lagfluid.rollout import rollout
from lagfluid.run import CONF_DIR
from lagfluid.tasks.config import build_initial_state, build_simulator

RESULTS = Path(__file__).resolve().parent / "results"
STAGES = ("neighbors", "advection", "collision", "pressure_assembly", "pressure_solve", "correction")


def measure(scene: str, warmup: int, steps: int, device: str, overrides: list[str]) -> dict:
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=[f"scene={scene}", f"device={device}", *overrides])
    state = build_initial_state(cfg)
    sim = build_simulator(cfg)
    state, _ = rollout(sim, state, warmup)
    start = time.perf_counter()
    state, record = rollout(sim, state, steps, reset=False)  # warm neighbour list and PPE start
    wall = time.perf_counter() - start
    step_ms = 1e3 * median(record["step_seconds"])
    row = {
        "scene": scene,
        "fluid": state.n_fluid,
        "boundary": state.num_particles - state.n_fluid,
        "ms_per_step": round(step_ms, 1),
        "steps_per_s": round(1e3 / step_ms, 2),
        # the mean carries the steps that rebuilt the Verlet list (the median hides them)
        "mean_ms_per_step": round(1e3 * sum(record["step_seconds"]) / len(record["step_seconds"]), 1),
        **{f"{k}_ms": round(1e3 * median(record["stage_seconds"].get(k, [0.0])), 1) for k in STAGES},
        "ppe_iterations": median(record["info"].get("ppe_iterations", [0])),
        "list_rebuilds": int(sum(record["info"].get("list_rebuilds", [0]))),
        "steps": steps,
        "wall_s": round(wall, 1),
    }
    return row


def main(argv: list[str] | None = None) -> None:
    keep_freed_memory()  # as the CLI does: the timings are a user's
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["dam_medium", "dam_large"])
    ap.add_argument("--warmup", type=int, default=10)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    ap.add_argument(
        "--override", nargs="*", default=[], help="extra Hydra overrides, e.g. solver.ppe.tol=1e-8"
    )
    ap.add_argument("--no-save", action="store_true")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    load_before = os.getloadavg()[0]
    rows = [measure(s, args.warmup, args.steps, args.device, args.override) for s in args.scenes]
    prov = provenance("benchmarks.mps_speed", load_before, args.device)
    print(markdown_table(rows))
    print(markdown(prov))
    if not args.no_save:
        intro = (
            "# MPS time per step by stage\n\nMedian over the timed steps (after warm-up). "
            "Stages: neighbour search and filtering, advection (viscosity + gravity), collision, "
            "PPE assembly (number density, divergence, matrix), PPE solve (Jacobi-CG), "
            "correction (pressure gradient)."
        )
        write_results(RESULTS, "mps_speed", rows, intro, prov)


if __name__ == "__main__":
    main()
