"""``python -m benchmarks.extremes``: verdicts from evaluate's metrics, the holds summary, a quick sweep."""

from __future__ import annotations

import csv
import math

import pytest

from benchmarks.extremes import (
    AXES,
    DEGRADED_CHAMFER_L0,
    DEGRADED_DENSITY_FACTOR,
    DENSITY_ERROR_FLOOR,
    README_END,
    README_START,
    entries,
    holds,
    main,
    verdict,
)
from benchmarks.tables.bench import Run
from benchmarks.tables.simulators import Simulator

L0 = 0.05
FGN, MPS = Simulator("fgn", "FGN", "fgn"), Simulator("mps", "MPS", "mps")


def _run(sim=FGN, complete=True, chamfer_mm=5.0, density=0.02, reference=0.01, stop="", error=""):
    run = Run("k", sim.label, sim, None, [])
    if error:
        run.error = error
        return run
    run.metrics = {
        "complete": complete,
        "stop_reason": stop,
        "steps": 7,
        "summary": {
            "chamfer_mm": {"mean": chamfer_mm},
            "density_error": {"model": {"mean": density}, "reference": {"mean": reference}},
        },
    }
    return run


def test_verdicts_follow_the_stated_bounds():
    assert verdict(_run(), L0) == ("stable", "")
    just = 1e3 * L0 * DEGRADED_CHAMFER_L0
    assert verdict(_run(chamfer_mm=just), L0)[0] == "stable"  # the bound itself is still stable
    kind, reason = verdict(_run(chamfer_mm=just * 1.01), L0)
    assert kind == "degraded" and "Chamfer" in reason
    kind, reason = verdict(_run(density=0.01 * DEGRADED_DENSITY_FACTOR * 1.01), L0)
    assert kind == "degraded" and "density error" in reason
    assert verdict(_run(chamfer_mm=math.nan), L0)[0] == "degraded"  # no finite error is never stable
    # early in a run MPS's density error is ~0.1 %: many times it, yet under the floor, is not degraded
    small = DENSITY_ERROR_FLOOR * 0.9
    assert verdict(_run(density=small, reference=small / 10), L0) == ("stable", "")
    kind, reason = verdict(_run(density=DENSITY_ERROR_FLOOR * 1.1, reference=DENSITY_ERROR_FLOOR / 10), L0)
    assert kind == "degraded" and "11x MPS's" in reason


def test_earlier_csv_rows_are_judged_again_by_todays_criterion(tmp_path):
    from benchmarks.extremes import merged_rows

    path = tmp_path / "extremes.csv"
    fields = ["axis", "value", "simulator", "verdict", "reason", "steps", "steps_requested",
              "chamfer_mean_mm", "density_error_mean", "density_error_ratio_to_mps", "divergence_mean_per_s",
              "fluid_particles", "wall_s"]  # fmt: skip
    old = dict(zip(fields, ["particles", "1024", "fgn", "degraded", "density error 3.5x MPS's > 3x", "40",
                            "40", "0.9", "0.0035", "3.5", "0.1", "1024", "3.0"], strict=True))  # fmt: skip
    stop = {**old, "simulator": "gns", "verdict": "stopped", "reason": "step 3: NaN"}
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows([old, stop])
    rows, kept = merged_rows(path, [], L0)
    assert kept == 2
    assert (rows[0]["verdict"], rows[0]["reason"]) == ("stable", "")
    assert (rows[1]["verdict"], rows[1]["reason"]) == ("stopped", "step 3: NaN")  # only completed runs


def test_a_guard_stop_and_a_refusal_keep_their_reason():
    stop = "step 12: fluid particle 3 left the domain at [1.0, 2.0, 3.0] (domain ...); reduce dt"
    assert verdict(_run(complete=False, stop=stop), L0) == (
        "stopped",
        "step 12: fluid particle 3 left the domain",
    )
    refused = "SceneError: scene 'dam': fluid block 0 ... lies in or beyond a wall"
    assert verdict(_run(error=refused), L0) == (
        "refused",
        "scene 'dam': fluid block 0 ... lies in or beyond a wall",
    )
    # the MPS reference stopping is MPS's own stop; a learned model then has nothing to be compared with
    reference = (
        "RolloutError: the MPS reference stopped, nothing to compare with: step 0: Courant number 0.8 (x)"
    )
    assert verdict(_run(sim=MPS, error=reference), L0) == ("stopped", "step 0: Courant number 0.8")
    assert verdict(_run(error=reference), L0) == ("no reference", "MPS stopped: step 0: Courant number 0.8")
    na = _run()
    na.info["not_applicable"] = "steps by its training frames' 8 ms"
    assert verdict(na, L0) == ("n/a", "steps by its training frames' 8 ms")


def test_holds_lists_stable_then_degraded_then_stops():
    dt = AXES["dt"]
    cells = [
        (0.0005, "stable"),
        (0.002, "stable"),
        (0.004, "degraded"),
        (0.008, "stopped"),
        (0.016, "stopped"),
    ]
    assert holds(dt, cells) == "stable 0.5 ms..2 ms; degraded 4 ms; stops 8 ms..16 ms"
    # a range never spans another verdict: separate segments
    apart = [(1.0, "stable"), (9.8, "degraded"), (30.0, "stable"), (100.0, "stopped")]
    assert holds(AXES["gravity"], apart) == "stable 1; degraded 9.8; stable 30; stops 100"
    assert holds(dt, [(0.002, "n/a")]) == "n/a"


def test_every_simulator_with_a_dam_row_and_both_mps_profiles_are_swept():
    keys = [e.sim.key for e in entries(None)]
    for key in ("mps", "mps_corrected", "fgn", "hybrid_advection", "hybrid_pressure", "fgn_original", "gns"):
        assert key in keys
    for key in ("cconv", "cconv_original", "fgn_trained_here", "fgn_gcn", "fgn_sage", "fgn_mlp"):
        assert key in keys
    assert "solver=mps_corrected" in next(e for e in entries(["mps_corrected"])).extra
    with pytest.raises(ValueError, match="unknown simulators \\['bogus'\\]"):
        entries(["bogus"])


def test_a_quick_sweep_writes_verdicts_tables_plots_and_the_readme_section(tmp_path, capsys):
    readme = tmp_path / "README.md"
    readme.write_text(f"# x\n\n{README_START}\nold\n{README_END}\nrest\n")
    argv = ["--quick", "--axes", "dt", "velocity", "particles", "--simulators", "mps", "fgn", "--readme"]
    argv += ["--results", str(tmp_path), "--runs-dir", str(tmp_path / "runs"), "--readme-path", str(readme)]
    assert main(argv) == 0
    with open(tmp_path / "extremes_quick.csv") as f:
        rows = {(r["axis"], r["value"], r["simulator"]): r for r in csv.DictReader(f)}
    assert len(rows) == 10
    assert rows[("particles", "1024", "mps")]["verdict"] == "stable"  # "1,024" in a folder name once broke it
    assert rows[("dt", "0.002", "mps")]["verdict"] == "stable"
    assert float(rows[("dt", "0.002", "mps")]["chamfer_mean_mm"]) == 0.0  # MPS is its own reference there
    assert rows[("dt", "0.04", "fgn")]["verdict"] == "stopped"  # 20x its training dt: the guard ends it
    assert rows[("velocity", "20.0", "mps")]["verdict"] == "stopped"  # Courant 0.8 at the start
    assert rows[("velocity", "20.0", "mps")]["reason"].startswith("step 0: Courant number 0.8")
    text = (tmp_path / "extremes_quick.md").read_text()
    assert "## Summary" in text and "### time step (ms)" in text and "stopped @0" in text
    assert (tmp_path / "extremes_quick_dt.png").stat().st_size > 10_000
    new = readme.read_text()
    assert "old" not in new and "| mps | stable 2 ms" in new and new.endswith(f"{README_END}\nrest\n")
    # a rerun of one axis and simulator completes the results instead of replacing them
    assert main([*argv[:1], "--axes", "velocity", "--simulators", "mps", *argv[8:]]) == 0
    with open(tmp_path / "extremes_quick.csv") as f:
        again = {(r["axis"], r["value"], r["simulator"]): r for r in csv.DictReader(f)}
    assert again.keys() == rows.keys()
    assert again[("dt", "0.04", "fgn")]["date"] == rows[("dt", "0.04", "fgn")]["date"]
    assert "10 runs:" in (tmp_path / "extremes_quick.md").read_text()  # every row, not only this run's
    assert "8 rows of other axes or simulators kept" in (tmp_path / "extremes_quick.md").read_text()
    # --redraw: the tables and plots again from the csv, nothing run
    (tmp_path / "extremes_quick_dt.png").unlink()
    capsys.readouterr()
    assert main([*argv[:1], "--redraw", "--simulators", "fgn", *argv[8:]]) == 0
    said = capsys.readouterr().out
    assert "nothing runs" in said and "estimated" not in said  # no estimate for a run that runs nothing
    summary = (tmp_path / "extremes_quick.md").read_text().split("## Summary")[1]
    assert summary.index("| mps |") < summary.index("| fgn |")  # the tables' order, not the rerun's first
    with open(tmp_path / "extremes_quick.csv") as f:
        assert {(r["axis"], r["value"], r["simulator"]) for r in csv.DictReader(f)} == set(rows)
    assert (tmp_path / "extremes_quick_dt.png").is_file() and not (
        tmp_path / "runs" / "extremes_redraw"
    ).exists()
