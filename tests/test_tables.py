"""benchmarks.tables: the Pareto front, the row files, and a tiny profile end to end (untrained weights)."""

from __future__ import annotations

import argparse
import copy
import csv
import math
from dataclasses import replace

import pytest

from benchmarks.pareto import dominates, pareto_front
from benchmarks.tables.bench import Bench
from benchmarks.tables.cli import run_all
from benchmarks.tables.config import coarsened_scene, compose_config, hydra_value, steps_in
from benchmarks.tables.profiles import QUICK
from benchmarks.tables.report import MARK_END, MARK_START, write_readme
from benchmarks.tables.rows import status
from lagfluid.errors import ConfigError
from lagfluid.run import CONF_DIR
from lagfluid.tasks.evaluate import EvaluateOptions, key_hash, reference_key, reference_settings


# ------------------------------------------------------------------------------------------- Pareto front
def test_pareto_front_of_hand_made_points():
    points = [
        (1.0, 10.0),  # 0 front: the second cheapest
        (2.0, 5.0),  # 1 front
        (3.0, 5.0),  # 2 dominated by 1 (dearer, same error)
        (4.0, 1.0),  # 3 front
        (5.0, 2.0),  # 4 dominated by 3 (dearer and worse)
        (0.5, 20.0),  # 5 front: the cheapest, however bad
        (2.0, 5.0),  # 6 front: equal to 1, and neither of two equal points dominates the other
        (math.nan, 0.0),  # 7 a run that stopped: never on the front
        (10.0, 0.5),  # 8 front: the most accurate
        (10.0, 0.7),  # 9 dominated by 8 (same cost, worse)
        (0.5, math.inf),  # 10 not finite
    ]
    assert pareto_front(points) == [5, 0, 1, 6, 3, 8]


def test_dominates_needs_one_strict_improvement():
    assert dominates((1, 1), (2, 2)) and dominates((1, 2), (1, 3)) and dominates((1, 3), (2, 3))
    assert not dominates((1, 1), (1, 1)) and not dominates((1, 3), (2, 2)) and not dominates((2, 2), (1, 1))


def test_pareto_front_of_nothing_or_one_point():
    assert (
        pareto_front([]) == [] and pareto_front([(3.0, 4.0)]) == [0] and pareto_front([(math.nan, 1)]) == []
    )


# ------------------------------------------------------------------------------------------- helpers
def test_coarsened_scene_keeps_the_physical_dam():
    dam = compose_config(["scene=dam"]).scene
    assert coarsened_scene(dam, 2) == {"l0": 0.1, "fluid_size": [5, 10, 10], "tank_size": [21, 11]}
    small = compose_config(["scene=dam_small"]).scene
    c = coarsened_scene(small, 2)
    # fluid 0.4 x 0.4 x 0.5 m and tank surfaces 1.0 x 0.4 m apart at both spacings
    assert [f * c["l0"] for f in c["fluid_size"]] == pytest.approx([f * 0.05 for f in small.fluid_size])
    assert [(t - 1) * c["l0"] for t in c["tank_size"]] == pytest.approx(
        [(t - 1) * 0.05 for t in small.tank_size]
    )
    with pytest.raises(
        ConfigError, match=r"dam_medium .*fluid_size \[20, 25, 20\].* cannot be coarsened by 2"
    ):
        coarsened_scene(compose_config(["scene=dam_medium"]).scene, 2)
    with pytest.raises(ConfigError, match="waterfall has no fluid_size"):
        coarsened_scene(compose_config(["scene=waterfall"]).scene, 2)


def test_steps_in_names_a_duration_that_is_not_whole_steps():
    assert steps_in(1.0, 0.002, "x") == 500 and steps_in(0.04, 0.0025, "x") == 16
    with pytest.raises(
        ConfigError, match=r"frame interval: 0.04 s is not a whole number of steps of dt = 0.003"
    ):
        steps_in(0.04, 0.003, "frame interval")


def test_quick_profile_fits_every_time_step_it_runs():
    """Durations and frame interval are whole steps of 2 ms (MPS, FGN), 4 ms (the test plugin), 8 ms (GNS's
    training frames) and of the quick Fig. 5 and trade-off dts."""
    dts = {0.002, 0.004, 0.008, *QUICK.fig5_dts, *QUICK.mps_dts}
    for dt in dts:
        for what in ("dam_duration", "frame_interval", "waterfall_duration"):
            steps_in(getattr(QUICK, what), dt, what)
    assert steps_in(QUICK.table4_duration, 0.002, "table4") == 20


def test_hydra_value_round_trips_through_an_override():
    value = {"dt": None, "steps": 500, "scene": {"params": {"l0": 0.05}, "fluid_size": [10, 20, 20]}}
    cfg = compose_config([f"evaluate.reference={hydra_value(value)}"])
    assert cfg.evaluate.reference == value


def test_every_tradeoff_and_fig5_row_file_is_compared_with_the_default_mps():
    """The row files of the full profile: one reference (MPS at the defaults on the dam) for all of them."""
    default = key_hash(reference_key(compose_config(["experiment=table3_dam_mps"])))
    names = ["fig5_fgn", *(p.stem for p in (CONF_DIR / "experiment").glob("tradeoff_*.yaml"))]
    names += [p.stem for p in (CONF_DIR / "experiment").glob("table3_dam_*.yaml")]
    assert len(names) >= 12
    for name in names:
        cfg = compose_config([f"experiment={name}"])
        assert cfg.task == "evaluate", name
        overrides = EvaluateOptions.from_config(cfg.evaluate).reference
        assert key_hash(reference_key(reference_settings(cfg, overrides))) == default, name


def test_the_gns_rows_run_alone_are_compared_with_the_default_mps_of_their_case():
    """GNS steps by 8 ms: its row files' steps and frames, run alone, make evaluate ask MPS for the very
    reference of the MPS rows (steps and frames times 4 at 2 ms)."""
    from types import SimpleNamespace

    from lagfluid.tasks.evaluate.task import reference_overrides

    gns = SimpleNamespace(dt=0.008, name="gns")  # the simulator's dt is all the reference depends on
    for case in ("dam", "waterfall"):
        mps = compose_config([f"experiment=table3_{case}_mps"])
        cfg = compose_config([f"experiment=table3_{case}_gns"])
        assert cfg.steps * 0.008 == pytest.approx(mps.steps * 0.002)
        overrides = reference_overrides(cfg, EvaluateOptions.from_config(cfg.evaluate), gns, None)
        got = key_hash(reference_key(reference_settings(cfg, overrides)))
        assert got == key_hash(reference_key(mps)), case


# ------------------------------------------------------------------------------------------- simulators
@pytest.fixture
def runtime_plugin(monkeypatch):
    """Register simulators and experiment rows in this process only (as a plugin would, at import)."""
    from hydra.core.config_store import ConfigStore

    from lagfluid import registry

    store = ConfigStore.instance()
    monkeypatch.setattr(registry, "_REGISTERED", dict(registry._REGISTERED))
    monkeypatch.setattr(store, "repo", copy.deepcopy(store.repo))

    def add(name: str, rows: dict[str, dict] | None = None) -> None:
        registry.register_simulator(name)(lambda cfg: None)
        for row, node in (rows or {}).items():
            node = {"defaults": [{"override /model": name}], **node}
            store.store(group="experiment", name=row, node=node, package="_global_")

    return add


def test_the_built_in_simulators_come_from_their_row_files_in_the_papers_order():
    from benchmarks.tables.simulators import Simulator, all_simulators, simulator

    sims = all_simulators()
    assert sims[:5] == [
        Simulator("mps", "MPS", "mps", "none"),
        Simulator("fgn", "FGN", "fgn", "fgn"),
        Simulator("hybrid_pressure", "hybrid: learned pressure", "hybrid", "fgn"),
        Simulator("hybrid_advection", "hybrid: learned advection", "hybrid", "fgn"),
        Simulator("fgn_original", "FGN, authors' weights", "fgn_original", "none"),
    ]
    assert all(
        s.rows == (f"table2_{s.key}", f"table3_dam_{s.key}", f"table3_waterfall_{s.key}") for s in sims[:5]
    )
    # the GNS baseline plugin's rows (baselines/gns/conf/experiment): its shipped weights in every table, the
    # paper-size untrained network in Table 2 alone, timed for fewer steps
    gns, paper = sims[5:7]
    assert (gns.key, gns.label, gns.model, gns.timing_steps) == ("gns", "GNS (CPU size)", "gns", None)
    assert gns.rows == ("table2_gns", "table3_dam_gns", "table3_waterfall_gns") and "shipped" in gns.note
    assert (paper.key, paper.model, paper.rows) == ("gns_paper", "gns", ("table2_gns_paper",))
    assert "paper size" in paper.label and "timing only" in paper.label and paper.timing_steps == 2
    assert paper.appears_in("table2_gns_paper") and not paper.appears_in("table3_dam_gns_paper")
    assert compose_config(["experiment=table2_gns_paper"]).model.weights == "untrained"
    # the CConv plugin's rows (baselines/cconv/conf/experiment): DeepLagrangianFluids' published network in
    # every table, the weights the package ships (the model's default: nothing passed)
    cconv = sims[7]
    assert (cconv.key, cconv.model, cconv.weights) == ("cconv_original", "cconv_original", "none")
    names = ("table2_cconv_original", "table3_dam_cconv_original", "table3_waterfall_cconv_original")
    assert cconv.rows == names
    assert cconv.model_overrides(None) == [] and sims[4].model_overrides(None) == []
    assert [s.key for s in all_simulators(["fgn_original", "mps"])] == ["mps", "fgn_original"]
    with pytest.raises(ConfigError, match=r"no simulator 'nope' in the tables; available: mps, fgn, "):
        simulator("nope")


def test_a_simulator_registered_at_runtime_with_rows_is_listed_with_its_label(runtime_plugin):
    from benchmarks.tables.simulators import Simulator, all_simulators, simulator

    table = {"label": "toy MLP", "order": 2.5, "weights": "none"}
    rows = {f"table3_{case}_toy_mlp": {"task": "evaluate", "table": table} for case in ("dam", "waterfall")}
    runtime_plugin("toy_mlp", {**rows, "table2_toy_mlp": {"task": "simulate", "table": table}})
    runtime_plugin("toy_plain")  # no row files: run as model=toy_plain, after every simulator with rows
    keys = [s.key for s in all_simulators()]
    assert keys[:6] == ["mps", "fgn", "hybrid_pressure", "toy_mlp", "hybrid_advection", "fgn_original"]
    assert keys[-1] == "toy_plain"
    assert simulator("toy_mlp") == Simulator("toy_mlp", "toy MLP", "toy_mlp", "none")
    assert simulator("toy_plain") == Simulator("toy_plain", "toy_plain", "toy_plain", "none")
    assert simulator("toy_plain").appears_in("table3_dam_toy_plain")  # no row files: in every table
    assert compose_config(["experiment=table3_dam_toy_mlp"]).model.name == "toy_mlp"  # the row runs it


def test_a_bad_table_block_names_the_row_and_the_value(runtime_plugin):
    from benchmarks.tables.simulators import all_simulators

    runtime_plugin("toy_bad", {"table2_toy_bad": {"table": {"label": "x", "weights": "shipped"}}})
    with pytest.raises(
        ConfigError, match=r"experiment=table2_toy_bad: table.weights 'shipped' is not one of"
    ):
        all_simulators()


def test_a_key_with_only_a_table2_row_is_timed_and_in_no_other_table(runtime_plugin, tmp_path):
    from benchmarks.tables.simulators import simulator

    table = {"label": "toy, timing only", "weights": "none", "timing_steps": 2, "note": "untrained."}
    runtime_plugin("toy_timed", {"table2_toy_timed": {"task": "simulate", "table": table}})
    sim = simulator("toy_timed")
    assert sim.rows == ("table2_toy_timed",) and sim.timing_steps == 2 and sim.note == "untrained."
    profile = replace(TINY, simulators=("mps", "toy_timed"), waterfall=("scene.scale=0.25",))
    bench = Bench(profile, argparse.Namespace(weights=None, threads=1, runs_dir=str(tmp_path)))
    asked: list[str] = []  # the rows the parts would run (none is run here)
    bench.evaluate = lambda run, **_: asked.append(run.key) or run
    bench.time_steps = lambda run: asked.append(run.key) or run
    bench.own_dt = lambda sim: None
    bench.accuracy_runs("dam"), bench.accuracy_runs("waterfall"), bench.table2_runs()
    assert asked == ["table3/dam/mps", "table3/waterfall/mps", "table2/mps", "table2/toy_timed"]


def test_a_row_whose_weights_are_missing_is_skipped_with_its_reason_not_failed(runtime_plugin, tmp_path):
    from lagfluid import registry
    from lagfluid.models.checkpoint import MissingWeightsError

    def no_weights(cfg):
        raise MissingWeightsError("no toy weights at /nowhere/toy.pt")

    def broken(cfg):
        raise RuntimeError("a real failure")

    for name, factory in (("toy_unshipped", no_weights), ("toy_broken", broken)):
        runtime_plugin(name, {f"table2_{name}": {"task": "simulate", "table": {"label": name}}})
        registry.register_simulator(name)(factory)
    profile = replace(TINY, simulators=("toy_unshipped", "toy_broken"))
    bench = Bench(profile, argparse.Namespace(weights=None, threads=1, runs_dir=str(tmp_path)))
    runs = {run.sim.key: run for run in bench.table2_runs()}
    unshipped, broken_run = runs["toy_unshipped"], runs["toy_broken"]
    assert unshipped.skipped and not unshipped.failed and unshipped.state == "skipped"
    assert status(unshipped) == "skipped: MissingWeightsError: no toy weights at /nowhere/toy.pt"
    assert broken_run.failed and not broken_run.skipped and broken_run.state == "FAILED"
    assert status(broken_run) == "failed: RuntimeError: a real failure"


def test_table2_rows_time_fewer_steps_when_a_row_asks_and_never_a_start_up(runtime_plugin):
    from benchmarks.tables.bench import timing_warmup
    from benchmarks.tables.simulators import all_simulators

    assert timing_warmup(QUICK, 0) == QUICK.timing_warmup  # a one-step scheme: the profile's warm-up
    assert timing_warmup(QUICK, 5) == 6  # 5 start-up steps (a warm start by MPS), then its first own step
    assert timing_warmup(replace(QUICK, timing_warmup=10), 5) == 10
    runtime_plugin("toy_steps", {"table3_dam_toy_steps": {"table": {"timing_steps": 2}}})
    with pytest.raises(ConfigError, match=r"table3_dam_toy_steps: table.timing_steps is for a Table 2 row"):
        all_simulators()


def test_row_files_of_one_simulator_must_agree(runtime_plugin):
    from benchmarks.tables.simulators import all_simulators

    runtime_plugin(
        "toy_two",
        {"table2_toy_two": {"table": {"label": "two"}}, "table3_dam_toy_two": {"table": {"label": "Two"}}},
    )
    with pytest.raises(ConfigError, match=r"the row files of 'toy_two' describe it differently"):
        all_simulators()


# ------------------------------------------------------------------------------------------- end to end
TINY = replace(
    QUICK,
    name="tiny",
    prefix="tables_tiny",
    dam_duration=0.02,
    frame_interval=0.01,
    waterfall=None,
    timing_warmup=1,
    timing_steps=2,
    table4_duration=0.01,
    table4_materials=((2.0, 1e-3), (50.0, 0.05)),
    fig5_dts=(0.001, 0.002, 0.005),
    mps_dts=(0.005,),
    ppe_tols=(1e-1,),
    coarse=((2, None),),
    simulators=("mps", "fgn", "hybrid_pressure", "fgn_gcn"),
    figures=False,
    description="tiny test profile",
)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory, untrained_weights, untrained_weights_of):
    import shutil

    import lagfluid.models.fgn.simulator as fgn_simulator

    root = tmp_path_factory.mktemp("tables")
    shipped = root / "weights"  # the GCN ablation's "shipped" node nets, FGN's collision net beside them
    shutil.copytree(untrained_weights, shipped / "fgn")
    shutil.copytree(untrained_weights_of("fgn_gcn"), shipped / "fgn_gcn")
    readme = root / "README.md"
    readme.write_text(f"# x\n\n## Results\n\nprose\n\n{MARK_START}\nold\n{MARK_END}\n\n## Next\n")
    args = argparse.Namespace(
        only=None,
        weights=str(untrained_weights),
        threads=1,
        device="cpu",
        results=str(root / "results"),
        runs_dir=str(root / "runs"),
        readme=True,
        readme_path=str(readme),
    )
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(fgn_simulator, "WEIGHTS_ROOT", shipped)
        return root, run_all(TINY, args), args, shipped


def test_tiny_profile_writes_every_output(tiny_run):
    root, written, *_ = tiny_run
    results = root / "results"
    for name in ("report.md", "table2.csv", "table3.csv", "table4.csv", "fig5.csv", "tradeoff.csv"):
        assert (results / f"tables_tiny_{name}").stat().st_size > 100, name
    for name in ("fig5.png", "tradeoff.png"):
        assert (results / f"tables_tiny_{name}").stat().st_size > 10_000, name
    assert written["failed"] == []
    report = (results / "tables_tiny_report.md").read_text()
    for heading in (
        "## Tables 1 and 3",
        "## Table 2",
        "## Table 4",
        "## Fig. 5",
        "## Speed/accuracy",
        "## Provenance",
    ):
        assert heading in report
    assert "python -m lagfluid.run experiment=tradeoff_dam_mps_l0_10cm" in report  # each row's command
    with (results / "tables_tiny_table3.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [r["simulator"] for r in rows] == ["Ground truth (MPS)", "FGN", "hybrid: learned pressure"]
    assert all(r["machine"] and r["git_commit"] and r["overrides"] for r in rows)  # provenance per number


def test_table5_sets_the_ablations_beside_table3s_own_fgn_and_mps_rows(tiny_run):
    root, written, *_ = tiny_run
    results = root / "results"
    assert written["failed"] == []
    with (results / "tables_tiny_table5.csv").open() as f:
        table5 = list(csv.DictReader(f))
    with (results / "tables_tiny_table3.csv").open() as f:
        table3 = list(csv.DictReader(f))
    assert [r["simulator"] for r in table5] == ["Ground truth (MPS)", "FGN", "GCN (FGN ablation)"]
    assert table5[2]["experiment"] == "table5_dam_fgn_gcn" and table5[2]["status"] == "complete"
    # the same FGN and MPS rows as Table 3's (same scene, steps and reference), the ablation in Table 5 alone
    same = [(table5[i]["density_error_mean"], table3[i]["density_error_mean"]) for i in (0, 1)]
    assert all(a == b for a, b in same), same
    assert not any("GCN" in r["simulator"] for r in table3)
    report = (results / "tables_tiny_report.md").read_text()
    assert "## Table 5" in report and "## Tables 1 and 3" in report


def test_table4_pressure_rows_are_the_rows_with_a_learned_pressure_stage(tiny_run):
    _, written, *_ = tiny_run
    pressure = [r["case"] for r in written["rows"]["table4"] if r["network"] == "pressure"]
    assert pressure == ["FGN, dam", "hybrid: learned pressure, dam"]


def test_tiny_profile_rewrites_only_the_marked_readme_part(tiny_run):
    root, written, *_ = tiny_run
    text = (root / "README.md").read_text()
    assert written["readme"] and "old" not in text and "prose" in text and text.endswith("## Next\n")
    assert (
        "**Table 1**" in text and "**Table 2**" in text and "**Table 4**" in text and "tiny profile" in text
    )


def test_tradeoff_rows_share_one_reference_and_mark_the_front(tiny_run):
    _, written, *_ = tiny_run
    rows = written["rows"]["tradeoff"]
    labels = {r["simulator"]: r for r in rows}
    assert {"MPS", "FGN", "MPS dt = 5 ms", "MPS PPE tol 0.1 (rel)", "MPS l0 = 10 cm", "FGN dt = 5 ms"} <= set(
        labels
    )
    assert len({r["reference"] for r in rows}) == 1
    mps = labels["MPS"]
    assert mps["chamfer_mean_mm"] == 0.0 and mps["chamfer_t0_mm"] == 0.0  # MPS against itself
    # a coarse particle sits at the centre of a cube of 8 reference particles: sqrt(3)/2 l0 away at t = 0
    assert labels["MPS l0 = 10 cm"]["chamfer_t0_mm"] == pytest.approx(1e3 * 0.05 * math.sqrt(3) / 2, rel=1e-4)
    assert labels["MPS dt = 5 ms"]["steps"] == 4 and labels["MPS dt = 5 ms"]["chamfer_t0_mm"] == 0.0
    for metric in ("chamfer_mean_mm", "density_error_mean"):
        points = [
            (r["s_per_simulated_s"], r[metric]) if r["status"] == "complete" else (math.nan,) * 2
            for r in rows
        ]
        assert [i for i, r in enumerate(rows) if r[f"pareto_{metric}"]] == sorted(pareto_front(points))
    # MPS is the most accurate row (Chamfer 0): on that front unless another row is as accurate and cheaper
    as_good_and_cheaper = [
        r
        for r in rows
        if r is not mps and r["chamfer_mean_mm"] == 0.0 and r["s_per_simulated_s"] < mps["s_per_simulated_s"]
    ]
    assert mps["pareto_chamfer_mean_mm"] == (not as_good_and_cheaper)


def test_write_readme_without_markers_leaves_the_file(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text("# nothing marked\n")
    assert write_readme("new", readme) is False and readme.read_text() == "# nothing marked\n"


def test_bench_rejects_a_frame_interval_that_is_not_whole_steps(untrained_weights, tmp_path):
    args = argparse.Namespace(weights=str(untrained_weights), threads=1, runs_dir=str(tmp_path))
    bench = Bench(replace(TINY, frame_interval=0.003), args)
    with pytest.raises(ConfigError, match=r"0\.003 s is not a whole number of steps of dt = 0\.002"):
        bench.dam_overrides("dam_small", 0.03)


def test_an_only_rerun_replaces_its_parts_and_keeps_the_others(tmp_path):
    from benchmarks.tables.report import Report, earlier_parts, merge_parts

    first = Report(tmp_path / "tables", {"date": "day 1", "script_commit": "aaa"})
    first.sections = {"table2": "T2 old", "table3": "T3 old"}
    first.readme = {"table1": "R1 old", "table2": "R2 old"}
    merge_parts(
        first, partial=False, commands={"table2/mps": "cmd 2", "table3/dam/mps": "cmd 3"}, invocation="full"
    )

    rerun = Report(tmp_path / "tables", {"date": "day 2", "script_commit": "bbb"})
    rerun.sections, rerun.readme = {"table2": "T2 new"}, {"table2": "R2 new"}
    merged = merge_parts(rerun, partial=True, commands={"table2/mps": "cmd 2 quiet"}, invocation="only t2")
    assert merged["sections"] == {"table2": "T2 new", "table3": "T3 old"}
    assert merged["readme"] == {"table1": "R1 old", "table2": "R2 new"}
    assert merged["commands"] == {"table2/mps": "cmd 2 quiet", "table3/dam/mps": "cmd 3"}
    assert merged["history"] == {"day 1 at commit aaa": "full", "day 2 at commit bbb": "only t2"}
    note = earlier_parts(merged, "sections", "day 2 at commit bbb")
    assert "table3: day 1 at commit aaa" in note and "table2" not in note

    full = Report(tmp_path / "tables", {"date": "day 3", "script_commit": "ccc"})
    full.sections = {"table2": "T2 full"}
    assert merge_parts(full, partial=False, commands={})["sections"] == {"table2": "T2 full"}  # afresh


def test_an_only_run_without_an_earlier_full_run_is_refused(tmp_path):
    from benchmarks.tables.report import Report, merge_parts
    from lagfluid.errors import ConfigError

    report = Report(tmp_path / "tables", {"date": "d", "script_commit": "c"})
    with pytest.raises(ConfigError, match=r"tables_parts\.json is missing"):
        merge_parts(report, partial=True, commands={})


def test_runtime_estimate_counts_only_the_parts_asked_for():
    from benchmarks.tables.profiles import FULL, PARTS, estimate_seconds

    full = estimate_seconds(FULL)
    alone = {part: estimate_seconds(FULL, [part]) for part in PARTS}
    assert all(0 < t < full for t in alone.values()), alone
    # the dam rows are shared by every part but Table 2: counted once in the full run, in each part alone
    assert full < sum(alone.values())
    assert estimate_seconds(FULL, ["table3", "table4"]) < alone["table3"] + alone["table4"]
    assert alone["table2"] < alone["table4"]  # Table 2 is ten timed steps, no 1 s dam


def test_device_option_is_checked_and_keeps_the_cpu_results_and_readme(capsys):
    from benchmarks.tables.cli import parse_args
    from benchmarks.tables.report import RESULTS

    args = parse_args(["--only", "table2"])
    assert args.device == "cpu" and args.results == str(RESULTS) and args.readme
    for bad, says in (("bogus", "unknown device 'bogus'"), ("mps", "is not supported")):
        with pytest.raises(SystemExit):
            parse_args(["--device", bad])
        assert says in capsys.readouterr().err


def test_simulators_option_runs_those_keys_beside_mps_and_fgn_under_their_own_prefix(capsys, tmp_path):
    from benchmarks.tables.cli import chosen_profile, main, parse_args
    from benchmarks.tables.simulators import all_simulators

    args = parse_args(["--quick", "--simulators", "gns_unroll", "cconv", "gns_unroll"])
    profile = chosen_profile(args)
    assert profile.simulators == ("mps", "fgn", "cconv", "gns_unroll")  # the tables' order, however typed
    assert profile.prefix == "tables_quick_cconv_gns_unroll" and profile.name == "quick"
    assert profile.description.endswith("; only cconv gns_unroll beside MPS and FGN (--simulators)")
    assert chosen_profile(parse_args(["--quick", "--simulators", "cconv", "gns_unroll"])) == profile
    assert {s.key for s in all_simulators(profile.simulators)} == set(profile.simulators)
    assert parse_args(["--simulators", "gns"]).readme is False  # the full profile's default would be True
    assert chosen_profile(parse_args(["--quick"])).prefix == "tables_quick"
    both = chosen_profile(parse_args(["--simulators", "fgn", "mps"]))
    assert both.prefix == "tables_mps_fgn" and both.description.endswith("; MPS and FGN only (--simulators)")
    for argv, says in (
        (["--simulators", "gns_unrol"], "--simulators: unknown gns_unrol; available: mps, fgn,"),
        (["--simulators", "gns", "--readme"], "--simulators and --readme exclude each other"),
    ):
        with pytest.raises(SystemExit):
            parse_args(argv)
        assert says in capsys.readouterr().err
    # --only merges with the subset's own earlier run: without one it is refused before any row runs
    argv = ["--quick", "--simulators", "gns_unroll", "--only", "table3", "--results", str(tmp_path)]
    assert main(argv) == 2
    err = capsys.readouterr()
    says = "tables_quick_gns_unroll_parts.json is missing: run the whole profile first with --simulators "
    says += "gns_unroll (without --only)"
    assert says in err.err and "[tables] table3" not in err.out
    assert list(tmp_path.iterdir()) == []


def test_the_tradeoff_figure_keeps_every_key_line_and_title_line_inside_the_figure(tmp_path, monkeypatch):
    """Long row labels (a model with exact stages after it) wrap instead of running off the figure's edge."""
    import math

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from benchmarks.tables.plots import plot_tradeoff

    long = "GNS (CPU size), DAgger + exact collision + MPS pressure (K=3, w=0.5)"

    def row(name, key, seconds, status="complete"):
        return {
            "simulator": name, "simulator_key": key, "status": status, "s_per_simulated_s": seconds,
            "chamfer_mean_mm": 20.0 + seconds, "chamfer_t0_mm": 0.0, "density_error_mean": 0.01,
            "pareto_chamfer_mean_mm": True, "pareto_density_error_mean": True,
        }  # fmt: skip

    rows = [row("MPS", "mps", 40.0), row(long, "gns_dagger_exact", 45.0)]
    rows += [row(f"{long} stopped variant {k}", f"gns_{k}", math.nan, "stopped") for k in range(6)]
    figures = []
    monkeypatch.setattr(plt, "close", figures.append)  # keep the figure to measure its texts
    plot_tradeoff(tmp_path / "t.png", rows, "Speed/accuracy on dam, 1 s")
    (fig,) = figures
    renderer = fig.canvas.get_renderer()
    width, height = fig.bbox.width, fig.bbox.height
    key = [t for t in fig.texts if t is not fig._suptitle]
    texts = [*key, fig._suptitle]
    assert sum(long.split()[0] in t.get_text() for t in key) == 1
    for text in texts:
        box = text.get_window_extent(renderer)
        assert box.x0 >= 0 and box.x1 <= width and box.y1 <= height, (text.get_text(), box, width)
    assert max(len(line) for t in key for line in t.get_text().splitlines()) <= 4 + 36
