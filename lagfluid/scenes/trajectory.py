"""The ``trajectory`` scene: frame ``t`` of a lagfluid trajectory file, and the frames before it.

A rollout of ``task=simulate``/``task=evaluate`` (``rollout.h5``) or a scene file of ``task=generate``
(``scenes/scene_*.h5``) is a lagfluid HDF5 file (layout in :mod:`lagfluid.data.store`; group ``00000``).
Starting a rollout from its frame ``t`` (LagrangeBench-style evaluation) needs

* the state of frame ``t``: the fluid's stored position, velocity and pressure, the static boundary stored
  once, the frame's time, and its step ``round(time / dt)`` at the file's ``dt``;
* for a simulator with a history (GNS: 5 earlier states), frames ``t-H .. t-1``, oldest first, which must
  be spaced by the simulator's time step (:func:`trajectory_history`).

Physical parameters default to the file's attributes (``dt``, ``l0``, ``gravity``, ``viscosity``,
``density``, ``dim``): the trajectory was made with them. The caller's ``params`` win where given (the
``trajectory`` config has them all null = the file's; ``scene.params.X=...`` or ``dt=...`` overrides one).

The fluid's stored values are float32 whatever the run's dtype; boundary particles' pressures are not
stored and start at zero. The domain ``bounds`` are the file's ``bounds`` attribute where it has one
(generated scenes), else the boundary particles' extent as for grid files
(:func:`lagfluid.scenes.grid_file.grid_bounds`).

Reading is done here with h5py because scenes sit below ``lagfluid.data`` in the layer rule
(``tests/test_layers.py``); the format check mirrors :func:`lagfluid.data.store.open_lagfluid_file`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch

from lagfluid.data.store import TrajectoryFileError, open_lagfluid_file
from lagfluid.errors import ConfigError
from lagfluid.scenes.grid_file import grid_bounds
from lagfluid.scenes.validation import FILE_ADVICE, validated_state
from lagfluid.state import ParticleState, ParticleType, SceneError, SceneParams

__all__ = [
    "PARAMETER_KEYS",
    "from_trajectory",
    "trajectory_history",
    "trajectory_params",
    "trajectory_states",
]

GROUP = "00000"
PARAMETER_KEYS = ("gravity", "viscosity", "density", "dt", "l0", "dim")
"""The :class:`~lagfluid.state.SceneParams` fields a trajectory file stores as attributes."""

_ARRAYS = ("time", "position", "velocity", "pressure", "boundary_position", "boundary_type")
_SPACING_RTOL = 1e-6  # stored times are sums of float64 steps: equal spacings agree to round-off


def _open(path: str | Path) -> h5py.File:
    """Open ``path`` read-only as a lagfluid trajectory file with group ``00000`` and its arrays."""
    try:
        f = open_lagfluid_file(path, "trajectory file")
    except TrajectoryFileError as err:
        raise SceneError(str(err)) from None
    problem = None
    if GROUP not in f:
        problem = f"has no trajectory group '{GROUP}' (groups: {sorted(f)})"
    else:
        missing = [name for name in _ARRAYS if name not in f[GROUP]]
        if missing:
            problem = f"lacks the array(s) {', '.join(missing)} in group '{GROUP}'"
    if problem:
        f.close()
        raise SceneError(f"{path} {problem}")
    return f


def _frame_index(frame: object, count: int, path: str | Path) -> int:
    """``frame`` as an index into ``count`` stored frames (negative counts from the end)."""
    if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)):
        raise SceneError(f"scene.frame must be an integer, got {frame!r}")
    index = int(frame) + count if frame < 0 else int(frame)
    if not 0 <= index < count:
        raise SceneError(
            f"frame {frame} is out of range for {path}: it stores {count} frames, "
            f"valid frames are 0 .. {count - 1} (or -{count} .. -1 from the end)"
        )
    return index


def trajectory_params(path: str | Path) -> dict[str, Any]:
    """The physical parameters a trajectory file was made with (its attributes ``PARAMETER_KEYS``).

    Returns:
        ``{key: value}`` for the keys the file has: ``gravity`` a 3-tuple, ``dim`` an int, the others floats.
    """
    with _open(path) as f:
        attrs = f[GROUP].attrs
        out: dict[str, Any] = {}
        for key in PARAMETER_KEYS:
            if key in attrs:
                value = attrs[key]
                if key == "gravity":
                    out[key] = tuple(float(g) for g in np.asarray(value).reshape(-1))
                elif key == "dim":
                    out[key] = int(value)
                else:
                    out[key] = float(value)
    return out


def _file_params(path: str | Path, params: SceneParams | None) -> SceneParams:
    return params if params is not None else SceneParams(**trajectory_params(path))


def trajectory_states(
    path: str | Path,
    frames: Sequence[int],
    params: SceneParams | None = None,
    dtype: torch.dtype = torch.float32,
    min_distance: float = 0.0,
) -> list[ParticleState]:
    """The states of stored ``frames`` of a trajectory file (each with the file's static boundary).

    Args:
        path: a lagfluid trajectory or scene file.
        frames: frame indices (negative count from the end).
        params: physical parameters; None = the file's (:func:`trajectory_params`).
        dtype: floating dtype of the states.
        min_distance: closest allowed particle distance in l0 (0: only exact duplicates are rejected; the
            frames are what a simulator made, not a lattice).

    Returns:
        one state per frame, sorted fluid, wall, dummy, with the frame's time and step.

    Raises:
        SceneError: missing or non-lagfluid file, a frame out of range (the message gives the valid range),
            or an invalid frame (non-finite values, fluid outside the domain).
    """
    params = _file_params(path, params)
    with _open(path) as f:
        g = f[GROUP]
        count = int(g["time"].shape[0])
        indices = [_frame_index(frame, count, path) for frame in frames]
        boundary_pos = np.asarray(g["boundary_position"][()], dtype=np.float64).reshape(-1, 3)
        boundary_type = np.asarray(g["boundary_type"][()], dtype=np.int64).reshape(-1)
        file_dt = float(g.attrs.get("dt", params.dt))
        stored_bounds = g.attrs.get("bounds")
        rows = [
            (float(g["time"][i]), g["position"][i], g["velocity"][i], g["pressure"][i], i) for i in indices
        ]
    nf = rows[0][1].shape[0] if rows else 0
    ptype = np.concatenate([np.full(nf, int(ParticleType.FLUID), np.int64), boundary_type])
    if isinstance(stored_bounds, np.ndarray) and stored_bounds.shape == (2, 3):
        bounds = stored_bounds.astype(np.float64)
    else:
        bounds = grid_bounds(boundary_pos, boundary_type) if len(boundary_pos) else None
    states = []
    for time, position, velocity, pressure, index in rows:
        pos = np.concatenate([np.asarray(position, np.float64), boundary_pos])
        vel = np.concatenate([np.asarray(velocity, np.float64), np.zeros_like(boundary_pos)])
        state = validated_state(
            pos, vel, ptype, params, bounds, dtype, min_distance, f"{path} frame {index}", FILE_ADVICE
        )
        # from_arrays sorts stably by type: fluid rows keep the file's order and come first
        state.pressure[:nf] = torch.as_tensor(np.asarray(pressure), dtype=dtype)
        state.time = time
        state.step = round(time / file_dt)
        states.append(state)
    return states


def from_trajectory(
    params: SceneParams | None = None,
    dtype: torch.dtype = torch.float32,
    path: str | Path | None = None,
    frame: int = 0,
    min_distance: float = 0.0,
) -> ParticleState:
    """The ``trajectory`` scene: frame ``frame`` of the file at option ``path`` (see the module doc).

    Args:
        params: physical parameters; None = the file's.
        dtype: floating dtype of the state.
        path: a lagfluid trajectory or scene file (required).
        frame: the stored frame to start from; negative counts from the end (-1 = the last).
        min_distance: see :func:`trajectory_states`.
    """
    if path is None:
        raise SceneError("scene 'trajectory' needs the option path=<lagfluid trajectory file (.h5)>")
    (state,) = trajectory_states(path, [frame], params, dtype, min_distance)
    return state


def trajectory_history(
    path: str | Path,
    frame: int,
    length: int,
    dt: float,
    params: SceneParams | None = None,
    dtype: torch.dtype = torch.float32,
) -> list[ParticleState]:
    """The ``min(length, t)`` stored frames before frame ``t = frame``, oldest first.

    Args:
        path: a lagfluid trajectory or scene file.
        frame: the frame the rollout starts from (negative counts from the end).
        length: how many earlier frames the simulator wants (its ``history_length``).
        dt: the simulator's time step, s: the spacing the history must have.
        params: physical parameters of the states; None = the file's.
        dtype: floating dtype of the states.

    Returns:
        frames ``t-H .. t-1`` as states (same boundary as frame ``t``); empty when ``length`` or ``t`` is 0.

    Raises:
        SceneError: as :func:`trajectory_states`, or frames ``t-H .. t`` not uniformly spaced in time (the
            last frame of a run whose steps are not a multiple of ``write_every`` is off the grid).
        ConfigError: the frames' spacing is not ``dt`` (a history at another spacing would give the model
            wrong velocities); the message names both spacings.
    """
    with _open(path) as f:
        times = np.asarray(f[GROUP]["time"][()], dtype=np.float64)
    t = _frame_index(frame, len(times), path)
    h = min(int(length), t)
    if h <= 0:
        return []
    spacings = np.diff(times[t - h : t + 1])
    if not np.allclose(spacings, spacings[0], rtol=_SPACING_RTOL, atol=0.0):
        raise SceneError(
            f"frames {t - h} .. {t} of {path} are not uniformly spaced in time (spacings "
            f"{', '.join(f'{s:.6g}' for s in spacings)} s); a history of {h} frames needs equal spacings: "
            "start from another scene.frame"
        )
    spacing = float(spacings[0])
    if not math.isclose(spacing, dt, rel_tol=_SPACING_RTOL):
        raise ConfigError(
            f"the frames of {path} are {spacing:.6g} s apart, but the simulator steps by dt={dt:.6g} s: its "
            f"history (frames {t - h} .. {t - 1}) must be spaced by its time step; use a trajectory written "
            "every step at that dt (write_every=1) or one whose frame spacing is the model's dt"
        )
    return trajectory_states(path, range(t - h, t), params, dtype)
