"""``model.exact_after``: the exact collision rule and pressure projection after an end-to-end step."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import pytest
import torch
from hydra import compose, initialize_config_dir

from lagfluid.errors import ConfigError
from lagfluid.integrate import drift
from lagfluid.models.exact_after import ExactAfter, ExactAfterOptions
from lagfluid.neighbors import radius_graph
from lagfluid.physics import operators as ops
from lagfluid.physics.mps import CollisionRule, ExactPressure
from lagfluid.physics.scheme import SplitStepSimulator
from lagfluid.physics.settings import SolverSettings
from lagfluid.physics.step_context import StepContext
from lagfluid.physics.timing import StageTimer
from lagfluid.run import CONF_DIR, check_command_line
from lagfluid.scenes import build_scene
from lagfluid.state import ParticleState, ParticleType, SceneParams
from lagfluid.tasks.config import at_simulator_time_step, build_initial_state, build_simulator
from lagfluid.tasks.simulate import simulate

L0, DT = 0.05, 0.004


def _compose(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


class Still:
    """A stand-in end-to-end model whose step moves nothing: the exact stages see the state it was given."""

    name = "still"
    dt = DT
    history_length = 0
    max_courant = None
    parameters = 0
    last_fields = None

    def __init__(self) -> None:
        self.last_timings = {"network": 0.0}
        self.last_info: dict[str, float] = {}

    def reset(self, state, history=()):
        pass

    def step(self, state, *, record=False):
        nf = state.n_fluid
        return state.advanced_fluid(state.pos[:nf], state.vel[:nf], self.dt)

    def attributes(self):
        return {"kind": "still"}


class Drift(Still):
    """A stand-in model that moves every fluid particle by ``v dt`` (the split step without advection)."""

    name = "drift"

    def step(self, state, *, record=False):
        nf = state.n_fluid
        return state.advanced_fluid(drift(state.pos[:nf], state.vel[:nf], self.dt), state.vel[:nf], self.dt)


def _fluid(pos, vel) -> ParticleState:
    n = len(pos)
    return ParticleState(
        pos=torch.tensor(pos, dtype=torch.float64),
        vel=torch.tensor(vel, dtype=torch.float64),
        ptype=torch.full((n,), int(ParticleType.FLUID)),
        params=SceneParams(dt=DT, l0=L0),
    )


def test_exact_collision_after_a_step_is_the_collision_rule_applied_directly():
    # 0 and 1 approach head on, 0.5 l0 apart (< re_collision 0.92 l0); 2 is alone, 5 l0 away
    state = _fluid([[0, 0, 0], [0.5 * L0, 0, 0], [5 * L0, 0, 0]], [[1, 0, 0], [-1, 0, 0], [0, 0, 1]])
    settings = SolverSettings()
    sim = ExactAfter(Still(), ExactAfterOptions(collision=True), settings)
    sim.reset(state)
    new = sim.step(state)
    # the rule by hand: v_i -= (1 + e)/2 (v_ij . r_ij / |r_ij|^2) r_ij, e = 0.2: 1 - 0.6 * 2 = -0.2
    e = settings.restitution
    expected = torch.tensor([1 - (1 + e), -1 + (1 + e), 0], dtype=torch.float64)
    torch.testing.assert_close(new.vel[:, 0], expected)
    assert new.vel[2].tolist() == [0.0, 0.0, 1.0]
    # positions: x += (v_new - v_old) dt
    expected = torch.tensor([-(1 + e) * DT, 0.5 * L0 + (1 + e) * DT, 5 * L0], dtype=torch.float64)
    torch.testing.assert_close(new.pos[:, 0], expected)
    # bit for bit CollisionRule on the same positions and velocities
    direct = SplitStepSimulator("rule", settings, None, CollisionRule(), None)
    direct.reset(state)
    ctx = StepContext(state, settings, direct.constants, direct.neighbors, StageTimer())
    rule = CollisionRule()(ctx, state.pos.clone(), state.vel.clone())
    assert torch.equal(new.vel, rule)
    assert torch.equal(new.pos, state.pos + (rule - state.vel) * DT)
    assert new.time == pytest.approx(DT) and new.step == 1
    assert sim.name == "still + exact collision" and sim.last_info["collisions"] == 2.0
    assert set(sim.last_timings) >= {"network", "exact_collision", "neighbors"}


def _compressed_block(spacing: float) -> ParticleState:
    axis = torch.arange(7, dtype=torch.float64) * spacing * L0
    grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1).reshape(-1, 3)
    return _fluid(grid.tolist(), torch.zeros_like(grid).tolist())


def _core_density_error(state: ParticleState, sim: ExactAfter) -> float:
    """Mean ``|n / n0 - 1|`` of the block's 5^3 core (the same particles before and after)."""
    radius, n0 = sim.exact.settings.re_density * L0, sim.exact.constants.n0
    n = ops.number_density(state.pos, radius_graph(state.pos, radius), radius, num_nodes=len(state.pos))
    core = torch.arange(7**3).reshape(7, 7, 7)[1:-1, 1:-1, 1:-1].reshape(-1)
    return float((n[core] / n0 - 1).abs().mean())


def test_mps_pressure_after_a_step_lowers_a_compressed_blocks_density_error():
    state = _compressed_block(0.9)  # 7^3 particles at rest at 0.9 l0: the core is 40 % too dense
    after, pressure = {}, {}
    for options in (
        ExactAfterOptions(pressure=True),
        ExactAfterOptions(pressure=True, relaxation=0.5),
        ExactAfterOptions(pressure=True, iterations=3),
    ):
        sim = ExactAfter(Still(), options, SolverSettings())
        sim.reset(state)
        new = sim.step(state)
        after[options.describe()], pressure[options.describe()] = _core_density_error(new, sim), new.pressure
        assert sim.last_info["ppe_iterations"] > 0 and "exact_pressure_solve" in sim.last_timings
    alone = _core_density_error(Still().step(state), sim)  # the network's step alone leaves it
    once, half, thrice = after.values()
    assert alone == pytest.approx(0.40, abs=0.01)
    # one projection removes more than half of it (the minimum-pressure gradient only repels), w = 0.5 less
    assert once < 0.45 * alone and once < half < 0.75 * alone, after
    # a second projection in the same step finds nothing left: the first one's velocity (div v > 0) cancels
    # the density term of MPS's source, its pressure clamps to 0, and K = 3 ends where K = 1 did
    assert thrice == once and pressure["MPS pressure (K=3, w=1)"].abs().max() == 0
    assert pressure["MPS pressure"].max() > 1e4


def test_the_wrapper_is_the_split_step_after_a_drift_bit_for_bit():
    # the split step without advection drifts, collides and projects: the same as Drift + exact stages
    state = build_scene("dam", SceneParams(dt=DT), fluid_size=[6, 6, 8], tank_size=[15, 8])
    gen = torch.Generator().manual_seed(0)
    vel = state.vel.clone()
    vel[: state.n_fluid] = torch.randn(state.n_fluid, 3, generator=gen) * 0.5
    state = ParticleState(pos=state.pos, vel=vel, ptype=state.ptype, params=state.params, bounds=state.bounds)
    settings = SolverSettings()
    wrapped = ExactAfter(Drift(), ExactAfterOptions(collision=True, pressure=True), settings)
    split = SplitStepSimulator("split", settings, None, CollisionRule(), ExactPressure())
    a, b = state, state
    wrapped.reset(a)
    split.reset(b)
    for _ in range(3):
        a, b = wrapped.step(a), split.step(b)
        for name in ("pos", "vel", "pressure"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert wrapped.last_info["collisions"] > 0 and a.pressure.max() > 0


def test_exact_after_off_builds_the_model_itself():
    for extra in ([], ["model.exact_after.iterations=1", "model.exact_after.relaxation=1.0"]):
        sim = build_simulator(_compose("model=gns", "scene=dam_small", *extra))
        assert type(sim).__name__ == "GNSSimulator" and sim.name == "gns"
    sim = build_simulator(_compose("model=gns", "scene=dam_small", "model.exact_after.pressure=true"))
    assert isinstance(sim, ExactAfter) and sim.name == "gns + MPS pressure"
    assert (sim.dt, sim.history_length, sim.max_courant) == (0.008, 5, 1.0)


def test_gns_history_after_a_corrected_step_is_the_corrected_displacement():
    overrides = ("model=gns", "scene=dam_small")
    on = ("model.exact_after.collision=true", "model.exact_after.pressure=true")
    cfg = _compose(*overrides, *on)
    sim, plain = build_simulator(cfg), build_simulator(_compose(*overrides))
    state = at_simulator_time_step(build_initial_state(cfg), sim, cfg)
    sim.reset(state)
    plain.reset(state)
    a = b = state
    for _ in range(5):  # the MPS warm start: its frames are left as they are
        a, b = sim.step(a), plain.step(b)
        assert not sim.model.last_step_learned and torch.equal(a.pos, b.pos)
        assert not sim.last_step_learned  # the hybrid says so too: a DAgger rollout labels none of these
        assert "exact_pressure_solve" not in sim.last_timings
    nf, dt = state.n_fluid, sim.dt
    for _ in range(2):
        before = a
        a, b = sim.step(before), plain.step(before)
        assert sim.model.last_step_learned and not torch.equal(a.pos, b.pos)  # the stages moved particles
        assert sim.last_step_learned
        assert torch.equal(sim.model._velocities[:, -1], (a.pos[:nf] - before.pos[:nf]) / dt)
        torch.testing.assert_close(sim.model._velocities[:, -1], a.vel[:nf], rtol=0, atol=1e-4)
        plain.restore_rollout_memory(a, sim.model.rollout_memory())  # the plain one follows the corrected run
    assert json.dumps(sim.attributes())  # plain values, storable
    assert sim.attributes()["base_model"] == "gns" and sim.attributes()["exact_after_collision"] is True


def test_labels_reach_rollout_and_metrics(tmp_path):
    out = tmp_path / "run"
    simulate(
        _compose(
            "experiment=debug",
            "model=cconv",
            "steps=3",
            "model.exact_after.collision=true",
            "model.exact_after.pressure=true",
            "model.exact_after.iterations=2",
            "model.exact_after.relaxation=0.5",
            f"out_dir={out}",
        )
    )
    label = "cconv + exact collision + MPS pressure (K=2, w=0.5)"
    with h5py.File(out / "rollout.h5") as f:
        attrs = f["00000"].attrs
        assert attrs["model"] == label and attrs["base_model"] == "cconv"
        assert bool(attrs["exact_after_pressure"]) and attrs["exact_after_iterations"] == 2
        assert attrs["exact_after_relaxation"] == 0.5
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["model"] == label and metrics["complete"]
    stages = {"network", "neighbors", "exact_collision", "exact_pressure_solve"}
    assert stages <= set(metrics["stage_median_s"])


@pytest.mark.parametrize(
    ("node", "message"),
    [
        ({"iterations": 0}, r"iterations must be a whole number >= 1, got 0"),
        ({"pressure": True, "iterations": 2.5}, r"iterations must be a whole number >= 1, got 2.5"),
        ({"pressure": True, "relaxation": 0}, r"relaxation must be a number in \(0, 1\], got 0"),
        ({"pressure": True, "relaxation": 1.5}, r"relaxation must be a number in \(0, 1\], got 1.5"),
        ({"colision": True}, r"has no key 'colision'; keys: collision, pressure, iterations, relaxation"),
        ({"collision": "yes"}, r"collision must be true or false, got 'yes'"),
        ({"iterations": 3}, r"none is on: set model.exact_after.collision=true"),
        ({"collision": True, "relaxation": 0.5}, r"scales the pressure correction, but .*pressure is false"),
        ([1, 2], r"must be a mapping"),
    ],
)
def test_a_bad_exact_after_is_one_config_error_naming_it(node, message):
    with pytest.raises(ConfigError, match=r"model\.exact_after.*" + message):
        ExactAfterOptions.from_config(node)


def test_a_bad_exact_after_on_the_command_line_is_one_line(tmp_path):
    for arg in ("model.exact_after.colision=true", "+model.exact_after.colision=true"):
        assert check_command_line(["model=gns", arg]) == (
            "lagfluid: model.exact_after has no key 'colision'; "
            "keys: collision, pressure, iterations, relaxation"
        )
    assert check_command_line(["model.exact_after.relaxation=0.5"]) is None
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "lagfluid.run",
            "experiment=debug",
            "model.exact_after.iterations=0",
            f"out_dir={tmp_path}",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    console = out.stdout + out.stderr
    errors = [line for line in console.splitlines() if "ERROR" in line]
    assert out.returncode == 1 and "Traceback" not in console
    assert len(errors) == 1 and "model.exact_after.iterations must be a whole number >= 1, got 0" in errors[0]


def test_a_stopped_gns_with_exact_stages_resumes_bit_for_bit(tmp_path, monkeypatch):
    # n0_from=initial: the resumed run resets at the checkpoint's state; the stages keep frame 0's constants
    from test_simulate_resume import _assert_same_run, _stopped_at

    overrides = ("experiment=debug", "checkpoint_every_s=0", "model=gns", "steps=8", "solver.n0_from=initial")
    overrides += ("model.exact_after.collision=true", "model.exact_after.pressure=true")
    simulate(_compose(*overrides, f"out_dir={tmp_path / 'whole'}"))
    with monkeypatch.context() as patch:
        _stopped_at(patch, 7, KeyboardInterrupt)
        with pytest.raises(KeyboardInterrupt):
            simulate(_compose(*overrides, f"out_dir={tmp_path / 'stopped'}"))
    simulate(_compose(*overrides, "resume=true", f"out_dir={tmp_path / 'stopped'}"))
    _assert_same_run(tmp_path / "whole", tmp_path / "stopped")


def test_an_exact_after_that_is_off_leaves_a_resumes_settings_as_they_were():
    # a run checkpointed before model.exact_after existed resumes: the key counts only when a stage is on
    from lagfluid.tasks.simulate_resume import run_settings

    assert "exact_after" not in run_settings(_compose("model=gns"))["model"]
    on = run_settings(_compose("model=gns", "model.exact_after.pressure=true"))["model"]["exact_after"]
    assert on == {"collision": False, "pressure": True, "iterations": 1, "relaxation": 1.0}


def _metrics(model: str, complete: bool, steps: int, chamfer: float, options: dict | None = None) -> dict:
    attrs = {f"exact_after_{k}": v for k, v in (options or {}).items()}
    density = {"model": {"mean": 0.01}, "reference": {"mean": 0.002}}
    summary = {"chamfer_mm": {"mean": chamfer, "max": 2 * chamfer}, "density_error": density}
    return {
        "model": model,
        "complete": complete,
        "steps": steps,
        "dt": 0.008,
        "summary": summary,
        "simulator": attrs,
    }


def test_the_exact_after_benchmark_reports_each_row_and_the_minimum_that_completes():
    from benchmarks.exact_after import result_row, verdict

    both = {"collision": True, "pressure": True, "iterations": 3, "relaxation": 0.5}
    plain = result_row(_metrics("gns", False, 29, 14.37), ["python", "-m", "lagfluid.run", "model=gns"])
    assert plain["rollout"] == "stops at step 30 (0.24 s)" and plain["exact stages after the step"] == "none"
    assert plain["Chamfer to MPS mean / max (mm)"] == "14.4 / 28.7" and plain["command"].startswith("`python")
    assert plain["density error mean (MPS)"] == "0.0100 (0.0020)"
    relaxed = result_row(_metrics("gns + ...", False, 119, 50.0, both), ["x"])
    assert relaxed["exact stages after the step"] == "exact collision + MPS pressure (K=3, w=0.5)"
    assert (
        verdict("gns", [plain, relaxed])
        == "`gns`: none completes; the furthest is gns + ..., which stops at step 120 (0.96 s)."
    )
    done = [
        result_row(_metrics(f"m{i}", True, 125, c, {"pressure": True}), ["x"])
        for i, c in ((1, 30.0), (2, 20.0))
    ]
    assert verdict("m", [plain, *done]) == (
        "`m`: complete with MPS pressure; MPS pressure; closest to MPS: m2 (20.0 / 40.0 mm)."
    )
    alone = result_row(_metrics("m", True, 125, 10.0), ["x"])
    assert verdict("m", [alone, *done]).startswith("`m`: complete with no exact stage; MPS pressure; MPS")


def test_the_tables_list_the_exact_after_rows_under_their_own_labels():
    from benchmarks.tables.config import compose_config
    from benchmarks.tables.simulators import simulator

    for key, base, label in (
        ("gns_exact", "gns", "GNS (CPU size) + exact collision + MPS pressure"),
        ("cconv_original_exact", "cconv_original", "CConv, DLF's weights + exact collision + MPS pressure"),
        ("cconv_exact", "cconv", "CConv (CPU training) + exact collision + MPS pressure"),
        (
            "cconv_finetuned_exact",
            "cconv_finetuned",
            "CConv, DLF's weights fine-tuned here + exact collision + MPS pressure",
        ),
    ):
        sim = simulator(key)
        assert (sim.label, sim.model) == (label, base) and "not the plain" in sim.note
        assert sim.rows == (f"table2_{key}", f"table3_dam_{key}", f"table3_waterfall_{key}")
        plain = compose_config([f"experiment=table3_dam_{base}"])
        cfg = compose_config([f"experiment=table3_dam_{key}"])
        assert (cfg.steps, cfg.write_every, cfg.scene.name) == (
            plain.steps,
            plain.write_every,
            plain.scene.name,
        )
        assert build_simulator(cfg).name == f"{base} + exact collision + MPS pressure"


def test_the_fine_tuned_cconv_has_a_collision_only_row_labelled_so():
    """The row that completes the dam with the least exact work: collision rule only, no projection."""
    from benchmarks.tables.config import compose_config
    from benchmarks.tables.simulators import simulator

    key = "cconv_finetuned_collision"
    sim = simulator(key)
    assert (sim.label, sim.model) == (
        "CConv, DLF's weights fine-tuned here + exact collision",
        "cconv_finetuned",
    )
    assert "no pressure projection" in sim.note and "not the plain" in sim.note
    assert sim.rows == (f"table2_{key}", f"table3_dam_{key}", f"table3_waterfall_{key}")
    for row in sim.rows:
        cfg = compose_config([f"experiment={row}"])
        assert (cfg.model.exact_after.collision, cfg.model.exact_after.pressure) == (True, False)
    assert build_simulator(compose_config([f"experiment=table3_dam_{key}"])).name == (
        "cconv_finetuned + exact collision"
    )


def test_gns_dagger_ships_its_weights_and_its_exact_row_runs_them_with_k3():
    """``model=gns_dagger`` loads the DAgger weights shipped beside their card, under its own name; its
    exact row is the one that completes the dam: collision and pressure, K = 3 at relaxation 0.5."""
    from baselines.gns.simulator import DAGGER
    from benchmarks.tables.config import compose_config
    from benchmarks.tables.simulators import all_simulators, simulator

    assert (DAGGER / "MODEL_CARD.md").is_file()
    sim = build_simulator(compose_config(["model=gns_dagger", "scene=dam"]))
    assert (sim.name, sim.weights, sim.dt) == ("gns_dagger", str(DAGGER / "gns.pt"), 0.008)
    assert build_simulator(compose_config(["model=gns", "scene=dam"])).weights != sim.weights
    plain, exact = simulator("gns_dagger"), simulator("gns_dagger_exact")
    assert (plain.label, plain.model, exact.model) == ("GNS (CPU size), DAgger", "gns_dagger", "gns_dagger")
    assert exact.label == "GNS (CPU size), DAgger + exact collision + MPS pressure (K=3, w=0.5)"
    assert "not the plain row" in exact.note
    keys = [s.key for s in all_simulators()]
    assert keys.index("gns_dagger") + 1 == keys.index("gns_dagger_exact")
    cfg = compose_config(["experiment=table3_dam_gns_dagger_exact"])
    assert (cfg.steps, cfg.write_every) == (125, 5)
    assert dict(cfg.model.exact_after) == {
        "collision": True,
        "pressure": True,
        "iterations": 3,
        "relaxation": 0.5,
    }


def test_gns_unroll_ships_its_weights_beside_the_daggers_and_its_rows_say_so():
    """``model=gns_unroll`` loads its own shipped weights (not the DAgger ones it started from), and its
    rows are labelled with both levers; the exact row is the dam-completing K = 3 one."""
    from baselines.gns.simulator import DAGGER, UNROLL
    from benchmarks.tables.config import compose_config
    from benchmarks.tables.simulators import all_simulators, simulator

    assert (UNROLL / "MODEL_CARD.md").is_file()
    sim = build_simulator(compose_config(["model=gns_unroll", "scene=dam"]))
    assert (sim.name, sim.weights, sim.dt) == ("gns_unroll", str(UNROLL / "gns.pt"), 0.008)
    assert sim.weights != str(DAGGER / "gns.pt")
    plain, exact = simulator("gns_unroll"), simulator("gns_unroll_exact")
    assert (plain.label, plain.model, exact.model) == (
        "GNS (CPU size), DAgger + unrolled loss",
        "gns_unroll",
        "gns_unroll",
    )
    assert (
        exact.label == "GNS (CPU size), DAgger + unrolled loss + exact collision + MPS pressure (K=3, w=0.5)"
    )
    assert "not the plain row" in exact.note and "unroll_loss=4" in plain.note
    keys = [s.key for s in all_simulators()]
    assert keys.index("gns_dagger_exact") < keys.index("gns_unroll") == keys.index("gns_unroll_exact") - 1
    cfg = compose_config(["experiment=table3_dam_gns_unroll_exact"])
    assert dict(cfg.model.exact_after) == {
        "collision": True,
        "pressure": True,
        "iterations": 3,
        "relaxation": 0.5,
    }


def test_the_benchmark_rolls_out_the_weights_it_is_given():
    """``benchmarks.exact_after --weights DIR`` runs every row on ``model.weights=DIR`` (the GNS
    frame-interval measurement's 16 ms network), none without it (the shipped weights)."""
    import argparse

    from benchmarks.exact_after import command

    args = argparse.Namespace(duration=1.0, threads=1, reference_dir="ref", scene="dam", weights=None)
    plain = command("gns", 0.008, (), Path("out"), args)
    assert not any(a.startswith("model.weights=") for a in plain) and "steps=125" in plain
    args.weights = "runs/train/gns-16ms"
    given = command("gns", 0.016, ("model.exact_after.collision=true",), Path("out"), args)
    assert "model.weights=runs/train/gns-16ms" in given and "steps=62" in given
    assert given.index("model.weights=runs/train/gns-16ms") < given.index("model.exact_after.collision=true")


def test_levers_runs_each_levers_weights_in_its_own_folder(tmp_path, monkeypatch):
    """``benchmarks.levers``: every lever's rows come from its own weights and run folder, labelled with
    its name and what made it; a lever that is not NAME=DIR=TEXT, or whose DIR is missing, is refused."""
    import argparse

    import benchmarks.levers as levers

    seen = []

    def fake_run_model(model, args):
        seen.append((model, args.weights, args.runs_dir))
        return [{"simulator": model, "rollout": "complete"}]

    monkeypatch.setattr(levers, "run_model", fake_run_model)
    args = argparse.Namespace(runs_dir=str(tmp_path), weights=None, model="gns")
    rows = levers.lever_rows("dagger2", "runs/x", args)
    assert seen == [("gns", "runs/x", str(tmp_path / "dagger2"))]
    args.model = "cconv"
    levers.lever_rows("dagger1", "runs/y", args)
    assert seen[-1] == ("cconv", "runs/y", str(tmp_path / "dagger1"))
    row = {"lever": "dagger2", "weights": "runs/x", "simulator": "gns"}
    assert rows == [{**row, "rollout": "complete"}]
    assert levers.parse_lever(f"a={tmp_path}=what made it=x") == ("a", str(tmp_path), "what made it=x")
    with pytest.raises(SystemExit, match="is not NAME=DIR=TEXT"):
        levers.parse_lever("a=b")
    with pytest.raises(SystemExit, match=r"/no/such \(of a\) is not a folder of the model's weights"):
        levers.parse_lever("a=/no/such=text")


def test_each_models_control_is_mps_at_its_dt_against_the_same_reference():
    """The control of a model stepping by 8 ms: MPS's own step at 8 ms under the model's guard, compared
    with the reference the model's rows use (MPS at the scene's 2 ms, MPS's own guard, frames every 40 ms)."""
    import argparse

    from benchmarks.exact_after import control_command, control_verdict, result_row
    from lagfluid.tasks.evaluate.options import EvaluateOptions
    from lagfluid.tasks.evaluate.reference import reference_key, reference_settings

    args = argparse.Namespace(duration=1.0, threads=1, reference_dir="ref", scene="dam", weights=None)
    cmd = control_command(0.008, 1.0, Path("out"), args, scene_dt=0.002)
    assert cmd[:6] == ["python", "-m", "lagfluid.run", "task=evaluate", "model=mps", "scene=dam"]
    overrides = cmd[3:]
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        control = compose(config_name="config", overrides=overrides)
        models_reference = compose(
            config_name="config",
            overrides=["task=evaluate", "model=mps", "scene=dam", "steps=500", "write_every=20"],
        )
    assert control.dt == 0.008 and control.steps == 125 and control.write_every == 5
    assert control.solver.guard.max_courant == 1.0 != models_reference.solver.guard.max_courant
    options = EvaluateOptions.from_config(control.evaluate)
    assert reference_key(reference_settings(control, options.reference)) == reference_key(models_reference)

    def row(name, complete, steps, chamfer):
        return result_row(_metrics(name, complete, steps, chamfer), ["x"])

    stopped_control = row("mps", False, 63, 11.37)
    stopped_control["simulator"] = "control of gns: MPS at 8 ms, no network"
    far = row("gns + both", True, 125, 125.4)
    assert control_verdict([far, stopped_control]) == (
        "Its control (MPS at 8 ms, no network) stops at step 64 (0.512 s) at 11.4 / 22.7 mm; the network "
        "earns its place in gns + both."
    )
    further = row("gns + pressure", False, 115, 187.4)
    assert control_verdict([row("gns", False, 29, 14.4), further, stopped_control]) == (
        "Its control (MPS at 8 ms, no network) stops at step 64 (0.512 s) at 11.4 / 22.7 mm; with the "
        "network gns + pressure gets further (it stops at step 116 (0.928 s))."
    )
    assert control_verdict([row("gns", False, 29, 14.4), stopped_control]).endswith(
        "; no row with the network gets further."
    )
    done_control = row("mps", True, 500, 0.0)
    done_control["simulator"] = "control of cconv: MPS at 2 ms, no network"
    assert control_verdict([row("cconv + both", True, 500, 36.3), done_control]).endswith(
        "completes at 0.0 / 0.0 mm; no row with the network completes closer to MPS than it."
    )
