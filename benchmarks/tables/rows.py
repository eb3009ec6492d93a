"""The CSV rows of each part, computed from the runs' metrics, and the cells of the markdown tables."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from typing import Any

import numpy as np

from benchmarks.pareto import pareto_front
from benchmarks.tables.bench import Run
from benchmarks.tables.simulators import GROUND_TRUTH, Simulator

TRADEOFF_METRICS = ("chamfer_mean_mm", "density_error_mean")


def fmt(value: Any, digits: int = 3) -> str:
    """A table cell: ``digits`` significant digits for floats, '-' for missing values."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}g}" if abs(value) < 10**digits else f"{value:,.0f}"
    return str(value)


def md_table(header: Sequence[str], rows: Sequence[Sequence[Any]], align: str | None = None) -> str:
    """A markdown table; ``align`` gives l, r or c per column (default: first left, others right)."""
    align = align or "l" + "r" * (len(header) - 1)
    sep = [{"l": "---", "r": "---:", "c": ":---:"}[a] for a in align]
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join(sep) + " |"]
    lines += ["| " + " | ".join(c if isinstance(c, str) else fmt(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def status(run: Run) -> str:
    """How a row ended, for the tables: complete, stopped (by the guard, where), skipped or failed (why)."""
    if not run.ok:
        return f"{'skipped' if run.skipped else 'failed'}: {run.error}"
    if not run.complete:
        # the guard's message without its coordinates and advice: "step 12: fluid particle 3 left the domain"
        reason = re.split(r" at \[| \[|; | \(", str(run.metrics.get("stop_reason", "")))[0]
        return f"stopped: {reason}"
    return "complete"


def seconds_per_simulated_second(run: Run) -> float:
    """Wall seconds of the steps over the simulated seconds they covered (NaN without steps)."""
    m = run.metrics or {}
    steps, dt = int(m.get("steps") or 0), float(m.get("dt") or 0.0)
    total = float((m.get("timing") or {}).get("steps_total_s", math.nan))
    return total / (steps * dt) if steps and dt else math.nan


def chamfer_at_start(run: Run) -> float:
    """The Chamfer distance at t = 0 (mm): 0 at the reference's spacing, the lattice offset otherwise."""
    values = ((run.metrics or {}).get("frames") or {}).get("chamfer_mm") or []
    return float(values[0]) if values and values[0] is not None else math.nan


def provenance_columns(run: Run) -> dict[str, Any]:
    """Where a row's numbers come from: its experiment file, overrides, commit and time of the run."""
    return {
        "experiment": run.experiment or "",
        "overrides": " ".join(run.overrides),
        "git_commit": (run.metrics or {}).get("git_commit", ""),
        "created": (run.metrics or {}).get("created", ""),
    }


def table3_rows(case: str, runs: list[Run]) -> list[dict[str, Any]]:
    """CSV rows of Tables 1/3: every simulator; MPS's row is the ground truth's own field metrics."""
    rows = []
    for run in runs:
        is_gt = run.sim.key == GROUND_TRUTH
        who = "reference" if is_gt else "model"
        rows.append(
            {
                "case": case,
                "simulator": "Ground truth (MPS)" if is_gt else run.label,
                "density_error_mean": run.summary("density_error", who, "mean"),
                "density_error_max": run.summary("density_error", who, "max"),
                "divergence_mean_per_s": run.summary("velocity_divergence_per_s", who, "mean"),
                "divergence_max_per_s": run.summary("velocity_divergence_per_s", who, "max"),
                "chamfer_mean_mm": math.nan if is_gt else run.summary("chamfer_mm", "mean"),
                "chamfer_max_mm": math.nan if is_gt else run.summary("chamfer_mm", "max"),
                "fluid_particles": ((run.metrics or {}).get("particles") or {}).get("fluid"),
                "steps": (run.metrics or {}).get("steps"),
                "status": status(run),
                **provenance_columns(run),
            }
        )
    return rows


def table2_rows(runs: list[Run]) -> list[dict[str, Any]]:
    """CSV rows of Table 2, with each simulator's speed-up over MPS (time per step ratio)."""
    mps_ms = next((r.metrics["step_ms"] for r in runs if r.sim.key == GROUND_TRUTH and r.ok), math.nan)
    rows = []
    for run in runs:
        m = run.metrics or {}
        rows.append(
            {
                "simulator": run.label,
                "parameters": m.get("parameters"),
                "fluid_particles": m.get("fluid"),
                "step_ms": m.get("step_ms", math.nan),
                "inference_ms": m.get("inference_ms", math.nan),
                "neighbor_search_ms": m.get("neighbors_ms", math.nan),
                "speedup_vs_mps": ratio(mps_ms, m.get("step_ms", math.nan)),
                "warmup_steps": m.get("warmup_steps"),
                "timed_steps": m.get("timed_steps"),
                "stages_ms": " ".join(f"{k}={v:.1f}" for k, v in (m.get("stages_ms") or {}).items()),
                "status": "complete" if run.ok else status(run),
                **provenance_columns(run),
            }
        )
    return rows


def mean_std(values: Sequence[float | None]) -> tuple[float, float, int]:
    """Mean and (population) standard deviation of the finite values, and how many there were."""
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], dtype=float)
    if not v.size:
        return math.nan, math.nan, 0
    return float(v.mean()), float(v.std()), int(v.size)


def table4_rows(adv_runs: list[Run], pressure_runs: list[Run]) -> list[dict[str, Any]]:
    """CSV rows of Table 4: advection nMAE per sequence and over the sequences; PPE residual over frames."""
    rows: list[dict[str, Any]] = []
    for run in adv_runs:
        g, nu = run.info["material"]
        frames = ((run.metrics or {}).get("frames") or {}).get("advection_nmae", [])
        mean, std, n = mean_std(frames)
        rows.append(
            {
                "network": "advection",
                "case": f"g={g:g} nu={nu:g}",
                "metric": "normalised MAE (eq. 32): mean +- std over the stored steps",
                "mean": mean,
                "std": std,
                "n": n,
                "status": status(run),
                **provenance_columns(run),
            }
        )
    mean, std, n = mean_std([r["mean"] for r in rows])
    rows.append(
        {
            "network": "advection",
            "case": "all sequences",
            "metric": "normalised MAE (eq. 32): mean +- std of the sequences' means",
            "mean": mean,
            "std": std,
            "n": n,
            "status": "",
            **provenance_columns(Run("", "", Simulator("", "", ""), "table4_advection", [])),
        }
    )
    for run in pressure_runs:
        frames = ((run.metrics or {}).get("frames") or {}).get("ppe_relative_residual", [])
        mean, std, n = mean_std(frames)
        rows.append(
            {
                "network": "pressure",
                "case": f"{run.label}, dam",
                "metric": "PPE relative residual (eq. 31): mean +- std over the stored steps",
                "mean": mean,
                "std": std,
                "n": n,
                "status": status(run),
                **provenance_columns(run),
            }
        )
    return rows


def tradeoff_rows(runs: list[Run]) -> list[dict[str, Any]]:
    """CSV rows of the trade-off with their Pareto flags (only complete runs can be on a front)."""
    rows = []
    for run in runs:
        m = run.metrics or {}
        timing = m.get("timing") or {}
        rows.append(
            {
                "simulator": run.label,
                "simulator_key": run.sim.key,  # the plot's colour: a simulator and its variants share one
                "s_per_simulated_s": seconds_per_simulated_second(run),
                "ms_per_step_median": 1e3 * float(timing.get("time_per_step_median_s", math.nan)),
                "chamfer_mean_mm": run.summary("chamfer_mm", "mean"),
                "chamfer_max_mm": run.summary("chamfer_mm", "max"),
                "chamfer_t0_mm": chamfer_at_start(run),
                "density_error_mean": run.summary("density_error", "model", "mean"),
                "divergence_mean_per_s": run.summary("velocity_divergence_per_s", "model", "mean"),
                "dt_s": m.get("dt"),
                "fluid_particles": (m.get("particles") or {}).get("fluid"),
                "steps": m.get("steps"),
                "reference": (m.get("reference") or {}).get("key_hash", ""),
                "status": status(run),
                **provenance_columns(run),
            }
        )
    for metric in TRADEOFF_METRICS:
        points = [
            (r["s_per_simulated_s"], r[metric]) if r["status"] == "complete" else (math.nan,) * 2
            for r in rows
        ]
        front = set(pareto_front(points))
        for i, r in enumerate(rows):
            r[f"pareto_{metric}"] = i in front
    return rows


def ratio(a: float | None, b: float | None) -> float:
    """``a / b``; NaN when either is missing or ``b`` is 0."""
    if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)) or b == 0:
        return math.nan
    return a / b
