"""Where each simulator holds: every simulator of the zoo swept to the extremes, each run with a verdict.

Usage::

    python -m benchmarks.extremes                      # full profile (hours on 2 cores; prints the estimate)
    python -m benchmarks.extremes --quick              # CI size: dam_small, 20 steps, two values an axis
    python -m benchmarks.extremes --axes dt gravity --simulators mps fgn gns --threads 2

Axes (one at a time, everything else at the scene's values): the time step (0.5 ms to past the CFL
limit), gravity (1 to 100 m/s^2), viscosity (1e-6 to 0.1 m^2/s), the particle count (1k to 80k fluid
particles), the rollout length (1 s and 10 s of the dam with the walls raised so the spray stays in),
float32 and float64, an initial velocity at the wall (wall tunnelling; past the Courant limit the guard
refuses the start) and the start (a gap of one l0, touching at l0, overlapping a wall layer).

Every run is ``task=evaluate`` (:mod:`lagfluid.tasks.evaluate`) of the simulator's Table 3 row file against
the MPS reference at the same setting (on the dt axis: MPS at the scene's 2 ms, frames matched by time),
through :class:`benchmarks.tables.bench.Bench`, so the numbers are the tables'. Verdicts (:func:`verdict`):

* **stable**: the run completed, its mean Chamfer distance to the reference is at most
  :data:`DEGRADED_CHAMFER_L0` l0 and its mean density error at most :data:`DEGRADED_DENSITY_FACTOR` times
  the reference's;
* **degraded**: it completed beyond either bound;
* **stopped**: the rollout guard stopped it at step k (its reason: NaN, a particle leaving the domain, the
  Courant limit), the start included;
* **refused**: the configuration was refused before the first step (the message says why);
* **no reference**: the MPS reference at that setting stopped (MPS's own row says where), so a learned
  model has nothing to be compared with;
* **n/a**: the axis does not apply (a model that steps by its training frames' spacing on the dt axis).

MPS rows are compared with MPS at the same setting, so off the dt axis they can only be stable or stopped;
``mps_corrected`` is the corrected-gradient solver profile. Outputs (``benchmarks/results/``, prefix
``extremes`` or ``extremes_quick``): ``<prefix>.md`` (a table per axis, the holds summary, provenance),
``<prefix>.csv`` (every run), ``<prefix>_<axis>.png`` (Chamfer distance and density-error ratio against the
axis value). The full profile rewrites the README's "Where each simulator holds" table (between
``<!-- extremes:start -->`` and ``<!-- extremes:end -->``); ``--readme`` makes any profile do so.
"""

from __future__ import annotations

import argparse
import csv
import logging
import math
import os
import re
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch

from benchmarks.provenance import provenance, write_results
from benchmarks.tables.bench import Bench, Run
from benchmarks.tables.config import row_file
from benchmarks.tables.profiles import QUICK
from benchmarks.tables.report import REPO, RESULTS, write_readme
from benchmarks.tables.rows import fmt, md_table
from benchmarks.tables.simulators import GROUND_TRUTH, Simulator, all_simulators

log = logging.getLogger("benchmarks.extremes")

DEGRADED_CHAMFER_L0 = 0.5
"""A completed run is degraded beyond this mean Chamfer distance to the reference, in l0 (25 mm at 5 cm;
the shipped FGN's 1 s dam: 0.37 l0, ``benchmarks/results/fgn_recipe.md``)."""
DEGRADED_DENSITY_FACTOR = 3.0
"""... or beyond this many times the reference's mean density error (the shipped FGN's dam: 1.28) ..."""
DENSITY_ERROR_FLOOR = 0.005
"""... and beyond this mean density error: MPS's own over the 1 s dam is 0.57 % (``tables_table3.csv``), but
over the particle axis' first 0.08 s only 0.05-0.13 % (``extremes.csv``), where a ratio to it says nothing
about a model's use (FGN's 0.35 % there would read "7.5x")."""
VERDICTS = ("stable", "degraded", "stopped", "refused", "no reference", "n/a")
NO_REFERENCE = "the MPS reference stopped"
README_START, README_END = "<!-- extremes:start -->", "<!-- extremes:end -->"
CORRECTED = "mps_corrected"


@dataclass(frozen=True)
class Axis:
    """One swept quantity.

    Attributes:
        key: the axis's name (``dt``, ``gravity``, ...), on the command line and in the file names.
        label: the axis as the tables and plots name it, with its unit.
        nominal: the value every other axis runs at.
        overrides: ``value -> (scene, extra overrides)`` of a run at that value (scene: the profile's
            ``scene`` unless the axis needs another).
        show: ``value -> cell header`` (``2 ms``).
        log_scale: plot the values on a log axis.
        duration: ``profile -> simulated seconds`` of a run at a value (the profile's ``duration`` unless
            the axis is the length itself).
    """

    key: str
    label: str
    nominal: Any
    overrides: Callable[[Any, str], tuple[str, list[str]]]
    show: Callable[[Any], str]
    log_scale: bool = True
    duration: Callable[[Any, ExtremesProfile], float] | None = None


@dataclass(frozen=True)
class ExtremesProfile:
    """How big a sweep is.

    Attributes:
        name: ``full`` or ``quick`` (the run folder under ``runs/extremes``).
        prefix: file prefix in ``benchmarks/results``.
        scene: the dam every axis but the particle count runs (``dam_small``: 640 fluid particles).
        duration: simulated seconds of a run (a multiple of every dt of the dt axis and of the frames).
        frame_interval: seconds between compared frames.
        values: the values of every axis.
        particles_duration: simulated seconds of the particle-count runs (80k MPS steps are ~3 s each).
        simulators: the keys swept (None: every simulator with a Table 3 or 5 dam row, and mps_corrected).
        description: one line on the profile, printed in the report.
    """

    name: str
    prefix: str
    scene: str
    duration: float
    frame_interval: float
    values: dict[str, tuple[Any, ...]]
    particles_duration: float
    simulators: tuple[str, ...] | None
    description: str


# Fluid column and tank (l0) of the particle-count axis: the dam's 1:2 column in a tank 4 columns long.
DAMS = {
    1024: ([8, 8, 16], [33, 9]),
    4000: ([10, 20, 20], [41, 21]),
    10000: ([20, 25, 20], [81, 26]),
    40000: ([20, 50, 40], [81, 51]),
    80000: ([20, 100, 40], [81, 101]),
    1000000: ([50, 200, 100], [201, 201]),
}
STARTS = {"gap": [2, 1, 1], "touching": [1, 1, 1], "overlapping": [0, 1, 1]}
LONG_WALL_HEIGHT = 60  # l0: three times dam_small's column, so the 10 s of sloshing stay in the tank


def _vector(values: Sequence[float]) -> str:
    return "[" + ",".join(repr(v) for v in values) + "]"


AXES: dict[str, Axis] = {
    a.key: a
    for a in (
        Axis("dt", "time step (ms)", 0.002, lambda v, s: (s, []), lambda v: f"{1e3 * v:g} ms"),
        Axis(
            "gravity",
            "gravity (m/s^2)",
            9.8065,
            lambda v, s: (s, [f"scene.params.gravity={_vector([0.0, 0.0, -v])}"]),
            lambda v: f"{v:g}",
        ),
        Axis(
            "viscosity",
            "viscosity (m^2/s)",
            1e-6,
            lambda v, s: (s, [f"scene.params.viscosity={v!r}"]),
            lambda v: f"{v:g}",
        ),
        Axis(
            "particles",
            "fluid particles",
            4000,
            lambda v, s: (
                "dam",
                [f"scene.fluid_size={_vector(DAMS[v][0])}", f"scene.tank_size={_vector(DAMS[v][1])}"],
            ),
            lambda v: f"{v:,}",
            duration=lambda v, p: p.particles_duration,
        ),
        Axis(
            "length",
            "rollout length (s)",
            1.0,
            lambda v, s: (s, [f"scene.wall_height={LONG_WALL_HEIGHT}"]),
            lambda v: f"{v:g} s",
            duration=lambda v, p: float(v),
        ),
        Axis("dtype", "precision", "float32", lambda v, s: (s, [f"dtype={v}"]), str, log_scale=False),
        Axis(
            "velocity",
            "initial speed at the wall (m/s)",
            0.0,
            lambda v, s: (s, [f"scene.velocity={_vector([-v, 0.0, 0.0])}"]),
            lambda v: f"{v:g}",
            log_scale=False,
        ),
        Axis(
            "start",
            "start",
            "touching",
            lambda v, s: (s, [f"scene.fluid_lower={_vector(STARTS[v])}"]),
            str,
            log_scale=False,
        ),
    )
}

FULL = ExtremesProfile(
    name="full",
    prefix="extremes",
    scene="dam_small",
    duration=0.4,
    frame_interval=0.04,
    values={
        "dt": (0.0005, 0.001, 0.002, 0.004, 0.008, 0.02),  # divisors of the 40 ms frames
        "gravity": (1.0, 9.8065, 30.0, 100.0),
        "viscosity": (1e-6, 1e-4, 1e-2, 0.1),
        "particles": (1024, 4000, 10000, 40000, 80000),
        "length": (1.0, 10.0),
        "dtype": ("float32", "float64"),
        "velocity": (0.0, 2.0, 5.0, 10.0, 20.0),
        "start": ("gap", "touching", "overlapping"),
    },
    particles_duration=0.08,
    simulators=None,
    description=(
        "dam_small (640 fluid particles) for 0.4 s, frames every 40 ms; particle counts on the dam's column "
        "for 0.08 s; lengths 1 s and 10 s (5,000 steps of 2 ms) with the walls at 60 l0"
    ),
)

QUICK_EXTREMES = ExtremesProfile(
    name="quick",
    prefix="extremes_quick",
    scene="dam_small",
    duration=0.04,
    frame_interval=0.04,
    values={
        "dt": (0.002, 0.04),
        "gravity": (1.0, 100.0),
        "viscosity": (1e-6, 0.1),
        "particles": (1024,),
        "length": (0.08,),
        "dtype": ("float32", "float64"),
        "velocity": (5.0, 20.0),
        "start": ("touching", "overlapping"),
    },
    particles_duration=0.04,
    simulators=("mps", "fgn"),
    description="QUICK profile (CI smoke run): dam_small for 0.04 s, two values an axis, MPS and FGN only",
)


# ------------------------------------------------------------------------------------------- verdicts
def verdict(run: Run, l0: float) -> tuple[str, str]:
    """The run's verdict (one of :data:`VERDICTS`) and its reason, from evaluate's metrics (module doc)."""
    if run.info.get("not_applicable"):
        return "n/a", str(run.info["not_applicable"])
    if not run.ok:
        error = run.error.split(": ", 1)[-1]
        if NO_REFERENCE in error:  # MPS's own stop; a learned model then has nothing to be compared with
            reason = short_reason(error.split("nothing to compare with: ", 1)[-1])
            if run.sim.key in (GROUND_TRUTH, CORRECTED):
                return "stopped", reason
            return "no reference", f"MPS stopped: {reason}"
        return "refused", error
    m = run.metrics or {}
    if not m.get("complete"):
        return "stopped", short_reason(str(m.get("stop_reason", "")))
    chamfer_l0 = run.summary("chamfer_mm", "mean") / (1e3 * l0)
    density = run.summary("density_error", "model", "mean")
    reference = run.summary("density_error", "reference", "mean")
    ratio = density / reference if reference > 0 else math.nan
    return completed_verdict(chamfer_l0, density, ratio)


def completed_verdict(chamfer_l0: float, density: float, ratio: float) -> tuple[str, str]:
    """``stable`` or ``degraded`` (with the reasons) of a completed run.

    From its mean Chamfer distance to the reference in l0, its mean density error and that error over the
    reference's.
    """
    reasons = []
    if chamfer_l0 > DEGRADED_CHAMFER_L0:
        reasons.append(f"Chamfer {chamfer_l0:.2g} l0 > {DEGRADED_CHAMFER_L0:g}")
    if ratio > DEGRADED_DENSITY_FACTOR and density > DENSITY_ERROR_FLOOR:
        reasons.append(
            f"density error {ratio:.2g}x MPS's > {DEGRADED_DENSITY_FACTOR:g}x, "
            f"{100 * density:.2g} % > {100 * DENSITY_ERROR_FLOOR:g} %"
        )
    if not math.isfinite(chamfer_l0) or not math.isfinite(density):
        reasons.append("no finite error")
    return ("degraded", "; ".join(reasons)) if reasons else ("stable", "")


def short_reason(reason: str) -> str:
    """The guard's message without coordinates and advice: ``step 12: fluid particle 3 left the domain``."""
    return re.split(r" at \[| \[|; | \(", reason)[0]


def stop_step(reason: str) -> int | None:
    """The step a guard message names (``step 12: ...``), None when it names none."""
    found = re.match(r"step (\d+):", reason)
    return int(found[1]) if found else None


WORDS = {"stable": "stable", "degraded": "degraded", "stopped": "stops", "refused": "refused"}
WORDS["no reference"] = "no MPS reference"


def holds(axis: Axis, cells: Sequence[tuple[Any, str]]) -> str:
    """One line of where a simulator holds on ``axis``: its runs of equal verdicts, in the axis's order.

    ``stable 0.5 ms..2 ms; stops 4 ms..20 ms``: each segment is consecutive values of one verdict, so a range
    never spans a value of another verdict; n/a values are left out.

    Args:
        axis: the axis.
        cells: ``(value, verdict)`` in the axis's order.
    """
    segments: list[tuple[str, list[str]]] = []
    for value, got in cells:
        if got not in WORDS:
            continue
        if segments and segments[-1][0] == got:
            segments[-1][1].append(axis.show(value))
        else:
            segments.append((got, [axis.show(value)]))
    parts = [f"{WORDS[k]} {v[0]}" + (f"..{v[-1]}" if len(v) > 1 else "") for k, v in segments]
    return "; ".join(parts) or "n/a"


# ------------------------------------------------------------------------------------------- running
@dataclass(frozen=True)
class Entry:
    """A simulator of the sweep: the tables' simulator, its row file and extra overrides."""

    sim: Simulator
    row: str | None
    extra: tuple[str, ...] = ()


def entries(keys: Sequence[str] | None) -> list[Entry]:
    """Every simulator with a Table 3 or Table 5 dam row (the tables' order), and the corrected MPS profile.

    Raises:
        ValueError: a key of ``keys`` that is not one of them (the message lists them).
    """
    out = []
    for sim in all_simulators():
        row = row_file(f"table3_dam_{sim.key}") or row_file(f"table5_dam_{sim.key}")
        if sim.rows and row is None:  # a timing-only key (Table 2)
            continue
        out.append(Entry(sim, row))
        if sim.key == GROUND_TRUTH:
            corrected = replace(sim, key=CORRECTED, label="MPS (corrected gradient profile)")
            out.append(Entry(corrected, row, ("solver=mps_corrected",)))
    if keys is not None:
        unknown = sorted(set(keys) - {e.sim.key for e in out})
        if unknown:
            raise ValueError(f"unknown simulators {unknown}; available: {', '.join(e.sim.key for e in out)}")
        out = [e for e in out if e.sim.key in keys]
    return out


def sweep_run(bench: Bench, profile: ExtremesProfile, axis: Axis, value: Any, entry: Entry) -> Run:
    """Evaluate ``entry`` at ``value`` of ``axis`` (memoised by :class:`Bench`); n/a runs are not run."""
    # a folder name Hydra takes as one override value: no commas ("1,024" would be a sweep), no spaces
    key = f"{axis.key}/{re.sub(r'[^A-Za-z0-9._-]', '', axis.show(value))}/{entry.sim.key}"
    label = entry.sim.label
    scene, extra = axis.overrides(value, profile.scene)
    duration = axis.duration(value, profile) if axis.duration else profile.duration
    own = bench.own_dt(entry.sim)
    if axis.key == "dt":
        if own is not None and not math.isclose(own, value):
            run = Run(key, label, entry.sim, entry.row, [])
            run.info["not_applicable"] = f"steps by its training frames' {1e3 * own:g} ms"
            return run
        dt = value
    else:
        dt = own
    overrides = [*entry.extra, *bench.dam_overrides(scene, duration, dt=dt, extra=extra)]
    return bench.evaluate(Run(key, label, entry.sim, entry.row, overrides), one_step=False)


def result_rows(runs: Sequence[tuple[Axis, Any, Run]], l0: float) -> list[dict[str, Any]]:
    """One CSV row per run: axis, value, simulator, verdict and the numbers behind it."""
    rows = []
    for axis, value, run in runs:
        kind, reason = verdict(run, l0)
        m = run.metrics or {}
        density = run.summary("density_error", "model", "mean")
        reference = run.summary("density_error", "reference", "mean")
        rows.append(
            {
                "axis": axis.key,
                "value": value,
                "simulator": run.sim.key,
                "verdict": kind,
                "reason": reason,
                "steps": m.get("steps"),
                "steps_requested": m.get("steps_requested"),
                "chamfer_mean_mm": run.summary("chamfer_mm", "mean"),
                "density_error_mean": density,
                "density_error_ratio_to_mps": density / reference if reference > 0 else math.nan,
                "divergence_mean_per_s": run.summary("velocity_divergence_per_s", "model", "mean"),
                "fluid_particles": (m.get("particles") or {}).get("fluid"),
                "wall_s": run.info.get("wall_s", math.nan),
                "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                "command": "" if run.info.get("not_applicable") else run.command,
            }
        )
    return rows


def cell(row: dict[str, Any]) -> str:
    """A table cell: the verdict and its number (Chamfer mm, or the step the guard stopped at)."""
    kind = row["verdict"]
    if kind in ("stable", "degraded"):
        ratio = row["density_error_ratio_to_mps"]
        return f"{kind} {fmt(row['chamfer_mean_mm'], 2)} mm, {fmt(ratio, 2)}x"
    if kind == "stopped":
        step = stop_step(row["reason"])
        return f"stopped @{row['steps'] if step is None else step}"
    return kind


def axis_markdown(axis: Axis, values: Sequence[Any], rows: Sequence[dict[str, Any]], order: list[str]) -> str:
    """The table of one axis: a row per simulator, a column per value, and the reasons under it."""
    by = {(r["simulator"], r["value"]): r for r in rows if r["axis"] == axis.key}
    table = [[sim, *(cell(by[(sim, v)]) if (sim, v) in by else "-" for v in values)] for sim in order]
    notes = sorted(
        {
            f"- {r['simulator']} at {axis.show(r['value'])}: {r['verdict']}: {r['reason']}"
            for r in by.values()
            if r["verdict"] in ("stopped", "refused", "degraded", "no reference") and r["reason"]
        }
    )
    text = f"### {axis.label}\n\n" + md_table(["simulator", *(axis.show(v) for v in values)], table)
    return text + ("\n\n" + "\n".join(notes) if notes else "")


def holds_markdown(
    axes: Sequence[Axis], values: dict[str, Sequence[Any]], rows: Sequence[dict[str, Any]], order: list[str]
) -> str:
    """The summary: a row per simulator, a column per axis, each cell :func:`holds`."""
    table = []
    for sim in order:
        line = [sim]
        for axis in axes:
            got = {r["value"]: r["verdict"] for r in rows if r["axis"] == axis.key and r["simulator"] == sim}
            line.append(holds(axis, [(v, got[v]) for v in values[axis.key] if v in got]))
        table.append(line)
    return md_table(["simulator", *(a.label for a in axes)], table, "l" + "l" * len(axes))


def plot_axis(
    path: Path, axis: Axis, values: Sequence[Any], rows: Sequence[dict[str, Any]], order: list[str]
) -> None:
    """Chamfer distance and density-error ratio against the axis value, a line per simulator.

    Stable runs are filled circles, degraded ones open squares; a run the guard stopped or that was refused
    is an x on the top edge of each panel.
    """
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, panels = plt.subplots(1, 2, figsize=(11, 4.2))
    for panel in panels:  # up to 20 simulators, each its own colour
        panel.set_prop_cycle(color=plt.get_cmap("tab20").colors)
    xs = {v: (float(v) if axis.log_scale else i) for i, v in enumerate(values)}
    for sim in order:
        mine = [r for r in rows if r["axis"] == axis.key and r["simulator"] == sim and r["value"] in xs]
        for panel, column in zip(panels, ("chamfer_mean_mm", "density_error_ratio_to_mps"), strict=True):
            done = [r for r in mine if r["verdict"] in ("stable", "degraded") and math.isfinite(r[column])]
            (line,) = panel.plot(
                [xs[r["value"]] for r in done], [max(r[column], 1e-3) for r in done], "-", label=sim, lw=1.2
            )
            for r in done:
                filled = r["verdict"] == "stable"
                panel.plot(
                    xs[r["value"]],
                    max(r[column], 1e-3),
                    "o" if filled else "s",
                    color=line.get_color(),
                    mfc=line.get_color() if filled else "none",
                )
            for r in mine:
                if r["verdict"] in ("stopped", "refused", "no reference"):
                    panel.plot(
                        xs[r["value"]],
                        1.0,
                        "x",
                        color=line.get_color(),
                        ms=9,
                        mew=2,
                        transform=panel.get_xaxis_transform(),
                        clip_on=False,
                    )
    for panel, title in zip(
        panels, ("mean Chamfer distance to MPS (mm)", "density error / MPS's"), strict=True
    ):
        panel.set_yscale("log")
        panel.set_title(title, fontsize=10)
        panel.set_xlabel(axis.label)
        if axis.log_scale:
            panel.set_xscale("log")
            panel.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        panel.set_xticks(list(xs.values()), [axis.show(v) for v in values])
        panel.grid(alpha=0.3, which="both")
    panels[1].axhline(DEGRADED_DENSITY_FACTOR, color="grey", ls="--", lw=0.8)
    panels[0].legend(fontsize=7, ncol=2)
    fig.suptitle(
        f"{axis.label}: o stable, open square degraded, x at the top stopped, refused or without reference "
        "(0, e.g. MPS against itself, drawn at 1e-3)",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def estimate_seconds(profile: ExtremesProfile, axes: Sequence[Axis], simulators: int) -> float:
    """A rough runtime: per fluid particle and step ~40 us for MPS (references included), ~20 us learned."""
    total = 0.0
    for axis in axes:
        for value in profile.values[axis.key]:
            n = value if axis.key == "particles" else 640
            duration = axis.duration(value, profile) if axis.duration else profile.duration
            steps = duration / (value if axis.key == "dt" else 0.002)
            total += steps * n * (40e-6 + (simulators - 1) * 20e-6) + 2.0 * simulators
    return total


def _read_row(row: dict[str, str], l0: float) -> dict[str, Any]:
    """A CSV row with its numbers as numbers again (the value as its axis's type).

    A completed run is judged again by :func:`completed_verdict` (rows of an earlier criterion).
    """
    out: dict[str, Any] = dict(row)
    for key in (
        "chamfer_mean_mm",
        "density_error_mean",
        "density_error_ratio_to_mps",
        "divergence_mean_per_s",
        "wall_s",
    ):
        out[key] = float(row[key]) if row.get(key) not in (None, "") else math.nan
    for key in ("steps", "steps_requested", "fluid_particles"):
        out[key] = int(row[key]) if row.get(key) not in (None, "", "None") else None
    if out["verdict"] == "refused" and NO_REFERENCE in str(out.get("reason", "")):  # rows of older runs
        out["verdict"] = "no reference"
    if out["verdict"] in ("stable", "degraded"):
        chamfer_l0 = out["chamfer_mean_mm"] / (1e3 * l0)
        out["verdict"], out["reason"] = completed_verdict(
            chamfer_l0, out["density_error_mean"], out["density_error_ratio_to_mps"]
        )
    nominal = AXES[row["axis"]].nominal
    out["value"] = row["value"] if isinstance(nominal, str) else type(nominal)(float(row["value"]))
    return out


def merged_rows(path: Path, new: list[dict[str, Any]], l0: float) -> tuple[list[dict[str, Any]], int]:
    """``new`` plus the rows of ``path`` (an earlier run of the profile) that it does not redo.

    A run of some axes or simulators (``--axes``, ``--simulators``) so completes the profile's results
    instead of replacing them. Returns the rows (in axis order) and how many were kept from ``path``.
    """
    done = {(r["axis"], str(r["value"]), r["simulator"]) for r in new}
    earlier: list[dict[str, Any]] = []
    if path.is_file():
        with open(path, newline="") as f:
            earlier = [
                _read_row(r, l0)
                for r in csv.DictReader(f)
                if r.get("axis") in AXES and (r["axis"], r["value"], r["simulator"]) not in done
            ]
    rank = {key: i for i, key in enumerate(AXES)}
    rows = sorted(earlier + new, key=lambda r: rank[r["axis"]])  # stable: values keep their order
    return rows, len(earlier)


def run_sweep(profile: ExtremesProfile, args: argparse.Namespace) -> dict[str, Any]:
    """Run the sweep and write its files; returns ``rows`` and ``files``."""
    start, load = time.perf_counter(), os.getloadavg()[0]
    torch.set_num_threads(int(args.threads))
    axes = [AXES[k] for k in (args.axes or profile.values)]
    chosen = entries(args.simulators or profile.simulators)
    tables_profile = replace(QUICK, name=f"extremes_{profile.name}", frame_interval=profile.frame_interval)
    bench_args = argparse.Namespace(threads=args.threads, weights=None, runs_dir=args.runs_dir)
    bench = Bench(tables_profile, bench_args)
    if args.redraw:
        print("[extremes] --redraw: the tables and plots again from the csv; nothing runs", flush=True)
    else:
        print(
            f"[extremes] {len(axes)} axes x {len(chosen)} simulators; estimated "
            f"{estimate_seconds(profile, axes, len(chosen)) / 60:.0f} min",
            flush=True,
        )
    runs = []
    for axis in [] if args.redraw else axes:  # --redraw: the tables and plots of the csv, no run
        for value in profile.values[axis.key]:
            for entry in chosen:
                try:
                    run = sweep_run(bench, profile, axis, value, entry)
                except Exception as err:  # a cell that cannot even be set up is refused, the sweep goes on
                    key = f"{axis.key}/{value}/{entry.sim.key}"
                    run = Run(key, entry.sim.label, entry.sim, entry.row, [])
                    run.error = f"{type(err).__name__}: {err}".splitlines()[0]
                runs.append((axis, value, run))
    l0 = float(bench.scene(profile.scene).params.l0)
    out = Path(args.results)
    out.mkdir(parents=True, exist_ok=True)
    files = [out / f"{profile.prefix}.csv", out / f"{profile.prefix}.md"]
    rows, kept = merged_rows(files[0], result_rows(runs, l0), l0)
    # the tables' order of every simulator (a --simulators rerun does not move its rows to the top), then
    # any key the csv holds that is no simulator any more
    present = {r["simulator"] for r in rows}
    order = [e.sim.key for e in entries(None) if e.sim.key in present]
    order += sorted(present - set(order))
    axes = [a for a in AXES.values() if any(r["axis"] == a.key for r in rows)]
    for axis in axes:
        path = out / f"{profile.prefix}_{axis.key}.png"
        plot_axis(path, axis, profile.values[axis.key], rows, order)
        files.append(path)
    elapsed = time.perf_counter() - start
    prov = provenance(
        "benchmarks.extremes", load, runtime=f"{elapsed / 60:.1f} min", profile=profile.description
    )
    summary = holds_markdown(axes, profile.values, rows, order)
    counts = ", ".join(f"{sum(r['verdict'] == v for r in rows)} {v}" for v in VERDICTS)
    spent = sum(float(r["wall_s"]) for r in rows if math.isfinite(float(r["wall_s"])))
    counts += f" ({spent / 3600:.1f} h of runs, each row's command and seconds in the csv)"
    if kept:
        prov["earlier rows"] = (
            f"{kept} rows of other axes or simulators kept from earlier runs (their date in the csv)"
        )
    intro = (
        f"# Where each simulator holds ({profile.name} profile)\n\n{profile.description}. {len(rows)} runs: "
        f"{counts}. A run is *stable* when it completes within {DEGRADED_CHAMFER_L0:g} l0 mean Chamfer "
        f"distance of the MPS reference at the same setting (on the dt axis: MPS at 2 ms) and "
        f"{DEGRADED_DENSITY_FACTOR:g}x its mean density error (or under {100 * DENSITY_ERROR_FLOOR:g} %), "
        "*degraded* beyond either, *stopped* when the "
        "rollout guard ended it (step and reason below), *refused* when the configuration was refused "
        "before the first step, *no reference* when MPS itself stopped there (`benchmarks/extremes.py`). "
        "Cells: verdict, mean Chamfer distance, density error over MPS's."
    )
    body = (
        f"## Summary\n\n{summary}\n\n## Per axis\n\n"
        + "\n\n".join(axis_markdown(a, profile.values[a.key], rows, order) for a in axes)
        + f"\n\nEvery run's numbers and command: `{files[0].name}`."
    )
    write_results(out, profile.prefix, rows, intro, prov, body)  # files[0] and files[1]
    readme = False
    if profile.name == "full" or args.readme:
        readme = write_readme(
            f"{summary}\n\nStable: within {DEGRADED_CHAMFER_L0:g} l0 and {DEGRADED_DENSITY_FACTOR:g}x MPS's "
            f"density error (or under {100 * DENSITY_ERROR_FLOOR:g} %) of MPS at the same setting; "
            f"{profile.description} "
            f"(`benchmarks/results/{profile.prefix}.md`).",
            Path(args.readme_path),
            (README_START, README_END),
        )
    print(f"[extremes] {counts} in {elapsed / 60:.1f} min: {', '.join(str(f) for f in files)}", flush=True)
    return {"rows": rows, "files": files, "readme": readme}


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m benchmarks.extremes``."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.extremes", description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="the CI profile")
    parser.add_argument("--axes", nargs="+", choices=list(AXES), help="only these axes")
    parser.add_argument("--simulators", nargs="+", help="only these simulator keys")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--runs-dir", default="runs/extremes", help="rollouts and MPS references")
    parser.add_argument("--results", default=str(RESULTS))
    parser.add_argument("--readme", action="store_true", help="rewrite the README's table from this profile")
    parser.add_argument("--redraw", action="store_true", help="only redraw tables and plots from the csv")
    parser.add_argument("--readme-path", default=str(REPO / "README.md"))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        run_sweep(QUICK_EXTREMES if args.quick else FULL, args)
    except ValueError as err:
        sys.stderr.write(f"benchmarks.extremes: {err}\n")
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
