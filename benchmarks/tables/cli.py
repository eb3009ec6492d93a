"""The command line of ``python -m benchmarks.tables``: run the chosen parts of a profile, write it all."""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf

import benchmarks.tables
from benchmarks.provenance import git_commit, markdown, provenance
from benchmarks.tables.bench import Bench
from benchmarks.tables.parts import (
    part_fig5,
    part_table2,
    part_table3,
    part_table4,
    part_table5,
    part_tradeoff,
)
from benchmarks.tables.profiles import DEFAULT_PARTS, FULL, PARTS, QUICK, Profile, estimate_seconds
from benchmarks.tables.report import (
    README,
    REPO,
    RESULTS,
    Report,
    cpu_model,
    earlier_parts,
    merge_parts,
    missing_parts_message,
    parts_file,
    write_readme,
)
from benchmarks.tables.simulators import FGN, GROUND_TRUTH, all_simulators
from lagfluid.errors import ConfigError
from lagfluid.memory import keep_freed_memory
from lagfluid.models.fgn.simulator import SHIPPED_WEIGHTS
from lagfluid.tasks.config import run_device


def run_all(profile: Profile, args: argparse.Namespace) -> dict[str, Any]:
    """Run the selected parts of ``profile`` and write every output.

    Returns:
        ``files`` written, CSV ``rows`` per part, ``failed`` and ``skipped`` (weights missing) row keys,
        ``elapsed_s`` and ``readme`` (whether the README was rewritten).
    """
    start = time.perf_counter()
    load = os.getloadavg()[0]
    torch.set_num_threads(int(args.threads))
    parts = set(args.only or DEFAULT_PARTS)
    bench = Bench(profile, args)
    out_dir = Path(args.results)
    out_dir.mkdir(parents=True, exist_ok=True)
    machine = (
        f"{cpu_model()}, {os.cpu_count()} cores, torch {torch.__version__}, {args.threads} torch threads"
    )
    if args.device != "cpu":
        machine += f"; device {args.device} ({torch.cuda.get_device_name(torch.device(args.device))})"
    meta = {"machine": machine, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    meta["script_commit"] = git_commit()
    report = Report(out_dir / profile.prefix, meta)

    if "table2" in parts:  # first: the timing rows run before anything else has warmed or loaded the machine
        part_table2(bench, report)
    # every dam row for Tables 1/3, 4 and the trade-off; Table 5 alone needs only MPS and FGN beside its rows
    dam_keys = None if parts & {"table3", "table4", "tradeoff"} else (GROUND_TRUTH, FGN)
    dam_runs = bench.accuracy_runs("dam", keys=dam_keys) if parts - {"table2"} else []
    if "table3" in parts:
        part_table3(bench, report, dam_runs)
    fig5 = bench.fig5_runs() if parts & {"fig5", "tradeoff"} else ([], None, None)
    if "fig5" in parts:
        part_fig5(bench, report, fig5)
    if "table4" in parts:
        part_table4(bench, report, dam_runs)
    if "table5" in parts:
        part_table5(bench, report, dam_runs)
    if "tradeoff" in parts:
        part_tradeoff(bench, report, dam_runs, fig5[0])

    fgn_dam = bench.done.get(f"table3/dam/{FGN}")
    figures = ""
    if fgn_dam is not None and fgn_dam.ok and profile.figures:
        src = bench.runs_dir / fgn_dam.key.replace("/", "_")  # evaluate's out_dir of that row
        for name, fig in (("error_vs_time.png", "fig4_dam_fgn"), ("pressure_slice.png", "fig6_dam_fgn")):
            if (src / name).is_file():
                dest = report.path(f"{fig}.png")
                shutil.copy(src / name, dest)
                figures += f"![{fig}]({dest.name})\n\n"

    if figures:
        report.sections["figures"] = f"## Figs. 4 and 6: FGN on the dam\n\n{figures}"
    elapsed = time.perf_counter() - start
    extra = {"CPU": cpu_model(), "profile": f"{profile.name}: {profile.description}"}
    extra["runtime"] = f"{elapsed / 60:.1f} min"
    extra["FGN weights"] = str(args.weights or f"shipped ({SHIPPED_WEIGHTS.relative_to(REPO)})")
    prov = provenance("benchmarks.tables", load, args.device, **extra)
    invocation = f"`{prov['command']}`, {extra['runtime']}"
    merged = merge_parts(report, bool(args.only), {r.key: r.command for r in bench.done.values()}, invocation)
    history = "\n".join(f"- {when}: {what}" for when, what in merged["history"].items())
    runs_md = "\n".join(f"- `{key}`: `{command}`" for key, command in merged["commands"].items())
    run = f"{meta['date']} at commit {meta['script_commit']}"
    sections = merged["sections"]
    body = earlier_parts(merged, "sections", run) + "\n".join(
        sections[k] for k in ("table3", "table2", "table4", "table5", "fig5", "tradeoff") if k in sections
    )
    md = report.path("report.md")
    md.write_text(
        f"# Tables and figures ({profile.name} profile)\n\n{profile.description}.\n\n{body}\n"
        + sections.get("figures", "")
        + f"## Provenance\n\n{markdown(prov)}\n\n"
        + f"### Runs of the script that made this report\n\n{history}\n\n"
        + f"### Rows (each row's command)\n\n{runs_md}\n"
    )
    written: dict[str, Any] = {"files": report.files, "rows": report.rows, "readme": False}
    if args.readme and merged["readme"]:
        label = (
            f"*{profile.name} profile*: {profile.description}. Run {meta['date']} at commit "
            f"{meta['script_commit']} on {machine}; FGN weights: {extra['FGN weights']}. Every table, each "
            f"row's command and the figures: [`benchmarks/results/{md.name}`]"
            f"(benchmarks/results/{md.name}).\n\n"
        )
        order = ("table1", "table2", "table4", "table5", "fig5", "tradeoff")
        pieces = merged["readme"]
        section = label + earlier_parts(merged, "readme", run)
        section += "\n".join(pieces[k] for k in order if k in pieces)
        written["readme"] = write_readme(section, Path(args.readme_path))
    written["failed"] = [r.key for r in bench.done.values() if r.failed]
    written["skipped"] = [r.key for r in bench.done.values() if r.skipped]
    written["elapsed_s"] = elapsed
    print(
        f"[tables] done in {elapsed / 60:.1f} min; wrote {len(report.files)} files to {out_dir}", flush=True
    )
    if written["skipped"]:
        print(f"[tables] rows skipped (weights missing): {', '.join(written['skipped'])}", flush=True)
    if written["failed"]:
        print(f"[tables] rows that failed: {', '.join(written['failed'])}", flush=True)
    return written


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line (see :mod:`benchmarks.tables`)."""
    ap = argparse.ArgumentParser(
        prog="python -m benchmarks.tables", description=(benchmarks.tables.__doc__ or "").splitlines()[0]
    )
    ap.add_argument(
        "--quick", action="store_true", help="the reduced profile (< 5 min), tables_quick_* files"
    )
    ap.add_argument("--only", nargs="+", choices=PARTS, help="run only these parts")
    ap.add_argument(
        "--simulators",
        nargs="+",
        metavar="KEY",
        help="only these simulators' rows beside MPS and FGN (e.g. a plugin's key) in Tables 1-3, 5 and "
        "the trade-off (Table 4, Fig. 5 and the trade-off's MPS variants run as always); the files get the "
        "keys in their prefix and the README is left alone",
    )
    ap.add_argument("--weights", default=None, help="FGN checkpoint directory (default: the shipped weights)")
    ap.add_argument(
        "--threads", type=int, default=os.cpu_count() or 1, help="torch threads (default: all cores)"
    )
    ap.add_argument("--device", default="cpu", help="torch device of every row (cpu, cuda, cuda:1, ...)")
    ap.add_argument(
        "--results",
        default=None,
        help=f"where the md/csv/png files go (default: {RESULTS.relative_to(REPO)}, and its subfolder "
        "named by the device type off the CPU)",
    )
    ap.add_argument("--runs-dir", default="runs/tables", help="rollouts and MPS references")
    ap.add_argument(
        "--readme",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="rewrite the README's results tables (default: yes for the full profile of every simulator on "
        "the CPU, else no)",
    )
    ap.add_argument("--readme-path", default=str(README), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    try:
        device_type = run_device(OmegaConf.create({"device": args.device})).type
    except ConfigError as err:
        ap.error(f"--device {args.device}: {err}")
    if args.results is None:
        args.results = str(RESULTS if device_type == "cpu" else RESULTS / device_type)
    if args.simulators:
        known = [s.key for s in all_simulators()]
        unknown = [k for k in args.simulators if k not in known]
        if unknown:
            ap.error(f"--simulators: unknown {' '.join(unknown)}; available: {', '.join(known)}")
        if args.readme:
            ap.error("--simulators and --readme exclude each other: the README's tables hold every simulator")
        args.readme = False
    if args.readme is None:
        args.readme = not args.quick and args.device == "cpu"
    elif args.readme and args.device != "cpu":
        ap.error(f"the README's tables are the CPU's: --device {args.device} needs --no-readme")
    return args


def chosen_profile(args: argparse.Namespace) -> Profile:
    """The profile of ``args``: full or quick, and with ``--simulators`` only those keys beside MPS and FGN.

    A subset writes under its own prefix (``tables_quick_gns_unroll_*``), so it never replaces the whole
    zoo's tables, and its ``--only`` reruns merge with its own earlier run.
    """
    profile = QUICK if args.quick else FULL
    if not args.simulators:
        return profile
    keys = {GROUND_TRUTH, FGN, *args.simulators}
    listed = tuple(s.key for s in all_simulators() if s.key in keys)  # the tables' order, however typed
    own = [k for k in listed if k not in (GROUND_TRUTH, FGN)]
    only = f"only {' '.join(own)} beside MPS and FGN" if own else "MPS and FGN only"
    return replace(
        profile,
        simulators=listed,
        prefix="_".join((profile.prefix, *(own or (GROUND_TRUTH, FGN)))),
        description=f"{profile.description}; {only} (--simulators)",
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m benchmarks.tables``; returns the exit status (1 when a row failed)."""
    keep_freed_memory()  # as the CLI does: the timings are a user's
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    args = parse_args(argv)
    profile = chosen_profile(args)
    saved = parts_file(Path(args.results) / profile.prefix)
    if args.only and not saved.is_file():  # before any row runs, not after all of them (merge_parts)
        subset = f"--simulators {' '.join(args.simulators)}" if args.simulators else ""
        sys.stderr.write(f"benchmarks.tables: {missing_parts_message(saved, subset)}\n")
        return 2
    if args.weights is None and not (SHIPPED_WEIGHTS / "advection.pt").is_file():
        sys.stderr.write(
            f"benchmarks.tables: no shipped FGN weights in {SHIPPED_WEIGHTS}; pass --weights DIR (a "
            "task=train out_dir holding advection.pt, collision.pt, pressure.pt)\n"
        )
        return 2
    print(f"[tables] {profile.name} profile: {profile.description}", flush=True)
    est = estimate_seconds(profile, args.only or DEFAULT_PARTS)
    what = f"of {' '.join(args.only)} " if args.only else ""
    print(
        f"[tables] expected runtime {what}~{est / 60:.0f} min on the project's 2-core CPU machine", flush=True
    )
    written = run_all(profile, args)
    return 1 if written["failed"] else 0
