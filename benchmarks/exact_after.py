"""Which exact stages after a learned step let GNS and CConv complete the dam (``model.exact_after``).

For each model, ``task=evaluate`` on the 1 s dam (frames every 40 ms, against the same MPS reference at
2 ms) of the plain model, + exact collision, + MPS pressure, + both (K = 1), and, where one of those does
not complete, + both with K = 3 iterations and relaxation w = 0.5 (:mod:`lagfluid.models.exact_after`).
Per row: complete, or the step the rollout guard stops it at; the mean and largest Chamfer distance to
MPS over the frames it stored, and the mean density error beside MPS's.

Each model also gets its control without a network: MPS's own step at the model's dt (explicit viscosity
and gravity where the network's step was, then the same collision rule and pressure projection), stopped
by the model's Courant guard. A "+ exact" row that is no closer than its control, or no faster, owes its
accuracy to the solver's stages, not to the network.

Usage::

    python -m benchmarks.exact_after [--models gns cconv cconv_original] [--runs-dir runs/exact_after]
        [--scene dam] [--duration 1.0] [--name exact_after]

One run at a time (``--threads`` each). A row whose folder already holds ``metrics.json`` is read, not run
again. Writes ``benchmarks/results/<name>.{md,csv}`` (``exact_after``) with provenance and each row's command.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
from pathlib import Path
from typing import Any

from benchmarks.provenance import provenance, write_results
from benchmarks.tables.config import compose_config
from lagfluid.models.exact_after import ExactAfterOptions
from lagfluid.tasks.config import build_simulator, scene_params

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
FRAME_INTERVAL = 0.04  # s, as the tables
BOTH = ("model.exact_after.collision=true", "model.exact_after.pressure=true")
VARIANTS: dict[str, tuple[str, ...]] = {
    "": (),
    "collision": ("model.exact_after.collision=true",),
    "pressure": ("model.exact_after.pressure=true",),
    "both": BOTH,
}
RELAXED = ("both_k3_w05", (*BOTH, "model.exact_after.iterations=3", "model.exact_after.relaxation=0.5"))
"""The variant run only where one of :data:`VARIANTS`' exact ones does not complete."""


def folder(runs: Path, model: str, variant: str) -> Path:
    """The run folder of ``model`` with ``variant`` (``runs/gns``, ``runs/gns_collision``)."""
    return runs / (f"{model}_{variant}" if variant else model)


def command(
    model: str, dt: float, overrides: tuple[str, ...], out: Path, args: argparse.Namespace
) -> list[str]:
    """The ``task=evaluate`` command of one row: ``args.duration`` of ``args.scene`` in the model's steps."""
    steps, every = round(args.duration / dt), round(FRAME_INTERVAL / dt)
    return [
        *("python", "-m", "lagfluid.run", "task=evaluate", f"model={model}", f"scene={args.scene}"),
        *(f"steps={steps}", f"write_every={every}", f"threads={args.threads}", "progress=false"),
        f"evaluate.reference_dir={args.reference_dir}",
        *_weights(args),
        *overrides,
        f"out_dir={out}",
    ]


def control_command(
    dt: float, max_courant: float, out: Path, args: argparse.Namespace, scene_dt: float
) -> list[str]:
    """The ``task=evaluate`` command of a model's control: ``model=mps`` stepping by the model's ``dt``.

    The guard is the model's (``max_courant``); the reference stays the models' one (the scene's dt and
    MPS's own guard), as in :func:`command`.
    """
    steps, every = round(args.duration / dt), round(FRAME_INTERVAL / dt)
    ref_steps, ref_every = round(args.duration / scene_dt), round(FRAME_INTERVAL / scene_dt)
    own_guard = compose_config(["model=mps", f"scene={args.scene}"]).solver.guard.max_courant
    reference = (
        f"evaluate.reference={{dt:null,steps:{ref_steps},write_every:{ref_every},"
        f"solver:{{guard:{{max_courant:{own_guard}}}}}}}"
    )
    return [
        *("python", "-m", "lagfluid.run", "task=evaluate", "model=mps", f"scene={args.scene}"),
        *(f"dt={dt:g}", f"steps={steps}", f"write_every={every}", f"threads={args.threads}"),
        "progress=false",
        f"solver.guard.max_courant={max_courant:g}",
        f"evaluate.reference_dir={args.reference_dir}",
        reference,
        f"out_dir={out}",
    ]


def _weights(args: argparse.Namespace) -> tuple[str, ...]:
    """``model.weights=DIR`` where ``--weights`` names a folder, else nothing (the shipped weights)."""
    return (f"model.weights={args.weights}",) if args.weights else ()


def result_row(metrics: dict[str, Any], cmd: list[str]) -> dict[str, Any]:
    """One row of the results from a run's ``metrics.json``.

    The stages are read from the run's attributes (``exact_after_*``). A stopped run is reported at the step
    the guard refused (its ``steps`` done + 1) and that step's time.
    """
    s, dt = metrics["summary"], float(metrics["dt"])
    options = {
        k.removeprefix("exact_after_"): v
        for k, v in metrics["simulator"].items()
        if k.startswith("exact_after_")
    }
    stop = metrics["steps"] + 1
    result = "complete" if metrics["complete"] else f"stops at step {stop} ({stop * dt:.3g} s)"
    density = s["density_error"]
    return {
        "simulator": metrics["model"],
        "exact stages after the step": ExactAfterOptions(**options).describe() or "none",
        "dt (ms)": f"{1e3 * dt:g}",
        "rollout": result,
        "Chamfer to MPS mean / max (mm)": f"{s['chamfer_mm']['mean']:.1f} / {s['chamfer_mm']['max']:.1f}",
        "density error mean (MPS)": f"{density['model']['mean']:.4f} ({density['reference']['mean']:.4f})",
        "command": f"`{shlex.join(cmd)}`",
    }


def _stages(row: dict[str, Any]) -> str:
    stages = row["exact stages after the step"]
    return "no exact stage" if stages == "none" else stages


def verdict(model: str, rows: list[dict[str, Any]]) -> str:
    """One sentence: which variants of ``model`` complete (the cheapest first), or the furthest one."""
    done = [r for r in rows if r["rollout"] == "complete"]
    if done:
        best = min(done, key=_mean)
        return (
            f"`{model}`: complete with {'; '.join(_stages(r) for r in done)}; "
            f"closest to MPS: {best['simulator']} ({best['Chamfer to MPS mean / max (mm)']} mm)."
        )

    far = max(rows, key=_reach)
    return f"`{model}`: none completes; the furthest is {far['simulator']}, which {far['rollout']}."


def _run(cmd: list[str], out: Path, args: argparse.Namespace) -> dict[str, Any]:
    """``out``'s metrics.json, after running ``cmd`` where it is not there yet."""
    if not (out / "metrics.json").is_file():
        print(f"[exact_after] {shlex.join(cmd)}", flush=True)
        env = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
        subprocess.run([sys.executable, *cmd[1:]], cwd=REPO, env=env, check=False)
    if not (out / "metrics.json").is_file():
        raise SystemExit(f"[exact_after] {out} holds no metrics.json: the run failed (see its output)")
    return json.loads((out / "metrics.json").read_text())


def control_row(
    model: str, dt: float, max_courant: float, args: argparse.Namespace, scene_dt: float
) -> dict[str, Any]:
    """``model``'s control: MPS's own step at ``dt`` with the model's guard (:func:`control_command`)."""
    out = folder(Path(args.runs_dir), model, "control")
    cmd = control_command(dt, max_courant, out, args, scene_dt)
    row = result_row(_run(cmd, out, args), cmd)
    row["simulator"] = f"control of {model}: MPS at {1e3 * dt:g} ms, no network"
    row["exact stages after the step"] = f"MPS's own step (Courant guard {max_courant:g})"
    print(f"[exact_after] {row['simulator']}: {row['rollout']}", flush=True)
    return row


def control_verdict(rows: list[dict[str, Any]]) -> str:
    """One sentence on a model's control (``rows[-1]``) against the model's rows (``rows[:-1]``).

    The network earns its place where a row with it completes and the control does not, or completes
    closer to MPS; where neither completes, where the furthest row with it stops against the control.
    """
    control, rows = rows[-1], rows[:-1]
    done = control["rollout"] == "complete"
    said = (
        f"Its control ({control['simulator'].split(': ', 1)[1]}) "
        + ("completes" if done else control["rollout"])
        + f" at {control['Chamfer to MPS mean / max (mm)']} mm"
    )
    beaten = [
        r["simulator"] for r in rows if r["rollout"] == "complete" and (not done or _mean(r) < _mean(control))
    ]
    if beaten:
        return f"{said}; the network earns its place in {', '.join(beaten)}."
    if done:
        return f"{said}; no row with the network completes closer to MPS than it."
    far = max(rows, key=_reach)
    if _reach(far) > _reach(control):
        return f"{said}; with the network {far['simulator']} gets further (it {far['rollout']})."
    return f"{said}; no row with the network gets further."


def _reach(row: dict[str, Any]) -> int:
    """The step a stopped row's guard refused (a complete row: a step past every stopped one)."""
    return 10**9 if row["rollout"] == "complete" else int(row["rollout"].split()[3])


def _mean(row: dict[str, Any]) -> float:
    return float(row["Chamfer to MPS mean / max (mm)"].split(" / ")[0])


def run_model(model: str, args: argparse.Namespace) -> list[dict[str, Any]]:
    """The rows of ``model``, its control without a network last (:func:`control_row`).

    Every variant, and the relaxed one where one of them does not complete.
    """
    cfg = compose_config([f"model={model}", f"scene={args.scene}", *_weights(args)])
    simulator, scene_dt = build_simulator(cfg), scene_params(cfg).dt
    dt = float(simulator.dt) if simulator.dt is not None else scene_dt
    rows: list[dict[str, Any]] = []
    variants = list(VARIANTS.items())
    for i, (variant, overrides) in enumerate([*variants, RELAXED]):
        if i == len(variants) and all(r["rollout"] == "complete" for r in rows[1:]):
            break
        out = folder(Path(args.runs_dir), model, variant)
        cmd = command(model, dt, overrides, out, args)
        rows.append(result_row(_run(cmd, out, args), cmd))
        print(f"[exact_after] {rows[-1]['simulator']}: {rows[-1]['rollout']}", flush=True)
    limit = simulator.max_courant if simulator.max_courant is not None else cfg.solver.guard.max_courant
    return [*rows, control_row(model, dt, float(limit), args, scene_dt)]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", nargs="+", default=["gns", "cconv", "cconv_original"])
    ap.add_argument("--scene", default="dam")
    ap.add_argument("--duration", type=float, default=1.0, help="s of the scene")
    ap.add_argument("--runs-dir", default="runs/exact_after")
    ap.add_argument("--reference-dir", default="runs/reference", help="the MPS references' cache")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument(
        "--note-file",
        default=None,
        help="a markdown file added under the verdicts (where the runs were made)",
    )
    ap.add_argument("--results", default=str(RESULTS))
    ap.add_argument("--name", default="exact_after", help="results file name (<name>.md, <name>.csv)")
    ap.add_argument(
        "--weights",
        default=None,
        help="model.weights of every model: a task=train out_dir (default: each model's shipped weights)",
    )
    args = ap.parse_args(argv)
    load = os.getloadavg()[0]
    rows, verdicts = [], []
    for model in args.models:
        model_rows = run_model(model, args)
        rows += model_rows
        verdicts.append(verdict(model, model_rows[:-1]) + " " + control_verdict(model_rows))
    intro = (
        "# Exact stages after a learned step (`model.exact_after`)\n\n"
        f"`task=evaluate` on `{args.scene}` for {args.duration:g} s, frames every "
        f"{1e3 * FRAME_INTERVAL:g} ms, against one MPS reference at the scene's dt. Each model steps by its "
        "own dt; after each of its steps the exact stages named run on its positions and velocities "
        "(lagfluid/models/exact_after.py): the MPS collision rule, the PPE with the minimum-pressure "
        "gradient correction, both; K iterations with relaxation w where one of those does not complete. "
        "A stopped run is compared over the frames it stored. Chamfer: mean and largest over the frames "
        "of the symmetric mean nearest-neighbour distance to MPS's fluid; density error: mean |n/n0 - 1| "
        "over the interior fluid particles.\n\n"
        + "\n".join(f"- {v}" for v in verdicts)
        + (f"\n\n{Path(args.note_file).read_text().strip()}" if args.note_file else "")
    )
    prov = provenance("benchmarks.exact_after", load, runs=str(args.runs_dir))
    print(write_results(Path(args.results), args.name, rows, intro, prov))


if __name__ == "__main__":
    main()
