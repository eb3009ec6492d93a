import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf.errors import ConfigAttributeError

from lagfluid.errors import ConfigError, SceneError
from lagfluid.registry import UnknownNameError, available_simulators, get_simulator_factory, trainable_models
from lagfluid.run import (
    CONF_DIR,
    _group_names,
    available_models,
    check_command_line,
    check_out_dir_argument,
    dispatch,
)
from lagfluid.tasks.config import apply_threads, run_device, scene_params
from lagfluid.tasks.simulate import simulate


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


@pytest.mark.parametrize(
    ("arg", "kind"),
    [
        ("model=nope", "model"),
        ("scene=atlantis", "scene"),
        ("task=dance", "task"),
        ("solver=nope", "solver"),
        ("train=gpu", "train"),
        ("+experiment=table9", "experiment"),
        ("experiment=table9", "experiment"),
    ],
)
def test_unknown_names_give_one_line_listing_the_choices(arg, kind):
    msg = check_command_line([arg])
    bad = arg.split("=")[1]
    assert msg is not None and "\n" not in msg
    assert f"unknown {kind} '{bad}'" in msg and "available:" in msg


def test_known_names_pass_and_sweeps_are_left_to_hydra():
    assert check_command_line(["model=mps", "scene=dam", "steps=3"]) is None
    assert check_command_line(["solver=mps_corrected", "train=cpu", "experiment=debug", "data=tiny"]) is None
    assert check_command_line(["scene=dam,nope"]) is None


def test_cli_unknown_model_exits_nonzero_with_one_line():
    out = subprocess.run(
        [sys.executable, "-m", "lagfluid.run", "model=nope"], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "unknown model 'nope'" in lines[0] and "mps" in lines[0]
    out = subprocess.run(
        [sys.executable, "-m", "lagfluid.run", "solver=nope"], capture_output=True, text=True, timeout=120
    )
    solvers = ", ".join(sorted(p.stem for p in (CONF_DIR / "solver").glob("*.yaml")))
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [f"lagfluid: unknown solver 'nope'; available: {solvers}"]


def test_checking_a_command_line_imports_neither_torch_nor_a_plugins_code():
    """A typo is answered in a fraction of a second: finding the plugins' config folders imports their
    packages (``baselines.cconv`` imported its simulator, torch and PyG with it: 5.6 s for ``model=nope``)."""
    code = (
        "import sys; from lagfluid.run import check_command_line, help_config_groups; "
        "assert check_command_line(['model=nope']).startswith(\"lagfluid: unknown model 'nope'\"); "
        "help_config_groups(); "
        "print(sorted(m for m in sys.modules if m == 'torch' or m.endswith('.simulator')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_an_appended_unknown_top_level_key_is_refused_with_a_hint():
    msg = check_command_line(["+stepz=3"])
    assert (
        msg is not None
        and msg.startswith("lagfluid: unknown key 'stepz' (+stepz=... adds a key nothing reads)")
        and "closest: steps, stage;" in msg
    )
    assert check_command_line(["+train.iterations.line=60", "++stepz=3", "+experiment=debug"]) is None
    out = subprocess.run(
        [sys.executable, "-m", "lagfluid.run", "+stepz=3"], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 2 and out.stderr.strip().splitlines() == [msg]


def test_a_misspelt_key_names_the_closest_keys_not_hydras_plus_advice():
    top = (
        "animation, checkpoint_every_s, data, device, dt, dtype, evaluate, experiment, export, export_to, "
        "format, model, num_scenes, out_dir, progress, resume, run, scene, seed, solver, stage, steps, task, "
        "threads, train, write_every"
    )
    msg = check_command_line(["steps=3", "stepz=3"])
    assert msg == f"lagfluid: unknown key 'stepz'; closest: steps, stage; top-level keys: {top}"
    assert check_command_line(["evaluate.horizon=[1]"]) == (
        "lagfluid: unknown key 'evaluate.horizon'; closest: evaluate.horizons; keys of evaluate: figures, "
        "horizons, one_step, reference, reference_dir, reuse_reference, slice"
    )
    # keys Hydra owns or that depend on the option chosen are left to it; so are deletions and forced adds
    for fine in (
        "scene.fluid_size=[4,4,4]",
        "hydra.run.dir=x",
        "evaluate.reference.dt=0.004",
        "~seed",
        "++x=1",
        "--config-dir=x",
        "hydra/launcher=submitit_slurm",
    ):
        assert check_command_line([fine]) is None, fine
    out = subprocess.run(
        [sys.executable, "-m", "lagfluid.run", "stepz=3"], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 2 and out.stderr.strip().splitlines() == [msg]
    assert "+stepz" not in out.stdout + out.stderr


def test_help_lists_every_model_and_train_profile_plugins_included(monkeypatch):
    out = subprocess.run(
        [sys.executable, "-m", "lagfluid.run", "--help"], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0
    lines = {
        line.split(": ")[0]: line.split(": ")[1].split(", ")
        for line in out.stdout.splitlines()
        if ": " in line
    }
    assert set(lines["model"]) >= {"mps", "fgn", "hybrid", "gns", "cconv", "cconv_original"}
    assert set(lines["train"]) >= {"cpu", "paper", "gns_cpu", "gns_paper", "cconv_cpu", "cconv_paper"}
    assert {"table2_gns", "table3_dam_cconv"} <= set(lines["experiment"])
    # a plugin simulator without a config file is listed too
    from importlib import metadata

    import lagfluid.registry as registry
    from lagfluid.run import help_config_groups

    plugin = metadata.EntryPoint(
        name="plugin_sim", value="lagfluid.models.mps_simulator:build_mps", group=registry.ENTRY_POINT_GROUP
    )
    real = metadata.entry_points
    monkeypatch.setattr(
        registry.metadata,
        "entry_points",
        lambda **kw: metadata.EntryPoints([plugin]) if kw.get("group") == plugin.group else real(**kw),
    )
    assert "plugin_sim" in next(
        line for line in help_config_groups().splitlines() if line.startswith("model:")
    )


def test_an_out_dir_that_cannot_be_a_folder_is_refused_before_hydra_makes_it(tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("mine")
    assert (
        check_out_dir_argument([f"out_dir={a_file}"]) == f"lagfluid: out_dir={a_file} is a file, not a folder"
    )
    below = a_file / "run"
    assert check_out_dir_argument([f"out_dir={below}"]) == (
        f"lagfluid: out_dir={below} cannot be made: {a_file} is a file"
    )
    assert check_out_dir_argument([f"out_dir={tmp_path / 'new' / 'run'}", "steps=2"]) is None
    out = subprocess.run(
        [sys.executable, "-m", "lagfluid.run", "experiment=debug", f"out_dir={a_file}"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 1 and out.stderr.strip().splitlines() == [
        f"lagfluid: out_dir={a_file} is a file, not a folder"
    ]
    assert a_file.read_text() == "mine"


def test_registry_unknown_name_lists_available():
    with pytest.raises(UnknownNameError, match=r"available: .*mps"):
        get_simulator_factory("nope")


def test_struct_mode_rejects_typos():
    with pytest.raises((ConfigCompositionException, ConfigAttributeError)):
        _compose("stepz=3")  # the Python API (compose) too; the command line says it first, in one line


@pytest.fixture(scope="module")
def trajectory_file(tmp_path_factory):
    """A two-step ``experiment=debug`` rollout for ``scene=trajectory``."""
    from lagfluid.tasks.simulate import simulate

    out = tmp_path_factory.mktemp("trajectory")
    simulate(_compose("experiment=debug", "steps=2", f"out_dir={out}"))
    return out / "rollout.h5"


@pytest.fixture(scope="module")
def initial_states():
    """Scene name -> its initial state, built once: a scene's state does not depend on the model, and the
    full-size water fall takes ~1 s to build."""
    return {}


@pytest.mark.parametrize("model", available_models())
@pytest.mark.parametrize("scene", _group_names("scene"))
def test_every_model_and_scene_composes_and_instantiates(model, scene, request, initial_states):
    from lagfluid.tasks.config import build_initial_state, build_simulator

    # the file scene reads the authors' grid the repository ships; published weights are the models' defaults
    extra = [f"scene.path={request.getfixturevalue('authors_dam_grid')}"] if scene == "file" else []
    if scene == "trajectory":
        extra.append(f"scene.path={request.getfixturevalue('trajectory_file')}")
    if scene == "mesh":
        tank, block = request.getfixturevalue("mesh_files")
        extra += [f"scene.container={tank}", f"scene.fluid={block}"]
    if model in ("fgn", "hybrid", "fgn_trained_here", "fgn_gcn", "fgn_sage", "fgn_mlp"):
        weights = request.getfixturevalue("untrained_weights_of")("fgn" if model == "hybrid" else model)
        extra.append(f"model.weights={weights}")
    if model not in available_simulators():  # a model that trains but does not roll out yet (cconv)
        assert model in trainable_models()
        pytest.skip(f"model={model} has no simulator registered yet (only its trainable)")
    cfg = _compose(f"model={model}", f"scene={scene}", "steps=1", "dt=0.001", "device=cpu", "seed=3", *extra)
    assert cfg.model.name == model and cfg.scene.name == scene and cfg.dt == 0.001
    if scene not in initial_states:
        initial_states[scene] = build_initial_state(cfg)
    state = initial_states[scene].clone()  # a simulator's reset never sees another's
    assert state.params.dt == 0.001 and state.n_fluid > 0
    sim = build_simulator(cfg)
    assert sim.name == model
    sim.reset(state)


def test_corrected_solver_profile_composes_over_the_authors_one(tmp_path):
    from lagfluid.tasks.simulate import simulate

    authors, corrected = _compose("solver=mps"), _compose("solver=mps_corrected")
    assert authors.solver.pressure_gradient == "minimum" and authors.solver.re_laplacian == 3.1
    assert corrected.solver.pressure_gradient == "corrected" and corrected.solver.re_laplacian == 2.1
    assert authors.solver.source_density_reference_dt is None  # the authors' per-step density weight
    assert corrected.solver.source_density == 0.02 and corrected.solver.source_density_reference_dt == 0.002
    # everything else is the authors' profile
    changed = ("name", "pressure_gradient", "re_laplacian", "source_density", "source_density_reference_dt")
    same = {k: v for k, v in authors.solver.items() if k not in changed}
    assert same == {k: corrected.solver[k] for k in same}
    simulate(_compose("experiment=debug", "solver=mps_corrected", "steps=3", f"out_dir={tmp_path}"))
    assert (tmp_path / "metrics.json").exists()


def test_file_scene_without_path_is_a_clear_error():
    from lagfluid.errors import SceneError
    from lagfluid.tasks.config import build_initial_state

    with pytest.raises(SceneError, match="needs the option path"):
        build_initial_state(_compose("scene=file"))


def test_debug_experiment_writes_the_three_outputs(tmp_path):
    from lagfluid.data.store import read_trajectory
    from lagfluid.tasks.simulate import simulate

    cfg = _compose("experiment=debug", "steps=4", "write_every=2", f"out_dir={tmp_path}")
    metrics = simulate(cfg)
    assert (tmp_path / "preview.png").stat().st_size > 1000
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["steps"] == 4 and saved["complete"] and saved["model"] == "mps"
    assert saved == json.loads(json.dumps(metrics))
    assert 0 < saved["time_per_step_median_s"] and 0 < saved["time_per_step_mean_s"]
    traj = read_trajectory(tmp_path / "rollout.h5")
    assert traj["position"].shape[0] == 3  # frames 0, 2, 4
    assert traj["attrs"]["dt"] == cfg.scene.params.dt and "n0" in traj["attrs"]


def test_guard_stop_keeps_what_was_written_and_says_why(tmp_path):
    from lagfluid.data.store import read_trajectory
    from lagfluid.errors import RolloutError
    from lagfluid.tasks.simulate import simulate

    # dt = 0.05 s: after two steps of free fall |v| dt / l0 > 0.5, so the Courant guard fires.
    cfg = _compose("experiment=debug", "dt=0.05", "steps=10", f"out_dir={tmp_path}")
    with pytest.raises(RolloutError, match=r"step \d+: Courant number"):
        simulate(cfg)
    traj = read_trajectory(tmp_path / "rollout.h5")
    assert not bool(traj["attrs"]["complete"]) and "Courant" in traj["attrs"]["stop_reason"]
    assert 1 <= traj["position"].shape[0] < 11
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["complete"] is False and "Courant" in saved["stop_reason"] and saved["steps"] < 10
    assert (tmp_path / "preview.png").is_file()


def test_an_initial_velocity_past_the_courant_limit_stops_at_step_0_naming_it(tmp_path):
    from lagfluid.errors import RolloutError
    from lagfluid.tasks.simulate import simulate

    l0, k = 0.05, np.arange(-2, 6)
    lattice = np.stack(np.meshgrid(k, k, k, indexing="ij"), axis=-1).reshape(-1, 3)
    fluid = (lattice >= 0).all(axis=1) & (lattice <= 3).all(axis=1)
    pos = np.concatenate([lattice[fluid], lattice[(lattice < 0).any(axis=1)]]) * l0
    ptype = np.concatenate([np.ones(fluid.sum(), int), np.full(len(pos) - fluid.sum(), 2)])
    vel = np.zeros_like(pos)
    vel[3] = [1e30, 0.0, 0.0]  # finite in float32, inf once squared: used to fail inside the cell list
    np.savez(tmp_path / "fast.npz", pos=pos, vel=vel, ptype=ptype)
    cfg = _compose(
        "scene=file", f"scene.path={tmp_path / 'fast.npz'}", "steps=2", f"out_dir={tmp_path / 'run'}"
    )
    with pytest.raises(
        RolloutError, match=r"step 0: Courant number 4e\+28 at fluid particle 3 \(\|v\| = 1e\+30 m/s\)"
    ):
        simulate(cfg)
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["complete"] is False


def test_sigterm_stops_a_rollout_like_ctrl_c_keeping_its_outputs_and_reason(tmp_path):
    import signal
    import time

    out = tmp_path / "run"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "lagfluid.run",
            "experiment=debug",
            "steps=100000",
            f"out_dir={out}",
            "threads=1",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )

    def frames_written() -> int:
        import h5py

        try:
            with h5py.File(out / "rollout.part.h5.part", "r", locking=False) as f:
                return int(f["00000/time"].shape[0])
        except (OSError, KeyError):  # not there yet, or caught mid-write
            return 0

    deadline = time.monotonic() + 120
    while frames_written() < 2 and time.monotonic() < deadline:  # the rollout has begun (a loaded machine
        time.sleep(0.2)  # may take seconds between creating the file and its first frame)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM
    # one line; "; add resume=true ..." follows when the run left a checkpoint to continue from
    assert (
        err.strip()
        .splitlines()[-1]
        .startswith("lagfluid: stopped by SIGTERM (a timeout, the scheduler or docker stop)")
    )
    assert "Traceback" not in err
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["complete"] is False and "SIGTERM" in metrics["stop_reason"] and metrics["steps"] < 100000
    assert (out / "preview.png").is_file() and (out / "rollout.h5").is_file()


def test_ctrl_c_is_one_line_naming_how_to_continue_and_exit_status_130(tmp_path, interruptible):
    import signal
    import time

    out = tmp_path / "run"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "lagfluid.run",
            "experiment=debug",
            "steps=100000",
            "checkpoint_every_s=0",  # a checkpoint at every stored frame: there is one to continue from
            f"out_dir={out}",
            "threads=1",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **interruptible,
    )
    deadline = time.monotonic() + 120
    while not (out / "resume.pt").is_file() and time.monotonic() < deadline:
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)  # what Ctrl-C sends
    stdout, err = proc.communicate(timeout=120)
    assert proc.returncode == 130  # 128 + SIGINT, as a shell reports an interrupted command
    assert err.strip().splitlines() == [
        f"lagfluid: interrupted (Ctrl-C); add resume=true to the same command to continue it from "
        f"{out / 'resume.pt'}"
    ]
    assert "Traceback" not in stdout + err
    assert json.loads((out / "metrics.json").read_text())["complete"] is False  # the outputs are kept


def test_ctrl_c_outside_simulate_is_one_line_without_a_resume_hint():
    from omegaconf import OmegaConf

    from lagfluid.run import stop_hint, stop_line

    assert stop_line(KeyboardInterrupt()) == "lagfluid: interrupted (Ctrl-C)"
    assert stop_hint(OmegaConf.create({"task": "train", "out_dir": "."})) == ""


def test_a_guard_stop_is_an_error_under_simulate_and_evaluate_alike(tmp_path, monkeypatch):
    """Both tasks exit 1 with one line naming the stop (``_hydra_main`` turns a LagfluidError into that)."""
    from lagfluid import registry
    from lagfluid.errors import RolloutError

    with pytest.raises(RolloutError, match=r"step \d+: Courant number"):
        dispatch(_compose("experiment=debug", "dt=0.05", "steps=10", f"out_dir={tmp_path / 'simulate'}"))

    from tests.test_evaluate import _Exploding  # MPS whose velocities turn NaN at step 2

    monkeypatch.setitem(registry._REGISTERED, "exploding", _Exploding)
    out = tmp_path / "evaluate"
    cfg = _compose(
        "task=evaluate",
        "model.name=exploding",
        "scene=dam_small",
        "steps=4",
        "evaluate.figures=false",
        f"evaluate.reference_dir={tmp_path / 'reference'}",
        f"out_dir={out}",
    )
    with pytest.raises(
        RolloutError,
        match=rf"model exploding stopped after 1 of 4 steps: step 2: fluid particle 0 has a non-finite "
        rf"velocity .* \(the frames before the stop are evaluated in {re.escape(str(out))}\)",
    ):
        dispatch(cfg)
    metrics = json.loads((out / "metrics.json").read_text())  # evaluated and written first
    assert metrics["complete"] is False and metrics["frames"]["step"] == [0, 1]


def test_cli_guard_stop_is_one_clear_line(tmp_path):
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "lagfluid.run",
            "experiment=debug",
            "dt=0.05",
            "steps=10",
            f"out_dir={tmp_path}",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        env={**__import__("os").environ, "OMP_NUM_THREADS": "1"},
    )
    assert out.returncode == 1
    console = out.stdout + out.stderr  # Hydra logs to stdout; tqdm and warnings go to stderr
    errors = [line for line in console.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and "Courant number" in errors[0] and "reduce dt" in errors[0]
    assert "Traceback" not in console


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("solver.n0_from=foo", "solver.n0_from must be one of lattice, initial"),
        ("solver.neighbors.skin_fraction=-1", "solver.neighbors.skin_fraction must be >= 0"),
        ("solver.ppe.method=foo", "solver.ppe.method must be one of"),
        ("solver.pressure_gradient=steepest", "solver.pressure_gradient must be one of minimum, corrected"),
        ("solver.source_density_reference_dt=0", "solver.source_density_reference_dt must be a finite"),
        ("write_every=0", "write_every >= 1"),
        ("scene.builder=nope", "unknown scene 'nope'"),
        ("dtype=float16", "unknown dtype 'float16'"),
    ],
)
def test_bad_config_values_are_lagfluid_errors_naming_the_value(override, message, tmp_path):
    from lagfluid.errors import LagfluidError
    from lagfluid.tasks.simulate import simulate

    with pytest.raises(LagfluidError, match=message):
        simulate(_compose("experiment=debug", override, f"out_dir={tmp_path}"))


def test_a_crash_mid_run_is_recorded_as_incomplete(tmp_path):
    from lagfluid.data.store import read_trajectory
    from lagfluid.models.mps_simulator import build_mps
    from lagfluid.registry import _REGISTERED, register_simulator
    from lagfluid.tasks.simulate import simulate

    def broken(cfg):
        sim = build_mps(cfg)
        step, calls = sim.step, []

        def failing_step(state, **options):
            calls.append(1)
            if len(calls) == 3:
                raise RuntimeError("disk on fire")
            return step(state, **options)

        sim.step = failing_step
        return sim

    register_simulator("broken")(broken)
    try:
        cfg = _compose("experiment=debug", "steps=5", f"out_dir={tmp_path}")
        cfg.model.name = "broken"
        with pytest.raises(RuntimeError, match="disk on fire"):
            simulate(cfg)
    finally:
        _REGISTERED.pop("broken")
    traj = read_trajectory(tmp_path / "rollout.h5")
    assert (
        not bool(traj["attrs"]["complete"]) and "RuntimeError: disk on fire" in traj["attrs"]["stop_reason"]
    )
    assert traj["position"].shape[0] == 3  # frames 0, 1, 2: what was computed is kept
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["complete"] is False and saved["steps"] == 2


def test_plugins_register_through_the_entry_point_group(monkeypatch):
    from importlib import metadata

    import lagfluid.registry as registry

    plugin = metadata.EntryPoint(
        name="plugin_sim", value="lagfluid.models.mps_simulator:build_mps", group=registry.ENTRY_POINT_GROUP
    )
    real = metadata.entry_points

    def fake(**kwargs):
        if kwargs.get("group") == registry.ENTRY_POINT_GROUP:
            return metadata.EntryPoints([plugin])
        return real(**kwargs)

    monkeypatch.setattr(registry.metadata, "entry_points", fake)
    assert "plugin_sim" in registry.available_simulators()
    from lagfluid.models.mps_simulator import build_mps

    assert registry.get_simulator_factory("plugin_sim") is build_mps
    assert check_command_line(["model=plugin_sim"]) is None  # selectable on the command line


def test_threads_on_the_command_line_reach_openmp_before_torch_loads(monkeypatch):
    from lagfluid.run import limit_openmp

    for name in ("OMP_NUM_THREADS", "OMP_WAIT_POLICY"):
        monkeypatch.delenv(name, raising=False)
    limit_openmp(["model=fgn", "threads=2"])
    assert os.environ["OMP_NUM_THREADS"] == "2" and "OMP_WAIT_POLICY" not in os.environ
    monkeypatch.delenv("OMP_NUM_THREADS")
    limit_openmp(["threads=1,2"])  # a sweep: each job's own
    assert "OMP_NUM_THREADS" not in os.environ
    limit_openmp(["threads=1"])
    assert os.environ["OMP_NUM_THREADS"] == "1" and os.environ["OMP_WAIT_POLICY"] == "PASSIVE"
    monkeypatch.setenv("OMP_NUM_THREADS", "4")  # the user's own setting wins
    limit_openmp(["threads=1"])
    assert os.environ["OMP_NUM_THREADS"] == "4"


@pytest.mark.parametrize("value", ["0", "-1", "abc", "1.5"])
def test_threads_that_are_not_a_positive_whole_number_are_refused(value):
    with pytest.raises(ConfigError, match=r"threads must be a whole number >= 1 \(or null: every core\)"):
        apply_threads(_compose(f"threads={value}"))


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("solver.guard.check_every=0", "check_every must be a whole number >= 1, got 0"),
        ("solver.guard.max_courant=0", "max_courant must be > 0, got 0"),
    ],
)
def test_a_guard_that_cannot_work_is_refused_before_the_rollout(tmp_path, override, message):
    with pytest.raises(ConfigError, match=message):
        simulate(
            _compose(
                "model=mps", "scene=dam_small", "steps=2", "write_every=2", override, f"out_dir={tmp_path}"
            )
        )


@pytest.mark.parametrize(
    ("device", "message"),
    [
        ("bogus", "unknown device 'bogus'; use device=cpu or device=cuda"),
        ("mps", "device=mps is not supported; use device=cpu or device=cuda"),
        ("meta", "device=meta is not supported"),
    ],
)
def test_a_device_lagfluid_cannot_run_on_is_refused_naming_it(device, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        run_device(_compose(f"device={device}"))


@pytest.mark.parametrize("value", ["9.8", "[0,-9.8]"])
def test_gravity_that_is_not_a_3_vector_is_refused_naming_it(value):
    with pytest.raises(SceneError, match=r"gravity must be .*(vector|three finite numbers)"):
        scene_params(_compose(f"scene.params.gravity={value}"))


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("steps=abc", "steps must be a whole number >= 0, got 'abc'"),
        ("seed=abc", "seed must be a whole number >= 0, got 'abc'"),
        ("write_every=0", "write_every must be a whole number >= 1, got 0"),
        ("dt=abc", "dt must be a time step > 0 in s (or null: the scene's), got 'abc'"),
        ("dt=-0.001", "dt must be a time step > 0 in s (or null: the scene's), got -0.001"),
    ],
)
def test_top_level_numbers_of_the_wrong_kind_are_refused_naming_them(override, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        dispatch(_compose(override))


def test_a_sweep_composes_for_slurm_through_hydras_submitit_launcher():
    """``-m hydra/launcher=submitit_slurm``: the cluster launcher is Hydra's plugin, composed here without a
    cluster (submitting needs SLURM); our default (joblib) stays for a local multirun."""
    from hydra import compose, initialize_config_dir

    assert check_command_line(["-m", "hydra/launcher=submitit_slurm", "task=generate"]) is None
    overrides = [
        "hydra/launcher=submitit_slurm",
        "hydra.launcher.partition=cpu",
        "hydra.launcher.timeout_min=180",
        "hydra.launcher.cpus_per_task=2",
        "task=generate",
        "threads=1",
    ]
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides, return_hydra_config=True)
        local = compose(config_name="config", return_hydra_config=True)
    launcher = cfg.hydra.launcher
    assert launcher._target_ == "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"
    assert (launcher.partition, launcher.timeout_min, launcher.cpus_per_task) == ("cpu", 180, 2)
    assert local.hydra.launcher._target_.endswith("JoblibLauncher")


def test_timing_summary_gives_the_whole_runs_mean_beside_the_typical_median():
    from lagfluid.tasks.simulate import timing_summary

    # three cheap steps and one with a neighbour-list rebuild: the median hides the rebuild, the mean does not
    summary = timing_summary({"step_seconds": [1.0, 1.0, 1.0, 5.0], "stage_seconds": {}, "info": {}})
    assert summary["time_per_step_median_s"] == 1.0 and summary["time_per_step_mean_s"] == 2.0
    # and per stage: the rebuild's cost shows in the neighbour stage's mean, with the rebuilds counted
    record = {
        "step_seconds": [1.0, 1.0, 1.0, 5.0],
        "stage_seconds": {"neighbors": [0.25, 0.25, 0.25, 4.25], "network": [0.75] * 4},
        "info": {"list_rebuilds": [0.0, 0.0, 0.0, 1.0]},
    }
    summary = timing_summary(record)
    assert summary["stage_median_s"] == {"neighbors": 0.25, "network": 0.75}
    assert summary["stage_mean_s"] == {"neighbors": 1.25, "network": 0.75}
    assert summary["list_rebuilds"] == 1
