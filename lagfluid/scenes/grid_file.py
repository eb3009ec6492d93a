"""Scene files in the authors' grid formats.

* ``.npz``: arrays ``pos`` (N, 3) float, m; ``vel`` (N, 3) float, m/s; ``ptype`` (N,) int
  (1 fluid, 2 wall, 3 dummy). Their ``dam_col_4k.npz`` and ``training_scene/case*.npz`` are such files.
* ``.txt``: one particle per line, comma-separated ``x,y,z,vx,vy,vz,ptype`` with no header (their
  ``testing_scene/case*_grid.txt``); lines starting with ``#`` are ignored.

A file states no domain, so a loaded state's ``bounds`` are the extent of its boundary particles (a
fluid particle beyond the outermost boundary layer has certainly left the tank), with the upper z
bound raised by the extent's height because the authors' tanks are open at the top. A file without
boundary particles gets no bounds.
"""

from __future__ import annotations

import logging
import zipfile
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from lagfluid.scenes.validation import FILE_ADVICE, MIN_DISTANCE, validated_state
from lagfluid.state import ParticleState, ParticleType, SceneError, SceneParams

__all__ = ["from_file", "grid_bounds", "load_grid", "read_grid", "save_grid"]

log = logging.getLogger(__name__)

_TXT_COLUMNS = "x,y,z,vx,vy,vz,ptype"


def _integer_types(values: np.ndarray, path: Path) -> np.ndarray:
    values = np.asarray(values)
    if values.dtype.kind == "f":
        whole = np.isfinite(values) & (values == np.round(values))
        if not whole.all():
            i = int(np.flatnonzero(~whole)[0])
            raise SceneError(
                f"{path}: unknown particle type {values[i].item()!r} at particle {i}; "
                "expected 1 (fluid), 2 (wall) or 3 (dummy)"
            )
        return np.round(values).astype(np.int64)
    if values.dtype.kind not in "iu":
        raise SceneError(f"{path}: ptype must hold integers, got dtype {values.dtype}")
    return values.astype(np.int64)


def read_grid(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a grid file without validating its contents beyond its layout.

    Args:
        path: a ``.npz`` or ``.txt`` file in the authors' format.

    Returns:
        pos (N, 3) float64 m, vel (N, 3) float64 m/s, ptype (N,) int64, in file order.

    Raises:
        SceneError: the file is missing, of an unknown kind, lacks an array or column, or has
            mismatched shapes.
    """
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"grid file not found: {path}")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        arrays = _npz_arrays(path)
        for key in ("pos", "vel", "ptype"):
            if key not in arrays:
                raise SceneError(
                    f"{path}: missing array '{key}' (found: {', '.join(sorted(arrays)) or 'none'}); "
                    "expected pos (N, 3), vel (N, 3), ptype (N,)"
                )
        pos, vel, ptype = arrays["pos"], arrays["vel"], arrays["ptype"]
    elif suffix == ".txt":
        try:
            data = np.loadtxt(path, delimiter=",", ndmin=2, dtype=np.float64)
        except ValueError as err:
            raise SceneError(f"{path}: cannot read comma-separated {_TXT_COLUMNS} ({err})") from None
        if data.size == 0:
            raise SceneError(f"{path}: the file holds no particles")
        if data.shape[1] != 7:
            raise SceneError(f"{path}: expected 7 columns {_TXT_COLUMNS}, got {data.shape[1]}")
        pos, vel, ptype = data[:, :3], data[:, 3:6], data[:, 6]
    else:
        raise SceneError(f"{path}: unsupported grid file type '{path.suffix}'; expected .npz or .txt")
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise SceneError(f"{path}: pos must have shape (N, 3), got {pos.shape}")
    if vel.shape != pos.shape:
        raise SceneError(f"{path}: vel must have shape {pos.shape} like pos, got {vel.shape}")
    if ptype.shape != (pos.shape[0],):
        raise SceneError(f"{path}: ptype must have shape ({pos.shape[0]},) like pos, got {ptype.shape}")
    if not (np.issubdtype(pos.dtype, np.number) and np.issubdtype(vel.dtype, np.number)):
        raise SceneError(f"{path}: pos and vel must be numbers, got {pos.dtype} and {vel.dtype}")
    return pos.astype(np.float64), vel.astype(np.float64), _integer_types(ptype, path)


def grid_bounds(pos: np.ndarray, ptype: np.ndarray) -> np.ndarray | None:
    """(2, 3) bounds of a loaded grid: the boundary particles' extent, z raised for an open top.

    Args:
        pos: (N, 3) positions, m.
        ptype: (N,) types.

    Returns:
        (2, 3) lower and upper corner, m, or None when the boundary particles span no volume.
    """
    boundary = pos[ptype != ParticleType.FLUID]
    if len(boundary) == 0:
        return None
    lower, upper = boundary.min(axis=0), boundary.max(axis=0)
    if not (upper > lower).all():
        log.warning("the boundary particles span no volume (%s .. %s m); no bounds", lower, upper)
        return None
    upper = upper.copy()
    upper[2] += upper[2] - lower[2]
    return np.stack([lower, upper])


def _npz_arrays(path: Path) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` archive ``path``.

    Raises:
        SceneError: the file is empty, truncated, a single ``.npy`` array or no NumPy archive at all
            (numpy's own message for the last suggests ``allow_pickle``: never the fix for a grid file).
    """
    expected = "expected a .npz archive of arrays pos, vel, ptype"
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
        reason = "the file is empty" if path.stat().st_size == 0 else "truncated, or not a NumPy archive"
        raise SceneError(
            f"{path}: not a readable .npz file ({reason}: {type(err).__name__}); {expected}"
        ) from None
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise SceneError(f"{path}: holds a single array, not an archive; {expected}")
    try:
        with data:
            return {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
        raise SceneError(
            f"{path}: a damaged .npz archive ({type(err).__name__}: {err}); {expected}"
        ) from None


def load_grid(
    path: str | Path,
    params: SceneParams | None = None,
    dtype: torch.dtype = torch.float32,
    min_distance: float = MIN_DISTANCE,
) -> ParticleState:
    """Load and validate a grid file (see the module doc) into a state sorted fluid, wall, dummy.

    Args:
        path: ``.npz`` or ``.txt`` grid file.
        params: physical parameters; ``l0`` is used for the overlap check and should match the file.
        dtype: floating dtype of the state.
        min_distance: closest allowed particle distance, l0.

    Returns:
        the state, with ``bounds`` from :func:`grid_bounds`.
    """
    params = params or SceneParams()
    pos, vel, ptype = read_grid(path)
    bounds = grid_bounds(pos, ptype) if np.isfinite(pos).all() else None
    state = validated_state(pos, vel, ptype, params, bounds, dtype, min_distance, str(path), FILE_ADVICE)
    fluid = pos[ptype == ParticleType.FLUID]
    if len(fluid) > 1:
        # The solver's reference densities (solver.n0_from=lattice, the default) assume spacing l0, so a
        # grid at another spacing gives wrong pressures unless l0 matches it or n0 is measured from the
        # initial frame (solver.n0_from=initial). Usually a units mistake: say so loudly.
        spacing = float(np.median(cKDTree(fluid).query(fluid, k=2)[0][:, 1]))
        if abs(spacing / params.l0 - 1.0) > 0.01:
            log.warning(
                "%s: fluid spacing %.4g m differs from l0 = %.4g m; set scene.params.l0=%.4g "
                "(or solver.n0_from=initial), otherwise n0 and the pressures are wrong",
                path,
                spacing,
                params.l0,
                spacing,
            )
    log.info(
        "grid %s: %d fluid, %d wall, %d dummy particles",
        path,
        state.n_fluid,
        int(state.wall_mask.sum()),
        int(state.dummy_mask.sum()),
    )
    return state


def save_grid(state: ParticleState, path: str | Path) -> Path:
    """Write a state's particles in the authors' format, chosen by the suffix (``.npz`` or ``.txt``).

    ``.npz`` stores pos and vel as float32 and ptype as int64, as their files do; ``.txt`` writes
    six decimals (micrometres), enough for any lattice of practical spacing.

    Args:
        state: the state to write (pressure, time and bounds are not part of the format).
        path: destination file.

    Returns:
        the path written.
    """
    path = Path(path)
    pos = state.pos.detach().cpu().numpy()
    vel = state.vel.detach().cpu().numpy()
    ptype = state.ptype.detach().cpu().numpy().astype(np.int64)
    suffix = path.suffix.lower()
    if suffix == ".npz":
        np.savez(path, pos=pos.astype(np.float32), vel=vel.astype(np.float32), ptype=ptype)
    elif suffix == ".txt":
        table = np.concatenate([pos.astype(np.float64), vel.astype(np.float64), ptype[:, None]], axis=1)
        np.savetxt(path, table, fmt=["%.6f"] * 6 + ["%d"], delimiter=",")
    else:
        raise SceneError(f"{path}: unsupported grid file type '{path.suffix}'; expected .npz or .txt")
    return path


def from_file(
    params: SceneParams | None = None,
    dtype: torch.dtype = torch.float32,
    path: str | Path | None = None,
    min_distance: float = MIN_DISTANCE,
) -> ParticleState:
    """The ``file`` scene: :func:`load_grid` of option ``path`` (required)."""
    if path is None:
        raise SceneError("scene 'file' needs the option path=<grid file (.npz or .txt)>")
    return load_grid(path, params, dtype, min_distance)
