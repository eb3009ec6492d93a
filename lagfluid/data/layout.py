"""The on-disk layout of a generated dataset: scene files, splits and ``metadata.json`` names.

Formats only (``data/`` holds formats, tasks live above it: ``docs/architecture.md#layers``):
:mod:`lagfluid.tasks.generate` writes this layout, :mod:`lagfluid.data.datasets` reads it. ::

    DIR/                                 data.out_dir (default data/<profile>)
      scenes/scene_00007.h5              scene k (layout below)
      metadata.json                      once every scene is there: splits, statistics, provenance

Layout of a scene file (``format="lagfluid"``, ``format_version=1``; ``Nf`` fluid and ``Nb`` boundary
particles, ``T`` trajectory frames, ``S = ceil(steps / k)`` samples for ``k = sample_every``)::

    /00000                  the trajectory, exactly as lagfluid.data.store writes rollouts: frames at
                            steps 0, k, 2k, ... and the last step (T = S + 1)
        time (T,) f8, position (T, Nf, 3) f4, velocity (T, Nf, 3) f4, pressure (T, Nf) f4 (clamped, >= 0)
        boundary_position (Nb, 3) f4, boundary_type (Nb,) i1     static, stored once (2 wall, 3 dummy)
        attrs: dt, l0, gravity (3,), viscosity, density, dim, seed, scene_index, scene, scene_options,
               bounds (2, 3), n0, n0_lap, lambda, fingerprint, steps, sample_every, n_fluid, config,
               version, git_commit, created, complete, wall_time_s, step_time_median_s, ...
    /samples                one-step training samples (paper A.2) at solver steps n = 0, k, 2k, ... < steps
        step (S,) i8                 solver step n of sample s (= s k)
        frame (S,) i8                trajectory frame holding x^n and v^n (= s)
        advection/acceleration (S, Nf, 3) f4
                                     label a = (v* - v^n) / dt = nu lap(v^n) + g; the inputs are
                                     /00000/position[frame], velocity[frame], the boundary, g and nu
        pressure/position (S, Nf, 3) f4   x**: fluid positions after advection and collision
        pressure/velocity (S, Nf, 3) f4   v**: the pressure stage's input velocities
        pressure/offsets (S + 1,) i8      sample s owns rows offsets[s]:offsets[s + 1] of the ragged arrays
        pressure/index (M,) i4            particle row of each PPE unknown: < Nf fluid, else boundary
                                          row index - Nf; the unknowns are the non-dummy particles that
                                          are not on the free surface (n >= beta n0)
        pressure/number_density (M,) f4   n at x** (radius re_density, all particle types counted)
        pressure/pressure (M,) f4         label: the PPE solution (before the p >= 0 clamp)
        collision/position (C, Nc, 3) f4  x* of the collision-only particle system (input)
        collision/velocity (C, Nc, 3) f4  v* (input)
        collision/delta_velocity (C, Nc, 3) f4   label v** - v* given by the exact CollisionRule
        collision/system (C,) i8, collision/step (C,) i8   which system, which of its steps
        collision/boundary_position (Ncb, 3) f4, collision/boundary_type (Ncb,) i1   its static floor
        next/position (S', K, Nf, 3) f4   optional (data.next_steps = K > 0): the fluid positions of the K
                                          solver steps after sample s's step (n + 1 .. n + K), for models
                                          that step by the solver's dt and train on K-step windows (CConv:
                                          K = 2); S' <= S, the samples whose K steps the run reached
        attrs: format_version (samples layout), count, dt, complete; collision/: restitution,
               re_collision, num_systems, steps

The samples satisfy the update of :mod:`lagfluid.physics.scheme` exactly (same float32 operations):
``v* = v^n + a dt``, ``x* = x^n + v* dt``, ``x** = x* + (v** - v*) dt``. So the in-scene collision stage's
samples ``(x*, v*) -> v**`` are there too, without storing them twice.

The collision system (paper A.2: "another particle system that is updated only based on elastic
collision rule") is, per scene, ``collision.num_systems`` jittered fluid blocks above a wall floor with
random velocities, each advanced ``collision.steps`` times by a split-step simulator whose only stage is
:class:`~lagfluid.physics.mps.CollisionRule` (``x* = x + v dt``, then the rule); every step is a sample.

``metadata.json`` (LagrangeBench-style keys plus ours): ``bounds`` ([[lo, hi]] per axis, m, union over the
scenes), ``dt``, ``dim``, ``default_connectivity_radius`` (m: ``re_laplacian * l0`` = 3.1 l0, the largest
radius of the MPS operators), ``periodic_boundary_conditions``, ``sequence_length`` (frames per scene),
``write_every``, ``vel_mean``/``vel_std``/``acc_mean``/``acc_std`` (LagrangeBench units: first and second
differences of positions between uniformly spaced frames, m per frame), ``statistics`` (per feature:
mean, std, min, max, count), ``splits`` (file lists), ``counts``, ``scenes``, the solver, materials and
collision settings, ``version``, ``git_commit``, ``generation_time_s``. Every statistic is computed from
the **train** split only; they describe the data, a network's normalisation lives in its checkpoint
(``docs/architecture.md#conventions``, convention 6).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch

from lagfluid.data.store import TrajectoryFileError, open_lagfluid_file
from lagfluid.errors import LagfluidError

GROUP = "00000"
"""Trajectory group of a scene file (the one group a rollout file has)."""
SAMPLES_FORMAT_VERSION = 1
"""Version of the ``/samples`` layout (root attribute ``format_version`` is the trajectory format's)."""
METADATA_FILE = "metadata.json"
DATASET_FORMAT = "lagfluid-dataset"
SCENE_DIR = "scenes"
SPLITS = ("train", "valid", "test")
_COMPRESS = {"compression": "gzip", "compression_opts": 4, "shuffle": True}


def require_keys(meta: Mapping[str, Any], path: Path, keys: Iterable[str]) -> None:
    """Raise :class:`TrajectoryFileError` naming ``path`` and the first of ``keys`` that ``meta`` lacks."""
    for key in keys:
        if key not in meta:
            raise TrajectoryFileError(f"{path} lacks the key '{key}'")


def scene_path(out_dir: str | os.PathLike, index: int) -> Path:
    """``out_dir/scenes/scene_00007.h5`` for ``index = 7``."""
    return Path(out_dir) / SCENE_DIR / f"scene_{index:05d}.h5"


def split_counts(num_scenes: int, fractions: dict[str, float]) -> dict[str, int]:
    """Scenes per split: ``round(f n)`` valid and test scenes for fractions ``f``, the rest train.

    Valid and test get at least one scene each when ``n >= 3`` and their fraction is > 0.

    Raises:
        LagfluidError: nothing would be left for training.
    """
    total = sum(fractions.values())
    counts = {}
    for split in ("valid", "test"):
        f = fractions.get(split, 0.0) / total
        n = round(f * num_scenes)
        counts[split] = max(n, 1) if f > 0 and num_scenes >= 3 else n
    counts["train"] = num_scenes - counts["valid"] - counts["test"]
    if counts["train"] < 1:
        raise LagfluidError(f"data.splits {fractions} leave no training scene out of {num_scenes}")
    return {s: counts[s] for s in SPLITS}


def split_of(num_scenes: int, fractions: dict[str, float]) -> list[str]:
    """Split of every scene index: train first, then valid, then test (deterministic by index)."""
    counts = split_counts(num_scenes, fractions)
    return [s for s in SPLITS for _ in range(counts[s])]


METADATA_KEYS = ("dt", "l0", "default_connectivity_radius", "splits", "scenes")
"""The keys of ``metadata.json`` the datasets and the training read (:func:`load_metadata` checks them)."""


def load_metadata(root: str | os.PathLike) -> dict[str, Any]:
    """``root/metadata.json`` of a generated dataset.

    Raises:
        TrajectoryFileError: the directory or its metadata is missing, unreadable, of another format, or lacks
            a key of :data:`METADATA_KEYS` or a split of ``splits`` (the message names the file and the key).
    """
    root = Path(root)
    if not root.is_dir():
        raise TrajectoryFileError(f"dataset directory not found: {root}")
    path = root / METADATA_FILE
    if not path.is_file():
        raise TrajectoryFileError(
            f"{path} not found: not a generated dataset, or its generation is unfinished "
            "(rerun python -m lagfluid.run task=generate with the same data settings)"
        )
    try:
        meta = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise TrajectoryFileError(f"cannot read {path}: {err}") from err
    if meta.get("format") != DATASET_FORMAT or meta.get("format_version") != 1:
        raise TrajectoryFileError(
            f"{path} is not lagfluid dataset metadata version 1 "
            f"(format={meta.get('format')!r}, format_version={meta.get('format_version')!r})"
        )
    require_keys(meta, path, METADATA_KEYS)  # a hand-edited file: one line here, not a KeyError later
    splits = meta["splits"]
    missing = [s for s in SPLITS if s not in splits] if isinstance(splits, dict) else ["train"]
    if missing:
        raise TrajectoryFileError(f"{path} lacks the key 'splits.{missing[0]}' (its list of scene files)")
    return meta


# ------------------------------------------------------------------------------------------ scene files
@dataclass(frozen=True)
class SceneInfo:
    """What a finished scene file holds (read without loading its arrays).

    Attributes:
        path: the file.
        attrs: trajectory-group attributes.
        n_fluid: Nf.
        n_boundary: Nb.
        frames: T.
        samples: S (advection and pressure samples).
        collision_samples: C.
        complete: the trajectory and the samples were finished.
    """

    path: Path
    attrs: dict[str, Any]
    n_fluid: int
    n_boundary: int
    frames: int
    samples: int
    collision_samples: int
    complete: bool


_REQUIRED = {
    GROUP: ("time", "position", "velocity", "pressure", "boundary_position", "boundary_type"),
    "samples": ("step", "frame"),
    "samples/advection": ("acceleration",),
    "samples/pressure": ("position", "velocity", "offsets", "index", "number_density", "pressure"),
    "samples/collision": (
        "position",
        "velocity",
        "delta_velocity",
        "system",
        "step",
        "boundary_position",
        "boundary_type",
    ),
}


def check_scene_file(f: h5py.File, path: Path, samples: bool = True) -> None:
    """Raise :class:`TrajectoryFileError` unless ``f`` (format already checked) has a scene file's layout.

    ``samples=False``: a trajectory dataset's scene (``lagfluid.data.convert``): the trajectory group only.
    """
    if not samples:
        for name in _REQUIRED[GROUP]:
            if GROUP not in f or name not in f[GROUP]:
                raise TrajectoryFileError(f"{path} lacks the array '/{GROUP}/{name}'")
        return
    for group, names in _REQUIRED.items():
        if group not in f:
            raise TrajectoryFileError(f"{path} lacks the group '/{group}': not a scene file of task=generate")
        for name in names:
            if name not in f[group]:
                raise TrajectoryFileError(f"{path} lacks the array '/{group}/{name}'")
    version = int(f["samples"].attrs.get("format_version", -1))
    if version != SAMPLES_FORMAT_VERSION:
        raise TrajectoryFileError(
            f"{path} has samples format_version {version}; this lagfluid reads {SAMPLES_FORMAT_VERSION}"
        )
    g, s = f[GROUP], f["samples"]
    t, nf = g["position"].shape[:2]
    n = s["step"].shape[0]
    shapes_ok = (
        g["velocity"].shape == (t, nf, 3)
        and g["pressure"].shape == (t, nf)
        and s["frame"].shape == (n,)
        and s["advection/acceleration"].shape == (n, nf, 3)
        and s["pressure/position"].shape == (n, nf, 3)
        and s["pressure/velocity"].shape == (n, nf, 3)
        and s["pressure/offsets"].shape == (n + 1,)
        and (n == 0 or int(s["frame"][-1]) < t)
    )
    if not shapes_ok:
        raise TrajectoryFileError(f"{path}: arrays disagree in shape (T={t}, Nf={nf}, S={n})")


def read_scene_info(path: str | os.PathLike, samples: bool = True) -> SceneInfo:
    """Open a scene file, check its layout and return its sizes and attributes.

    ``samples=False``: the scene of a trajectory dataset (no ``/samples``: 0 samples, complete with its
    trajectory).

    Raises:
        TrajectoryFileError: missing, unreadable, another format or version, a missing group or array.
    """
    path = Path(path)
    with open_lagfluid_file(path, "scene file") as f:
        check_scene_file(f, path, samples)
        g = f[GROUP]
        s = f["samples"] if samples else None
        return SceneInfo(
            path=path,
            attrs=dict(g.attrs),
            n_fluid=int(g["position"].shape[1]),
            n_boundary=int(g["boundary_position"].shape[0]),
            frames=int(g["position"].shape[0]),
            samples=int(s["step"].shape[0]) if s is not None else 0,
            collision_samples=int(s["collision/position"].shape[0]) if s is not None else 0,
            complete=bool(g.attrs.get("complete", False))
            and (s is None or bool(s.attrs.get("complete", False))),
        )


# ------------------------------------------------------------------------------------------ samples
def appendable(
    group: h5py.Group, name: str, shape: tuple[int, ...], dtype: str, chunk: int = 0
) -> h5py.Dataset:
    """A dataset growing along axis 0: one sample per chunk for per-particle arrays, else ``chunk`` rows."""
    chunks = (1, *[max(s, 1) for s in shape]) if shape else (chunk or 4096,)
    return group.create_dataset(
        name, (0, *shape), maxshape=(None, *shape), dtype=dtype, chunks=chunks, **_COMPRESS
    )


def append_rows(ds: h5py.Dataset, values: np.ndarray) -> None:
    """Append ``values`` (n, ...) to ``ds`` along axis 0."""
    n = ds.shape[0]
    ds.resize(n + values.shape[0], axis=0)
    ds[n:] = values


class SampleWriter:
    """Appends the one-step samples of a scene to ``/samples`` of the open scene file.

    Args:
        group: the file's ``/samples`` group.
        n_fluid: Nf.
        dt: the solver's time step, s.
        next_steps: K > 0 also stores each sample's next K solver steps' fluid positions (``next/``).
    """

    def __init__(self, group: h5py.Group, n_fluid: int, dt: float, next_steps: int = 0) -> None:
        self.group, self.n_fluid, self.next_steps = group, n_fluid, int(next_steps)
        self._pending: dict[int, list[np.ndarray]] = {}  # sample step -> positions of its next steps so far
        if self.next_steps:
            nxt = group.create_group("next")
            nxt.attrs["steps"] = self.next_steps
            self.next_pos = appendable(nxt, "position", (self.next_steps, n_fluid, 3), "f4")
        group.attrs.update(format_version=SAMPLES_FORMAT_VERSION, dt=dt, complete=False, count=0)
        self.step = appendable(group, "step", (), "i8", 1024)
        self.frame = appendable(group, "frame", (), "i8", 1024)
        adv, prs = group.create_group("advection"), group.create_group("pressure")
        self.acc = appendable(adv, "acceleration", (n_fluid, 3), "f4")
        self.p_pos = appendable(prs, "position", (n_fluid, 3), "f4")
        self.p_vel = appendable(prs, "velocity", (n_fluid, 3), "f4")
        self.offsets = prs.create_dataset(
            "offsets", data=np.zeros(1, np.int64), maxshape=(None,), chunks=(1024,)
        )
        self.index = appendable(prs, "index", (), "i4", 1 << 16)
        self.density = appendable(prs, "number_density", (), "f4", 1 << 16)
        self.pressure = appendable(prs, "pressure", (), "f4", 1 << 16)
        self.count = 0

    def after_step(self, step: int, fluid_pos: torch.Tensor) -> None:
        """Keep ``fluid_pos`` (Nf, 3) of solver step ``step`` for the samples it is one of the next steps of.

        Call after every step, in order; a sample's row is written when its last next step arrives (the rows
        stay in sample order). Does nothing without ``next_steps``.
        """
        for start in list(self._pending):
            if 0 < step - start <= self.next_steps:
                self._pending[start].append(fluid_pos.detach().cpu().numpy().astype(np.float32, copy=False))
            if len(self._pending[start]) == self.next_steps:
                append_rows(self.next_pos, np.stack(self._pending.pop(start))[None])

    def append(self, step: int, fields: Any) -> None:
        """Store the sample of solver step ``step`` from that step's recorded intermediates.

        Args:
            step: the solver step ``n`` the sample starts at.
            fields: the split step's ``SplitStepFields`` (``advection_acceleration``, ``pos_collided``,
                ``vel_collided`` (Nf, 3); ``ppe_solved``, ``number_density``, ``pressure_unclamped`` (N,)).
        """

        def np32(values: torch.Tensor) -> np.ndarray:
            return values.detach().cpu().numpy().astype(np.float32, copy=False)

        solved = torch.nonzero(fields.ppe_solved).flatten().cpu().numpy()
        append_rows(self.step, np.array([step], np.int64))
        append_rows(self.frame, np.array([self.count], np.int64))
        append_rows(self.acc, np32(fields.advection_acceleration)[None])
        append_rows(self.p_pos, np32(fields.pos_collided)[None])
        append_rows(self.p_vel, np32(fields.vel_collided)[None])
        append_rows(self.index, solved.astype(np.int32))
        append_rows(self.density, np32(fields.number_density)[solved])
        append_rows(self.pressure, np32(fields.pressure_unclamped)[solved])
        append_rows(self.offsets, np.array([self.offsets[-1] + len(solved)], np.int64))
        if self.next_steps:
            self._pending[step] = []
        self.count += 1
        self.group.attrs["count"] = self.count
        self.group.file.flush()
