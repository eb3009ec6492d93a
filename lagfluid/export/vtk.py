"""A rollout as a ParaView time series: ``.vtu`` per frame and a ``.pvd`` collection, written by pyevtk.

The fluid of frame ``k`` is ``frame_<k>.vtu`` (unstructured points; point data ``velocity`` (3), ``speed``,
``pressure``, ``number_density`` (n/n0 at the run's ``solver.re_density``, boundary included) and
``particle_type``); the static boundary is ``boundary.vtu`` (``particle_type``: 2 wall, 3 dummy), listed
once as part 1 of the collection at the first time (ParaView's PVD reader shows a part's latest file at or
before the current time, so the boundary stays at every time). ``rollout.pvd`` lists the frames with their
times in seconds.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import yaml
from omegaconf import OmegaConf
from pyevtk.hl import pointsToVTK
from pyevtk.vtk import VtkGroup

from lagfluid.data.store import open_lagfluid_file
from lagfluid.neighbors import radius_graph
from lagfluid.physics import operators as ops
from lagfluid.physics.stages import SolverSettings, lattice_constants
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


def write_paraview(rollout: Path, out_dir: Path) -> Path:
    """Write ``out_dir/{rollout.pvd, frame_*.vtu, boundary.vtu}`` for the rollout file ``rollout``.

    Returns:
        The ``.pvd`` path.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    for old in out_dir.glob("frame_*.vtu"):  # a shorter rerun must not leave the old run's frames
        old.unlink()
    group = VtkGroup(str(out_dir / "rollout"))
    with open_lagfluid_file(rollout) as f:
        g = f["00000"]
        l0, dim = float(g.attrs["l0"]), int(g.attrs.get("dim", 3))
        settings = run_settings(g.attrs.get("config"))
        boundary, btype = g["boundary_position"][()], g["boundary_type"][()]
        times = g["time"][()]
        if len(boundary):
            _points(out_dir / "boundary", boundary, {"particle_type": btype.astype(np.int32)})
            first = float(times[0]) if len(times) else 0.0
            group.addFile(filepath=str(out_dir / "boundary.vtu"), sim_time=first, part="1", name="boundary")
        for k, t in enumerate(times):
            pos, vel, p = g["position"][k], g["velocity"][k], g["pressure"][k]
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
    return out_dir / "rollout.pvd"
