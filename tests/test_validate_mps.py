import numpy as np
import pytest

from benchmarks.validate_mps import common, report
from benchmarks.validate_mps.cli import parse_args
from benchmarks.validate_mps.mass import check_mass


def test_cli_flags_and_defaults():
    args = parse_args([])
    assert (args.quick, args.out, args.profile, args.solver) == (False, None, "mps", [])
    args = parse_args(
        ["--quick", "--profile", "mps_corrected", "--solver", "ppe.tol=1e-8", "re_laplacian=2.1"]
    )
    assert (
        args.quick and args.profile == "mps_corrected" and args.solver == ["ppe.tol=1e-8", "re_laplacian=2.1"]
    )


def test_unknown_solver_profile_names_it_and_lists_the_available():
    with pytest.raises(SystemExit, match=r"unknown solver profile 'nope'; available: .*mps_corrected"):
        common.profile_config("nope")


def test_solver_description_names_the_profile_and_dotted_overrides():
    profile, before = common.SOLVER_PROFILE[0], dict(common.SOLVER_OVERRIDES)
    common.SOLVER_PROFILE[0] = "mps"
    common.SOLVER_OVERRIDES.clear()
    try:
        common.SOLVER_OVERRIDES.update({"ppe": {"tol": 1e-8}, "surface_beta": 0.95})
        text = report.solver_description()
    finally:
        common.SOLVER_OVERRIDES.clear()
        common.SOLVER_OVERRIDES.update(before)
        common.SOLVER_PROFILE[0] = profile
    assert text.startswith("conf/solver/mps.yaml (authors' coefficients")
    assert "with ppe.tol=1e-08, surface_beta=0.95, scene dtype float32" in text


def test_write_report_counts_failures_and_writes_both_files(tmp_path):
    checks = [
        common.Check("1 a", "q1", "1.0", "<= 2", "PASS"),
        common.Check("2 b", "q2", "3.0", "<= 2", "FAIL"),
        common.Check("3 c", "q3", "x", "informative", "INFO"),
    ]
    stem = tmp_path / "sub" / "validate_mps_test"
    report.write_report(checks, {"commit": "abc"}, stem, "## Extra\n")
    md = stem.with_suffix(".md").read_text()
    assert "**1 check(s) failed** of 2 pass/fail checks" in md
    assert "| 2 b | q2 | 3.0 | <= 2 | **FAIL** |" in md and md.endswith("## Extra\n")
    csv_lines = stem.with_suffix(".csv").read_text().splitlines()
    assert csv_lines[0] == "# commit: abc"
    assert csv_lines[1] == "check,quantity,measured,criterion,status" and len(csv_lines) == 5


def test_mass_check_fails_when_the_fluid_count_changes_or_fluid_leaves_the_tank():
    lo, hi = np.zeros(3), np.array([1.0, 1.0, np.inf])
    kept = common.RunLog("kept", 10, lo, hi, 0.05, 0.002, steps_done=5, fluid_counts={10})
    lost = common.RunLog("lost", 10, lo, hi, 0.05, 0.002, steps_done=5, fluid_counts={9, 10})
    leak = common.RunLog("leak", 10, lo, hi, 0.05, 0.002, steps_done=5, fluid_counts={10}, outside_max=1)
    assert [c.status for c in check_mass([kept, lost, leak])] == ["PASS", "FAIL", "FAIL"]
