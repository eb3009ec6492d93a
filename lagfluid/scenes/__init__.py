"""Declarative scenes built into particle states, and loaders for the authors' grid files.

A scene lists what is in it (fluid blocks, a tank, obstacles; :mod:`lagfluid.scenes.geometry`) and is
discretised at the spacing ``l0`` with boundaries only as thick and as high as the fluid needs. Named
scenes (:mod:`lagfluid.scenes.library`, :mod:`lagfluid.scenes.grid_file`):

========== ===========================================================================================
dam        the authors' dam collapse: 10 x 20 x 20 fluid in a 41 x 21 l0 open tank (4,000 fluid)
dam_large  the same collapse with 40,000 fluid particles (20 x 50 x 40) for speed work
waterfall  80,000 fluid particles released in a corner, falling onto a ramp and round obstacles
random     the paper's training scenes: seeded fluid block, velocity and 1-2 obstacles in an 80 x 80 box
file       a grid file in the authors' format (``.npz`` or ``.txt``), option ``path``
trajectory frame ``frame`` of a lagfluid trajectory file (:mod:`lagfluid.scenes.trajectory`), option ``path``
========== ===========================================================================================

Example::

    state = build_scene("random", SceneParams(), seed=3)
"""

from __future__ import annotations

import inspect
from collections.abc import Callable

import torch

from lagfluid.scenes.geometry import (
    Box,
    Container,
    Cylinder,
    FluidBlock,
    Scene,
    Shape,
    Sphere,
    Wedge,
    lattice_block,
)
from lagfluid.scenes.grid_file import from_file, grid_bounds, load_grid, read_grid, save_grid
from lagfluid.scenes.library import (
    OBSTACLE_KINDS,
    RUNUP_FACTOR,
    dam,
    dam_large,
    dam_large_layout,
    dam_layout,
    random_layout,
    random_scene,
    waterfall,
    waterfall_layout,
)
from lagfluid.scenes.mesh import mesh_scene
from lagfluid.scenes.params import scene_builder, scene_params
from lagfluid.scenes.trajectory import (
    from_trajectory,
    trajectory_history,
    trajectory_params,
    trajectory_states,
)
from lagfluid.scenes.validation import MIN_DISTANCE, check_particles
from lagfluid.state import ParticleState, SceneError, SceneParams

__all__ = [
    "MIN_DISTANCE",
    "OBSTACLE_KINDS",
    "RUNUP_FACTOR",
    "SCENES",
    "Box",
    "Container",
    "Cylinder",
    "FluidBlock",
    "Scene",
    "Shape",
    "Sphere",
    "Wedge",
    "build_scene",
    "check_particles",
    "dam",
    "dam_large",
    "dam_large_layout",
    "dam_layout",
    "from_file",
    "from_trajectory",
    "grid_bounds",
    "lattice_block",
    "load_grid",
    "mesh_scene",
    "random_layout",
    "random_scene",
    "read_grid",
    "save_grid",
    "scene_builder",
    "scene_params",
    "trajectory_history",
    "trajectory_params",
    "trajectory_states",
    "waterfall",
    "waterfall_layout",
]

SceneBuilder = Callable[..., ParticleState]

SCENES: dict[str, SceneBuilder] = {
    "dam": dam,
    "dam_large": dam_large,
    "waterfall": waterfall,
    "random": random_scene,
    "file": from_file,
    "trajectory": from_trajectory,
    "mesh": mesh_scene,
}
"""Scene name -> builder ``(params=None, dtype=torch.float32, **options) -> ParticleState``."""


def build_scene(
    name: str, params: SceneParams | None = None, dtype: torch.dtype = torch.float32, **options
) -> ParticleState:
    """Build the scene registered as ``name``.

    Args:
        name: a key of :data:`SCENES`.
        params: physical parameters (``l0`` sets the particle spacing); default :class:`SceneParams`.
        dtype: floating dtype of the state.
        **options: the scene's options (e.g. ``seed`` for ``random``, ``path`` for ``file``, ``path``
            and ``frame`` for ``trajectory``).

    Returns:
        the validated initial state, particles sorted fluid, wall, dummy.

    Raises:
        SceneError: unknown name (the message lists the available ones), unknown option, or an
            invalid scene.
    """
    if name not in SCENES:
        raise SceneError(f"unknown scene '{name}'; available: {', '.join(sorted(SCENES))}")
    builder = SCENES[name]
    parameters = inspect.signature(builder).parameters
    if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()):
        # Builders taking **options check them against their layout; the others are checked here.
        accepted = [k for k in parameters if k not in ("params", "dtype")]
        unknown = sorted(set(options) - set(accepted))
        if unknown:
            raise SceneError(
                f"unknown option(s) {', '.join(unknown)} for scene '{name}'; available: {', '.join(accepted)}"
            )
    return builder(params, dtype, **options)
