"""A rollout as a ParaView time series: ``.vtu`` per frame and a ``.pvd`` collection, written by pyevtk.

The fluid of frame ``k`` is ``frame_<k>.vtu`` (unstructured points; point data ``velocity`` (3), ``speed``,
``pressure``, ``number_density`` (n/n0 at the run's ``solver.re_density``, boundary included) and
``particle_type``); the static boundary is ``boundary.vtu`` (``particle_type``: 2 wall, 3 dummy), listed
once as part 1 of the collection at the first time (ParaView's PVD reader shows a part's latest file at or
before the current time, so the boundary stays at every time). ``rollout.pvd`` lists the frames with their
times in seconds.

The files are written into ``paraview.part/`` and moved into ``paraview/`` once every frame is written
(the ``.pvd`` last): an export that fails (a damaged frame, a full disk) leaves the folder as it was, and
files of the user's own there (a ParaView state) stay.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import torch
import yaml
from omegaconf import OmegaConf
from pyevtk.hl import pointsToVTK
from pyevtk.vtk import VtkGroup

from lagfluid.data.store import open_lagfluid_file, read_array
from lagfluid.errors import ConfigError
from lagfluid.neighbors import radius_graph
from lagfluid.physics import operators as ops
from lagfluid.physics.settings import SolverSettings, lattice_constants
from lagfluid.state import ParticleType


def run_settings(config: str | None) -> SolverSettings:
    """The solver settings of the run whose config (YAML, the rollout's ``config`` attribute) is given."""
    if not config:
        return SolverSettings()
    solver = (yaml.safe_load(config) or {}).get("solver")
    return SolverSettings.from_config(OmegaConf.create(solver)) if solver else SolverSettings()


def number_density_ratio(
    fluid: np.ndarray,
    boundary: np.ndarray,
    boundary_type: np.ndarray,
    l0: float,
    dim: int = 3,
    settings: SolverSettings | None = None,
) -> np.ndarray:
    """n/n0 of every fluid particle (Nf,), boundary particles counted, at the run's ``re_density``."""
    settings = settings or SolverSettings()
    re = settings.re_density * l0
    pos = torch.from_numpy(np.concatenate([fluid, boundary]).astype(np.float64))
    ptype = torch.cat(
        [torch.full((len(fluid),), int(ParticleType.FLUID)), torch.from_numpy(boundary_type.astype(np.int64))]
    )
    edges = radius_graph(pos, re, receivers=ptype == ParticleType.FLUID)
    n = ops.number_density(pos, edges, re, num_nodes=pos.shape[0])
    return (n[: len(fluid)] / lattice_constants(l0, settings, dim).n0).numpy()


def _points(path: Path, pos: np.ndarray, data: dict[str, object]) -> None:
    x, y, z = (np.ascontiguousarray(pos[:, i], dtype=np.float64) for i in range(3))
    pointsToVTK(str(path), x, y, z, data=data)


def _ours(path: Path) -> bool:
    """Whether ``path`` is a file :func:`write_paraview` writes."""
    return path.is_file() and (path.name in ("rollout.pvd", "boundary.vtu") or path.match("frame_*.vtu"))


def _fresh_part_folder(out_dir: Path) -> Path:
    """An empty ``<out_dir>.part`` to write into; one a failed export left is emptied (only its files).

    Raises:
        ConfigError: the folder holds something an export does not write (not ours to delete).
    """
    part = out_dir.with_name(out_dir.name + ".part")
    if part.exists():
        foreign = [p.name for p in part.iterdir() if not _ours(p)] if part.is_dir() else [part.name]
        if foreign:
            raise ConfigError(
                f"{part} holds {', '.join(sorted(foreign)[:3])}, which no export wrote; move it away and "
                "export again"
            )
        shutil.rmtree(part)
    part.mkdir(parents=True)
    return part


def _publish(part: Path, out_dir: Path) -> None:
    """Move ``part``'s files into ``out_dir`` (the ``.pvd`` last); drop the frames the new ``.pvd`` lacks."""
    out_dir.mkdir(exist_ok=True)
    names = {p.name for p in part.iterdir()}
    for name in sorted(names, key=lambda n: n == "rollout.pvd"):
        os.replace(part / name, out_dir / name)
    for old in out_dir.glob("frame_*.vtu"):  # a shorter rerun must not leave the old run's frames
        if old.name not in names:
            old.unlink()
    part.rmdir()


def write_paraview(rollout: Path, out_dir: Path) -> Path:
    """Write ``out_dir/{rollout.pvd, frame_*.vtu, boundary.vtu}`` for the rollout file ``rollout``.

    Everything is written into ``<out_dir>.part`` first and moved into ``out_dir`` at the end.

    Returns:
        The ``.pvd`` path.

    Raises:
        TrajectoryFileError: the rollout is unreadable or a frame of it damaged (names the file and frame);
            ``out_dir`` is then left as it was.
    """
    part = _fresh_part_folder(out_dir)
    try:
        _write_series(rollout, part)
    except BaseException:
        shutil.rmtree(part, ignore_errors=True)
        raise
    _publish(part, out_dir)
    return out_dir / "rollout.pvd"


def _write_series(rollout: Path, out_dir: Path) -> None:
    """The ``.vtu`` of every frame, the boundary's and the ``.pvd`` listing them, into ``out_dir``."""
    group = VtkGroup(str(out_dir / "rollout"))
    with open_lagfluid_file(rollout) as f:
        g = f["00000"]
        l0, dim = float(g.attrs["l0"]), int(g.attrs.get("dim", 3))
        settings = run_settings(g.attrs.get("config"))
        boundary, btype = read_array(g, "boundary_position"), read_array(g, "boundary_type")
        times = read_array(g, "time")
        if len(boundary):
            _points(out_dir / "boundary", boundary, {"particle_type": btype.astype(np.int32)})
            first = float(times[0]) if len(times) else 0.0
            group.addFile(filepath=str(out_dir / "boundary.vtu"), sim_time=first, part="1", name="boundary")
        for k, t in enumerate(times):
            pos, vel, p = (read_array(g, name, k) for name in ("position", "velocity", "pressure"))
            v = np.ascontiguousarray(vel, dtype=np.float64)
            data = {
                "velocity": tuple(np.ascontiguousarray(v[:, i]) for i in range(3)),
                "speed": np.linalg.norm(v, axis=1),
                "pressure": p.astype(np.float64),
                "number_density": number_density_ratio(pos, boundary, btype, l0, dim, settings),
                "particle_type": np.full(len(pos), int(ParticleType.FLUID), dtype=np.int32),
            }
            _points(out_dir / f"frame_{k:05d}", pos, data)
            group.addFile(
                filepath=str(out_dir / f"frame_{k:05d}.vtu"), sim_time=float(t), part="0", name="fluid"
            )
    group.save()
