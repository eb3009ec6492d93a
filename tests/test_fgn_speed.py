"""benchmarks.fgn_speed: every stage's time is attributed to op kinds, the dense layers' FLOPs counted."""

from __future__ import annotations

import csv

from benchmarks.fgn_speed import kind_of, main


def test_kinds_of_ops():
    assert kind_of("aten::linear") == "linear" and kind_of("aten::addmm") == "sparse"
    assert kind_of("aten::native_layer_norm") == "layer_norm" and kind_of("aten::silu") == "activation"
    assert kind_of("aten::index_select") == "gather/scatter" and kind_of("aten::mul") == "elementwise"


def test_a_profile_of_the_small_dam(tmp_path):
    argv = [
        "--scenes",
        "dam_small",
        "--warmup",
        "1",
        "--steps",
        "1",
        "--threads",
        "1",
        "--results",
        str(tmp_path),
    ]
    assert main(argv) == 0
    with open(tmp_path / "fgn_speed.csv") as f:
        rows = list(csv.DictReader(f))
    cells = {(r["stage"], r["kind"]): r for r in rows}
    for stage in ("advection", "pressure_net"):
        assert float(cells[(stage, "linear")]["mflop"]) > 0 and float(cells[(stage, "linear")]["ms"]) > 0
        sparse = cells[(stage, "sparse")]
        # neither FLOPs nor bytes of the CSR matrix's dense shape, hence no bound
        assert float(sparse["mflop"]) == 0 and float(sparse["mb"]) == 0 and sparse["time_over_bound"] == ""
    assert float(cells[("neighbors", "compiled/python")]["ms"]) > 0  # the Numba filter, outside torch ops
    assert "GFLOP/s" in (tmp_path / "fgn_speed.md").read_text()


def test_a_rebuild_profile_names_the_verlet_lists_parts(tmp_path):
    argv = ["--scenes", "dam_small", "--warmup", "1", "--steps", "1", "--threads", "1"]
    assert main([*argv, "--rebuilds", "2", "--results", str(tmp_path)]) == 0
    with open(tmp_path / "fgn_speed_rebuild.csv") as f:
        rows = list(csv.DictReader(f))
    top = rows[0]
    assert top["function"].startswith("update (verlet.py") and float(top["share"]) == 1.0
    assert float(top["calls_per_rebuild"]) == 1.0 and int(top["candidates"]) > 0
    names = [r["function"] for r in rows]
    assert any(n.startswith("verlet_candidates") for n in names)  # the compiled split search was profiled
    # two queries a rebuild (fluid-fluid, fluid-boundary): the boundary's index is not remade by a reset
    assert [float(r["calls_per_rebuild"]) for r in rows if r["function"].startswith("query_rows")] == [2.0]
    assert all(0 < float(r["share"]) <= 1 for r in rows)
