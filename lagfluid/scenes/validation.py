"""Checks shared by every scene builder and the grid-file loader.

Scenes are validated on the raw (unsorted) arrays before a :class:`~lagfluid.state.ParticleState` is
made, so an error names particles by their index in the file or in the builder's own order, and every
problem is reported before a simulator ever sees the state.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np
import torch
from scipy.spatial import cKDTree

from lagfluid.state import ParticleState, ParticleType, SceneError, SceneParams

__all__ = [
    "FILE_ADVICE",
    "MIN_DISTANCE",
    "as_vector",
    "available_memory",
    "check_choice",
    "check_memory",
    "check_particles",
    "check_positive_int",
    "shrink_advice",
]

MIN_DISTANCE = 0.5
"""Closest allowed distance between two particles, in units of l0.

Lattice neighbours are 1 l0 apart; the authors' rotated obstacles put particles 0.5 l0 off the lattice,
so 0.5 l0 is the closest spacing that a valid grid has and anything closer is a duplicate or an
overlap that would give near-infinite kernel weights (``w = re / r - 1``).
"""

DENSITY_RADIUS = 2.1
"""Radius (l0) of the number-density check: the MPS density radius of every solver profile."""

MAX_FLUID_DENSITY = 1.1
"""Largest initial number density of a fluid particle, in units of a full lattice's (n0).

On a lattice every fluid particle has at most n0 (measured: 1.0000 on ``dam``, ``waterfall``, ``random``
and the authors' grids); one placed inside the wall layers or an obstacle has 1.16-1.32 n0 and starts
with many times the hydrostatic pressure.
"""

_TYPE_NAMES = {int(t): t.name.lower() for t in ParticleType}


def as_vector(
    name: str, value: object, n: int, *, integer: bool = False, positive: bool = False
) -> tuple[float, ...] | tuple[int, ...]:
    """Convert a scene option to a tuple of ``n`` finite numbers, raising :class:`SceneError` otherwise.

    Args:
        name: option name, used in the error message.
        value: a sequence of numbers (a list from a YAML config, a tuple, an array) or one number,
            which is repeated ``n`` times.
        n: expected length.
        integer: require whole numbers (lattice counts); they are returned as ``int``.
        positive: require every entry to be > 0.

    Returns:
        tuple of ``n`` floats, or ints when ``integer`` is set.
    """
    if isinstance(value, (int, float, np.integer, np.floating)):
        values = [value] * n
    else:
        try:
            values = list(value)  # type: ignore[call-overload]
        except TypeError:
            raise SceneError(f"{name} must be {n} numbers, got {value!r}") from None
    if len(values) != n:
        raise SceneError(f"{name} must be {n} numbers, got {len(values)}: {value!r}")
    try:
        floats = [float(v) for v in values]
    except (TypeError, ValueError):
        raise SceneError(f"{name} must be numbers, got {value!r}") from None
    if not all(math.isfinite(v) for v in floats):
        raise SceneError(f"{name} must be finite, got {value!r}")
    if positive and not all(v > 0 for v in floats):
        raise SceneError(f"{name} must be positive, got {value!r}")
    if integer:
        if not all(v == round(v) for v in floats):
            raise SceneError(f"{name} must be whole numbers of l0 (lattice counts), got {value!r}")
        return tuple(round(v) for v in floats)
    return tuple(floats)


def check_positive_int(name: str, value: object, minimum: int = 1) -> int:
    """Return ``value`` as an int >= ``minimum``, raising :class:`SceneError` naming ``name`` otherwise."""
    try:
        as_float = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise SceneError(f"{name} must be an integer >= {minimum}, got {value!r}") from None
    if not math.isfinite(as_float) or as_float != round(as_float) or as_float < minimum:
        raise SceneError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return round(as_float)


def check_particles(
    pos: np.ndarray,
    vel: np.ndarray,
    ptype: np.ndarray,
    l0: float,
    bounds: np.ndarray | None = None,
    min_distance: float = MIN_DISTANCE,
    source: str = "scene",
) -> None:
    """Raise :class:`SceneError` naming the first problem of a particle set, in a fixed order.

    Checked: array shapes, finite positions and velocities, known particle types, at least one fluid
    particle, fluid inside ``bounds``, and no two particles closer than ``min_distance * l0``.

    Args:
        pos: (N, 3) positions, m.
        vel: (N, 3) velocities, m/s.
        ptype: (N,) integer types (1 fluid, 2 wall, 3 dummy).
        l0: particle spacing, m.
        bounds: optional (2, 3) box (lower, upper corner), m; fluid must lie inside it.
        min_distance: closest allowed particle distance in units of l0.
        source: what is being checked (a scene name or a file path), quoted in messages.
    """
    pos = np.asarray(pos)
    vel = np.asarray(vel)
    ptype = np.asarray(ptype)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise SceneError(f"{source}: pos must have shape (N, 3), got {pos.shape}")
    n = pos.shape[0]
    if vel.shape != pos.shape:
        raise SceneError(f"{source}: vel must have shape {pos.shape} like pos, got {vel.shape}")
    if ptype.shape != (n,):
        raise SceneError(f"{source}: ptype must have shape ({n},) like pos, got {ptype.shape}")
    for name, values in (("pos", pos), ("vel", vel)):
        finite = np.isfinite(values).all(axis=1)
        if not finite.all():
            i = int(np.flatnonzero(~finite)[0])
            raise SceneError(
                f"{source}: {name} of particle {i} is not finite: {values[i].tolist()} "
                f"({int((~finite).sum())} particles affected)"
            )
    known = np.isin(ptype, list(_TYPE_NAMES))
    if not known.all():
        i = int(np.flatnonzero(~known)[0])
        raise SceneError(
            f"{source}: unknown particle type {ptype[i].item()!r} at particle {i}; "
            "expected 1 (fluid), 2 (wall) or 3 (dummy)"
        )
    fluid = ptype == ParticleType.FLUID
    if not fluid.any():
        raise SceneError(f"{source}: the scene has no fluid particles")
    if bounds is not None:
        bounds = np.asarray(bounds, dtype=np.float64)
        outside = fluid & ((pos < bounds[0]) | (pos > bounds[1])).any(axis=1)
        if outside.any():
            i = int(np.flatnonzero(outside)[0])
            raise SceneError(
                f"{source}: fluid particle {i} at {pos[i].tolist()} m is outside the tank "
                f"{bounds[0].tolist()} .. {bounds[1].tolist()} m "
                f"({int(outside.sum())} fluid particles outside)"
            )
    _check_overlaps(pos, ptype, l0, min_distance, source)
    _check_crowded_fluid(pos, ptype, l0, source)


def lattice_number_density(radius: float = DENSITY_RADIUS) -> float:
    """n0 of a full simple-cubic lattice for the kernel ``w = re/r - 1`` at ``re = radius`` (in l0)."""
    k = np.arange(-math.ceil(radius), math.ceil(radius) + 1)
    r = np.linalg.norm(np.stack(np.meshgrid(k, k, k), axis=-1).reshape(-1, 3), axis=1)
    r = r[(r > 0) & (r < radius)]
    return float(np.sum(radius / r - 1))


def _check_crowded_fluid(pos: np.ndarray, ptype: np.ndarray, l0: float, source: str) -> None:
    """Refuse a fluid particle whose number density exceeds :data:`MAX_FLUID_DENSITY` n0."""
    fluid = np.flatnonzero(ptype == ParticleType.FLUID)
    re = DENSITY_RADIUS * l0
    # the 48 nearest within re (a lattice has 32 there; 48 found is crowded anyway): one vectorised query
    dist, _ = cKDTree(pos).query(pos[fluid], k=min(49, len(pos)), distance_upper_bound=re)
    dist = dist.reshape(len(fluid), -1)[:, 1:]  # the first is the particle itself
    weights = np.where(np.isfinite(dist), re / np.where(dist > 0, dist, re) - 1, 0.0)
    density = weights.sum(axis=1) / lattice_number_density()
    crowded = density > MAX_FLUID_DENSITY
    if crowded.any():
        k = int(np.argmax(density))
        i = int(fluid[k])
        raise SceneError(
            f"{source}: fluid particle {i} at {pos[i].tolist()} m has number density {density[k]:.3g} n0 "
            f"(a lattice's: 1; allowed up to {MAX_FLUID_DENSITY:g}): it sits inside the wall layers or an "
            f"obstacle, or is packed among its neighbours, and would start far above hydrostatic pressure "
            f"(fluid particles above {MAX_FLUID_DENSITY:g} n0: {int(crowded.sum())})"
        )


def _check_overlaps(pos: np.ndarray, ptype: np.ndarray, l0: float, min_distance: float, source: str) -> None:
    radius = min_distance * l0
    # query_pairs includes pairs at exactly `radius`; shrink it a hair so lattice points exactly
    # min_distance apart (the authors' half-lattice obstacles) pass.
    pairs = cKDTree(np.asarray(pos, dtype=np.float64)).query_pairs(radius * (1 - 1e-6), output_type="ndarray")
    if len(pairs) == 0:
        return
    dist = np.linalg.norm(pos[pairs[:, 0]] - pos[pairs[:, 1]], axis=1)
    k = int(np.argmin(dist))
    i, j = (int(v) for v in sorted(pairs[k]))
    raise SceneError(
        f"{source}: particles {i} ({_TYPE_NAMES[int(ptype[i])]}) and {j} ({_TYPE_NAMES[int(ptype[j])]}) "
        f"overlap: {dist[k] / l0:.3g} l0 apart at {pos[i].tolist()} m, closer than {min_distance:g} l0 "
        f"({len(pairs)} overlapping pairs in all)"
    )


MAX_POSITION_SPACING = 1e-3
"""Coarsest spacing of representable positions allowed, in l0 (the float spacing at the farthest coordinate).

Kernel weights and distances are computed from position differences; far from the origin float32 rounds
them (at 1e6 m its spacing is 0.06 m > l0: 352 of 640 particles of a test grid became duplicates).
"""


def _check_resolution(
    pos: np.ndarray, bounds: np.ndarray | None, l0: float, dtype: torch.dtype, source: str
) -> None:
    """Refuse positions so far from the origin that ``dtype`` cannot resolve them to a fraction of l0."""
    far = float(np.abs(pos).max())
    if bounds is not None:
        far = max(far, float(np.abs(bounds).max()))
    spacing = far * torch.finfo(dtype).eps
    if spacing > MAX_POSITION_SPACING * l0:
        name = str(dtype).removeprefix("torch.")
        raise SceneError(
            f"{source}: coordinates reach {far:.3g} m from the origin, where {name} resolves positions only "
            f"to {spacing:.2g} m ({spacing / l0:.2g} l0; allowed {MAX_POSITION_SPACING:g} l0): distances and "
            "kernel weights would be rounded. Move the scene near the origin (subtract its lower corner) or "
            "use dtype=float64"
        )


def available_memory() -> int | None:
    """Bytes of memory the system can still give (Linux ``MemAvailable``), or None where unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


CHECK_BYTES_PER_FLUID = 2_000
CHECK_BYTES_PER_PARTICLE = 100
"""Memory :func:`check_particles` needs: the 49 nearest neighbours of every fluid particle with their kernel
weights (per fluid particle) and its k-d trees (per particle). Measured (peak RSS of the checks alone, dams of
40,000 and 80,000 fluid in 149k and 154k particles): 1.6 KB per fluid particle and under 30 B per particle."""

SHRINK = "make the scene smaller or l0 larger"
"""What :func:`check_memory` advises where the scene's own keys are not known (the Python API)."""


def shrink_advice(options: Iterable[str]) -> str:
    """What to make smaller to fit memory, naming the keys of the scene in use.

    Args:
        options: the scene's option names (its config keys, or its builder's parameters).
    """
    options = set(options)
    if "container" in options:  # scene=mesh: the meshes set the size, in their own units
        return (
            "meshes in millimetres need scene.scale=0.001 (mesh units -> m); otherwise make scene.scale or "
            "the meshes smaller, or scene.params.l0 larger"
        )
    if "path" in options:  # scene=file, scene=trajectory: the particles are the file's
        return "start from a file with fewer particles, or use a machine with more memory"
    keys = [
        f"scene.{k}"
        for k in ("scale", "fluid_size", "tank_size", "wall_height", "column_size")
        if k in options
    ]
    return (
        f"make {', '.join(keys)} smaller or scene.params.l0 larger" if keys else "make scene.params.l0 larger"
    )


FILE_ADVICE = shrink_advice(("path",))
"""What a file's particles too many for memory should shrink (``scene=file``, ``scene=trajectory``)."""


def check_memory(need: float, what: str, source: str, advice: str = SHRINK) -> None:
    """Refuse, naming the estimate, when ``need`` bytes exceed the memory available now.

    Args:
        need: bytes.
        what: what needs them ("building it", "a rollout of model mps").
        source: the scene or file, first in the message.
        advice: what to shrink, naming the scene's own keys (:func:`shrink_advice`).

    Raises:
        SceneError: the estimate is larger than the available memory.
    """
    have = available_memory()
    if have is not None and need > have:
        raise SceneError(
            f"{source}: {what} needs ~{need / 2**30:.3g} GiB, but {have / 2**30:.3g} GiB of memory are "
            f"available; {advice}"
        )


def check_choice(name: str, value: object, choices: Sequence[str]) -> str:
    """Return ``value`` if it is one of ``choices``, else raise :class:`SceneError` listing them."""
    if value not in choices:
        raise SceneError(f"{name} must be one of {', '.join(map(repr, choices))}; got {value!r}")
    return str(value)


def validated_state(
    pos: np.ndarray,
    vel: np.ndarray,
    ptype: np.ndarray,
    params: SceneParams,
    bounds: np.ndarray | None,
    dtype: torch.dtype,
    min_distance: float = MIN_DISTANCE,
    source: str = "scene",
    advice: str = SHRINK,
) -> ParticleState:
    """:func:`check_particles`, then the :class:`ParticleState` of these arrays (sorted by type).

    The checks' neighbour queries are refused first when they would not fit in memory (a huge file).

    Args:
        pos: (N, 3) positions, m.
        vel: (N, 3) velocities, m/s.
        ptype: (N,) particle types.
        params: physical parameters (``l0`` scales ``min_distance``).
        bounds: optional (2, 3) domain box, m.
        dtype: floating dtype of the state.
        min_distance: closest allowed particle distance, l0.
        source: what the particles came from, for the messages.
        advice: what a scene too large for memory should shrink (:func:`shrink_advice`).
    """
    n_fluid = int(np.count_nonzero(np.asarray(ptype) == ParticleType.FLUID))
    check_memory(
        CHECK_BYTES_PER_FLUID * n_fluid + CHECK_BYTES_PER_PARTICLE * len(pos),
        f"checking its {len(pos):,} particles",
        source,
        advice,
    )
    check_particles(pos, vel, ptype, params.l0, bounds, min_distance=min_distance, source=source)
    _check_resolution(pos, bounds, params.l0, dtype, source)
    return ParticleState.from_arrays(
        torch.from_numpy(pos),
        torch.from_numpy(vel),
        torch.from_numpy(ptype),
        params=params,
        bounds=None if bounds is None else torch.from_numpy(bounds),
        dtype=dtype,
    )
