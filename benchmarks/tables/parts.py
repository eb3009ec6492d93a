"""The parts of the tables (``--only`` names them): each runs its rows, writes its CSV, renders its text."""

from __future__ import annotations

import math
from typing import Any

from benchmarks.tables.bench import Bench, Run
from benchmarks.tables.plots import plot_fig5, plot_tradeoff
from benchmarks.tables.report import Report
from benchmarks.tables.rows import (
    TRADEOFF_METRICS,
    fmt,
    md_table,
    provenance_columns,
    ratio,
    status,
    table2_rows,
    table3_rows,
    table4_rows,
    tradeoff_rows,
)
from benchmarks.tables.simulators import CASES, FGN, GROUND_TRUTH, simulator
from lagfluid.errors import ConfigError

# The FGN paper's numbers (Li & Barati Farimani): Table 1 (density error mean/max, divergence mean/max,
# Chamfer mean/max mm), Table 2 (parameters, inference ms, NNS ms; a GPU) and Table 4 (percent, mean/std).
# Its baselines' rows (Table 3, Table 2) are the paper's facts too; a simulator of ours is set beside them
# when its label starts with the paper's model name (e.g. "GNS (CPU size)").
PAPER_TABLE1 = {
    ("dam", "FGN"): (0.0461, 0.0900, 0.0195, 0.0280, 24.2, 30.1),
    ("dam", "GNS"): (0.0898, 0.3387, 0.0210, 0.0311, 26.1, 33.1),
    ("dam", "CConv"): (0.1811, 0.2947, 0.0338, 0.1700, 31.4, 44.0),
    ("dam", "Ground truth"): (0.0380, 0.0710, 0.0190, 0.0268, None, None),
    ("waterfall", "FGN"): (0.0541, 0.1350, 0.0207, 0.0431, 24.8, 29.6),
    ("waterfall", "GNS"): (0.1035, 0.3512, 0.0223, 0.0399, 25.6, 31.8),
    ("waterfall", "CConv"): (0.2783, 0.4121, 0.0668, 0.2882, 40.4, 61.5),
    ("waterfall", "Ground truth"): (0.0429, 0.0966, 0.0196, 0.0398, None, None),
}
PAPER_BASELINES = ("GNS", "CConv")
# parameters, inference ms, NNS ms (CConv's on TensorFlow and Open3D)
PAPER_TABLE2 = {
    "FGN": (41996, 5.7, 46.4),
    "GNS": (1406272, 44.6, 33.1),
    "CConv": (692902, 28.9, 24.7),
    "MPS": (None, 313.2, 42.3),
}
PAPER_TABLE4 = {"advection": (12.4, 5.6), "pressure": (8.3, 1.1)}  # percent, mean and std
# Table 5 (ablations of the node-focused nets' aggregator), columns as Table 1's.
PAPER_TABLE5 = {
    ("dam", "FGN"): PAPER_TABLE1[("dam", "FGN")],
    ("dam", "GCN"): (0.0939, 0.3832, 0.0196, 0.0293, 27.7, 31.6),
    ("dam", "SAGE"): (0.0935, 0.3597, 0.0196, 0.0289, 26.4, 31.3),
    ("dam", "MLP"): (0.0963, 0.3624, 0.0196, 0.0289, 28.5, 32.8),
    ("dam", "Ground truth"): PAPER_TABLE1[("dam", "Ground truth")],
    ("waterfall", "FGN"): PAPER_TABLE1[("waterfall", "FGN")],
    ("waterfall", "GCN"): (0.0794, 0.3373, 0.0210, 0.0433, 25.5, 31.7),
    ("waterfall", "SAGE"): (0.0769, 0.3254, 0.0209, 0.0432, 25.3, 31.4),
    ("waterfall", "MLP"): (0.0830, 0.2967, 0.0209, 0.0433, 26.3, 32.4),
    ("waterfall", "Ground truth"): PAPER_TABLE1[("waterfall", "Ground truth")],
}
ACCURACY_KEYS = (
    "density_error_mean",
    "density_error_max",
    "divergence_mean_per_s",
    "divergence_max_per_s",
    "chamfer_mean_mm",
    "chamfer_max_mm",
)
ACCURACY_HEADER = ["density error mean", "max", "divergence mean (1/s)", "max", "Chamfer mean (mm)", "max"]


def row_notes(runs: list[Run]) -> str:
    """The notes of the rows' simulators (their row files' ``table.note``), one line each; '' when none."""
    notes = dict.fromkeys((r.label, r.sim.note) for r in runs if r.sim.note)
    return "".join(f"- {label}: {note}\n" for label, note in notes)


def part_table2(bench: Bench, report: Report) -> None:
    """Table 2: parameters and time per step, every simulator, one after another in this process."""
    p = bench.profile
    runs = bench.table2_runs()
    rows = table2_rows(runs)
    report.csv("table2", rows)

    def steps(r: dict[str, Any]) -> str:
        return "-" if r["timed_steps"] is None else f"{r['warmup_steps']} + {r['timed_steps']}"

    cells = [
        [
            r["simulator"],
            r["parameters"],
            r["fluid_particles"],
            r["step_ms"],
            r["inference_ms"],
            r["neighbor_search_ms"],
            r["speedup_vs_mps"],
            steps(r),
            r["status"],
        ]
        for r in rows
    ]
    header = [
        "simulator",
        "parameters",
        "fluid",
        "ms/step",
        "inference ms",
        "NNS ms",
        "MPS time / time",
        "steps (warm-up + timed)",
        "status",
    ]
    paper = [[k, v[0], v[1], v[2]] for k, v in PAPER_TABLE2.items()]
    notes = row_notes(runs)
    report.sections["table2"] = (
        f"## Table 2: time per step on `{p.timing_scene}`\n\n"
        f"Median over the profile's {p.timing_steps} timed steps after {p.timing_warmup} warm-up steps, "
        "every simulator in this process one after another. A simulator that starts from H earlier states "
        "(its `history_length`) warms up for at least H + 1 steps: on a scene built from scratch its first H "
        "steps are its start-up (e.g. a warm start by MPS), the next its first own step, and none of them is "
        "timed. A row file may time fewer steps than the profile (`table.timing_steps`, for a network too "
        "slow for the profile's number): the median is then over those few steps (column 'steps'). NNS: the "
        "neighbour search (Verlet list update and filtering; a graph network's graph construction); "
        "inference: the rest of the step (networks or exact stages, pressure gradient, update). Parameters: "
        f"trainable parameters of the learned stages. Machine: {report.meta['machine']}.\n\n"
        f"{md_table(header, cells, 'lrrrrrrrl')}\n\n"
        + (f"{notes}\n" if notes else "")
        + "The paper's Table 2 (a GPU, ~40k particles):\n\n"
        f"{md_table(['paper', 'parameters', 'inference ms', 'NNS ms'], paper)}\n"
    )
    fgn_label, mps_label = simulator(FGN).label, simulator(GROUND_TRUTH).label
    fgn = next((r for r in rows if r["simulator"] == fgn_label), None)
    mps = next((r for r in rows if r["simulator"] == mps_label), None)
    if fgn and mps:
        paper_ratio = (313.2 + 42.3) / (5.7 + 46.4)
        cells = [
            ["FGN, ours", fgn["parameters"], fgn["inference_ms"], fgn["neighbor_search_ms"], fgn["step_ms"]],
            ["MPS, ours", "-", mps["inference_ms"], mps["neighbor_search_ms"], mps["step_ms"]],
        ]
        paper_cells = [
            ["FGN, paper (GPU)", 41996, 5.7, 46.4, 5.7 + 46.4],
            ["MPS, paper (GPU)", "-", 313.2, 42.3, 313.2 + 42.3],
        ]
        for model in PAPER_BASELINES:  # ours beside the paper's, by label (module note on PAPER_TABLE1)
            for r in (r for r in rows if str(r["simulator"]).startswith(model)):
                cells.append(
                    [
                        f"{r['simulator']}, ours",
                        r["parameters"],
                        r["inference_ms"],
                        r["neighbor_search_ms"],
                        r["step_ms"],
                    ]
                )
            par, inf, nns = PAPER_TABLE2[model]
            paper_cells.append([f"{model}, paper (GPU)", par, inf, nns, inf + nns])
        cells += paper_cells  # ours first, then the paper's, as Table 1
        report.readme["table2"] = (
            f"**Table 2** (`{p.timing_scene}`, {fmt(mps['fluid_particles'])} fluid particles; "
            f"{report.meta['machine']}):\n\n"
            + md_table(["", "parameters", "inference ms", "NNS ms", "step ms"], cells)
            + f"\n\n- MPS / FGN time per step: ours {fmt(fgn['speedup_vs_mps'])}, paper {fmt(paper_ratio)} "
            f"(inference alone: ours {fmt(ratio(mps['inference_ms'], fgn['inference_ms']))}, paper "
            f"{fmt(313.2 / 5.7)}).\n"
        )


def accuracy_md(rows: list[dict[str, Any]], cases: dict[str, str]) -> str:
    """Tables 1/3/5's markdown: case, simulator, the accuracy columns and how each row ended."""
    cells = [[cases[r["case"]], r["simulator"], *(r[k] for k in ACCURACY_KEYS), r["status"]] for r in rows]
    return md_table(["case", "simulator", *ACCURACY_HEADER, "status"], cells, "ll" + "r" * 6 + "l")


def paper_accuracy_md(paper: dict[tuple[str, str], tuple[Any, ...]], cases: set[str]) -> str:
    """The paper's rows of an accuracy table (``PAPER_TABLE1`` or ``PAPER_TABLE5``) for ``cases``."""
    cells = [[c, m, *v] for (c, m), v in paper.items() if c in cases]
    return md_table(["case", "paper", *ACCURACY_HEADER], cells, "llrrrrrr")


def case_names(p: Any) -> dict[str, str]:
    """How the tables name each case of the profile ``p``: its scene, overrides and duration."""
    return {
        "dam": f"`{p.dam_scene}`, {p.dam_duration:g} s",
        "waterfall": f"`waterfall` {' '.join(p.waterfall or ())}, {p.waterfall_duration:g} s",
    }


def part_table5(bench: Bench, report: Report, dam_runs: list[Run]) -> None:
    """Table 5: FGN's kernel aggregator against GCN, SAGE (mean) and none (MLP), with FGN's and MPS's rows.

    The ablation rows are the ``table5_<case>_<key>`` files; FGN and the ground truth are Table 3's runs of
    the same case (the same rows, run once).
    """
    p = bench.profile
    cases = case_names(p)
    rows: list[dict[str, Any]] = []
    ablations: list[Run] = []
    for case in ("dam", "waterfall") if p.waterfall else ("dam",):
        own = [r for r in dam_runs if r.sim.key in (GROUND_TRUTH, FGN)]
        if case != "dam":  # Table 3's rows when it ran them (memoised), else these two alone
            own = bench.accuracy_runs(case, keys=(GROUND_TRUTH, FGN))
        ablations += bench.accuracy_runs(case, table="table5")
        rows += table3_rows(case, own + [r for r in ablations if r.key.startswith(f"table5/{case}/")])
    notes = row_notes(ablations)
    report.csv("table5", rows)
    report.sections["table5"] = (
        "## Table 5: the aggregator of FGN's node-focused networks\n\n"
        "FGN's advection and pressure nets with their two kernel-weighted aggregation layers replaced by "
        "PyG's `GCNConv` (neighbours weighted by degree), `SAGEConv` (mean) or no aggregation (MLP) "
        "(`model=fgn_gcn`, `fgn_sage`, `fgn_mlp`). Their reference is FGN with every net trained here "
        "(`model=fgn_trained_here`): the ablations are it with one layer type swapped, trained by the same "
        "recipe (`train=table5`: FGN's advection recipe; the pressure net of the recipe before the authors' "
        "pressure net shipped, fine-tuned by two on-policy rounds with the model's own advection net; each "
        "set of weights: its `MODEL_CARD.md`); the FGN row (the authors' pressure net) is shown "
        "beside them. Metrics and reference as Tables 1/3.\n\n"
        + accuracy_md(rows, cases)
        + "\n\n"
        + (f"{notes}\n" if notes else "")
        + "The paper's Table 5:\n\n"
        + paper_accuracy_md(PAPER_TABLE5, {r["case"] for r in rows})
        + "\n"
    )
    report.readme["table5"] = (
        f"**Table 5** (the aggregator ablation; dam: {cases['dam']}):\n\n{accuracy_md(rows, cases)}\n"
    )


def part_table3(bench: Bench, report: Report, dam_runs: list[Run]) -> None:
    """Tables 1 and 3: accuracy of every simulator against MPS on the dam and the water fall."""
    p = bench.profile
    rows = table3_rows("dam", dam_runs)
    waterfall_runs = bench.accuracy_runs("waterfall") if p.waterfall else []
    rows += table3_rows("waterfall", waterfall_runs)
    report.csv("table3", rows)
    notes = row_notes(dam_runs + waterfall_runs)
    cases = case_names(p)
    keys, header = ACCURACY_KEYS, ACCURACY_HEADER
    report.sections["table3"] = (
        "## Tables 1 and 3: accuracy against MPS\n\n"
        "`task=evaluate` for every simulator: the same initial state, MPS as the reference. Density error "
        "and divergence over the stored frames (mean and max); Chamfer distance (eq. 29) to MPS at the same "
        "time, mean and max over the frames. The MPS row is the ground truth's own density error and "
        "divergence.\n\n"
        + accuracy_md(rows, cases)
        + "\n"
        + (f"\n{notes}" if notes else "")
        + "\nThe paper's Tables 1 and 3 (dam ~10k, water fall ~80k particles):\n\n"
        + paper_accuracy_md(PAPER_TABLE1, set(CASES))
        + "\n"
    )
    ours, lines = [], []
    fgn_label = simulator(FGN).label
    for case in ("dam", "waterfall"):
        fgn = next((r for r in rows if r["case"] == case and r["simulator"] == fgn_label), None)
        gt = next((r for r in rows if r["case"] == case and r["simulator"].startswith("Ground")), None)
        p_fgn, p_gt = PAPER_TABLE1[(case, "FGN")], PAPER_TABLE1[(case, "Ground truth")]
        ours += [[case, "FGN, paper", *p_fgn], [case, "Ground truth, paper", *p_gt]]
        for who, r in (("FGN, ours", fgn), ("Ground truth (MPS), ours", gt)):
            if r:
                ours.append([case, who, *(r[k] for k in keys)])
        for model in PAPER_BASELINES:  # ours beside the paper's, by label (module note on PAPER_TABLE1)
            mine = [r for r in rows if r["case"] == case and str(r["simulator"]).startswith(model)]
            if mine:
                ours.append([case, f"{model}, paper", *PAPER_TABLE1[(case, model)]])
                for r in mine:
                    status = ": ".join(str(r["status"]).split(": ")[:2])  # "stopped: step 30"
                    ours.append([case, f"{r['simulator']}, ours ({status})", *(r[k] for k in keys)])
        if fgn and gt:
            lines.append(
                f"- {case}: FGN / MPS density error {fmt(ratio(fgn[keys[0]], gt[keys[0]]))} (paper "
                f"{fmt(p_fgn[0] / p_gt[0])}), divergence {fmt(ratio(fgn[keys[2]], gt[keys[2]]))} (paper "
                f"{fmt(p_fgn[2] / p_gt[2])}); FGN's Chamfer distance to MPS {fmt(fgn[keys[4]])} mm (paper "
                f"{p_fgn[4]} mm); FGN {fgn['status']}."
            )
    ours.sort(key=lambda r: (r[0], "paper" in r[1], r[1]))
    report.readme["table1"] = (
        f"**Table 1** (dam: {cases['dam']}; "
        f"water fall: {cases['waterfall'] if p.waterfall else 'not run'}):\n\n"
        + md_table(["case", "", *header], ours, "ll" + "r" * 6)
        + "\n\n"
        + "\n".join(lines)
        + "\n"
    )


def part_fig5(bench: Bench, report: Report, fig5: tuple[list[Run], float | None, float | None]) -> None:
    """Fig. 5: FGN's Chamfer distance against time for increasing dt; the largest dt that completes."""
    p = bench.profile
    runs, stable, stopped = fig5
    frames = [((r.metrics or {}).get("frames") or {}).get("chamfer_mm") or [None] for r in runs]
    rows = [
        {
            "dt_s": r.info["dt"],
            "steps": (r.metrics or {}).get("steps"),
            "chamfer_mean_mm": r.summary("chamfer_mm", "mean"),
            "chamfer_max_mm": r.summary("chamfer_mm", "max"),
            "chamfer_last_mm": math.nan if f[-1] is None else float(f[-1]),
            "density_error_mean": r.summary("density_error", "model", "mean"),
            "status": status(r),
            **provenance_columns(r),
        }
        for r, f in zip(runs, frames, strict=True)
    ]
    report.csv("fig5", rows)
    verdict = fig5_verdict(p.dam_duration, runs, stable, stopped)
    png = report.path("fig5.png")
    plot_fig5(png, runs, verdict, f"FGN vs MPS on {p.dam_scene} at several dt ({p.name} profile)")

    def tail(r: dict[str, Any]) -> list[Any]:
        return [r["chamfer_last_mm"], r["density_error_mean"], r["status"]]

    cells = [
        [fmt(1e3 * r["dt_s"]), *(r[k] for k in ("steps", "chamfer_mean_mm", "chamfer_max_mm")), *tail(r)]
        for r in rows
    ]
    header = ["dt (ms)", "steps", "Chamfer mean (mm)", "max", "at the end", "density error mean", "status"]
    report.sections["fig5"] = (
        "## Fig. 5: FGN at other time steps\n\n"
        f"FGN rolled out at each dt for {p.dam_duration:g} s against the MPS reference at the scene's dt, "
        f"frames matched by time every {1e3 * p.frame_interval:g} ms. The sweep stops at the first dt the "
        "rollout guard stops (NaN, a particle leaving the domain, or a Courant number max|v| dt / l0 above "
        f"`solver.guard.max_courant`, 0.5); {verdict}.\n\n"
        f"{md_table(header, cells, 'rrrrrrl')}\n\n![Fig. 5]({png.name})\n"
    )
    report.readme["fig5"] = f"**Fig. 5**: {verdict} (paper: FGN converges for every dt < 5 ms).\n"


def fig5_verdict(duration: float, runs: list[Run], stable: float | None, stopped: float | None) -> str:
    """One line on Fig. 5's sweep: the largest dt that completed and what stopped the next one."""
    if stable is None and stopped is None:
        return "no dt produced a rollout (every row failed, see the table)"
    text = f"largest dt whose {duration:g} s rollout completes: {fmt(1e3 * stable) if stable else 'none'} ms"
    if stopped is not None:
        why = next((status(r).removeprefix("stopped: ") for r in runs if r.info.get("dt") == stopped), "")
        return text + f"; the rollout guard stopped dt = {1e3 * stopped:g} ms ({why})"
    failed = [r.info["dt"] for r in runs if not r.ok]
    if failed:
        return text + f"; dt = {', '.join(f'{1e3 * d:g}' for d in failed)} ms failed (see the table)"
    return text + " (every dt tried completed; the largest tried is a lower bound)"


def part_table4(bench: Bench, report: Report, dam_runs: list[Run]) -> None:
    """Table 4: the advection net on held-out materials, the pressure net as a PPE solver."""
    p = bench.profile
    adv = bench.table4_runs()
    # every dam row whose pressure stage is a network (the authors' too: a yardstick for the paper's 8.3 %)
    pressure = [r for r in dam_runs if r.info.get("stages", {}).get("pressure") == "learned"]
    rows = table4_rows(adv, pressure)
    report.csv("table4", rows)
    cells = [[r["network"], r["case"], r["mean"], r["std"], r["n"], r["status"]] for r in rows]
    report.sections["table4"] = (
        "## Table 4: the networks as stand-alone solvers\n\n"
        f"Advection: {len(adv)} sequences on `{p.table4_scene}` ({p.table4_duration:g} s each) with held-out "
        "gravity g (m/s^2) and viscosity nu (m^2/s), rolled out with learned advection and exact collision "
        "and pressure (`table4_advection`); at every stored step the network's acceleration is compared with "
        "`g + nu lap(v)` at the same input (normalised MAE, eq. 32). Pressure: the network's pressure in the "
        "exact PPE at its own input (relative residual, eq. 31) over the stored steps of the dam rows "
        "(hybrid: exact advection and collision, so its input is MPS's; FGN: its own rollout).\n\n"
        + md_table(["network", "case", "mean", "std", "n", "status"], cells, "llrrrl")
        + f"\n\nPaper: advection {PAPER_TABLE4['advection'][0]} % +- {PAPER_TABLE4['advection'][1]} %, "
        f"pressure {PAPER_TABLE4['pressure'][0]} % +- {PAPER_TABLE4['pressure'][1]} %.\n"
    )

    def pct(r: dict[str, Any]) -> str:
        return f"{fmt(100 * r['mean'])} % +- {fmt(100 * r['std'])} %"

    adv_all = next(r for r in rows if r["case"] == "all sequences")
    cells = [
        ["advection", f"normalised MAE, {adv_all['n']} held-out (g, nu)", pct(adv_all), "12.4 % +- 5.6 %"]
    ]
    cells += [
        ["pressure", f"PPE relative residual, {r['case']}", pct(r), "8.3 % +- 1.1 %"]
        for r in rows
        if r["network"] == "pressure"
    ]
    report.readme["table4"] = (
        "**Table 4** (mean +- std):\n\n"
        + md_table(["network", "metric", "ours", "paper"], cells, "llrr")
        + "\n"
    )


def part_tradeoff(bench: Bench, report: Report, dam_runs: list[Run], fig5_runs: list[Run]) -> None:
    """The speed/accuracy trade-off on the dam: every simulator, hybrids, FGN and MPS variants."""
    p = bench.profile
    runs = dam_runs + bench.tradeoff_runs() + [r for r in fig5_runs if r.key.startswith("fig5/")]
    hashes = {r.metrics["reference"]["key_hash"] for r in runs if r.ok}
    if len(hashes) > 1:  # a row file whose reference settings drifted from the others'
        raise ConfigError(f"trade-off rows were compared with different MPS references: {sorted(hashes)}")
    rows = tradeoff_rows(runs)
    report.csv("tradeoff", rows)
    notes = row_notes(dam_runs)
    png = report.path("tradeoff.png")
    plot_tradeoff(png, rows, f"Speed/accuracy on {p.dam_scene}, {p.dam_duration:g} s ({p.name} profile)")
    order = sorted(rows, key=lambda r: (not math.isfinite(r["s_per_simulated_s"]), r["s_per_simulated_s"]))
    cells = [
        [
            r["simulator"],
            r["s_per_simulated_s"],
            r["ms_per_step_median"],
            r["chamfer_mean_mm"],
            r["chamfer_max_mm"],
        ]
        + [r["chamfer_t0_mm"], r["density_error_mean"]]
        + ["yes" if r[f"pareto_{m}"] else "" for m in TRADEOFF_METRICS]
        + [r["status"]]
        for r in order
    ]
    header = ["simulator", "s per simulated s", "ms/step", "Chamfer mean (mm)", "max", "at t = 0"]
    header += ["density error", "front: Chamfer", "front: density", "status"]
    report.sections["tradeoff"] = (
        "## Speed/accuracy trade-off\n\n"
        f"Every simulator on `{p.dam_scene}` for {p.dam_duration:g} s against one reference: MPS at the "
        "default settings (PPE to the absolute tolerance 1e-6, the scene's dt and l0; every row has the same "
        "reference hash). Cost: wall seconds of the steps per simulated second (writing and metrics "
        "excluded), the rows run one after another in one process. Accuracy: the Chamfer distance to the "
        "reference (mean over the frames) and the simulator's own density error. A run at a coarser spacing "
        "is compared in physical units in the frame of the boundary surface; its Chamfer distance includes "
        "the lattice offset already there at t = 0 (a coarse particle sits between reference particles; "
        "column 'at t = 0'). A simulator that starts from earlier states (its `history_length`) spends its "
        "first steps on a scene built from scratch on its start-up (e.g. a warm start by MPS): like any "
        "rollout from scratch, its cost and accuracy include them. On the front: no other complete row is "
        "both cheaper and at least as accurate.\n\n"
        f"{md_table(header, cells, 'lrrrrrrccl')}\n\n"
        + (f"{notes}\n" if notes else "")
        + f"![trade-off]({png.name})\n"
    )
    front = [r["simulator"] for r in order if r["pareto_chamfer_mean_mm"]]
    report.readme["tradeoff"] = (
        f"**Trade-off** ([plot](benchmarks/results/{png.name})): on the time/Chamfer front, cheapest first: "
        f"{'; '.join(front) or '-'}.\n\n![trade-off](benchmarks/results/{png.name})\n"
    )
