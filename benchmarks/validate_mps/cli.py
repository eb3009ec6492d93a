"""The command line of ``python -m benchmarks.validate_mps``: run the checks, print them, write the report."""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

import benchmarks.validate_mps
from benchmarks.validate_mps.common import (
    RESULTS,
    SOLVER_OVERRIDES,
    SOLVER_PROFILE,
    Check,
    RunLog,
    solver_config,
)
from benchmarks.validate_mps.dam import check_authors_dam, check_dt, plot_front
from benchmarks.validate_mps.free_fall import check_free_fall
from benchmarks.validate_mps.hydrostatic import check_hydrostatic
from benchmarks.validate_mps.mass import check_mass
from benchmarks.validate_mps.report import report_extra, run_provenance, write_report
from lagfluid.physics.settings import SolverSettings


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.validate_mps", description=benchmarks.validate_mps.__doc__.splitlines()[0]
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="reduced sizes and durations (runtime: benchmarks/results/validate_mps_quick.md)",
    )
    parser.add_argument("--out", type=Path, default=None, help="path stem for .md/.csv (default results/)")
    parser.add_argument(
        "--profile",
        default="mps",
        metavar="NAME",
        help="solver profile conf/solver/NAME.yaml, e.g. mps_corrected (default mps, the authors' scheme; "
        "report results/validate_mps_<NAME>... unless mps)",
    )
    parser.add_argument(
        "--solver",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="overrides of the profile for every run, e.g. pressure_gradient=corrected "
        "(default report: results/validate_mps_<key>_<value>...)",
    )
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    SOLVER_PROFILE[0] = args.profile
    SOLVER_OVERRIDES.clear()
    SOLVER_OVERRIDES.update(OmegaConf.to_container(OmegaConf.from_dotlist(args.solver)))
    variant = "" if args.profile == "mps" else "_" + args.profile
    variant += "".join("_" + item.replace("=", "_").replace(".", "_") for item in args.solver)
    suffix = ("_quick" if args.quick else "") + variant
    stem = args.out or RESULTS / f"validate_mps{suffix}"
    figdir = stem.parent
    figdir.mkdir(parents=True, exist_ok=True)
    settings = SolverSettings.from_config(solver_config())
    start, load_before = time.perf_counter(), os.getloadavg()[0]
    checks: list[Check] = []
    logs: list[RunLog] = []
    timings: dict[str, float] = {}

    t0 = time.perf_counter()
    hydro, hlog = check_hydrostatic(args.quick, settings, figdir, suffix)
    logs.append(hlog)
    timings["hydrostatic + resting tank"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    free = check_free_fall(args.quick)
    timings["free fall"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    dam, dlog, info = check_authors_dam(args.quick, settings, figdir, suffix)
    if dlog is not None:
        logs.append(dlog)
    timings["authors' dam"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    dtc, dlogs, curves = check_dt(args.quick, settings)
    logs += dlogs
    timings["dt robustness"] = time.perf_counter() - t0
    plot_front(figdir / f"validate_mps_dam_front{suffix}.png", info, curves)

    checks = [c for c in hydro if c.check.startswith("1")] + free + check_mass(logs)
    checks += [c for c in hydro if c.check.startswith("4")] + dam + dtc
    for c in checks:
        print(f"{c.status:4s}  {c.check}: {c.quantity}: {c.measured}  [{c.criterion}]")

    extra = report_extra(timings, info, suffix)
    runtime = time.perf_counter() - start
    write_report(checks, run_provenance(runtime, load_before), stem, extra)
    n_fail = sum(c.status == "FAIL" for c in checks)
    print(f"{n_fail} check(s) failed; runtime {runtime:.0f} s; report {stem.with_suffix('.md')}")
    return 1 if n_fail else 0
