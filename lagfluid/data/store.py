"""HDF5 trajectory files in the lagfluid format (LagrangeBench-like layout).

Layout of ``rollout.h5`` (``format="lagfluid"``, ``format_version=1`` on the root)::

    /00000                      one group per trajectory
        time               (T,)       float64  seconds; frame 0 is the initial state
        position           (T, Nf, 3) float32  fluid particles; these and boundary_position are float64
        velocity           (T, Nf, 3) float32  for a float64 run (stored as computed; readers take either)
        pressure           (T, Nf)    float32
        boundary_position  (Nb, 3)    float32  static boundary particles, stored once
        boundary_type      (Nb,)      int8     2 wall, 3 dummy
        attrs: dt, write_every, l0, gravity, viscosity, density, model, scene, config (YAML), version,
               git_commit, complete, stop_reason, ...

Frames are appended to ``<name>.part`` and flushed one by one, so an interrupted run leaves a readable
file; :meth:`TrajectoryWriter.close` renames it to the final name (atomic on POSIX).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from lagfluid.errors import LagfluidError

FORMAT = "lagfluid"
FORMAT_VERSION = 1


class TrajectoryFileError(LagfluidError, OSError):
    """A trajectory file is missing, corrupt or not in the lagfluid format."""


def _attr_value(value: Any) -> Any:
    """HDF5 attributes take numbers, strings and arrays; anything else is stored as JSON text."""
    if value is None:
        return "null"
    if isinstance(value, (str, bool, int, float, np.integer, np.floating, np.ndarray)):
        return value
    if isinstance(value, (list, tuple)) and all(isinstance(v, (int, float)) for v in value):
        return np.asarray(value, dtype=np.float64)
    return json.dumps(value)


def stored_dtype(state: Any) -> np.dtype:
    """How the frames of a run in ``state``'s dtype are stored: float64 for float64, else float32."""
    return np.dtype(np.float64 if state.pos.element_size() == 8 else np.float32)


class TrajectoryWriter:
    """Append frames of one trajectory to an HDF5 file.

    Args:
        path: final file path (``rollout.h5``); frames go to ``path + ".part"`` until :meth:`close`.
        n_fluid: number of fluid particles Nf.
        boundary_position: (Nb, 3) static boundary positions.
        boundary_type: (Nb,) boundary particle types.
        attrs: group attributes (physical and solver parameters, provenance).
        group: trajectory group name.
        dtype: how positions, velocities, pressures and boundary positions are stored: float32, or float64
            for a float64 run (float32 would round a grid 1e6 m from the origin to 6 cm steps).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        n_fluid: int,
        boundary_position: np.ndarray,
        boundary_type: np.ndarray,
        attrs: dict[str, Any],
        group: str = "00000",
        dtype: Any = np.float32,
    ) -> None:
        dtype = np.dtype(dtype)
        if dtype not in (np.float32, np.float64):
            raise ValueError(f"trajectories are stored as float32 or float64, not {dtype}")
        self.path = Path(path)
        self.tmp_path = self.path.with_name(self.path.name + ".part")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # No HDF5 file lock: a user (or a crash-recovery read) may open the .part file while a long run is
        # still writing it; frames are flushed one by one, so what they see is consistent up to the last one.
        self.file = h5py.File(self.tmp_path, "w", locking=False)
        self.file.attrs["format"] = FORMAT
        self.file.attrs["format_version"] = FORMAT_VERSION
        self.group = self.file.create_group(group)
        for key, value in attrs.items():
            self.group.attrs[key] = _attr_value(value)
        self.group.attrs["complete"] = False
        # fletcher32: a per-chunk checksum, so a damaged chunk is an error on read, never silent numbers
        compress = {"compression": "gzip", "compression_opts": 4, "shuffle": True, "fletcher32": True}
        # One frame per chunk: appends touch exactly one chunk, and readers can load any frame alone.
        nf = max(int(n_fluid), 1)
        self.time = self.group.create_dataset("time", (0,), maxshape=(None,), dtype="f8", chunks=(1024,))
        self.frame_arrays = {}
        for name, shape in (("position", (n_fluid, 3)), ("velocity", (n_fluid, 3)), ("pressure", (n_fluid,))):
            self.frame_arrays[name] = self.group.create_dataset(
                name,
                (0, *shape),
                maxshape=(None, *shape),
                dtype=dtype,
                chunks=(1, nf, *shape[1:]),
                **compress,
            )
        self.group.create_dataset("boundary_position", data=np.asarray(boundary_position, dtype), **compress)
        self.group.create_dataset("boundary_type", data=np.asarray(boundary_type, np.int8))
        self.frames = 0

    @classmethod
    def reopen(cls, path: str | os.PathLike, frames: int, group: str = "00000") -> TrajectoryWriter:
        """Continue the partial trajectory ``path + ".part"`` after its first ``frames`` frames.

        Frames stored after them (written after the resume checkpoint) are dropped.

        Raises:
            TrajectoryFileError: the file is unreadable (killed mid-write) or holds fewer frames.
        """
        self = cls.__new__(cls)
        self.path = Path(path)
        self.tmp_path = self.path.with_name(self.path.name + ".part")
        try:
            self.file = h5py.File(self.tmp_path, "r+", locking=False)
            self.group = self.file[group]
            self.time = self.group["time"]
            self.frame_arrays = {name: self.group[name] for name in ("position", "velocity", "pressure")}
        except (OSError, KeyError) as err:
            if getattr(self, "file", None) is not None:
                self.file.close()
            raise TrajectoryFileError(
                f"cannot continue the partial trajectory {self.tmp_path} (damaged by the stop?): {err}"
            ) from err
        have = min(int(d.shape[0]) for d in (self.time, *self.frame_arrays.values()))
        if have < frames:
            self.file.close()
            raise TrajectoryFileError(
                f"the partial trajectory {self.tmp_path} holds {have} whole frames, the checkpoint {frames}"
            )
        for ds in (self.time, *self.frame_arrays.values()):
            ds.resize(frames, axis=0)
        self.group.attrs["complete"] = False
        self.frames = int(frames)
        self.file.flush()
        return self

    def append(self, time: float, position: np.ndarray, velocity: np.ndarray, pressure: np.ndarray) -> None:
        """Append one frame: ``position``/``velocity`` (Nf, 3), ``pressure`` (Nf,); flushes to disk."""
        t = self.frames
        self.time.resize(t + 1, axis=0)
        self.time[t] = time
        for name, values in (("position", position), ("velocity", velocity), ("pressure", pressure)):
            ds = self.frame_arrays[name]
            ds.resize(t + 1, axis=0)
            ds[t] = values
        self.frames += 1
        self.file.flush()

    def set_attributes(self, attrs: dict[str, Any]) -> None:
        """Add group attributes as the constructor does (a dict, or a list of non-numbers, as JSON text)."""
        for key, value in attrs.items():
            self.group.attrs[key] = _attr_value(value)

    def append_state(self, state: Any) -> None:
        """Append the fluid rows of a :class:`~lagfluid.state.ParticleState` as one frame."""
        nf = state.n_fluid
        self.append(
            state.time,
            state.pos[:nf].detach().cpu().numpy(),
            state.vel[:nf].detach().cpu().numpy(),
            state.pressure[:nf].detach().cpu().numpy(),
        )

    def close(self, complete: bool = True, stop_reason: str | None = None) -> Path:
        """Mark the trajectory complete (or not, with the reason), close and rename to the final path."""
        if self.file.id.valid:
            self.group.attrs["complete"] = bool(complete)
            self.group.attrs["stop_reason"] = stop_reason or ""
            self.group.attrs["frames"] = self.frames
            self.file.close()
            os.replace(self.tmp_path, self.path)
        return self.path

    def __enter__(self) -> TrajectoryWriter:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        self.close(complete=exc is None, stop_reason=None if exc is None else str(exc))


def open_lagfluid_file(path: str | os.PathLike, what: str = "trajectory") -> h5py.File:
    """Open a lagfluid HDF5 file read-only, checking that it exists, is HDF5 and has this format version.

    Args:
        path: the file.
        what: what the caller expects, for the messages ("trajectory", "scene file", ...).

    Raises:
        TrajectoryFileError: missing, unreadable (corrupt or truncated), not a lagfluid file, or another
            ``format_version``; the message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise TrajectoryFileError(f"{what} not found: {path}")
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise TrajectoryFileError(f"cannot read {path} as HDF5 (corrupt or truncated?): {err}") from err
    if f.attrs.get("format") != FORMAT:
        found = f.attrs.get("format")
        f.close()
        raise TrajectoryFileError(f"{path} is not a lagfluid {what} (format={found!r})")
    version = int(f.attrs.get("format_version", -1))
    if version != FORMAT_VERSION:
        f.close()
        raise TrajectoryFileError(
            f"{path} has format_version {version}; this lagfluid reads {FORMAT_VERSION}"
        )
    return f


def read_array(group: h5py.Group, name: str, index: int | tuple = ()) -> np.ndarray:
    """``group[name][index]`` (a whole array for ``()``, a frame for an int), read or refused by name.

    Raises:
        TrajectoryFileError: the array is missing, or a chunk of it is damaged (its checksum or
            decompression fails); the message names the file, the array and the frame.
    """
    path, where = group.file.filename, f"frame {index} of '{name}'" if isinstance(index, int) else f"'{name}'"
    try:
        return group[name][index]
    except KeyError as err:
        raise TrajectoryFileError(f"{path} has no array '{name}' in {group.name}") from err
    except (OSError, RuntimeError) as err:  # h5py: "Can't synchronously read data (filter returned ...)"
        raise TrajectoryFileError(f"{path}: {where} is unreadable (damaged file): {err}") from err


def read_trajectory(path: str | os.PathLike, group: str = "00000") -> dict[str, Any]:
    """Load one trajectory into numpy arrays plus an ``attrs`` dict.

    Raises:
        TrajectoryFileError: the file is missing, unreadable, not a lagfluid file, of another format version,
            or lacks the group or an array.
    """
    f = open_lagfluid_file(path, "trajectory")
    with f:
        if group not in f:
            raise TrajectoryFileError(f"{path} has no trajectory group '{group}' (groups: {sorted(f)})")
        g = f[group]
        out: dict[str, Any] = {}
        for name in ("time", "position", "velocity", "pressure", "boundary_position", "boundary_type"):
            if name not in g:
                raise TrajectoryFileError(f"{path}:{group} lacks the array '{name}'")
            out[name] = g[name][()]
        out["attrs"] = dict(g.attrs)
    t, nf = out["position"].shape[:2]
    if out["velocity"].shape != (t, nf, 3) or out["pressure"].shape != (t, nf) or out["time"].shape != (t,):
        raise TrajectoryFileError(f"{path}:{group} arrays disagree in shape (T={t}, Nf={nf})")
    return out
