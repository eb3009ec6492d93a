"""Datasets of the field in and out: ``python -m lagfluid.data.convert SRC DST [--to FORMAT]``.

The source's format is recognised from its folder:

* **lagfluid** (``task=generate``: ``metadata.json`` with ``format: lagfluid-dataset``), written as
  **LagrangeBench** (default for this source): ``DST/{train,valid,test}.h5``, one group per trajectory
  (``00000``, ...) with ``position`` (T, N, 3) float32 (fluid, then the wall particles: static, repeated per
  frame; the MPS dummy layers are left out, ``--dummies`` keeps them as walls) and ``particle_type`` (N,)
  (LagrangeBench's: 0 fluid, 1 solid wall), and ``DST/metadata.json`` with their keys (``dim``, ``dx``,
  ``dt``, ``write_every``, ``sequence_length_*``, ``num_trajs_*``, ``num_particles_max``, ``bounds``,
  ``periodic_boundary_conditions``, ``default_connectivity_radius``, ``vel_/acc_mean/std`` in their units,
  ...), so LagrangeBench trains on our data. Its ``bounds`` hold every particle, walls too (its cell list
  covers them); ``domain_bounds`` keeps the fluid's domain for the way back. A trajectory shorter than
  LagrangeBench's default windows, or particles its default neighbour search would misplace, get a warning.
* **LagrangeBench** (``metadata.json`` and ``train.h5``) and **DeepMind** ``learning_to_simulate``
  (``metadata.json`` and ``train.tfrecord``, read by the ``tfrecord`` package, no TensorFlow), written as a
  lagfluid **trajectory dataset** (default for these sources): ``scenes/scene_*.h5`` with the trajectory
  group of a scene file (fluid positions, velocities as backward differences of the frames, the first as a
  forward one; pressure 0; the static boundary stored once) and ``metadata.json`` with ``samples: false``.
  GNS trains on it (:class:`~lagfluid.data.datasets.TrajectoryWindows`); the stage samples FGN learns from
  come from an MPS run only, so the other datasets refuse it by name.

``DST`` is written as ``DST.part`` (marked as ours by a ``.lagfluid-convert`` file written first), then
renamed: an existing ``DST.part`` without that mark is a user's and is refused, never removed.

Only 3D data converts (lagfluid's models are 3D; a 2D set is refused naming its ``dim``), only walled
domains (a periodic one is refused: wrapped positions would read as jumps) and only a static boundary (a
moving wall, a rigid body are refused). LagrangeBench stores the body force's magnitude only: it is written
as gravity along -z. Particle types: LagrangeBench 0 fluid, 1-3 walls; DeepMind 3
(kinematic) boundary, every other type fluid; lagfluid 1 fluid, 2 wall, 3 dummy.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import socket
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from scipy.spatial import cKDTree

from lagfluid.data.layout import (
    DATASET_FORMAT,
    METADATA_FILE,
    SPLITS,
    load_metadata,
    require_keys,
    scene_path,
)
from lagfluid.data.store import TrajectoryWriter, read_trajectory
from lagfluid.errors import LagfluidError
from lagfluid.state import ParticleType

log = logging.getLogger(__name__)

LB_FLUID, LB_WALL = 0, 1
DEEPMIND_KINEMATIC = 3
FORMATS = ("lagfluid", "lagrangebench", "deepmind")
PART_MARKER = ".lagfluid-convert"  # written first into DST.part: only a folder holding it is ours to remove
# LagrangeBench's defaults (lagrangebench/defaults.py): model.input_seq_length, the last of
# train.pushforward.unrolls, eval.n_rollout_steps; its H5Dataset asserts a trajectory holds its windows
LB_INPUT_SEQ_LENGTH, LB_PUSHFORWARD_UNROLLS, LB_ROLLOUT_STEPS = 6, 3, 20


class ConversionError(LagfluidError):
    """A dataset that cannot be converted (its format, its dimension, a moving boundary); names the cause."""


@dataclass
class Trajectory:
    """One trajectory in memory: ``position`` (T, N, 3) float32 and ``fluid`` (N,) bool."""

    position: np.ndarray
    fluid: np.ndarray
    boundary_type: np.ndarray | None = None  # (N - Nf,) lagfluid types of the non-fluid rows, when known


@dataclass
class Dataset:
    """Trajectories per split and what every format needs to describe them.

    Attributes:
        splits: ``{split: [Trajectory, ...]}``.
        frame_dt: seconds between stored frames.
        write_every: solver steps between stored frames (1 when unknown).
        l0: particle spacing (m; estimated from the first frame when the source has none).
        radius: the connectivity radius of the source (m).
        bounds: (2, 3) domain box, or None.
        source: where the data came from (kept in the metadata).
        extra: the source's own metadata keys, kept.
    """

    splits: dict[str, list[Trajectory]]
    frame_dt: float
    write_every: int
    l0: float
    radius: float
    bounds: np.ndarray | None
    source: dict[str, Any] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)


def detect(src: Path) -> str:
    """The format of the dataset folder ``src`` (one of :data:`FORMATS`).

    Raises:
        ConversionError: none is recognised (the message says what each would hold).
    """
    meta = src / METADATA_FILE
    if meta.is_file():
        try:
            fmt = json.loads(meta.read_text()).get("format")
        except json.JSONDecodeError as err:
            raise ConversionError(f"{meta} is not JSON: {err}") from err
        if fmt == DATASET_FORMAT:
            return "lagfluid"
        if (src / "train.h5").is_file():
            return "lagrangebench"
        if (src / "train.tfrecord").is_file():
            return "deepmind"
    raise ConversionError(
        f"{src} is no dataset this reads: a lagfluid dataset (metadata.json, scenes/), LagrangeBench "
        "(metadata.json, train.h5) or DeepMind learning_to_simulate (metadata.json, train.tfrecord)"
    )


def _spacing(position: np.ndarray) -> float:
    """Median nearest-neighbour distance of the points (N, 3): the particle spacing of a frame."""
    if len(position) < 2:
        return float("nan")
    dist, _ = cKDTree(position).query(position, k=2)
    return float(np.median(dist[:, 1]))


def _check_3d(dim: int, src: Path) -> None:
    if dim != 3:
        raise ConversionError(
            f"{src} is {dim}D: lagfluid's simulators and training are 3D (positions (N, 3)); only 3D data "
            "converts"
        )


def _first(splits: dict[str, list[Trajectory]], src: Path) -> Trajectory:
    """The first trajectory of the first split that has one."""
    for trajs in splits.values():
        if trajs:
            return trajs[0]
    raise ConversionError(f"{src} holds no trajectory in {', '.join(SPLITS)}")


def _static_boundary(traj: Trajectory, where: str) -> np.ndarray:
    """The boundary rows of frame 0 (M, 3), checked to stay put in every frame."""
    boundary = traj.position[:, ~traj.fluid]
    if boundary.size and float(np.abs(boundary - boundary[:1]).max()) > 1e-6:
        raise ConversionError(f"{where}: its boundary particles move; lagfluid stores a static boundary only")
    return boundary[0] if len(boundary) else np.zeros((0, 3), np.float32)


# ------------------------------------------------------------------------------------------- readers
def read_lagfluid(src: Path, dummies: bool = False) -> Dataset:
    """A lagfluid dataset's trajectories: fluid frames, then its walls (and dummies if asked), per frame."""
    meta = load_metadata(src)  # names a missing l0, splits, ... in one line
    require_keys(meta, src / METADATA_FILE, ("steps", "sample_every"))
    splits: dict[str, list[Trajectory]] = {s: [] for s in SPLITS}
    for split in SPLITS:
        for name in meta["splits"].get(split, []):
            run = read_trajectory(src / name)
            # the uniformly spaced frames: a run whose steps are no multiple of sample_every also stored its
            # last step, closer to the one before
            uniform = int(meta["steps"]) // int(meta["sample_every"]) + 1
            run["position"] = run["position"][:uniform]
            keep = (run["boundary_type"] == ParticleType.WALL) | (
                dummies & (run["boundary_type"] == ParticleType.DUMMY)
            )
            walls = run["boundary_position"][keep]
            frames = run["position"].shape[0]
            position = np.concatenate(
                [run["position"], np.broadcast_to(walls, (frames, *walls.shape))], axis=1
            )
            fluid = np.arange(position.shape[1]) < run["position"].shape[1]
            splits[split].append(Trajectory(position.astype(np.float32), fluid, run["boundary_type"][keep]))
    bounds = np.asarray(meta["bounds"], dtype=np.float64).T if meta.get("bounds") else None
    return Dataset(
        splits,
        frame_dt=float(meta["dt"]) * int(meta["sample_every"]),
        write_every=int(meta["sample_every"]),
        l0=float(meta["l0"]),
        radius=float(meta["default_connectivity_radius"]),
        bounds=bounds,
        source={"format": "lagfluid", "path": str(src), "git_commit": meta.get("git_commit", "")},
        extra={
            "viscosity": _one(meta, "viscosity"),
            "gravity": _one(meta, "gravity"),
            "solver_dt": meta["dt"],
        },
    )


def _one(meta: dict[str, Any], key: str) -> Any:
    """A material value shared by every scene of a lagfluid dataset (None when they differ)."""
    values = {json.dumps(s.get(key)) for s in meta.get("scenes", [])}
    return json.loads(values.pop()) if len(values) == 1 else None


def read_lagrangebench(src: Path) -> Dataset:
    """A LagrangeBench dataset (their HDF5 layout and metadata keys)."""
    meta = json.loads((src / METADATA_FILE).read_text())
    require_keys(meta, src / METADATA_FILE, ("dt", "default_connectivity_radius"))
    _check_3d(int(meta.get("dim", 3)), src)
    periodic = [bool(p) for p in meta.get("periodic_boundary_conditions", [])]
    if any(periodic):
        raise ConversionError(
            f"{src} is periodic along {periodic} (periodic_boundary_conditions): lagfluid's domains are "
            "walled; its wrapped positions would read as jumps of a box length"
        )
    splits = {split: _read_lagrangebench_split(src / f"{split}.h5") for split in SPLITS}
    write_every = int(meta.get("write_every", 1))
    # a set written by write_lagrangebench keeps its fluid's domain apart from the bounds round every particle
    box = meta.get("domain_bounds") or meta.get("bounds")
    bounds = np.asarray(box, dtype=np.float64).T if box else None
    first = _first(splits, src)
    return Dataset(
        splits,
        frame_dt=float(meta["dt"]) * write_every,
        write_every=write_every,
        l0=float(meta.get("dx") or _spacing(first.position[0][first.fluid])),
        radius=float(meta["default_connectivity_radius"]),
        bounds=bounds,
        source={"format": "lagrangebench", "path": str(src), "case": meta.get("case", "")},
        extra={k: meta[k] for k in ("viscosity", "g_ext_magnitude", "case", "solver") if k in meta},
    )


def _read_lagrangebench_split(path: Path) -> list[Trajectory]:
    """The trajectories of one LagrangeBench split file (none when it is absent).

    Raises:
        ConversionError: the file is no readable HDF5 (corrupt, truncated), a group lacks ``position`` or
            ``particle_type``, or holds a particle type lagfluid does not convert.
    """
    if not path.is_file():
        return []
    trajs = []
    try:
        with h5py.File(path, "r") as f:
            for key in sorted(f):
                missing = [name for name in ("particle_type", "position") if name not in f[key]]
                if missing:
                    raise ConversionError(f"{path}:{key} lacks {missing} (LagrangeBench's trajectory arrays)")
                ptype = f[key]["particle_type"][()]
                unknown = sorted(set(np.unique(ptype).tolist()) - {LB_FLUID, LB_WALL})
                if unknown:
                    raise ConversionError(
                        f"{path}:{key} has particle types {unknown} (LagrangeBench: 2 moving wall, 3 rigid "
                        "body); lagfluid converts fluid (0) and static walls (1) only"
                    )
                trajs.append(Trajectory(f[key]["position"][()].astype(np.float32), ptype == LB_FLUID))
    except OSError as err:  # h5py's word for a truncated or corrupt file, at open or at a read
        raise ConversionError(f"cannot read {path} as HDF5 (corrupt or truncated?): {err}") from err
    return trajs


def read_deepmind(src: Path) -> Dataset:
    """A DeepMind ``learning_to_simulate`` dataset (``{split}.tfrecord``: SequenceExamples)."""
    try:
        from tfrecord.reader import sequence_loader
    except ImportError as err:
        raise ConversionError(
            "reading .tfrecord files needs the tfrecord package: pip install tfrecord"
        ) from err
    meta = json.loads((src / METADATA_FILE).read_text())
    require_keys(meta, src / METADATA_FILE, ("dt", "default_connectivity_radius"))
    dim = int(meta.get("dim", 2))
    _check_3d(dim, src)
    splits: dict[str, list[Trajectory]] = {s: [] for s in SPLITS}
    for split in SPLITS:
        path = src / f"{split}.tfrecord"
        if not path.is_file():
            continue
        records = sequence_loader(
            str(path), None, {"key": "int", "particle_type": "byte"}, {"position": "byte"}
        )
        for context, features in records:
            ptype = np.frombuffer(bytes(context["particle_type"]), dtype=np.int64)
            frames = [
                np.frombuffer(bytes(p), dtype=np.float32).reshape(-1, dim) for p in features["position"]
            ]
            position = np.stack(frames).astype(np.float32)
            splits[split].append(Trajectory(position, ptype != DEEPMIND_KINEMATIC))
    first = _first(splits, src)
    bounds = np.asarray(meta["bounds"], dtype=np.float64).T if "bounds" in meta else None
    return Dataset(
        splits,
        frame_dt=float(meta["dt"]),
        write_every=1,
        l0=_spacing(first.position[0][first.fluid]),
        radius=float(meta["default_connectivity_radius"]),
        bounds=bounds,
        source={"format": "deepmind", "path": str(src)},
    )


# ------------------------------------------------------------------------------------------- writers
def _differences(trajs: Sequence[Trajectory], frame_dt: float) -> dict[str, list[float]]:
    """LagrangeBench's ``vel_/acc_mean/std``: first and second differences of the fluid, per frame (m)."""
    vel = np.concatenate([np.diff(t.position[:, t.fluid], axis=0).reshape(-1, 3) for t in trajs])
    acc = np.concatenate([np.diff(t.position[:, t.fluid], n=2, axis=0).reshape(-1, 3) for t in trajs])
    return {
        "vel_mean": vel.mean(0).tolist(),
        "vel_std": vel.std(0).tolist(),
        "acc_mean": acc.mean(0).tolist(),
        "acc_std": acc.std(0).tolist(),
    }


def write_lagrangebench(data: Dataset, dst: Path) -> Path:
    """``dst/{train,valid,test}.h5`` and ``dst/metadata.json`` in LagrangeBench's layout; returns ``dst``."""
    dst.mkdir(parents=True, exist_ok=True)
    for split, trajs in data.splits.items():
        tmp = dst / f"{split}.h5.part"
        with h5py.File(tmp, "w") as f:
            for k, t in enumerate(trajs):
                g = f.create_group(f"{k:05d}")
                g.create_dataset("particle_type", data=np.where(t.fluid, LB_FLUID, LB_WALL).astype(np.int64))
                g.create_dataset("position", data=t.position, dtype=np.float32, compression="gzip")
        os.replace(tmp, dst / f"{split}.h5")
    train, test = data.splits["train"], data.splits["test"] or data.splits["valid"]
    # LagrangeBench builds its cell list over the bounds: they hold every particle (the walls lie outside the
    # fluid's domain), else its neighbour list misses their pairs; the domain is kept apart for the way back
    containing = _containing_bounds(data)
    domain = data.bounds if data.bounds is not None else containing
    meta = {
        "case": "LAGFLUID",
        "solver": "MPS" if data.source.get("format") == "lagfluid" else str(data.extra.get("solver", "")),
        "dim": 3,
        "dx": data.l0,
        "dt": data.frame_dt / data.write_every,
        "write_every": data.write_every,
        "t_end": data.frame_dt * (train[0].position.shape[0] - 1) if train else 0.0,
        "viscosity": data.extra.get("viscosity"),
        "g_ext_magnitude": float(np.linalg.norm(data.extra["gravity"]))
        if data.extra.get("gravity")
        else None,
        "sequence_length_train": int(train[0].position.shape[0] - 1) if train else 0,
        "num_trajs_train": len(train),
        "sequence_length_test": int(test[0].position.shape[0] - 1) if test else 0,
        "num_trajs_test": len(data.splits["test"]),
        "num_particles_max": max(t.position.shape[1] for trajs in data.splits.values() for t in trajs),
        "periodic_boundary_conditions": [False, False, False],
        "bounds": containing.T.tolist(),
        "domain_bounds": domain.T.tolist(),
        "default_connectivity_radius": data.radius,
        **_differences(train, data.frame_dt),
        "source": data.source,
    }
    _write_json(dst / METADATA_FILE, meta)
    return dst


def _bounds_of(data: Dataset) -> np.ndarray:
    """(2, 3) lowest and highest coordinates of every particle (fluid and walls) in every frame."""
    trajs = [t.position.reshape(-1, 3) for split in data.splits.values() for t in split if t.position.size]
    lo = np.min([p.min(0) for p in trajs], axis=0)
    hi = np.max([p.max(0) for p in trajs], axis=0)
    return np.stack([lo, hi]).astype(np.float64)


def _containing_bounds(data: Dataset) -> np.ndarray:
    """(2, 3) box holding the source's domain (when it has one) and every particle of every frame."""
    extent = _bounds_of(data)
    if data.bounds is None:
        return extent
    return np.stack([np.minimum(extent[0], data.bounds[0]), np.maximum(extent[1], data.bounds[1])])


def lagrangebench_warnings(data: Dataset, dst: Path) -> list[str]:
    """What would stop LagrangeBench's defaults on ``data`` written to ``dst``: a line each (none: nothing).

    * Trajectories shorter than its windows: it trains on ``input_seq_length + 1 + pushforward`` frames and
      validates on ``input_seq_length + n_rollout_steps``; its ``H5Dataset`` asserts a trajectory holds one.
      A warning, not a refusal: those are settings there (``input_seq_length`` down to 2).
    * Particles its default neighbour search files in a wrong cell: LagrangeBench hands jax-md's cell list the
      box size ``hi - lo`` only, and jax-md bins a coordinate ``x`` into cell ``int(x / cell)`` of
      ``[0, hi - lo)`` (cells of at least the connectivity radius, the index truncated toward 0); a coordinate
      at or below ``-cell`` or at or beyond ``hi - lo`` lands in a wrong cell and its pairs are missed.
    """
    lines = []
    need = {"train": LB_INPUT_SEQ_LENGTH + 1 + LB_PUSHFORWARD_UNROLLS}
    need["valid"] = need["test"] = LB_INPUT_SEQ_LENGTH + LB_ROLLOUT_STEPS
    frames = {s: min(t.position.shape[0] for t in trajs) for s, trajs in data.splits.items() if trajs}
    short = {s: n for s, n in frames.items() if n < need[s]}
    if short:
        lines.append(
            f"{dst}: trajectories of {', '.join(f'{n} frames ({s})' for s, n in short.items())} are shorter "
            f"than LagrangeBench's default windows: train {need['train']} frames (input_seq_length "
            f"{LB_INPUT_SEQ_LENGTH} + 1 target + {LB_PUSHFORWARD_UNROLLS} pushforward unrolls), valid/test "
            f"{need['valid']} (input_seq_length + eval.n_rollout_steps {LB_ROLLOUT_STEPS}); lower those "
            "there or store more frames (data.steps)"
        )
    lo, hi = _containing_bounds(data)
    extent = _bounds_of(data)
    box = hi - lo
    cell = box / np.maximum(np.floor(box / data.radius), 1.0)
    axes = ["xyz"[a] for a in range(3) if extent[0, a] <= -cell[a] or extent[1, a] >= box[a]]
    if axes:
        lines.append(
            f"{dst}: particles lie outside [0, hi - lo) along {', '.join(axes)} (coordinates "
            f"{extent[0].round(6).tolist()} to {extent[1].round(6).tolist()}), the region LagrangeBench's "
            "default neighbour search (jax-md's cell list) bins, and it would miss their pairs: train there "
            "with neighbors.backend=matscipy"
        )
    return lines


def write_lagfluid(data: Dataset, dst: Path) -> Path:
    """A lagfluid trajectory dataset (``scenes/``, ``metadata.json`` with ``samples: false``) in ``dst``."""
    (dst / "scenes").mkdir(parents=True, exist_ok=True)
    bounds = data.bounds if data.bounds is not None else _bounds_of(data)
    solver_dt = data.frame_dt / data.write_every
    gravity = data.extra.get("gravity") or [0.0, 0.0, -float(data.extra.get("g_ext_magnitude") or 0.0)]
    viscosity = float(data.extra.get("viscosity") or 0.0)
    scenes, splits = [], {s: [] for s in SPLITS}
    index = 0
    for split, trajs in data.splits.items():
        for t in trajs:
            where = f"{data.source.get('path')} {split} trajectory {len(splits[split])}"
            fluid = t.position[:, t.fluid]
            boundary = _static_boundary(t, where)
            btype = (
                t.boundary_type if t.boundary_type is not None else np.full(len(boundary), ParticleType.WALL)
            )
            velocity = np.empty_like(fluid)
            velocity[1:] = np.diff(fluid, axis=0) / data.frame_dt
            velocity[0] = velocity[1] if len(fluid) > 1 else 0.0
            frames = fluid.shape[0]
            attrs = {
                "dt": solver_dt,
                "sample_every": data.write_every,
                "steps": (frames - 1) * data.write_every,
                "l0": data.l0,
                "gravity": [float(g) for g in gravity],
                "viscosity": viscosity,
                "density": 1000.0,
                "dim": 3,
                "scene_index": index,
                "scene": f"converted:{data.source.get('format')}",
                "bounds": bounds,
                "source": json.dumps(data.source),
            }
            path = scene_path(dst, index)
            with TrajectoryWriter(path, fluid.shape[1], boundary, btype.astype(np.int8), attrs) as w:
                for k in range(frames):
                    w.append(k * data.frame_dt, fluid[k], velocity[k], np.zeros(fluid.shape[1], np.float32))
            name = str(path.relative_to(dst))
            splits[split].append(name)
            scenes.append(
                {
                    "index": index,
                    "file": name,
                    "split": split,
                    "gravity": [float(g) for g in gravity],
                    "viscosity": viscosity,
                    "n_fluid": int(fluid.shape[1]),
                    "n_boundary": len(boundary),
                    "frames": int(frames),
                    "samples": 0,
                }
            )
            index += 1
    train = data.splits["train"]
    meta = {
        "format": DATASET_FORMAT,
        "format_version": 1,
        "samples": False,
        "name": f"converted from {data.source.get('format')}",
        "num_scenes": index,
        "steps": scenes[0]["frames"] * data.write_every - data.write_every if scenes else 0,
        "sample_every": data.write_every,
        "write_every": data.write_every,
        "sequence_length": scenes[0]["frames"] if scenes else 0,
        "dt": solver_dt,
        "dim": 3,
        "l0": data.l0,
        "bounds": bounds.T.tolist(),
        "periodic_boundary_conditions": [False, False, False],
        "default_connectivity_radius": data.radius,
        **_differences(train, data.frame_dt),
        "splits": splits,
        "counts": {s: len(v) for s, v in splits.items()},
        "scenes": scenes,
        "source": data.source,
    }
    _write_json(dst / METADATA_FILE, meta)
    return dst


def _write_json(path: Path, value: Any) -> None:
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(json.dumps(value, indent=1))
    os.replace(tmp, path)


READERS = {"lagfluid": read_lagfluid, "lagrangebench": read_lagrangebench, "deepmind": read_deepmind}
WRITERS = {"lagfluid": write_lagfluid, "lagrangebench": write_lagrangebench}


def convert(src: Path, dst: Path, to: str | None = None, dummies: bool = False) -> Path:
    """Convert the dataset folder ``src`` into ``dst`` (a new folder); returns ``dst``.

    Args:
        src: a lagfluid, LagrangeBench or DeepMind dataset folder.
        dst: the output folder (must not exist yet: nothing of a user's is overwritten).
        to: ``lagfluid`` or ``lagrangebench``; default: LagrangeBench for a lagfluid source, else lagfluid.
        dummies: lagfluid source: keep the dummy layers (as walls) besides the wall particles.

    Raises:
        ConversionError: an unknown source, an existing ``dst``, a 2D set or a moving boundary.
    """
    fmt = detect(src)
    to = to or ("lagrangebench" if fmt == "lagfluid" else "lagfluid")
    if to not in WRITERS:
        raise ConversionError(f"--to must be one of {', '.join(WRITERS)}, got {to!r}")
    if dst.exists():
        raise ConversionError(f"{dst} exists: give a new folder (nothing is overwritten)")
    data = read_lagfluid(src, dummies) if fmt == "lagfluid" else READERS[fmt](src)
    part = dst.with_name(dst.name + ".part")
    _claim_part(part)
    try:
        WRITERS[to](data, part)
        (part / PART_MARKER).unlink()
        os.replace(part, dst)  # a finished conversion appears whole
    except BaseException:
        shutil.rmtree(part, ignore_errors=True)  # made by this run (_claim_part): nothing of a user's
        raise
    if to == "lagrangebench":
        for line in lagrangebench_warnings(data, dst):
            log.warning(line)
    return dst


def _claim_part(part: Path) -> None:
    """Create ``part`` (``DST.part``) for this run, marked as ours; an unfinished conversion's is replaced.

    Raises:
        ConversionError: ``part`` exists without our marker (a user's: nothing of it is removed), or a
            conversion still running on this machine is writing it.
    """
    marker = part / PART_MARKER
    if part.exists() or part.is_symlink():
        if part.is_symlink() or not marker.is_file():
            raise ConversionError(
                f"{part} exists and was not made by lagfluid.data.convert (no {PART_MARKER} in it): move it "
                "away or give another DST (nothing of it is removed)"
            )
        owner = _marker_owner(marker)
        if owner is not None:
            raise ConversionError(f"{part} is being written by another conversion ({owner}): wait for it")
        log.info("removing %s: an unfinished conversion left it", part)
        shutil.rmtree(part)
    try:
        part.mkdir(parents=True)
    except FileExistsError as err:  # another conversion made it just now
        raise ConversionError(f"{part} was just made by another process: give another DST") from err
    marker.write_text(json.dumps({"pid": os.getpid(), "host": socket.gethostname()}))


def _marker_owner(marker: Path) -> str | None:
    """The live conversion that wrote ``marker`` (``"process N on HOST"``), or None if it has ended."""
    try:
        owner = json.loads(marker.read_text())
        pid, host = int(owner["pid"]), str(owner["host"])
    except (OSError, ValueError, KeyError, TypeError):
        return None  # a marker cut short by a crash: its run is over
    if host != socket.gethostname():
        return f"process {pid} on {host}"  # cannot tell from here: left alone
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return None
    except PermissionError:
        pass  # alive, another user's
    return f"process {pid} on {host}"


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m lagfluid.data.convert SRC DST [--to FORMAT] [--dummies]``."""
    parser = argparse.ArgumentParser(
        prog="python -m lagfluid.data.convert", description=__doc__.split("\n")[0]
    )
    parser.add_argument("src", type=Path)
    parser.add_argument("dst", type=Path)
    parser.add_argument("--to", choices=list(WRITERS), help="default: lagrangebench for a lagfluid source")
    parser.add_argument("--dummies", action="store_true", help="lagfluid source: keep the dummy layers")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        out = convert(args.src, args.dst, args.to, args.dummies)
    except LagfluidError as err:
        sys.stderr.write(f"lagfluid.data.convert: {err}\n")
        return 1
    log.info("wrote %s", out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
