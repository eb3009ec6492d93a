"""task=export and simulate export=...: a ParaView series read back with meshio, an animation looked at."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import h5py
import meshio
import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from PIL import Image

from lagfluid.data.store import read_trajectory
from lagfluid.errors import ConfigError
from lagfluid.run import CONF_DIR
from lagfluid.tasks.export import export_task
from lagfluid.tasks.simulate import simulate

REPO = Path(__file__).resolve().parents[1]


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=["experiment=debug", *overrides])


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = tmp_path_factory.mktemp("exported")
    simulate(_compose("steps=6", "write_every=2", "export=vtu", f"out_dir={out}"))
    return out


def test_the_paraview_series_holds_every_frame_and_field(exported):
    run = read_trajectory(exported / "rollout.h5")
    collection = ET.parse(exported / "paraview" / "rollout.pvd").getroot().find("Collection")
    fluid = [d.attrib for d in collection if d.attrib["part"] == "0"]
    boundary = [d.attrib for d in collection if d.attrib["part"] == "1"]
    assert [float(d["timestep"]) for d in fluid] == pytest.approx(run["time"].tolist())
    assert len(boundary) == 1 and boundary[0]["file"] == "boundary.vtu"
    for k, entry in enumerate(fluid):
        mesh = meshio.read(exported / "paraview" / entry["file"])
        np.testing.assert_allclose(mesh.points, run["position"][k], rtol=0, atol=1e-6)
        np.testing.assert_allclose(mesh.point_data["velocity"], run["velocity"][k], rtol=0, atol=1e-6)
        np.testing.assert_allclose(mesh.point_data["pressure"].ravel(), run["pressure"][k], rtol=1e-6)
        speed = np.linalg.norm(run["velocity"][k].astype(np.float64), axis=1)
        np.testing.assert_allclose(mesh.point_data["speed"].ravel(), speed, rtol=1e-6)
        assert set(mesh.point_data["particle_type"].ravel().tolist()) == {1}
    # frame 0 is the built lattice: particles with a full neighbourhood have n/n0 = 1; none more than that
    n = meshio.read(exported / "paraview" / "frame_00000.vtu").point_data["number_density"].ravel()
    assert n.max() == pytest.approx(1.0, abs=1e-6) and (np.abs(n - 1) < 1e-6).sum() > 0.5 * len(n)
    walls = meshio.read(exported / "paraview" / "boundary.vtu")
    np.testing.assert_allclose(walls.points, run["boundary_position"], atol=1e-6)
    assert sorted(set(walls.point_data["particle_type"].ravel().tolist())) == [2, 3]


def test_an_export_of_a_run_folder_as_gif_has_a_frame_per_stored_frame(exported):
    out = export_task(_compose("task=export", f"run={exported}", "format=gif", "animation.color=speed"))
    assert out == exported / "rollout.gif"
    with Image.open(out) as gif:
        assert gif.n_frames == 4 and gif.size[0] > 300  # frames 0, 2, 4, 6
    capped = export_task(
        _compose("task=export", f"run={exported / 'rollout.h5'}", "format=gif", "animation.max_frames=2")
    )
    with Image.open(capped) as gif:
        assert gif.n_frames == 2


def test_bad_exports_are_refused_before_the_run(tmp_path):
    with pytest.raises(ConfigError, match=r"export format must be one of vtu, gif, mp4, got 'avi'"):
        simulate(_compose("steps=2", "export=avi", f"out_dir={tmp_path / 'run'}"))
    assert not (tmp_path / "run").exists()  # refused before the folder was made
    with pytest.raises(ConfigError, match=r"run=.*nowhere: no rollout there"):
        export_task(_compose("task=export", f"run={tmp_path / 'nowhere'}"))
    with pytest.raises(ConfigError, match=r"task=export needs run=DIR"):
        export_task(_compose("task=export"))
    if shutil.which("ffmpeg") is None:
        with pytest.raises(ConfigError, match=r"mp4 needs ffmpeg on the PATH"):
            simulate(_compose("steps=2", "export=mp4", f"out_dir={tmp_path / 'run'}"))


# ------------------------------------------------------------------------------------------- pictures
class _WithoutPressure:
    """MPS's motion with the pressure dropped, as GNS and CConv step: a plugin-style simulator."""

    name, dt, history_length, max_courant, last_fields = "no_pressure", None, 0, None, None
    predicts_pressure = False
    blow_up_at = None  # a step whose velocities turn NaN (the guard stops the run there)

    def __init__(self, cfg):
        from lagfluid.models.mps_simulator import build_mps

        self.inner, self.last_info, self.parameters = build_mps(cfg), {}, 0

    @property
    def last_timings(self):
        return self.inner.last_timings

    def reset(self, state, history=()):
        self.inner.reset(state)

    def step(self, state, *, record=False):
        new = self.inner.step(state)
        nf = new.n_fluid
        vel = new.vel[:nf].clone()
        if self.blow_up_at is not None and new.step >= self.blow_up_at:
            vel[0] = float("nan")
        return state.advanced_fluid(new.pos[:nf], vel, new.params.dt)  # pressure: zeros

    def attributes(self):
        return {}


class _BlowsUpAtStep2(_WithoutPressure):
    name, blow_up_at = "blows_up", 2


@pytest.fixture
def drawn(monkeypatch):
    """The preview figures drawn while the test runs (the figure objects, before they are saved)."""
    import lagfluid.viz

    figures, original = [], lagfluid.viz.preview_figure

    def keep(*args, **kwargs):
        figures.append(original(*args, **kwargs))
        return figures[-1]

    monkeypatch.setattr(lagfluid.viz, "preview_figure", keep)
    return figures


def _panels(fig):
    """Per panel of a preview: the fluid's colour values, sorted (the boundary is the first scatter)."""
    return [np.sort(np.asarray(ax.collections[1].get_array())) for ax in fig.axes[:-1]]


def test_the_field_a_picture_colours_by_follows_what_the_simulator_predicts():
    from baselines.cconv.simulator import CConvSimulator
    from baselines.gns.simulator import GNSSimulator
    from lagfluid.tasks.config import build_simulator
    from lagfluid.viz import FIELDS, colour_field, field_values

    assert colour_field(GNSSimulator) == colour_field(CConvSimulator) == "speed"
    assert colour_field(build_simulator(_compose("model=mps"))) == "pressure"  # no attribute: it predicts one
    assert (FIELDS["speed"], FIELDS["pressure"]) == ("speed (m/s)", "pressure (Pa)")
    vel, p = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, -2.0]]), np.array([7.0, 9.0])
    np.testing.assert_array_equal(field_values("speed", vel, p), [5.0, 2.0])
    np.testing.assert_array_equal(field_values("pressure", vel, p), [7.0, 9.0])


@pytest.mark.parametrize(("model", "field"), [("mps", "pressure"), ("no_pressure", "speed")])
def test_a_preview_colours_by_pressure_only_for_a_simulator_that_predicts_it(
    model, field, tmp_path, monkeypatch, drawn
):
    from lagfluid import registry

    monkeypatch.setitem(registry._REGISTERED, "no_pressure", _WithoutPressure)
    simulate(_compose(f"model.name={model}", "steps=4", f"out_dir={tmp_path}"))
    (fig,) = drawn
    assert fig.axes[-1].get_ylabel() == {"pressure": "pressure (Pa)", "speed": "speed (m/s)"}[field]
    assert fig._suptitle.get_text() == f"{model} on dam_small"
    run = read_trajectory(tmp_path / "rollout.h5")
    for k, values in zip((0, 2, 4), _panels(fig), strict=True):  # first, middle and last frame
        speed = np.linalg.norm(run["velocity"][k], axis=1)
        expected = run["pressure"][k] if field == "pressure" else speed
        np.testing.assert_allclose(values, np.sort(expected), rtol=1e-6)
    if field == "pressure":
        assert run["pressure"][4].max() > 0  # MPS's pressure is there to be drawn


def test_a_run_stopped_by_the_guard_says_so_on_its_preview(tmp_path, monkeypatch, drawn):
    from lagfluid import registry
    from lagfluid.errors import RolloutError
    from lagfluid.viz import stopped_title

    assert stopped_title("gns on dam", "", by_guard=True) == "gns on dam"
    assert stopped_title("gns on dam", "step 57: Courant number 0.61", by_guard=True) == (
        "gns on dam\nstopped by the guard: step 57: Courant number 0.61"
    )
    assert stopped_title("gns on dam", "KeyboardInterrupt: ", by_guard=False) == (
        "gns on dam\nstopped: KeyboardInterrupt:"
    )
    monkeypatch.setitem(registry._REGISTERED, "blows_up", _BlowsUpAtStep2)
    with pytest.raises(RolloutError, match="step 2: fluid particle 0 has a non-finite velocity"):
        simulate(_compose("model.name=blows_up", "steps=4", f"out_dir={tmp_path}"))
    (fig,) = drawn
    title = fig._suptitle.get_text()
    assert title.startswith(
        "blows_up on dam_small\nstopped by the guard: step 2: fluid particle 0 has a non-finite velocity"
    ), title
    assert fig.axes[-1].get_ylabel() == "speed (m/s)" and (tmp_path / "preview.png").is_file()


# ------------------------------------------------------------------------------------------- ParaView values
def test_the_number_density_of_each_frame_is_that_frames_own(tmp_path):
    """Two particles 10 l0 apart (n = 0), then 1 l0 apart (each sees w = re/l0 - 1 = 1.1): n/n0 by hand."""
    from lagfluid.data.store import TrajectoryWriter
    from lagfluid.physics.settings import SolverSettings, lattice_constants
    from lagfluid.tasks.export.vtk import write_paraview

    l0 = 0.05
    n0 = lattice_constants(l0, SolverSettings(), 3).n0  # the ideal lattice's, at re = 2.1 l0
    far = np.array([[100.0, 100.0, 100.0]])  # one dummy particle out of reach
    with TrajectoryWriter(tmp_path / "rollout.h5", 2, far, np.array([3]), {"l0": l0, "dim": 3}) as w:
        for t, gap in ((0.0, 10 * l0), (0.002, l0)):
            pos = np.array([[1.0, 1.0, 1.0], [1.0 + gap, 1.0, 1.0]])
            w.append(t, pos, np.zeros((2, 3)), np.zeros(2))
    write_paraview(tmp_path / "rollout.h5", tmp_path / "paraview")
    density = [
        meshio.read(tmp_path / "paraview" / f"frame_{k:05d}.vtu").point_data["number_density"].ravel()
        for k in (0, 1)
    ]
    np.testing.assert_allclose(density[0], [0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(density[1], [1.1 / n0, 1.1 / n0], rtol=1e-5)


# ------------------------------------------------------------------------------------------- damaged files
def _damage_frame(path, frame, dataset="position"):
    """Overwrite bytes in the middle of one frame's chunk: its checksum then fails on read."""
    with h5py.File(path, "r") as f:
        chunk = f["00000"][dataset].id.get_chunk_info(frame)
    with open(path, "r+b") as f:
        f.seek(chunk.byte_offset + chunk.size // 2)
        f.write(b"\x00\xff" * 8)


def _tree(folder):
    """Every file under ``folder``: its relative path and bytes."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def test_a_damaged_frame_is_named_and_the_last_export_stays_whole(exported, tmp_path):
    from lagfluid.data.store import TrajectoryFileError

    run = tmp_path / "run"
    run.mkdir()
    shutil.copy(exported / "rollout.h5", run / "rollout.h5")
    export_task(_compose("task=export", f"run={run}", "format=vtu"))
    (run / "paraview" / "view.pvsm").write_text("the user's ParaView state")
    before = _tree(run)
    _damage_frame(run / "rollout.h5", 2)
    damaged = _tree(run)["rollout.h5"]
    message = rf"{run / 'rollout.h5'}: frame 2 of 'position' is unreadable \(damaged file\)"
    for fmt in ("vtu", "gif"):
        with pytest.raises(TrajectoryFileError, match=message):
            export_task(_compose("task=export", f"run={run}", f"format={fmt}"))
    # no half-written series, no part folder or file: the last export and the user's file as they were
    assert _tree(run) == {**before, "rollout.h5": damaged}


def test_cli_export_of_a_damaged_run_is_one_line_and_makes_no_folder_of_its_own(exported, tmp_path):
    """``task=export`` writes beside the run: no ``runs/export/<model>-<scene>`` where it was started."""
    run, cwd = tmp_path / "run", tmp_path / "cwd"
    run.mkdir()
    cwd.mkdir()
    shutil.copy(exported / "rollout.h5", run / "rollout.h5")
    _damage_frame(run / "rollout.h5", 3, "velocity")
    done = subprocess.run(
        [sys.executable, "-m", "lagfluid.run", "task=export", f"run={run}", "format=vtu", "threads=1"],
        cwd=cwd,
        capture_output=True,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)},
        timeout=300,
    )
    assert done.returncode == 1
    lines = (done.stdout + done.stderr).strip().splitlines()  # Hydra's log handler writes to stdout
    assert len(lines) == 1 and "Traceback" not in lines[0], lines
    assert f"{run / 'rollout.h5'}: frame 3 of 'velocity' is unreadable (damaged file)" in lines[0]
    assert sorted(p.name for p in run.iterdir()) == ["rollout.h5"]  # no paraview/, .part, .hydra or log
    assert list(cwd.iterdir()) == []  # no runs/export/mps-dam_small with Hydra's files
