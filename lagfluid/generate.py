"""Dataset generation: the MPS solver on seeded scenes, one HDF5 file per scene, then ``metadata.json``.

``python -m lagfluid.run task=generate scene=random data=cpu [num_scenes=N] [steps=N]`` (profiles in
``conf/data/``: ``paper``, ``cpu``, ``tiny``) writes::

    DIR/                                 data.out_dir (default data/<profile>)
      scenes/scene_00007.h5              scene k, built with seed data.seed + k (layout below)
      metadata.json                      once every scene is there: splits, statistics, provenance

Each scene is independent, so Hydra multirun parallelises generation (joblib launcher)::

    python -m lagfluid.run -m task=generate scene=random data=cpu threads=1 'data.scene_index=range(0,12)'
    python -m lagfluid.run task=generate scene=random data=cpu     # finishes missing scenes, metadata

With ``data.scene_index`` set a job makes only that scene; the job that finds every scene present writes
``metadata.json`` (so a complete sweep needs no second command; the plain run is harmless and resumes).
``threads=1`` keeps each job on one core (the joblib launcher runs one job per core).

**Resume.** Frames and samples go to ``scene_00007.h5.part``; the file is renamed to ``scene_00007.h5``
(atomic) only when the scene is complete. A rerun skips finished scenes, regenerates missing ones and
overwrites leftover ``.part`` files, so an interrupted generation never duplicates or corrupts a scene.
Each file carries a *fingerprint* of everything that determines its content (scene options and seed,
physical parameters, steps, sampling, solver and collision settings); a finished file with another
fingerprint is an error rather than silently mixed into the dataset. A scene stopped by the rollout guard
(NaN, Courant number, a particle leaving the tank) is kept as ``scene_00007.failed.h5`` for inspection;
the other scenes still run and the generation then fails naming it.

The scene-file layout is :mod:`lagfluid.data.layout`'s; the statistics in ``metadata.json`` are
:mod:`lagfluid.data.statistics`'.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from statistics import median
from typing import Any

import h5py
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

import lagfluid
from lagfluid import integrate
from lagfluid.config import git_commit, run_attributes, scene_params
from lagfluid.data.layout import (
    DATASET_FORMAT,
    GROUP,
    METADATA_FILE,
    SAMPLES_FORMAT_VERSION,
    SPLITS,
    SampleWriter,
    append_rows,
    appendable,
    read_scene_info,
    scene_path,
    split_counts,
    split_of,
)
from lagfluid.data.statistics import STATISTICS, dataset_statistics
from lagfluid.data.store import TrajectoryFileError, TrajectoryWriter
from lagfluid.errors import LagfluidError, RolloutError, SceneError
from lagfluid.models.mps_simulator import build_mps
from lagfluid.physics.mps import CollisionRule
from lagfluid.physics.stages import SolverSettings, SplitStepSimulator, solver_identity
from lagfluid.rollout import Guard, rollout
from lagfluid.scenes import build_scene
from lagfluid.state import ParticleState, ParticleType, SceneParams

__all__ = ["DataSpec", "collision_system", "generate", "generate_scene", "write_metadata"]

log = logging.getLogger(__name__)


def _range(name: str, value: Any, positive: bool) -> tuple[float, float]:
    lo, hi = (float(v) for v in value)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi) or (positive and lo <= 0):
        raise LagfluidError(
            f"{name} must be [low, high] with low <= high{' and low > 0' if positive else ''}"
        )
    return lo, hi


def _draw(rng: np.random.Generator, lo: float, hi: float, log_uniform: bool) -> float:
    if log_uniform:
        return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
    return float(rng.uniform(lo, hi))


@dataclass(frozen=True)
class DataSpec:
    """Everything ``task=generate`` needs, read and checked once from the composed config.

    Attributes:
        name: profile name.
        out_dir: dataset directory.
        num_scenes: number of scenes.
        steps: solver steps per scene.
        sample_every: k: frames and samples every k-th step.
        seed: scene k is built with ``seed + k``.
        scene_index: only this scene (multirun), or None for all.
        splits: fraction of the scenes per split.
        builder: scene builder name.
        scene_options: builder options shared by every scene (``seed`` is set per scene when the scene
            takes one).
        params: physical parameters before the per-scene materials.
        materials: ``vary``, ``gravity`` and ``viscosity`` ranges, ``log_uniform``.
        collision: collision-system settings.
        solver: the ``solver`` config as a plain dict.
        dtype: floating dtype of the simulation.
        device: torch device.
    """

    name: str
    out_dir: Path
    num_scenes: int
    steps: int
    sample_every: int
    seed: int
    scene_index: int | None
    splits: dict[str, float]
    builder: str
    scene_options: dict[str, Any]
    params: SceneParams
    materials: dict[str, Any]
    collision: dict[str, Any]
    solver: dict[str, Any]
    dtype: torch.dtype
    device: torch.device

    @classmethod
    def from_config(cls, cfg: DictConfig) -> DataSpec:
        """Read ``cfg.data``, ``cfg.scene``, ``cfg.solver`` and the top-level overrides."""
        data = OmegaConf.to_container(cfg.data, resolve=True)
        num_scenes, steps, every = int(cfg.num_scenes), int(cfg.steps), int(data["sample_every"])
        for key, value in (("num_scenes", num_scenes), ("steps", steps), ("data.sample_every", every)):
            if value < 1:
                raise LagfluidError(f"{key} must be >= 1, got {value}")
        seed = int(data["seed"])
        if seed < 0:
            raise LagfluidError(f"data.seed must be >= 0, got {seed}")
        index = data.get("scene_index")
        if index is not None and not 0 <= int(index) < num_scenes:
            raise LagfluidError(f"data.scene_index must be in [0, {num_scenes}), got {index}")
        splits = {k: float(v) for k, v in (data.get("splits") or {}).items()}
        if set(splits) - set(SPLITS) or any(v < 0 for v in splits.values()) or splits.get("train", 0) <= 0:
            raise LagfluidError(
                f"data.splits must map {', '.join(SPLITS)} to fractions >= 0 (train > 0), got {splits}"
            )
        materials = dict(data["materials"])
        _range("data.materials.gravity", materials["gravity"], positive=materials["log_uniform"])
        _range("data.materials.viscosity", materials["viscosity"], positive=materials["log_uniform"])
        collision = dict(data["collision"])
        if int(collision["num_systems"]) < 0 or int(collision["steps"]) < 1:
            raise LagfluidError("data.collision needs num_systems >= 0 and steps >= 1")
        if len(collision["block"]) != 3 or min(int(b) for b in collision["block"]) < 1:
            raise LagfluidError(f"data.collision.block must be 3 positive ints, got {collision['block']}")
        _range("data.collision.spacing", collision["spacing"], positive=True)
        _range("data.collision.speed", collision["speed"], positive=True)
        scene = OmegaConf.to_container(cfg.scene, resolve=True)
        options = {k: v for k, v in scene.items() if k not in ("name", "builder", "params")}
        options.update(data.get("scene_options") or {})
        params = scene_params(cfg)
        if cfg.dt is None and data.get("dt") is not None:
            params = params.with_overrides(dt=float(data["dt"]))
        dtype = {"float32": torch.float32, "float64": torch.float64}.get(cfg.dtype)
        if dtype is None:
            raise LagfluidError(f"unknown dtype '{cfg.dtype}'; available: float32, float64")
        return cls(
            name=str(data["name"]),
            out_dir=Path(data["out_dir"]),
            num_scenes=num_scenes,
            steps=steps,
            sample_every=every,
            seed=seed,
            scene_index=None if index is None else int(index),
            splits=splits,
            builder=str(cfg.scene.get("builder") or cfg.scene.name),
            scene_options=options,
            params=params,
            materials=materials,
            collision=collision,
            solver=OmegaConf.to_container(cfg.solver, resolve=True),
            dtype=dtype,
            device=torch.device(cfg.device),
        )

    @property
    def num_samples(self) -> int:
        """Samples per scene: one at every k-th step before the last, S = ceil(steps / k)."""
        return -(-self.steps // self.sample_every)

    def scene_setup(self, index: int) -> tuple[dict[str, Any], SceneParams, int]:
        """Options, physical parameters (materials drawn when they vary) and seed of scene ``index``."""
        seed = self.seed + index
        options = dict(self.scene_options)
        if "seed" in options:
            options["seed"] = seed
        params = self.params
        if self.materials["vary"]:
            rng = np.random.default_rng([seed, 1])  # a stream of its own: the scene draws from seed alone
            m = self.materials
            g = _draw(rng, *m["gravity"], m["log_uniform"])
            nu = _draw(rng, *m["viscosity"], m["log_uniform"])
            direction = np.asarray(params.gravity, dtype=np.float64)
            norm = float(np.linalg.norm(direction))
            direction = direction / norm if norm > 0 else np.array([0.0, 0.0, -1.0])
            params = replace(params, gravity=tuple(float(v) for v in g * direction), viscosity=nu)
        return options, params, seed

    def fingerprint(self, index: int) -> str:
        """Hash of everything that determines the content of scene ``index``."""
        options, params, seed = self.scene_setup(index)
        # The guard and the (exact) neighbour backend do not change what a finished file holds.
        solver = {k: v for k, v in solver_identity(self.solver).items() if k not in ("guard", "neighbors")}
        content = {
            "builder": self.builder,
            "options": options,
            "params": asdict(params),
            "seed": seed,
            "steps": self.steps,
            "sample_every": self.sample_every,
            "solver": solver,
            "collision": self.collision,
            "dtype": str(self.dtype),
            "samples_format": SAMPLES_FORMAT_VERSION,
        }
        return hashlib.sha256(json.dumps(content, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _scene_done(path: Path, fingerprint: str) -> bool:
    """True for a finished scene file made with ``fingerprint``; False when it must be (re)generated.

    Raises:
        LagfluidError: a finished file made with another configuration.
    """
    if not path.exists():
        return False
    try:
        info = read_scene_info(path)
    except TrajectoryFileError as err:
        log.warning("%s; regenerating it", err)
        return False
    if not info.complete:
        log.warning("%s is incomplete; regenerating it", path)
        return False
    found = str(info.attrs.get("fingerprint", ""))
    if found != fingerprint:
        raise LagfluidError(
            f"{path} was generated with another configuration (fingerprint {found}, this run {fingerprint}: "
            "scene options, materials, steps, sample_every, solver or collision settings differ); "
            "use another data.out_dir or delete the file"
        )
    return True


# ------------------------------------------------------------------------------------------ collision system
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
    scale = _draw(rng, lo, hi, log_uniform=True)
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


def _write_collision_samples(
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


# ------------------------------------------------------------------------------------------ one scene
def generate_scene(cfg: DictConfig, spec: DataSpec, index: int) -> Path:
    """Simulate scene ``index`` with MPS and write its file (trajectory + samples); returns the path.

    Raises:
        LagfluidError: the rollout guard stopped the scene (the file is kept as ``*.failed.h5``), or the scene
            is invalid.
    """
    path = scene_path(spec.out_dir, index)
    failed = path.with_name(path.stem + ".failed.h5")
    options, params, seed = spec.scene_setup(index)
    try:
        state = build_scene(spec.builder, params, dtype=spec.dtype, **options).to(device=spec.device)
    except SceneError as err:
        raise SceneError(f"scene {index} (seed {seed}): {err}") from err
    settings = SolverSettings.from_config(cfg.solver)
    sim = build_mps(cfg)
    sim.reset(state)
    nf = state.n_fluid
    attrs = {
        **run_attributes(state, cfg, sim.name, spec.builder, spec.sample_every),
        "scene_options": options,
        "scene_index": index,
        "seed": seed,
        "sample_every": spec.sample_every,
        "steps": spec.steps,
        "bounds": state.bounds.cpu().numpy().astype(np.float64) if state.bounds is not None else None,
        "fingerprint": spec.fingerprint(index),
        "dataset": spec.name,
        **sim.attributes(),
    }
    writer = TrajectoryWriter(
        path, nf, state.pos[nf:].cpu().numpy(), state.ptype[nf:].cpu().numpy(), attrs, group=GROUP
    )
    start = time.perf_counter()
    try:
        samples = SampleWriter(writer.file.create_group("samples"), nf, params.dt)
        guard = Guard(float(cfg.solver.guard.max_courant), int(cfg.solver.guard.check_every))
        every = spec.sample_every

        def keep_sample(before: ParticleState, after: ParticleState, fields: Any) -> None:
            if fields is not None:
                samples.append(before.step, fields)

        _, record = rollout(
            sim,
            state,
            spec.steps,
            guard=guard,
            write_every=every,
            on_frame=writer.append_state,
            on_step=keep_sample,
            record_when=lambda s: s.step % every == 0,  # recording costs copies: only the sampled steps
            progress=bool(cfg.progress),
        )
        sim_seconds = time.perf_counter() - start
        collisions = _write_collision_samples(
            samples.group.create_group("collision"), spec, settings, params, seed
        )
        samples.group.attrs["complete"] = True
        writer.group.attrs.update(
            wall_time_s=time.perf_counter() - start,
            simulation_time_s=sim_seconds,
            step_time_median_s=median(record["step_seconds"]),
            ppe_iterations_median=median(record["info"].get("ppe_iterations", [0.0])),
            collision_samples=collisions,
        )
        writer.close(complete=True)
        failed.unlink(missing_ok=True)  # a failure of an earlier run with other settings
    except RolloutError as err:
        writer.file.close()
        os.replace(writer.tmp_path, failed)
        raise LagfluidError(
            f"scene {index} ({path.name}, seed {seed}) stopped: {err}; kept as {failed}"
        ) from err
    except BaseException:
        # Interrupted or failed otherwise: leave the .part file; the next run overwrites it.
        if writer.file.id.valid:
            writer.file.close()
        raise
    log.info(
        "scene %d: %d steps in %.0f s (%.0f ms/step median), %d + %d collision samples -> %s",
        index,
        spec.steps,
        time.perf_counter() - start,
        1e3 * median(record["step_seconds"]),
        spec.num_samples,
        collisions,
        path,
    )
    return path


# ------------------------------------------------------------------------------------------ metadata
def _write_json(path: Path, content: dict[str, Any]) -> None:
    """Write atomically: a per-process temporary file, then rename (parallel jobs may race here)."""
    tmp = path.with_name(f"{path.name}.{os.getpid()}.part")
    tmp.write_text(json.dumps(content, indent=2))
    os.replace(tmp, path)


def write_metadata(spec: DataSpec, generation_seconds: float | None = None) -> dict[str, Any]:
    """Write ``metadata.json`` for the scenes ``0 .. num_scenes-1`` (all must be finished); returns it."""
    infos = [read_scene_info(scene_path(spec.out_dir, k)) for k in range(spec.num_scenes)]
    splits = split_of(spec.num_scenes, spec.splits)
    rel = [str(i.path.relative_to(spec.out_dir)) for i in infos]
    first = infos[0].attrs
    settings = SolverSettings.from_config(spec.solver)
    l0, dim = float(first["l0"]), int(first["dim"])
    bounds = [i.attrs["bounds"] for i in infos if not isinstance(i.attrs.get("bounds"), str)]
    box = None
    if bounds:
        lo = np.min([np.asarray(b)[0] for b in bounds], axis=0)
        hi = np.max([np.asarray(b)[1] for b in bounds], axis=0)
        box = [[float(a), float(b)] for a, b in zip(lo, hi, strict=True)]
    counts = {}
    for split in SPLITS:
        members = [i for i, s in zip(infos, splits, strict=True) if s == split]
        counts[split] = {
            "scenes": len(members),
            "frames": sum(i.frames for i in members),
            "advection_samples": sum(i.samples for i in members),
            "pressure_samples": sum(i.samples for i in members),
            "collision_samples": sum(i.collision_samples for i in members),
        }
    train = [i.path for i, s in zip(infos, splits, strict=True) if s == "train"]
    stats = dataset_statistics(train)
    seconds = [float(i.attrs.get("wall_time_s", 0.0)) for i in infos]
    meta = {
        "format": DATASET_FORMAT,
        "format_version": 1,
        "samples_format_version": SAMPLES_FORMAT_VERSION,
        "name": spec.name,
        "num_scenes": spec.num_scenes,
        "steps": spec.steps,
        "sample_every": spec.sample_every,
        "write_every": spec.sample_every,
        "sequence_length": infos[0].frames,
        "dt": float(first["dt"]),
        "dim": dim,
        "l0": l0,
        "bounds": box,
        "periodic_boundary_conditions": [False] * dim,
        "default_connectivity_radius": settings.re_laplacian * l0,
        "default_connectivity_radius_note": "re_laplacian * l0: the largest radius of the MPS operators",
        "radii_l0": {
            "density": settings.re_density,
            "gradient": settings.re_gradient,
            "laplacian": settings.re_laplacian,
            "collision": settings.re_collision,
        },
        "n0": float(first["n0"]),
        "n0_lap": float(first["n0_lap"]),
        "lambda": float(first["lambda"]),
        "statistics_split": "train",
        "statistics_features": STATISTICS,
        **stats,
        "splits": {split: [r for r, s in zip(rel, splits, strict=True) if s == split] for split in SPLITS},
        "counts": counts,
        "scenes": [
            {
                "index": k,
                "file": rel[k],
                "split": splits[k],
                "seed": int(i.attrs["seed"]),
                "gravity": [float(g) for g in i.attrs["gravity"]],
                "viscosity": float(i.attrs["viscosity"]),
                "n_fluid": i.n_fluid,
                "n_boundary": i.n_boundary,
                "frames": i.frames,
                "samples": i.samples,
                "collision_samples": i.collision_samples,
                "wall_time_s": seconds[k],
                "step_time_median_s": float(i.attrs.get("step_time_median_s", math.nan)),
            }
            for k, i in enumerate(infos)
        ],
        "scene": {"builder": spec.builder, "options": spec.scene_options},
        "materials": spec.materials,
        "collision": spec.collision,
        "solver": spec.solver,
        "model": "mps",
        "version": lagfluid.__version__,
        "git_commit": git_commit(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "generation_time_s": sum(seconds),
        "generation_run_time_s": generation_seconds,
    }
    _write_json(spec.out_dir / METADATA_FILE, meta)
    return meta


# ------------------------------------------------------------------------------------------ task
def generate(cfg: DictConfig) -> dict[str, Any] | None:
    """``task=generate``: make the missing scenes (or only ``data.scene_index``), then ``metadata.json``.

    Returns:
        the metadata once every scene is there, else None (other multirun jobs are still working).

    Raises:
        LagfluidError: bad settings, a scene file from another configuration, or scenes stopped by the guard
            (named; the others are still generated).
    """
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    spec = DataSpec.from_config(cfg)
    if "seed" not in spec.scene_options:
        log.warning(
            "scene '%s' takes no seed: every scene starts alike (use scene=random for the paper's data)",
            spec.builder,
        )
    split_counts(spec.num_scenes, spec.splits)  # fail on impossible splits before hours of simulation
    start = time.perf_counter()
    todo: Sequence[int] = range(spec.num_scenes) if spec.scene_index is None else [spec.scene_index]
    log.info(
        "generating %s of %d scenes (%d steps, samples every %d) into %s",
        "all" if spec.scene_index is None else f"scene {spec.scene_index}",
        spec.num_scenes,
        spec.steps,
        spec.sample_every,
        spec.out_dir,
    )
    failed = []
    for k in todo:
        path = scene_path(spec.out_dir, k)
        if _scene_done(path, spec.fingerprint(k)):
            log.info("scene %d: %s is done, skipped", k, path)
            continue
        try:
            generate_scene(cfg, spec, k)
        except LagfluidError as err:
            if spec.scene_index is not None:
                raise
            log.error("%s", err)
            failed.append(str(err))
    if failed:
        raise LagfluidError(f"{len(failed)} scene(s) failed: " + " | ".join(failed))
    missing = [
        k for k in range(spec.num_scenes) if not _scene_done(scene_path(spec.out_dir, k), spec.fingerprint(k))
    ]
    if missing:
        log.info("metadata.json waits for scenes %s (other jobs, or rerun task=generate)", missing)
        return None
    meta = write_metadata(spec, time.perf_counter() - start)
    log.info(
        "wrote %s: %d scenes (%s), %d advection/pressure and %d collision training samples",
        spec.out_dir / METADATA_FILE,
        spec.num_scenes,
        ", ".join(f"{s} {meta['counts'][s]['scenes']}" for s in SPLITS),
        meta["counts"]["train"]["advection_samples"],
        meta["counts"]["train"]["collision_samples"],
    )
    return meta
