"""task=export and simulate export=...: a ParaView series read back with meshio, an animation looked at."""

from __future__ import annotations

import shutil
import xml.etree.ElementTree as ET

import meshio
import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from PIL import Image

from lagfluid.data.store import read_trajectory
from lagfluid.errors import ConfigError
from lagfluid.export import export_task
from lagfluid.run import CONF_DIR
from lagfluid.simulate import simulate


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
