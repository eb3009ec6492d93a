"""The collision-only particle systems of a scene and their one-step samples (paper A.2)."""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import Any

import h5py
import numpy as np
import torch

from lagfluid import integrate
from lagfluid.data.layout import (
    append_rows,
    appendable,
)
from lagfluid.physics.mps import CollisionRule
from lagfluid.physics.scheme import SplitStepSimulator
from lagfluid.physics.settings import SolverSettings
from lagfluid.state import ParticleState, ParticleType, SceneParams
from lagfluid.tasks.generate.spec import DataSpec, draw

log = logging.getLogger(__name__)


def collision_system(
    rng: np.random.Generator, collision: dict[str, Any], params: SceneParams, dtype: torch.dtype
) -> ParticleState:
    """One particle system for collision samples: a jittered fluid block with random velocities.

    The block has ``collision.block`` particles on a lattice of spacing U(``spacing``) l0 with uniform noise
    of +- ``jitter`` l0, so many pairs are closer than the collision radius (0.92 l0). Velocities are
    ``drift + scale N(0, I) / sqrt(3)`` with a log-uniform ``scale`` in ``speed`` (m/s) and a drift of random
    direction and size U(0, scale). With ``floor`` a floor of 2 wall layers and 1 dummy layer lies 1 l0
    below the block's lowest lattice plane (wall collisions; dummies are ignored by the rule).

    Args:
        rng: random generator (one per scene).
        collision: the ``data.collision`` settings.
        params: physical parameters (``l0``, ``dt``).
        dtype: floating dtype.

    Returns:
        the state, particles sorted fluid, wall, dummy.
    """
    l0 = params.l0
    nx, ny, nz = (int(b) for b in collision["block"])
    spacing = rng.uniform(*collision["spacing"]) * l0
    axes = [np.arange(n, dtype=np.float64) * spacing for n in (nx, ny, nz)]
    fluid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    fluid += rng.uniform(-1.0, 1.0, fluid.shape) * float(collision["jitter"]) * l0
    lo, hi = (float(v) for v in collision["speed"])
    scale = draw(rng, lo, hi, log_uniform=True)
    direction = rng.normal(size=3)
    drift = direction / np.linalg.norm(direction) * rng.uniform(0.0, scale)
    vel = drift + scale * rng.normal(size=fluid.shape) / math.sqrt(3.0)
    pos, types = [fluid], [np.full(len(fluid), int(ParticleType.FLUID))]
    if collision.get("floor", True):
        extent = [(-2, math.ceil(a[-1] / l0) + 2) for a in axes[:2]]
        xs, ys = (np.arange(a, b + 1, dtype=np.float64) * l0 for a, b in extent)
        for layer, kind in ((1, ParticleType.WALL), (2, ParticleType.WALL), (3, ParticleType.DUMMY)):
            grid = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
            pos.append(np.column_stack([grid, np.full(len(grid), -layer * l0)]))
            types.append(np.full(len(grid), int(kind)))
    pos_all = np.concatenate(pos)
    vel_all = np.zeros_like(pos_all)
    vel_all[: len(fluid)] = vel
    return ParticleState.from_arrays(
        torch.from_numpy(pos_all),
        torch.from_numpy(vel_all),
        torch.from_numpy(np.concatenate(types)),
        params,
        dtype=dtype,
    )


def write_collision_samples(
    group: h5py.Group, spec: DataSpec, settings: SolverSettings, params: SceneParams, seed: int
) -> int:
    """Simulate the scene's collision systems and store their samples in ``group``; returns the count."""
    col = spec.collision
    rng = np.random.default_rng([seed, 2])
    # Collision-only dynamics: no gravity or viscosity stage, no pressure: x* = x + v dt, then the rule.
    params = replace(params, gravity=(0.0, 0.0, 0.0), viscosity=0.0)
    systems = [collision_system(rng, col, params, spec.dtype) for _ in range(int(col["num_systems"]))]
    template = systems[0] if systems else collision_system(np.random.default_rng(0), col, params, spec.dtype)
    nc = template.n_fluid
    group.attrs.update(
        restitution=settings.restitution,
        re_collision=settings.re_collision,
        num_systems=len(systems),
        steps=int(col["steps"]),
        l0=params.l0,
        dt=params.dt,
    )
    group.create_dataset("boundary_position", data=template.pos[nc:].numpy().astype(np.float32))
    group.create_dataset("boundary_type", data=template.ptype[nc:].numpy().astype(np.int8))
    arrays = {
        name: appendable(group, name, (nc, 3), "f4") for name in ("position", "velocity", "delta_velocity")
    }
    system_ds = appendable(group, "system", (), "i8", 1024)
    step_ds = appendable(group, "step", (), "i8", 1024)
    count = 0
    for k, state in enumerate(systems):
        state = state.to(device=spec.device)
        sim = SplitStepSimulator("collision", settings, None, CollisionRule(), None)
        for j in range(int(col["steps"])):
            new = sim.step(state, record=True)
            f = sim.last_fields
            dv = integrate.collision_target(f.vel_star, f.vel_collided)
            for name, values in (
                ("position", f.pos_star),
                ("velocity", f.vel_star),
                ("delta_velocity", dv),
            ):
                append_rows(arrays[name], values.cpu().numpy().astype(np.float32)[None])
            append_rows(system_ds, np.array([k], np.int64))
            append_rows(step_ds, np.array([j], np.int64))
            count += 1
            state = new
    return count
