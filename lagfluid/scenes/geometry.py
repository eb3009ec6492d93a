"""Building blocks of declarative scenes: fluid blocks, a box tank and solid obstacles on one lattice.

**Units and lattice.** Every length in this module is in units of the particle spacing ``l0``, and every
particle sits on the integer lattice (positions are ``l0`` times integer coordinates once built). The
origin is the tank's inner corner: the innermost wall layers lie on the planes x = 0, y = 0 and z = 0,
exactly as in the authors' grid files, so a fluid block whose first particle is at (1, 1, 1) starts
1 l0 from the inner wall layer, and fluid and boundary particles never overlap by construction.

**Solids and layers.** The tank and each obstacle are solids described by the *depth* ``d(p)`` of a
lattice point below the solid's surface (negative outside; for an obstacle ``d = -sdf``). Boundary
particles fill the shell under the surface and nothing else::

    wall  (ptype 2):  0 <= d < n_wall                   take part in the pressure solve
    dummy (ptype 3):  n_wall <= d < n_wall + n_dummy    only complete the wall particles' neighbourhoods
    empty:            d >= n_wall + n_dummy             no fluid particle can ever see it

The defaults (2 + 2 layers) are the authors': two dummy layers cover the 2.1 l0 number-density radius
of the outer wall layer. Where solids touch or overlap, a point's depth is the largest of its depths in
each solid, so the floor under an obstacle that is sunk into it, or a wall that an obstacle leans
against, is left empty instead of being filled with particles the fluid cannot reach.

**Tank.** :class:`Container` is an axis-aligned box tank; its depth is the Chebyshev distance beyond the
inner wall planes, which fills edges and corners the way the authors' grids do. With an open top the
side walls stop at ``height`` (``rim="flat"``), or each layer one l0 higher than the one inside it
(``rim="stepped"``, the authors' dam-collapse grid: a closed box with the lid's pyramid cut away).
"""

from __future__ import annotations

import logging
import math
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np
import torch

from lagfluid.scenes.validation import (
    MIN_DISTANCE,
    SHRINK,
    as_vector,
    check_choice,
    check_memory,
    check_positive_int,
    validated_state,
)
from lagfluid.state import ParticleState, ParticleType, SceneError, SceneParams

__all__ = [
    "Box",
    "Container",
    "Cylinder",
    "FluidBlock",
    "Scene",
    "Shape",
    "Sphere",
    "Wedge",
    "lattice_block",
]

log = logging.getLogger(__name__)

# Depths of lattice points are exact integers for lattice-aligned faces and square roots for curved
# ones; this tolerance keeps a point that lies on a surface (depth 0 up to rounding) in the solid.
_EPS = 1e-6

# Bytes per lattice point while a scene is built: a float64 depth, two masks and int64 coordinates of the
# box the boundary layers are cut from, and the fluid's coordinates, velocities and validation (generous).
_BUILD_BYTES_PER_POINT = 64


def lattice_block(lower: tuple[int, int, int], size: tuple[int, int, int]) -> np.ndarray:
    """Integer lattice points of a block, x slowest and z fastest.

    Args:
        lower: lattice coordinates of the block's first point, (3,).
        size: number of points along x, y, z, (3,), each > 0.

    Returns:
        (size_x * size_y * size_z, 3) int64 coordinates.
    """
    axes = [np.arange(lo, lo + n, dtype=np.int64) for lo, n in zip(lower, size, strict=True)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


# ---------------------------------------------------------------------------------------------- shapes
class Shape(ABC):
    """A solid obstacle: a signed distance function in l0 units and a bounding box."""

    @abstractmethod
    def sdf(self, points: np.ndarray) -> np.ndarray:
        """Signed distance to the surface, negative inside.

        Args:
            points: (M, 3) float64 lattice coordinates.

        Returns:
            (M,) distances in l0. Exact inside the solid (where the layers are cut); outside only its
            sign is used, so a lower bound of the distance is enough there.
        """

    @abstractmethod
    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        """(3,) lower and (3,) upper corner of a box containing the solid, l0."""

    def depth(self, points: np.ndarray) -> np.ndarray:
        """(M,) depth below the surface (``-sdf``) of (M, 3) lattice points."""
        return -self.sdf(points)


def _box_sdf(q: np.ndarray) -> np.ndarray:
    """Signed distance from per-face distances ``q`` (M, K), positive outside a face (exact for boxes)."""
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    inside = np.minimum(q.max(axis=1), 0.0)
    return outside + inside


def _set_corners(shape: Box | Wedge, kind: str) -> None:
    """Validate and store a frozen shape's ``lower`` and ``upper`` corners as float tuples."""
    lower = as_vector(f"{kind}.lower", shape.lower, 3)
    upper = as_vector(f"{kind}.upper", shape.upper, 3)
    if not all(u > lo for lo, u in zip(lower, upper, strict=True)):
        raise SceneError(f"{kind}.upper must exceed {kind}.lower on every axis, got {lower} .. {upper}")
    object.__setattr__(shape, "lower", lower)
    object.__setattr__(shape, "upper", upper)


@dataclass(frozen=True)
class Box(Shape):
    """Axis-aligned box, faces on the planes ``lower`` and ``upper`` (its outer wall layer sits there).

    Attributes:
        lower: (3,) lower corner, l0.
        upper: (3,) upper corner, l0, > lower on every axis.
    """

    lower: tuple[float, float, float]
    upper: tuple[float, float, float]

    def __post_init__(self) -> None:
        _set_corners(self, "Box")

    def sdf(self, points: np.ndarray) -> np.ndarray:  # noqa: D102
        lower, upper = np.asarray(self.lower), np.asarray(self.upper)
        return _box_sdf(np.concatenate([lower - points, points - upper], axis=1))

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:  # noqa: D102
        return np.asarray(self.lower, dtype=np.float64), np.asarray(self.upper, dtype=np.float64)


@dataclass(frozen=True)
class Sphere(Shape):
    """Ball of radius ``radius`` around ``center`` (l0)."""

    center: tuple[float, float, float]
    radius: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", as_vector("Sphere.center", self.center, 3))
        object.__setattr__(self, "radius", as_vector("Sphere.radius", self.radius, 1, positive=True)[0])

    def sdf(self, points: np.ndarray) -> np.ndarray:  # noqa: D102
        return np.linalg.norm(points - np.asarray(self.center), axis=1) - self.radius

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:  # noqa: D102
        c = np.asarray(self.center, dtype=np.float64)
        return c - self.radius, c + self.radius


@dataclass(frozen=True)
class Cylinder(Shape):
    """Finite solid cylinder with flat caps, axis from ``start`` to ``end`` (any direction), in l0.

    Attributes:
        start: (3,) centre of one cap.
        end: (3,) centre of the other cap.
        radius: radius, > 0.
    """

    start: tuple[float, float, float]
    end: tuple[float, float, float]
    radius: float

    def __post_init__(self) -> None:
        start = as_vector("Cylinder.start", self.start, 3)
        end = as_vector("Cylinder.end", self.end, 3)
        if start == end:
            raise SceneError(f"Cylinder.start and Cylinder.end must differ, both are {start}")
        object.__setattr__(self, "start", start)
        object.__setattr__(self, "end", end)
        object.__setattr__(self, "radius", as_vector("Cylinder.radius", self.radius, 1, positive=True)[0])

    def sdf(self, points: np.ndarray) -> np.ndarray:  # noqa: D102
        p0, p1 = np.asarray(self.start), np.asarray(self.end)
        length = float(np.linalg.norm(p1 - p0))
        axis = (p1 - p0) / length
        rel = points - p0
        t = rel @ axis
        radial = np.linalg.norm(rel - t[:, None] * axis, axis=1) - self.radius
        along = np.maximum(-t, t - length)
        return _box_sdf(np.stack([radial, along], axis=1))

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:  # noqa: D102
        p0, p1 = np.asarray(self.start), np.asarray(self.end)
        axis = (p1 - p0) / np.linalg.norm(p1 - p0)
        # A cap disk reaches r * sqrt(1 - axis_k^2) along axis k (0 along the cylinder's own axis).
        reach = self.radius * np.sqrt(np.clip(1.0 - axis**2, 0.0, 1.0))
        return np.minimum(p0, p1) - reach, np.maximum(p0, p1) + reach


@dataclass(frozen=True)
class Wedge(Shape):
    """A ramp: the box ``lower .. upper`` cut by a sloped top face.

    The top face runs along ``axis`` (0 = x, 1 = y) from height ``upper[2]`` at the high edge down to
    height ``low`` at the low edge; ``descending=True`` puts the high edge at ``lower[axis]`` (the ramp
    falls towards +axis). A floor-standing ramp is sunk into the floor by giving ``lower[2] < 0`` and
    ``low = 0``, so that its bottom merges with the floor instead of adding a hidden double floor.

    Attributes:
        lower: (3,) lower corner of the bounding box, l0.
        upper: (3,) upper corner of the bounding box, l0.
        axis: horizontal axis along which the top slopes, 0 or 1.
        descending: the top falls towards +axis (True) or -axis (False).
        low: height of the top face at the low edge, ``lower[2] <= low < upper[2]``; default
            ``lower[2]`` (a full wedge).
    """

    lower: tuple[float, float, float]
    upper: tuple[float, float, float]
    axis: int = 0
    descending: bool = True
    low: float | None = None

    def __post_init__(self) -> None:
        _set_corners(self, "Wedge")
        if self.axis not in (0, 1):
            raise SceneError(f"Wedge.axis must be 0 (x) or 1 (y), got {self.axis!r}")
        low = self.lower[2] if self.low is None else as_vector("Wedge.low", self.low, 1)[0]
        if not self.lower[2] <= low < self.upper[2]:
            raise SceneError(
                f"Wedge.low must lie in [lower z, upper z) = [{self.lower[2]}, {self.upper[2]}), got {low}"
            )
        object.__setattr__(self, "low", low)

    def sdf(self, points: np.ndarray) -> np.ndarray:  # noqa: D102
        lower, upper = np.asarray(self.lower), np.asarray(self.upper)
        box_q = np.concatenate([lower - points, points - upper], axis=1)
        a = self.axis
        run = upper[a] - lower[a]
        drop = upper[2] - self.low
        # Fraction of the run from the high edge; the top height falls linearly by `drop` along it.
        frac = (points[:, a] - lower[a]) / run if self.descending else (upper[a] - points[:, a]) / run
        top = upper[2] - drop * frac
        slope_q = (points[:, 2] - top) / math.hypot(1.0, drop / run)  # distance to the sloped plane
        # Intersection of half-spaces: max of the plane distances is exact inside a convex solid.
        return np.maximum(box_q.max(axis=1), slope_q)

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:  # noqa: D102
        return np.asarray(self.lower, dtype=np.float64), np.asarray(self.upper, dtype=np.float64)


# ---------------------------------------------------------------------------------------------- tank
@dataclass(frozen=True)
class Container:
    """Box tank: inner wall layers on x = 0 and x = size[0], y = 0 and y = size[1], z = 0 (floor).

    Fluid particles may occupy lattice points 1 .. size - 1 across the tank (``size - 1`` points), from
    z = 1 up. The authors' dam-collapse tank is ``size = (41, 21)``, ``height = 41``, ``rim = "stepped"``.

    Attributes:
        size: (2,) distance between opposite inner wall layers along x and y, l0.
        height: z of the inner wall layer's top (open top) or of the lid's inner layer (closed), l0.
        open_top: no lid; the side walls stop at ``height``.
        rim: open top only: ``"flat"`` (every layer stops at ``height``) or ``"stepped"`` (layer k,
            counted from 0 inside, stops at ``height + k``, as in the authors' dam grid).
    """

    size: tuple[int, int]
    height: int
    open_top: bool = True
    rim: str = "flat"

    def __post_init__(self) -> None:
        size = as_vector("tank_size", self.size, 2, integer=True, positive=True)
        if min(size) < 2:
            raise SceneError(f"tank_size must be >= 2 l0 on each axis to hold any fluid, got {size}")
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "height", check_positive_int("wall_height", self.height, minimum=1))
        object.__setattr__(self, "rim", check_choice("rim", self.rim, ("flat", "stepped")))

    def raw_depth(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Chebyshev depth beyond the inner wall planes (broadcasting), ignoring the open top's cut.

        Args:
            x: lattice x coordinates; ``x``, ``y`` and ``z`` broadcast together.
            y: lattice y coordinates.
            z: lattice z coordinates.

        Returns:
            depth, the broadcast shape; negative inside the tank, 0 on the inner wall layer.
        """
        lx, ly = self.size
        d = np.maximum(np.maximum(-x, x - lx), np.maximum(-y, y - ly))
        d = np.maximum(d, -z)
        if not self.open_top:
            d = np.maximum(d, z - self.height)
        return d.astype(np.float64)

    def depth(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Like :meth:`raw_depth`, with ``-inf`` (not part of the tank) above an open top's rim."""
        d = self.raw_depth(x, y, z)
        if self.open_top:
            rim = self.height + (d if self.rim == "stepped" else 0.0)
            d = np.where(np.broadcast_to(z, d.shape) > rim, -np.inf, d)
        return d

    def extent(self, layers: int) -> tuple[np.ndarray, np.ndarray]:
        """Inclusive (3,) lower and upper lattice corners of a tank built with ``layers`` layers."""
        k = layers - 1
        top = self.height + (k if (not self.open_top or self.rim == "stepped") else 0)
        return np.array([-k, -k, -k]), np.array([self.size[0] + k, self.size[1] + k, top])

    def bounds(self, fluid_top: float) -> np.ndarray:
        """(2, 3) domain box in l0: the inner wall planes; fluid outside it has left the tank.

        An open tank has no upper wall, so its upper z bound is generous: twice the higher of the wall
        top and the initial fluid top. Fluid thrown that high is far outside anything a scene intends.
        """
        top = self.height if not self.open_top else 2.0 * max(self.height, fluid_top)
        return np.array([[0.0, 0.0, 0.0], [self.size[0], self.size[1], top]])


# ---------------------------------------------------------------------------------------------- fluid
@dataclass(frozen=True)
class FluidBlock:
    """Box of fluid particles on the lattice.

    Attributes:
        lower: (3,) lattice coordinates of the first particle (1 = one l0 from the inner wall layer).
        size: (3,) number of particles along x, y, z (the block is ``size`` l0 thick).
        velocity: (3,) initial velocity of every particle, m/s.
    """

    lower: tuple[int, int, int]
    size: tuple[int, int, int]
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "lower", as_vector("fluid lower corner", self.lower, 3, integer=True))
        object.__setattr__(self, "size", as_vector("fluid_size", self.size, 3, integer=True, positive=True))
        object.__setattr__(self, "velocity", as_vector("fluid velocity", self.velocity, 3))

    @property
    def upper(self) -> tuple[int, int, int]:
        """(3,) lattice coordinates of the last particle (inclusive)."""
        return tuple(lo + n - 1 for lo, n in zip(self.lower, self.size, strict=True))

    def sites(self) -> np.ndarray:
        """(M, 3) int64 lattice coordinates of the block's particles."""
        return lattice_block(self.lower, self.size)


# ---------------------------------------------------------------------------------------------- scene
@dataclass(frozen=True)
class Scene:
    """A declarative scene: what is in it, not how it is discretised.

    Attributes:
        name: scene name, used in messages and logs.
        fluid: fluid blocks (at least one).
        container: the tank, or None for obstacles only (then the state has no bounds).
        obstacles: solid obstacles; fluid particles inside them are removed.
        n_wall: number of wall layers (>= 1).
        n_dummy: number of dummy layers outside (behind) the wall layers (>= 0).
        description: free text for logs (e.g. what a random scene drew).
    """

    name: str
    fluid: tuple[FluidBlock, ...]
    container: Container | None = None
    obstacles: tuple[Shape, ...] = ()
    n_wall: int = 2
    n_dummy: int = 2
    description: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "fluid", tuple(self.fluid))
        object.__setattr__(self, "obstacles", tuple(self.obstacles))
        if not self.fluid:
            raise SceneError(f"scene '{self.name}' has no fluid blocks")
        object.__setattr__(self, "n_wall", check_positive_int("n_wall", self.n_wall, minimum=1))
        object.__setattr__(self, "n_dummy", check_positive_int("n_dummy", self.n_dummy, minimum=0))
        if self.container is None and not self.obstacles:
            log.info("scene '%s' has neither a tank nor obstacles: its fluid falls freely", self.name)

    @property
    def layers(self) -> int:
        """Total boundary thickness in layers (wall + dummy)."""
        return self.n_wall + self.n_dummy

    # ------------------------------------------------------------------------------------ particles
    def fluid_sites(self) -> tuple[np.ndarray, np.ndarray]:
        """Lattice points and velocities of the fluid, minus the points inside obstacles.

        Returns:
            (F, 3) int64 lattice coordinates and (F, 3) float64 velocities, m/s.

        Raises:
            SceneError: a fluid particle lies in or beyond the tank's walls, or no fluid is left.
        """
        sites = [block.sites() for block in self.fluid]
        vel = [
            np.broadcast_to(np.asarray(b.velocity), s.shape) for b, s in zip(self.fluid, sites, strict=True)
        ]
        if self.container is not None:
            for i, (block, s) in enumerate(zip(self.fluid, sites, strict=True)):
                d = self.container.raw_depth(s[:, 0], s[:, 1], s[:, 2])
                if (d > -_EPS).any():
                    p = s[int(np.argmax(d))].tolist()
                    lx, ly = self.container.size
                    raise SceneError(
                        f"scene '{self.name}': fluid block {i} (lower {block.lower}, fluid_size "
                        f"{block.size}) does not fit in the tank: its particle at {p} l0 lies in or "
                        f"beyond a wall; fluid may occupy x 1..{lx - 1}, y 1..{ly - 1}, z >= 1"
                        + ("" if self.container.open_top else f", z <= {self.container.height - 1}")
                    )
        xyz = np.concatenate(sites)
        v = np.concatenate(vel).astype(np.float64)
        if self.obstacles:
            inside = np.zeros(len(xyz), dtype=bool)
            points = xyz.astype(np.float64)
            for shape in self.obstacles:
                inside |= shape.depth(points) > -_EPS
            if inside.any():
                log.info(
                    "scene '%s': removed %d fluid particles inside obstacles", self.name, int(inside.sum())
                )
            xyz, v = xyz[~inside], v[~inside]
        if len(xyz) == 0:
            raise SceneError(f"scene '{self.name}': no fluid particle is left outside the obstacles")
        return xyz, v

    def boundary_points(self) -> tuple[int, int]:
        """Lattice points of the box :meth:`boundary_sites` evaluates, and an upper bound of its particles.

        The bound is the box minus the tank's inside (a tank's layers), or the whole box for obstacles
        alone; computed without making any array.
        """
        if self.container is not None:
            lo, hi = self.container.extent(self.layers)
            inner = np.asarray(self.container.extent(0)[1], dtype=np.float64) - 1  # the fluid's room
            room = float(np.prod(np.maximum(inner, 0)))
        elif self.obstacles:
            boxes = [s.bbox() for s in self.obstacles]
            lo, hi, room = (
                np.floor(np.min([b[0] for b in boxes], axis=0)),
                np.ceil(np.max([b[1] for b in boxes], axis=0)),
                0.0,
            )
        else:
            return 0, 0
        box = float(np.prod(np.asarray(hi, dtype=np.float64) - np.asarray(lo, dtype=np.float64) + 1))
        return int(box), int(max(box - room, 0.0))

    def boundary_sites(self) -> tuple[np.ndarray, np.ndarray]:
        """Lattice points and types of the wall and dummy particles of the tank and obstacles.

        Returns:
            (B, 3) int64 lattice coordinates and (B,) int64 types (2 wall, 3 dummy).
        """
        if self.container is None and not self.obstacles:
            return np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int64)
        if self.container is not None:
            # Obstacle parts beyond the tank's outer layer are outside the scene and are dropped.
            lo, hi = self.container.extent(self.layers)
        else:
            boxes = [s.bbox() for s in self.obstacles]
            lo = np.floor(np.min([b[0] for b in boxes], axis=0)).astype(np.int64)
            hi = np.ceil(np.max([b[1] for b in boxes], axis=0)).astype(np.int64)
        axes = [np.arange(a, b + 1, dtype=np.int64) for a, b in zip(lo, hi, strict=True)]
        if self.container is not None:
            depth = self.container.depth(
                axes[0][:, None, None], axes[1][None, :, None], axes[2][None, None, :]
            )
        else:
            depth = np.full([len(a) for a in axes], -np.inf)
        for shape in self.obstacles:
            b_lo, b_hi = shape.bbox()
            # Only the shape's bounding box can be inside it: evaluate the SDF on that sub-grid alone.
            i0 = np.clip(np.floor(b_lo).astype(np.int64) - lo, 0, hi - lo + 1)
            i1 = np.clip(np.ceil(b_hi).astype(np.int64) - lo + 1, 0, hi - lo + 1)
            if np.any(i1 <= i0):
                log.warning("scene '%s': obstacle %s lies outside the tank and is ignored", self.name, shape)
                continue
            sub = tuple(slice(a, b) for a, b in zip(i0, i1, strict=True))
            pts = np.stack(
                np.meshgrid(*[ax[s] for ax, s in zip(axes, sub, strict=True)], indexing="ij"), axis=-1
            )
            d = shape.depth(pts.reshape(-1, 3).astype(np.float64)).reshape(pts.shape[:3])
            depth[sub] = np.maximum(depth[sub], d)
        wall = (depth > -_EPS) & (depth < self.n_wall - _EPS)
        dummy = (depth >= self.n_wall - _EPS) & (depth < self.layers - _EPS)
        out = []
        for mask, kind in ((wall, ParticleType.WALL), (dummy, ParticleType.DUMMY)):
            idx = np.nonzero(mask)
            xyz = np.stack([axes[k][idx[k]] for k in range(3)], axis=1)
            out.append((xyz, np.full(len(xyz), int(kind), dtype=np.int64)))
        return np.concatenate([o[0] for o in out]), np.concatenate([o[1] for o in out])

    def bounds(self, fluid_xyz: np.ndarray) -> np.ndarray | None:
        """(2, 3) domain box in l0 (see :meth:`Container.bounds`), or None without a tank."""
        if self.container is None:
            return None
        return self.container.bounds(float(fluid_xyz[:, 2].max()))

    # ------------------------------------------------------------------------------------ build
    def build(
        self,
        params: SceneParams | None = None,
        dtype: torch.dtype = torch.float32,
        min_distance: float = MIN_DISTANCE,
        advice: str = SHRINK,
    ) -> ParticleState:
        """Discretise the scene into particles at spacing ``params.l0``.

        Args:
            params: physical parameters (``l0`` sets the spacing); defaults to :class:`SceneParams`.
            dtype: floating dtype of the state.
            min_distance: closest allowed particle distance, l0 (see :func:`check_particles`).
            advice: what a scene too large for memory should shrink, naming its keys (:func:`shrink_advice`).

        Returns:
            a validated state with N = F + B particles sorted fluid, wall, dummy: ``pos`` (N, 3) m,
            ``vel`` (N, 3) m/s (zero on the boundary) and ``bounds`` (2, 3) m when the scene has a tank.
        """
        t0 = time.perf_counter()
        params = params or SceneParams()
        l0 = params.l0
        source = f"scene '{self.name}'"
        # estimated before any array is made: a too-large scene is refused, not killed by the OS later
        fluid_points = sum(int(np.prod(block.size)) for block in self.fluid)
        box, _ = self.boundary_points()
        check_memory(_BUILD_BYTES_PER_POINT * (fluid_points + box), "building it", source, advice)
        fluid_xyz, fluid_vel = self.fluid_sites()
        bnd_xyz, bnd_type = self.boundary_sites()
        pos = np.concatenate([fluid_xyz, bnd_xyz]).astype(np.float64) * l0
        vel = np.concatenate([fluid_vel, np.zeros((len(bnd_xyz), 3))])
        ptype = np.concatenate([np.full(len(fluid_xyz), int(ParticleType.FLUID), dtype=np.int64), bnd_type])
        bounds = self.bounds(fluid_xyz)
        bounds = None if bounds is None else bounds * l0
        state = validated_state(pos, vel, ptype, params, bounds, dtype, min_distance, source, advice)
        n_wall = int((bnd_type == ParticleType.WALL).sum())
        log.info(
            "scene '%s'%s: %d fluid, %d wall, %d dummy particles (built in %.2f s)",
            self.name,
            f" ({self.description})" if self.description else "",
            len(fluid_xyz),
            n_wall,
            len(bnd_type) - n_wall,
            time.perf_counter() - t0,
        )
        return state
