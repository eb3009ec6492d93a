"""Check 3: mass conservation of every run (fluid count constant, nothing beyond the inner walls, finite)."""

from __future__ import annotations

from benchmarks.validate_mps.common import Check, RunLog, status


def check_mass(logs: list[RunLog]) -> list[Check]:
    out = []
    for log in logs:
        counts = sorted(log.fluid_counts)
        walled = log.inner_lo is not None
        ok = counts == [log.n_fluid] and log.nonfinite_steps == 0 and (not walled or log.outside_max == 0)
        out.append(
            Check(
                "3 mass",
                f"{log.name}: fluid count over {log.steps_done} steps; fluid beyond the inner wall layers",
                f"{counts} (start {log.n_fluid}); "
                + (
                    f"max {log.outside_max} outside, closest approach {log.min_clearance:.2f} l0"
                    if walled
                    else "no walls"
                ),
                "constant; 0 outside; finite",
                status(ok),
            )
        )
    return out
