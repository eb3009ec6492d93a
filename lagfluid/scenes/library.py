"""The named scenes: dam collapse (small and large), water fall, random training scenes.

Each scene has a *layout* function (options -> :class:`~lagfluid.scenes.geometry.Scene`, cheap and
inspectable) and a *builder* (``params, dtype, **options`` -> :class:`~lagfluid.state.ParticleState`)
that :data:`lagfluid.scenes.SCENES` maps its name to. All lengths are in units of ``l0``; coordinates
are lattice coordinates with the tank's inner wall layers on x = 0, y = 0 and z = 0 (see
:mod:`lagfluid.scenes.geometry`).

**How high the walls are.** A scene models only what its fluid can reach, and the open tanks' side
walls are the largest part of every scene, so their height is chosen, not copied:

* Dam collapse: ``RUNUP_FACTOR * h`` for a column of height ``h``. Ritter's ideal dam-break solution
  has its front moving at ``2 sqrt(g h)``, whose stagnation head ``(2 sqrt(g h))^2 / 2g = 2 h`` bounds
  the run-up on the far wall; bed friction, viscosity and the finite column only lower it. The
  authors' grid (walls to 41-42 l0 for h = 20 l0) made the same choice with one more layer.
* Water fall: the top of the released fluid. Everything in that scene falls first; the far-wall run-up
  of the spreading sheet is fed by the fall height, and the open top lets thin spray go.
* Random training scenes: the paper's box height (40 l0), with the fluid block's top at most half of
  it, so the 2 h run-up rule above holds for every draw (the initial speed, <= 0.1 m/s, adds
  v^2 / 2g < 0.01 l0 of head).
"""

from __future__ import annotations

import inspect
import logging
from collections.abc import Callable, Sequence

import numpy as np
import torch

from lagfluid.scenes.geometry import Box, Container, Cylinder, FluidBlock, Scene, Shape, Sphere, Wedge
from lagfluid.scenes.validation import as_vector, check_positive_int, shrink_advice
from lagfluid.state import ParticleState, SceneError, SceneParams

__all__ = [
    "OBSTACLE_KINDS",
    "RUNUP_FACTOR",
    "dam",
    "dam_large",
    "dam_large_layout",
    "dam_layout",
    "random_layout",
    "random_scene",
    "sink_depth",
    "waterfall",
    "waterfall_layout",
]

log = logging.getLogger(__name__)

RUNUP_FACTOR = 2
"""Dam-break wall height in units of the fluid column height (Ritter's run-up bound, see module doc)."""

OBSTACLE_KINDS = ("box", "cylinder", "sphere", "wedge")
"""The basic obstacle shapes of the paper's training scenes (A.2)."""


def build_layout(
    name: str,
    layout: Callable[..., Scene],
    params: SceneParams | None,
    dtype: torch.dtype,
    options: dict[str, object],
) -> ParticleState:
    """Call ``layout(**options).build(params, dtype)``, turning unknown options into a clear error."""
    accepted = list(inspect.signature(layout).parameters)
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise SceneError(
            f"unknown option(s) {', '.join(unknown)} for scene '{name}'; available: {', '.join(accepted)}"
        )
    return layout(**options).build(params, dtype, advice=shrink_advice(accepted))


def sink_depth(n_wall: int, n_dummy: int) -> int:
    """How far (l0) floor-standing obstacles reach below z = 0, and wall-touching ones beyond the wall.

    A point's depth in overlapping solids is the largest of its depths, so an obstacle's hidden faces
    must lie more than one boundary thickness beyond the tank's outermost layer: then no point of the
    tank's shell is within ``n_wall + n_dummy`` of them, and the floor under the obstacle is left empty.
    """
    return 2 * (n_wall + n_dummy)


# ------------------------------------------------------------------------------------------- dam
def dam_layout(
    fluid_size: Sequence[int] = (10, 20, 20),
    tank_size: Sequence[int] = (41, 21),
    wall_height: int | None = None,
    rim: str = "flat",
    n_wall: int = 2,
    n_dummy: int = 2,
    name: str = "dam",
    velocity: Sequence[float] = (0.0, 0.0, 0.0),
    fluid_lower: Sequence[int] = (1, 1, 1),
) -> Scene:
    """Dam collapse: a fluid column against the x = 0 wall of an open tank.

    Geometry (l0): fluid particles at x 1..fx, y 1..fy, z 1..fz (``fluid_size`` = (fx, fy, fz)); inner
    wall layers at x = 0 and x = Lx, y = 0 and y = Ly (``tank_size`` = (Lx, Ly)), floor at z = 0; side
    walls up to z = ``wall_height``. The defaults are the authors' dam collapse (4,000 fluid particles
    in a 41 x 21 l0 tank) with walls only as high as the collapse can reach.

    Args:
        fluid_size: (3,) number of fluid particles along x, y, z.
        tank_size: (2,) distance between opposite inner wall layers, l0; holds ``size - 1`` particles.
        wall_height: top of the side walls, l0; default ``RUNUP_FACTOR * fz`` (the authors': 41 with
            ``rim="stepped"``).
        rim: ``"flat"`` or ``"stepped"`` (see :class:`~lagfluid.scenes.geometry.Container`).
        n_wall: wall layers.
        n_dummy: dummy layers.
        name: scene name for messages.
        velocity: (3,) initial fluid velocity, m/s (a jet at the wall: ``[-5, 0, 0]``).
        fluid_lower: (3,) lattice coordinates of the column's first particle; (1, 1, 1) touches the x = 0,
            y = 0 walls and the floor at one l0; 0 on an axis puts a fluid layer on the wall's (refused by
            the scene validation: fluid inside the wall layers).

    Returns:
        the scene.
    """
    fx, fy, fz = as_vector("fluid_size", fluid_size, 3, integer=True, positive=True)
    lx, ly = as_vector("tank_size", tank_size, 2, integer=True, positive=True)
    lower = as_vector("fluid_lower", fluid_lower, 3, integer=True)
    if fx + lower[0] - 1 > lx - 1 or fy + lower[1] - 1 > ly - 1 or min(lower) < 0:
        raise SceneError(
            f"{name}: fluid_size {(fx, fy, fz)} from fluid_lower {tuple(lower)} does not fit in tank_size "
            f"{(lx, ly)}: the tank holds at most {lx - 1} x {ly - 1} fluid particles across, from 1"
        )
    height = RUNUP_FACTOR * fz if wall_height is None else check_positive_int("wall_height", wall_height)
    if height < fz + lower[2] - 1:
        raise SceneError(
            f"{name}: wall_height {height} is below the fluid column's top (z = {fz + lower[2] - 1} l0)"
        )
    return Scene(
        name=name,
        fluid=(FluidBlock(lower=lower, size=(fx, fy, fz), velocity=tuple(velocity)),),
        container=Container(size=(lx, ly), height=height, open_top=True, rim=rim),
        n_wall=n_wall,
        n_dummy=n_dummy,
    )


def dam_large_layout(
    fluid_size: Sequence[int] = (20, 50, 40),
    tank_size: Sequence[int] = (81, 51),
    wall_height: int | None = None,
    rim: str = "flat",
    n_wall: int = 2,
    n_dummy: int = 2,
) -> Scene:
    """Large dam collapse for speed work: 40,000 fluid particles, same shape in the x-z plane.

    The column keeps the small dam's x:z aspect (1:2) and the tank its length (4 column widths + 1),
    so the collapse is the same flow at twice the resolution in x and z; y is widened to reach 40k.
    Fluid x 1..20, y 1..50, z 1..40 in an 81 x 51 l0 tank with walls to 80 l0.

    Args:
        fluid_size: (3,) fluid particles along x, y, z.
        tank_size: (2,) inner tank size, l0.
        wall_height: side wall top, l0; default ``RUNUP_FACTOR * fz``.
        rim: ``"flat"`` or ``"stepped"``.
        n_wall: wall layers.
        n_dummy: dummy layers.

    Returns:
        the scene.
    """
    return dam_layout(fluid_size, tank_size, wall_height, rim, n_wall, n_dummy, name="dam_large")


def dam(params: SceneParams | None = None, dtype: torch.dtype = torch.float32, **options) -> ParticleState:
    """Build the dam-collapse scene; ``options`` are those of :func:`dam_layout`."""
    return build_layout("dam", dam_layout, params, dtype, options)


def dam_large(
    params: SceneParams | None = None, dtype: torch.dtype = torch.float32, **options
) -> ParticleState:
    """Build the 40k-particle dam collapse; ``options`` are those of :func:`dam_large_layout`."""
    return build_layout("dam_large", dam_large_layout, params, dtype, options)


# ------------------------------------------------------------------------------------------- water fall
def waterfall_layout(
    scale: float = 1.0,
    wall_height: int | None = None,
    n_wall: int = 2,
    n_dummy: int = 2,
) -> Scene:
    """Water fall: a block of fluid released high in one corner falls onto a ramp and flows round obstacles.

    The paper's water fall (~80k fluid particles) does not publish its geometry; this one has the same
    particle count and exercises falling, impact on a slope, and flow past three obstacle shapes.
    Geometry at ``scale=1`` (l0; s = :func:`sink_depth` = 8 by default, how far obstacles reach into the
    floor and walls so that no hidden floor or wall is built behind them):

    * tank: 80 x 80 (x, y) inner size, open top, walls up to the fluid's top (80);
    * fluid: 40 x 40 x 50 = 80,000 particles at x 1..40, y 1..40, z 31..80 (in the x = 0, y = 0
      corner), at rest;
    * ramp (wedge): x -s..48, y -s..44, falling along +x from z = 24 at x = -s to the floor at x = 48,
      under the fluid (9+ l0 of free fall before impact);
    * cylinder: vertical, axis (62, 22), radius 6, top z = 20 - downstream of the ramp;
    * box: x 56..68, y 50..62, top z = 14;
    * sphere: centre (25, 62, 7), radius 8 (resting on, and 1 l0 into, the floor).

    Args:
        scale: multiplies every length above (rounded to the lattice); 0.25 gives a ~1k-particle
            version for tests. Layer counts are not scaled.
        wall_height: side wall top, l0; default the top of the released fluid.
        n_wall: wall layers.
        n_dummy: dummy layers.

    Returns:
        the scene.
    """
    (scale,) = as_vector("scale", scale, 1, positive=True)
    n_wall = check_positive_int("n_wall", n_wall, minimum=1)
    n_dummy = check_positive_int("n_dummy", n_dummy, minimum=0)
    s = sink_depth(n_wall, n_dummy)

    def n(v: float) -> int:
        return max(1, round(v * scale))

    fluid = FluidBlock(lower=(1, 1, n(30) + 1), size=(n(40), n(40), n(50)))
    top = fluid.upper[2]
    height = top if wall_height is None else check_positive_int("wall_height", wall_height)
    obstacles: list[Shape] = [
        Wedge(lower=(-s, -s, -s), upper=(n(48), n(44), n(24)), axis=0, descending=True, low=0),
        Cylinder(start=(n(62), n(22), -s), end=(n(62), n(22), n(20)), radius=6 * scale),
        Box(lower=(n(56), n(50), -s), upper=(n(68), n(62), n(14))),
        Sphere(center=(n(25), n(62), 8 * scale - 1), radius=8 * scale),
    ]
    return Scene(
        name="waterfall",
        fluid=(fluid,),
        container=Container(size=(n(80), n(80)), height=height, open_top=True),
        obstacles=tuple(obstacles),
        n_wall=n_wall,
        n_dummy=n_dummy,
    )


def waterfall(
    params: SceneParams | None = None, dtype: torch.dtype = torch.float32, **options
) -> ParticleState:
    """Build the water-fall scene; ``options`` are those of :func:`waterfall_layout`."""
    return build_layout("waterfall", waterfall_layout, params, dtype, options)


# ------------------------------------------------------------------------------------------- random
def _aabb_disjoint(a_lo: np.ndarray, a_hi: np.ndarray, b_lo: np.ndarray, b_hi: np.ndarray) -> bool:
    """True when two inclusive lattice boxes share no point (so their particles are >= 1 l0 apart)."""
    return bool(np.any(a_hi < b_lo) or np.any(b_hi < a_lo))


def _random_obstacle(
    rng: np.random.Generator, kind: str, tank: tuple[int, int], wall_height: int, sink: int
) -> tuple[Shape, np.ndarray, np.ndarray]:
    """Draw one floor-standing obstacle; return it and its visible (z >= 0) inclusive lattice box."""
    lx, ly = tank
    top_max = max(2, min(25, wall_height - 1))

    def foot(lo: int, hi: int, axis_len: int) -> int:
        # Footprint size in [lo, hi], but never wider than the tank's interior minus a margin.
        return int(rng.integers(min(lo, axis_len - 2), min(hi, axis_len - 2) + 1))

    def corner(size: int, axis_len: int) -> int:
        # Lower corner such that the shape spans lattice points 1 .. axis_len - 1.
        if size > axis_len - 1:
            raise SceneError(f"random: a {kind} of {size} l0 does not fit in tank_size {tank}")
        return int(rng.integers(1, axis_len - size + 1))

    if kind in ("box", "wedge"):
        lo_f, hi_f = (6, 20) if kind == "box" else (10, 25)
        sx, sy = foot(lo_f, hi_f, lx), foot(lo_f, hi_f, ly)
        h = int(rng.integers(min(6, top_max), top_max + 1))
        x0, y0 = corner(sx, lx), corner(sy, ly)
        lower, upper = (x0, y0, -sink), (x0 + sx - 1, y0 + sy - 1, h)
        if kind == "box":
            shape: Shape = Box(lower=lower, upper=upper)
        else:
            shape = Wedge(
                lower=lower, upper=upper, axis=int(rng.integers(2)), descending=bool(rng.integers(2)), low=0
            )
        return shape, np.array([lower[0], lower[1], 0]), np.array(upper)
    r = int(rng.integers(3, max(4, min(10, (min(lx, ly) - 2) // 2) + 1)))
    cx, cy = corner(2 * r + 1, lx) + r, corner(2 * r + 1, ly) + r
    if kind == "cylinder":
        h = int(rng.integers(min(6, top_max), top_max + 1))
        shape = Cylinder(start=(cx, cy, -sink), end=(cx, cy, h), radius=r)
        return shape, np.array([cx - r, cy - r, 0]), np.array([cx + r, cy + r, h])
    shape = Sphere(center=(cx, cy, r), radius=r)  # resting on the floor (touches z = 0)
    return shape, np.array([cx - r, cy - r, 0]), np.array([cx + r, cy + r, 2 * r])


def _against_wall(
    rng: np.random.Generator,
    across: int,
    along: int,
    height: int,
    tank: tuple[int, int],
    bottom: int,
    what: str,
) -> FluidBlock:
    """A block at rest against a drawn side wall (which of the four, then in a corner of it or anywhere).

    ``across`` particles from the wall inwards, ``along`` along it, ``height`` up from lattice z ``bottom``.
    """
    normal = int(rng.integers(2))  # the wall's axis: x or y
    side = int(rng.integers(2))  # the low or the high wall
    place = int(rng.integers(3))  # low corner, high corner, anywhere along the wall
    size = [0, 0, height]
    size[normal], size[1 - normal] = across, along
    if size[0] > tank[0] - 1 or size[1] > tank[1] - 1:
        raise SceneError(f"random: {what} does not fit in tank_size {tank}")
    lower = [0, 0, bottom]
    lower[normal] = 1 if side == 0 else tank[normal] - across
    span = tank[1 - normal] - along  # lattice starts 1 .. span
    lower[1 - normal] = (1, span, int(rng.integers(1, span + 1)))[place]
    return FluidBlock(lower=tuple(lower), size=tuple(size))


def _wall_column(
    rng: np.random.Generator, column_size: Sequence[int], tank: tuple[int, int], wall_height: int
) -> FluidBlock:
    """A fluid column at rest on the floor against a drawn side wall: in one of its corners or anywhere."""
    thin, along, height = as_vector("column_size", column_size, 3, integer=True, positive=True)
    if 2 * height > wall_height:
        raise SceneError(
            f"random: column height {height} l0 needs walls of 2 x {height} l0 (Ritter's run-up bound), "
            f"wall_height is {wall_height}"
        )
    return _against_wall(rng, thin, along, height, tank, 1, f"column_size {tuple(column_size)}")


def random_layout(
    seed: int = 0,
    tank_size: Sequence[int] = (80, 80),
    wall_height: int = 40,
    fluid_size: Sequence[int] = (25, 25, 10),
    n_obstacles: int | None = None,
    obstacle_kinds: Sequence[str] = OBSTACLE_KINDS,
    max_speed: float = 0.1,
    max_fluid_top: int | None = None,
    n_wall: int = 2,
    n_dummy: int = 2,
    column_probability: float = 0.0,
    column_size: Sequence[int] = (10, 25, 20),
    edge_probability: float = 0.0,
) -> Scene:
    """Random training scene after the paper (A.2): one fluid block and one or two obstacles in a box.

    Draws, from ``numpy.random.default_rng(seed)`` (same seed, same scene):

    * the fluid block's place: any lattice position in the tank with its top at most ``max_fluid_top``
      (default ``wall_height // 2``, see the module doc on wall heights), so it may start in the air;
    * its initial velocity: speed U(0, ``max_speed``) m/s along one axis drawn from x, y, z, with a
      random sign;
    * with probability ``column_probability`` (drawn only when it is > 0, so the other draws of a seed
      stay those of the paper's scenes), a column collapse instead: a ``column_size`` block at rest on
      the floor against one side wall (which of the four drawn), in a corner of it or anywhere along it
      (one in three each). The paper's blocks rarely start at a wall, and nothing in them stands as deep
      as a dam's column against one: a model that never saw hydrostatic pressure on a side wall does
      not learn to hold it (GNS's dam rollouts, ``baselines/gns/weights/MODEL_CARD.md``). The default
      column is the dam's height (20 l0), so the tank's 40 l0 walls are Ritter's ``2 h`` bound;
    * else, with probability ``edge_probability`` (drawn only when it is > 0), the ``fluid_size`` block
      released at rest in the air against a drawn side wall (in a corner of it or anywhere along it), its
      top level with the wall's top edge: fluid beside the end of a wall, as at the water fall's start.
      Nothing in the paper's scenes puts fluid there (their tops stay at ``max_fluid_top``, half the
      walls), and DeepLagrangianFluids' network fine-tuned without it pushes such fluid up and over the
      edge (``baselines/cconv/weights/dlf_finetuned/MODEL_CARD.md``);
    * ``n_obstacles`` obstacles (default: 1 or 2, drawn), each of a kind drawn from
      ``obstacle_kinds``, standing on the floor (sunk into it, see :func:`sink_depth`), inside
      the tank and not touching the fluid block or each other: box (footprint 6-20 l0, height 6-25),
      wedge (footprint 10-25, height 6-25, sloping along a drawn axis and direction), vertical
      cylinder (radius 3-10, height 6-25), sphere (radius 3-10).

    The tank is the paper's 80 x 80 x 40 l0 box. It is open at the top, like the authors' training
    grids, which have no lid (theirs are 61 x 41 or 41 x 41 l0 with walls to 41 l0).

    Args:
        seed: random seed.
        tank_size: (2,) inner tank size, l0.
        wall_height: side wall top, l0.
        fluid_size: (3,) fluid particles along x, y, z.
        n_obstacles: number of obstacles; None draws 1 or 2.
        obstacle_kinds: kinds to draw from, a subset of :data:`OBSTACLE_KINDS`.
        max_speed: upper end of the initial speed, m/s.
        max_fluid_top: highest lattice z of the fluid block; default ``wall_height // 2``.
        n_wall: wall layers.
        n_dummy: dummy layers.
        column_probability: chance in [0, 1] that the scene is a column collapse.
        column_size: (3,) the column's particles along its thin side, along the wall and up.
        edge_probability: chance in [0, 1] that a scene that is not a column collapse is a block
            released against a wall's top edge.

    Returns:
        the scene; its ``description`` says what was drawn.
    """
    seed = check_positive_int("seed", seed, minimum=0)
    column_probability = float(column_probability)
    edge_probability = float(edge_probability)
    for name, chance in (("column_probability", column_probability), ("edge_probability", edge_probability)):
        if not 0.0 <= chance <= 1.0:
            raise SceneError(f"{name} must be in [0, 1], got {chance}")
    lx, ly = as_vector("tank_size", tank_size, 2, integer=True, positive=True)
    wall_height = check_positive_int("wall_height", wall_height)
    fx, fy, fz = as_vector("fluid_size", fluid_size, 3, integer=True, positive=True)
    (max_speed,) = as_vector("max_speed", max_speed, 1)
    if max_speed < 0:
        raise SceneError(f"max_speed must be >= 0, got {max_speed}")
    kinds = tuple(obstacle_kinds)
    bad = [k for k in kinds if k not in OBSTACLE_KINDS]
    if bad or not kinds:
        raise SceneError(f"obstacle_kinds must be a non-empty subset of {OBSTACLE_KINDS}, got {kinds!r}")
    top = wall_height // 2 if max_fluid_top is None else check_positive_int("max_fluid_top", max_fluid_top)
    if fx > lx - 1 or fy > ly - 1 or fz > top:
        raise SceneError(
            f"random: fluid_size {(fx, fy, fz)} does not fit in tank_size {(lx, ly)} below "
            f"max_fluid_top {top}"
        )
    if edge_probability > 0.0 and fz > wall_height:  # checked before any draw: every seed would need it
        raise SceneError(f"random: fluid_size {(fx, fy, fz)} is taller than wall_height {wall_height}")
    rng = np.random.default_rng(seed)
    if column_probability > 0.0 and rng.uniform() < column_probability:
        block = _wall_column(rng, column_size, (lx, ly), wall_height)
        fx, fy, fz = block.size
    elif edge_probability > 0.0 and rng.uniform() < edge_probability:
        # the block against a wall, its top level with the wall's top edge
        block = _against_wall(rng, fx, fy, fz, (lx, ly), wall_height - fz + 1, f"fluid_size {(fx, fy, fz)}")
    else:
        lower = (
            int(rng.integers(1, lx - fx + 1)),
            int(rng.integers(1, ly - fy + 1)),
            int(rng.integers(1, top - fz + 2)),
        )
        axis = int(rng.integers(3))
        velocity = [0.0, 0.0, 0.0]
        velocity[axis] = float(rng.uniform(0.0, max_speed)) * (1.0 if rng.integers(2) else -1.0)
        block = FluidBlock(lower=lower, size=(fx, fy, fz), velocity=tuple(velocity))
    lower, velocity = block.lower, block.velocity
    f_lo, f_hi = np.array(block.lower), np.array(block.upper)

    count = (
        int(rng.integers(1, 3)) if n_obstacles is None else check_positive_int("n_obstacles", n_obstacles, 0)
    )
    sink = sink_depth(check_positive_int("n_wall", n_wall), check_positive_int("n_dummy", n_dummy, minimum=0))
    obstacles: list[Shape] = []
    placed: list[tuple[np.ndarray, np.ndarray]] = [(f_lo, f_hi)]
    for i in range(count):
        # Rejection sampling: with the default sizes a free place is found in a few draws; the cap
        # turns an impossible request (a tank filled by fluid) into an error instead of a hang.
        for _ in range(1000):
            kind = str(rng.choice(kinds))
            shape, lo, hi = _random_obstacle(rng, kind, (lx, ly), wall_height, sink)
            if all(_aabb_disjoint(lo, hi, a, b) for a, b in placed):
                obstacles.append(shape)
                placed.append((lo, hi))
                break
        else:
            raise SceneError(
                f"random: could not place obstacle {i + 1} of {count} without touching the fluid block "
                f"or another obstacle in tank_size {(lx, ly)}; use a smaller fluid_size or fewer obstacles"
            )
    description = (
        f"seed {seed}: fluid {fx}x{fy}x{fz} at {lower}, velocity {tuple(round(v, 4) for v in velocity)} m/s; "
        + "; ".join(repr(o) for o in obstacles)
    )
    log.debug("random scene %s", description)
    return Scene(
        name="random",
        fluid=(block,),
        container=Container(size=(lx, ly), height=wall_height, open_top=True),
        obstacles=tuple(obstacles),
        n_wall=n_wall,
        n_dummy=n_dummy,
        description=description,
    )


def random_scene(
    params: SceneParams | None = None, dtype: torch.dtype = torch.float32, **options
) -> ParticleState:
    """Build a random training scene; ``options`` are those of :func:`random_layout` (``seed`` first)."""
    return build_layout("random", random_layout, params, dtype, options)
