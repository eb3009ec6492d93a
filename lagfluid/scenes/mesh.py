"""The ``mesh`` scene: a tank, the fluid and obstacles from the user's own meshes (any format trimesh reads).

``scene=mesh scene.container=tank.stl scene.fluid=block.stl [scene.obstacles=[rock.obj]] [scene.scale=0.001]``

Every particle sits on the lattice of spacing ``l0`` (the built scenes' rule), in the mesh's coordinates
times ``scale``. With ``d`` the signed distance of a lattice site to the container's surface (positive
inside, trimesh's convention):

* **fluid**: sites inside the fluid mesh or on its surface (within ``l0 / 4``) with ``d >= l0 / 2`` (so the
  first fluid layer is one ``l0`` from the wall layer on the surface, as in the dam);
* **wall**: ``-(n_wall - 1/2) l0 < d < l0 / 2``; **dummy**: the next ``n_dummy`` layers outward;
* **obstacles**: the same shells inward from each obstacle's surface (its inside beyond them stays empty),
  and no fluid inside an obstacle.

Model only what the scene requires: with ``open_top`` (default) the boundary stops at ``RUNUP_FACTOR`` times
the fluid's height above the container's floor, as the built tanks' walls do (a collapse cannot run up
higher); the domain box the guard checks is the container's, its top raised likewise.

Refused, naming the file: a mesh that is not watertight (inside and outside are undefined), fluid outside
the container, and a container under 4 ``l0`` or over 1 km across (units off by 1000: ``scale=0.001``
turns millimetres into metres).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from lagfluid.scenes.library import RUNUP_FACTOR
from lagfluid.scenes.validation import check_memory, shrink_advice, validated_state
from lagfluid.state import ParticleState, ParticleType, SceneError, SceneParams

LATTICE_BYTES_PER_SITE = 64  # the build's arrays per lattice site (positions, distances, masks)
ADVICE = shrink_advice(("container", "fluid", "obstacles", "scale"))  # too large: what to shrink, by its keys


def load_mesh(path: str | Path, scale: float, what: str):
    """The watertight mesh in ``path``, scaled by ``scale`` (a ``trimesh.Trimesh``).

    Raises:
        SceneError: a missing or unreadable file, or a mesh that is not watertight.
    """
    try:
        import trimesh
    except ImportError as err:
        raise SceneError("scene 'mesh' needs trimesh and rtree: pip install 'lagfluid[mesh]'") from err

    path = Path(path)
    if not path.is_file():
        raise SceneError(f"scene 'mesh': {what} mesh not found: {path}")
    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as err:  # whatever the file's parser raises
        raise SceneError(
            f"scene 'mesh': cannot read {what} mesh {path}: {type(err).__name__}: {err}"
        ) from err
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise SceneError(f"scene 'mesh': {path} holds no triangle surface ({what})")
    if not mesh.is_watertight:
        raise SceneError(
            f"scene 'mesh': the {what} mesh {path} is not watertight (its inside is undefined); close its "
            "holes (e.g. trimesh's fill_holes, or MeshLab) before using it"
        )
    mesh.apply_scale(float(scale))
    return mesh


def _signed_distance(mesh, points: np.ndarray) -> np.ndarray:
    """Signed distance (M,) of the points to the mesh surface, positive inside (trimesh's convention)."""
    import trimesh

    out = np.empty(len(points))
    for lo in range(0, len(points), 200_000):  # bounded memory for big lattices
        out[lo : lo + 200_000] = trimesh.proximity.signed_distance(mesh, points[lo : lo + 200_000])
    return out


def mesh_scene(
    params: SceneParams | None = None,
    dtype: torch.dtype = torch.float32,
    container: str | None = None,
    fluid: str | None = None,
    obstacles: Sequence[str] = (),
    scale: float = 1.0,
    n_wall: int = 2,
    n_dummy: int = 2,
    open_top: bool = True,
    velocity: Sequence[float] = (0.0, 0.0, 0.0),
) -> ParticleState:
    """Build the ``mesh`` scene (module doc) from the mesh files ``container``, ``fluid``, ``obstacles``."""
    params = params or SceneParams()
    if container is None or fluid is None:
        raise SceneError("scene 'mesh' needs scene.container=<mesh file> and scene.fluid=<mesh file>")
    if not scale > 0:
        raise SceneError(f"scene 'mesh': scale must be > 0, got {scale}")
    l0 = params.l0
    tank = load_mesh(container, scale, "container")
    water = load_mesh(fluid, scale, "fluid")
    solids = [load_mesh(path, scale, f"obstacle {k}") for k, path in enumerate(obstacles)]
    size = float((tank.bounds[1] - tank.bounds[0]).max())
    if size < 4 * l0 or size > 1000.0:
        raise SceneError(
            f"scene 'mesh': the container {container} is {size:.4g} m across at scale {scale} (l0 = {l0} m): "
            "units off by 1000? scene.scale=0.001 reads millimetres as metres"
        )
    outside = water.bounds[0] < tank.bounds[0] - 1e-9 * size, water.bounds[1] > tank.bounds[1] + 1e-9 * size
    if np.any(outside[0]) or np.any(outside[1]):
        raise SceneError(
            f"scene 'mesh': the fluid {fluid} (bounds {water.bounds.tolist()} m) reaches outside the "
            f"container {container} (bounds {tank.bounds.tolist()} m)"
        )

    shell = n_wall + n_dummy
    lower = np.floor(tank.bounds[0] / l0) - shell - 1
    upper = np.ceil(tank.bounds[1] / l0) + shell + 1
    counts = (upper - lower + 1).astype(int)
    check_memory(
        float(np.prod(counts)) * LATTICE_BYTES_PER_SITE,
        f"the lattice of its {size:.4g} m container at l0 = {l0} m",
        f"scene 'mesh' ({container})",
        ADVICE,
    )
    axes = [np.arange(lower[i], upper[i] + 1) * l0 for i in range(3)]
    sites = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    d = _signed_distance(tank, sites)
    # sites on the fluid mesh's surface count (a quarter spacing of tolerance): a 0.3 m block holds 6 layers
    near = np.all((sites > water.bounds[0] - l0) & (sites < water.bounds[1] + l0), axis=1)
    in_water = np.zeros(len(sites), dtype=bool)
    in_water[near] = _signed_distance(water, sites[near]) >= -0.25 * l0
    lost = in_water & (d < -0.5 * l0)  # fluid beyond the container's wall layer: outside it
    if lost.any():
        raise SceneError(
            f"scene 'mesh': {int(lost.sum())} lattice sites of the fluid {fluid} lie outside the container "
            f"{container} (e.g. at {sites[lost][0].round(4).tolist()} m)"
        )
    in_fluid = in_water & (d >= 0.5 * l0)
    wall = (d < 0.5 * l0) & (d > -(n_wall - 0.5) * l0)
    dummy = (d <= -(n_wall - 0.5) * l0) & (d > -(shell - 0.5) * l0)
    for solid in solids:  # distances only near the solid: beyond its shell a site is unaffected
        near = np.all((sites > solid.bounds[0] - shell * l0) & (sites < solid.bounds[1] + shell * l0), axis=1)
        ds = np.full(len(sites), -np.inf)
        ds[near] = _signed_distance(solid, sites[near])
        in_fluid &= ds <= -0.5 * l0
        wall |= (ds > -0.5 * l0) & (ds < (n_wall - 0.5) * l0)
        dummy |= (ds >= (n_wall - 0.5) * l0) & (ds < (shell - 0.5) * l0)
    dummy &= ~wall
    if not in_fluid.any():
        raise SceneError(
            f"scene 'mesh': no lattice site of spacing {l0} m lies inside both {fluid} and {container}"
        )
    floor = float(tank.bounds[0][2])
    fluid_top = float(sites[in_fluid, 2].max())
    top = floor + RUNUP_FACTOR * (fluid_top - floor) if open_top else float(tank.bounds[1][2]) + shell * l0
    wall &= sites[:, 2] <= top
    dummy &= sites[:, 2] <= top
    pos = np.concatenate([sites[in_fluid], sites[wall], sites[dummy]])
    ptype = np.concatenate(
        [
            np.full(int(in_fluid.sum()), ParticleType.FLUID),
            np.full(int(wall.sum()), ParticleType.WALL),
            np.full(int(dummy.sum()), ParticleType.DUMMY),
        ]
    ).astype(np.int64)
    vel = np.zeros_like(pos)
    vel[: int(in_fluid.sum())] = np.asarray(velocity, dtype=np.float64)
    bounds = np.stack([tank.bounds[0], tank.bounds[1]]).astype(np.float64)
    bounds[1, 2] = max(bounds[1, 2], top) + (top - floor if open_top else 0.0)
    return validated_state(
        pos, vel, ptype, params, bounds, dtype, source=f"scene 'mesh' ({container})", advice=ADVICE
    )
