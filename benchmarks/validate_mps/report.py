"""The report: provenance, the solver description, the .md/.csv files and the text after the table."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from benchmarks.provenance import markdown, provenance
from benchmarks.validate_mps.common import SOLVER_OVERRIDES, SOLVER_PROFILE, Check


def run_provenance(runtime: float, load_before: float) -> dict[str, str]:
    return provenance(
        "benchmarks.validate_mps",
        load_before,
        runtime=f"{runtime:.0f} s ({runtime / 60:.1f} min)",
        solver=solver_description(),
    )


def solver_description() -> str:
    """The profile and overrides every run used, for the report."""
    name = SOLVER_PROFILE[0]
    text = f"conf/solver/{name}.yaml"
    if name == "mps":
        text += " (authors' coefficients, n0 from the ideal lattice)"
    if SOLVER_OVERRIDES:
        dotted = OmegaConf.to_container(OmegaConf.create(SOLVER_OVERRIDES))
        text += " with " + ", ".join(f"{k}={v}" for k, v in _dotted_items(dotted))
    return text + ", scene dtype float32"


def _dotted_items(tree: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    """``{"ppe": {"tol": 1e-8}}`` -> ``[("ppe.tol", 1e-8)]``, as ``--solver`` takes them."""
    items: list[tuple[str, Any]] = []
    for key, value in tree.items():
        if isinstance(value, dict):
            items += _dotted_items(value, f"{prefix}{key}.")
        else:
            items.append((f"{prefix}{key}", value))
    return items


def write_report(checks: list[Check], prov: dict[str, str], stem: Path, extra: str) -> None:
    stem.parent.mkdir(parents=True, exist_ok=True)
    lines = ["| check | quantity | measured | criterion | status |", "|---|---|---|---|:---:|"]
    for c in checks:
        lines.append(f"| {c.check} | {c.quantity} | {c.measured} | {c.criterion} | **{c.status}** |")
    n_fail = sum(c.status == "FAIL" for c in checks)
    notes = markdown(prov)
    stem.with_suffix(".md").write_text(
        "# MPS solver: physical validation\n\n"
        f"{notes}\n\n**{n_fail} check(s) failed** of {sum(c.status != 'INFO' for c in checks)} pass/fail "
        "checks (INFO rows are informative).\n\n" + "\n".join(lines) + "\n\n" + extra
    )
    with stem.with_suffix(".csv").open("w", newline="") as f:
        for k, v in prov.items():
            f.write(f"# {k}: {v}\n")
        w = csv.writer(f)
        w.writerow(["check", "quantity", "measured", "criterion", "status"])
        for c in checks:
            w.writerow([c.check, c.quantity, c.measured, c.criterion, c.status])


def report_extra(timings: dict[str, float], info: dict[str, Any], suffix: str) -> str:
    """The report's sections after the table: timings, the surge front, notes on the criteria, figures."""
    extra = "## Timings\n\n" + "\n".join(f"- {k}: {v:.0f} s" for k, v in timings.items()) + "\n"
    if info:
        extra += "\n## Surge front of the authors' dam (99th percentile of x within 2 l0 of the floor)\n\n"
        extra += f"a = {info['a']:.3f} m, h = {info['h']:.3f} m (h/a = {info['h'] / info['a']:.2f}).\n\n"
        extra += "| t (s) | T | Z (p99) | Z (max) |\n|---:|---:|---:|---:|\n"
        every = max(1, round(0.05 / (info["t"][1] - info["t"][0]))) if len(info["t"]) > 1 else 1
        for i in range(0, len(info["t"]), every):
            row = (info["t"][i], info["T"][i], info["Z99"][i], info["Zmax"][i])
            extra += "| {:.3f} | {:.3f} | {:.3f} | {:.3f} |\n".format(*row)
    extra += (
        "\n## Notes on the criteria\n\n"
        "- Hydrostatic: the column starts on an exact lattice at rest; 1 s (0.3 s with --quick) is several "
        "times the gravity-wave crossing time 2 L / sqrt(g h) ~ 0.35 s, and the pressure is averaged "
        "over the last 0.1 s to remove the step-to-step MPS pressure noise. The free-surface layer and the "
        "two below it, and the three layers next to the floor, are left out of the fit.\n"
        "- Resting tank: 'near zero' is set against the paper's MPS ground-truth values on the dam collapse "
        "(FGN Table 1: density error 0.038, divergence 0.019): a fluid at rest must be at least as "
        "incompressible as a violent flow. The paper's divergence may not be defined exactly as ours (their "
        "released divergence kernel has a defect, FGN_ORIGINAL.md item 8); the density error is comparable.\n"
        "- Surge front: x is measured from the inner wall layer (x = 0) to the 99th percentile of the fluid "
        "particles within 2 l0 of the floor, Z = x / a with a the initial column width (particle centre to "
        "particle centre, so Z(0) = 1); only reference points before the front reaches the far wall count. "
        "Martin & Moyce's fronts lag most simulations by ~10% (finite gate-removal time, bed friction); a "
        "deviation above 30% fails the check, and a front ahead of the shallow-water (Ritter) front "
        "x = a + 2 sqrt(g h) t is impossible and fails it too.\n"
    )
    extra += (
        f"\n## Figures\n\n- `validate_mps_hydrostatic{suffix}.png`: p vs depth (time-averaged) with rho g "
        "depth; residual velocity of the resting column vs time\n"
        f"- `validate_mps_dam_front{suffix}.png`: surge front Z vs T against Martin & Moyce (1952), "
        "Koshizuka & Oka (1996) and the shallow-water bound; dt robustness of the small dam\n"
    )
    return extra
