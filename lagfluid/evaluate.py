"""``task=evaluate``: a model against the MPS ground truth, rolled out from the same initial state.

``python -m lagfluid.run task=evaluate model=X scene=Y steps=N`` writes in ``out_dir``
(default ``runs/evaluate/<model>-<scene>``):

* ``rollout.h5``          the model's trajectory (the rollout format of :mod:`lagfluid.data.store`);
* ``metrics.json``        per-frame arrays of every metric, their summaries (mean and max over the run,
  position MSE at fixed horizons), the model's step timings (``timing``: median per step and stage, total)
  and provenance (config, reference file and whether it was reused);
* ``error_vs_time.png``   paper Fig. 4: Chamfer distance, density error, divergence, position MSE, kinetic
  energy and the one-step errors against time, model and MPS;
* ``pressure_slice.png``  paper Fig. 6: a vertical slice through the tank at one frame, model and MPS side
  by side on one colour scale.

**The reference.** MPS (``conf/model/mps.yaml``) with the run's scene, solver, dt, steps, write_every,
dtype and device is rolled out once by ``task=simulate`` into
``<evaluate.reference_dir>/<scene>-<hash>/`` (``rollout.h5``, ``metrics.json``, ``preview.png``), the hash
being that of the resolved key (:func:`reference_key`), which is also stored in the file as the attribute
``reference_key``. A later evaluation with the same key reuses the file only if it is readable, complete,
made by MPS, holds every frame and carries the same key; anything else (another dt, an interrupted run, a
file of another version) is recomputed, never silently used. A lock file serialises concurrent evaluations
of one reference (Hydra multiruns).

**Another reference.** ``evaluate.reference`` holds settings merged over the run's for the reference only
(null by default: the same settings), so a model run at other settings can be compared with MPS at the
defaults, e.g. ``dt=0.004 steps=250`` against ``evaluate.reference={dt:null,steps:500}``, or a coarser
``scene.params.l0`` against the default one. Frames are matched by *time*, not step number. Runs at
different particle spacings are compared in the frame of the boundary surface: the built scenes put the
inner wall layer on x, y, z = 0, so that surface lies half a spacing inside, at ``l0 / 2`` (each rollout
is shifted by ``-l0 / 2`` before the Chamfer distance); position MSE needs corresponding particles and is
NaN when the particle counts differ.

**Per frame** (frames ``0, k, 2k, ..., N`` with ``k = write_every``), :mod:`lagfluid.metrics`:

* ``chamfer_mm``: Chamfer distance model -> MPS (eq. 29) in mm;
* ``position_mse_m2``: LagrangeBench's position MSE per coordinate (particles keep their index);
* ``density_error``, ``velocity_divergence_per_s``: of the model and of MPS;
* ``kinetic_energy_J`` of both and ``kinetic_energy_rel_error = |E_model - E_MPS| / E_MPS``;
* one-step errors of the model's step that produced the frame, against the exact stage at the same input
  (paper Table 4; null at frame 0, and for a stage the model does not have):
  ``advection_nmae`` (eq. 32, the advection acceleration against ``g + nu lap(v)``) and
  ``ppe_relative_residual`` (eq. 31, the pressure stage's output in the exact PPE at ``(x**, v**)``).

A model stopped by the rollout guard is a result, not a failure: what it wrote is evaluated and
``complete: false`` with the reason is recorded. A reference that stops is an error.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

import lagfluid
from lagfluid.data.store import TrajectoryFileError, TrajectoryWriter, open_lagfluid_file
from lagfluid.errors import ConfigError, RolloutError
from lagfluid.metrics import (
    FieldMetrics,
    chamfer_distance,
    field_metrics,
    kinetic_energy,
    mse_horizons,
    normalized_mae,
    position_mse,
    relative_error,
    summarize,
)
from lagfluid.models.simulator import Simulator
from lagfluid.neighbor_list import VerletNeighborList
from lagfluid.physics.mps import ExactAdvection
from lagfluid.physics.reference import (
    exact_context,
    mps_constants,
    mps_neighbor_list,
    ppe_relative_residual,
)
from lagfluid.physics.stages import MPSConstants, SolverSettings, lattice_constants, solver_identity
from lagfluid.rollout import (
    Guard,
    _timing_summary,
    build_initial_state,
    build_simulator,
    git_commit,
    rollout,
    run_attributes,
    scene_params,
    simulate,
)
from lagfluid.state import ParticleState, ParticleType

log = logging.getLogger(__name__)

CONF_DIR = Path(__file__).resolve().parent.parent / "conf"
OUTPUTS = ("rollout.h5", "metrics.json", "error_vs_time.png", "pressure_slice.png")
_AXES = {"x": 0, "y": 1}


# ------------------------------------------------------------------------------------------- options
@dataclass(frozen=True)
class EvaluateOptions:
    """The ``evaluate:`` block of the config (see ``conf/config.yaml``).

    Attributes:
        reference_dir: root of the cached MPS reference rollouts.
        reuse_reference: reuse a cached reference whose key matches (False: always recompute).
        horizons: steps at which the position MSE is reported (those the run stores).
        one_step: compute the one-step errors (advection nMAE, PPE residual) at every stored frame.
        figures: write ``error_vs_time.png`` and ``pressure_slice.png`` (False: metrics only).
        slice_time: time (s) of the pressure slice; None = the middle stored frame.
        slice_axis: normal of the vertical slice plane, ``"x"`` or ``"y"``.
        slice_position: coordinate (m) of the plane along ``slice_axis``; None = the fluid layer nearest
            the initial fluid's centre.
        slice_width: thickness of the slab shown, in l0.
        reference: settings merged over the run's config for the MPS reference only (plain nested dict;
            empty = the run's own settings).
    """

    reference_dir: Path
    reuse_reference: bool = True
    horizons: tuple[int, ...] = (1, 10, 50, 100)
    one_step: bool = True
    figures: bool = True
    slice_time: float | None = None
    slice_axis: str = "y"
    slice_position: float | None = None
    slice_width: float = 1.0
    reference: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_config(cls, node: Any) -> EvaluateOptions:
        """Build and check the options of ``cfg.evaluate``; a bad value is a :class:`ConfigError`."""
        sl = node.get("slice") or {}
        horizons = tuple(int(h) for h in (node.get("horizons") or ()))
        if any(h < 1 for h in horizons):
            raise ConfigError(f"evaluate.horizons must be steps >= 1, got {list(horizons)}")
        axis = str(sl.get("axis", "y"))
        if axis not in _AXES:
            raise ConfigError(f"evaluate.slice.axis must be x or y (the slice is vertical), got '{axis}'")
        slice_time = sl.get("time")
        if slice_time is not None and not (math.isfinite(float(slice_time)) and float(slice_time) >= 0):
            raise ConfigError(f"evaluate.slice.time must be a time >= 0 in s or null, got {slice_time!r}")
        width = float(sl.get("width", 1.0))
        if not (math.isfinite(width) and width > 0):
            raise ConfigError(f"evaluate.slice.width must be > 0 (l0), got {width!r}")
        position = sl.get("position")
        reference = node.get("reference") or {}
        if OmegaConf.is_config(reference):
            reference = OmegaConf.to_container(reference, resolve=True)
        if not isinstance(reference, dict):
            raise ConfigError(f"evaluate.reference must be a mapping of settings, got {reference!r}")
        return cls(
            reference_dir=Path(str(node.get("reference_dir") or "runs/reference")),
            reuse_reference=bool(node.get("reuse_reference", True)),
            horizons=horizons,
            one_step=bool(node.get("one_step", True)),
            figures=bool(node.get("figures", True)),
            slice_time=None if slice_time is None else float(slice_time),
            slice_axis=axis,
            slice_position=None if position is None else float(position),
            slice_width=width,
            reference=dict(reference),
        )


# ------------------------------------------------------------------------------------------- reference
def _file_digest(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def reference_key(cfg: DictConfig) -> dict[str, Any]:
    """What the MPS reference rollout depends on: the resolved scene, solver, dt, steps, output and precision.

    Also the lagfluid version (a release may change the solver) and, for ``scene=file``, the SHA-256 of the
    grid file (the same path may hold another grid later).
    """
    scene = OmegaConf.to_container(cfg.scene, resolve=True)
    key: dict[str, Any] = {
        "scene": scene,
        "solver": solver_identity(OmegaConf.to_container(cfg.solver, resolve=True)),
        "dt": scene_params(cfg).dt,
        "steps": int(cfg.steps),
        "write_every": int(cfg.write_every),
        "dtype": str(cfg.dtype),
        "device": torch.device(str(cfg.device)).type,  # CPU and CUDA runs differ in round-off
        "lagfluid_version": lagfluid.__version__,
    }
    path = scene.get("path") if isinstance(scene, dict) else None
    if path and Path(str(path)).is_file():
        key["scene_file_sha256"] = _file_digest(Path(str(path)))
    return key


def _key_json(key: dict[str, Any]) -> str:
    return json.dumps(key, sort_keys=True, default=str)


def key_hash(key: dict[str, Any]) -> str:
    """12 hex digits of the SHA-256 of the key's canonical JSON (the cache folder's suffix)."""
    return hashlib.sha256(_key_json(key).encode()).hexdigest()[:12]


def expected_frames(steps: int, write_every: int) -> int:
    """Frames a complete rollout stores: ``0, k, 2k, ...`` and the last step."""
    return steps // write_every + 1 + (1 if steps % write_every else 0)


def cached_reference_problem(path: Path, key: dict[str, Any], frames: int) -> str | None:
    """Why the file at ``path`` cannot serve as the reference for ``key``, or None when it can."""
    try:
        f = open_lagfluid_file(path, "reference rollout")
    except TrajectoryFileError as err:
        return str(err)
    with f:
        if "00000" not in f:
            return f"{path} has no trajectory group"
        g = f["00000"]
        if not bool(g.attrs.get("complete", False)):
            return f"{path} is incomplete ({g.attrs.get('stop_reason', '')})"
        if g.attrs.get("model") != "mps":
            return f"{path} was made by model {g.attrs.get('model')!r}, not mps"
        if g.attrs.get("reference_key") != _key_json(key):
            return f"{path} was made with another configuration"
        if g["time"].shape[0] != frames or g["position"].shape[0] != frames:
            return f"{path} holds {g['time'].shape[0]} frames, {frames} expected"
    return None


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``path`` (POSIX; elsewhere no lock)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    with path.open("w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def reference_settings(cfg: DictConfig, overrides: dict[str, Any]) -> DictConfig:
    """The run's config with ``overrides`` (``evaluate.reference``) merged over it: what the reference uses.

    Raises:
        ConfigError: an override names a key the config does not have (struct mode).
    """
    if not overrides:
        return cfg
    merged = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    OmegaConf.set_struct(merged, True)
    try:
        return OmegaConf.merge(merged, overrides)
    except OmegaConfBaseException as err:  # an unknown key or a bad type: name the bad value
        raise ConfigError(f"evaluate.reference={overrides!r} does not fit the config: {err}") from err


def reference_config(cfg: DictConfig, out_dir: Path) -> DictConfig:
    """``cfg`` with ``model=mps`` and ``task=simulate`` writing to ``out_dir`` (struct mode kept)."""
    plain = OmegaConf.to_container(cfg, resolve=True)
    plain["model"] = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "model" / "mps.yaml"), resolve=True)
    plain["task"] = "simulate"
    plain["out_dir"] = str(out_dir)
    ref = OmegaConf.create(plain)
    OmegaConf.set_struct(ref, True)
    return ref


def reference_rollout(cfg: DictConfig, options: EvaluateOptions) -> tuple[Path, bool, dict[str, Any]]:
    """The MPS reference rollout for ``cfg``: reused from the cache when valid, else computed.

    Returns:
        The path of its ``rollout.h5``, whether it was reused, and its key.

    Raises:
        RolloutError: the MPS run stopped (guard); the message says how.
    """
    cfg = reference_settings(cfg, options.reference)
    key = reference_key(cfg)
    folder = options.reference_dir / f"{cfg.scene.name}-{key_hash(key)}"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "rollout.h5"
    frames = expected_frames(int(cfg.steps), int(cfg.write_every))
    with _locked(folder / ".lock"):
        if options.reuse_reference:
            problem = cached_reference_problem(path, key, frames) if path.exists() else "none cached"
            if problem is None:
                log.info("reusing the MPS reference %s", path)
                return path, True, key
            log.info("computing the MPS reference in %s (%s)", folder, problem)
        try:
            simulate(reference_config(cfg, folder))
        except RolloutError as err:
            raise RolloutError(f"the MPS reference stopped, nothing to compare with: {err}") from err
        # Stamped only after a complete run: a file without it (a crash in between) is never reused.
        with h5py.File(path, "a") as f:
            f["00000"].attrs["reference_key"] = _key_json(key)
    return path, False, key


# ------------------------------------------------------------------------------------------- model run
class _StepProbe:
    """A simulator that keeps the input state of its last step and has its stages' intermediates recorded.

    The one-step errors compare a stage's output with the exact stage *at the same input*; the rollout loop
    only hands out the states after each step, so the probe keeps the one before.
    """

    def __init__(self, inner: Simulator, record: bool = True) -> None:
        self.inner = inner
        self.name = inner.name
        self.last_input: ParticleState | None = None
        # Recording copies the intermediates every step: only when the one-step errors need them, so
        # that timed runs (evaluate.one_step=false) measure the simulator alone.
        if record and hasattr(inner, "record_intermediates"):
            inner.record_intermediates = True

    @property
    def last_timings(self) -> dict[str, float]:
        """The wrapped simulator's stage timings."""
        return self.inner.last_timings

    @property
    def last_info(self) -> dict[str, float]:
        """The wrapped simulator's diagnostics."""
        return getattr(self.inner, "last_info", {})

    @property
    def last_fields(self) -> dict[str, torch.Tensor]:
        """Intermediates of the last step (empty for simulators that do not record them)."""
        return getattr(self.inner, "last_fields", {}) or {}

    def reset(self, state: ParticleState) -> None:
        """Reset the wrapped simulator."""
        self.last_input = None
        self.inner.reset(state)

    def step(self, state: ParticleState) -> ParticleState:
        """One step of the wrapped simulator, remembering ``state``."""
        new = self.inner.step(state)
        self.last_input = state
        return new

    def attributes(self) -> dict[str, Any]:
        """The wrapped simulator's attributes."""
        return self.inner.attributes()


def _one_step_errors(
    probe: _StepProbe, settings: SolverSettings, constants: MPSConstants, neighbors: VerletNeighborList
) -> tuple[float, float]:
    """Advection nMAE (eq. 32) and PPE relative residual (eq. 31) of the probe's last step (NaN if n/a)."""
    inp, fields = probe.last_input, probe.last_fields
    nmae = residual = math.nan
    if inp is None:
        return nmae, residual
    if "advection_acceleration" in fields:
        ctx = exact_context(inp, settings, constants, neighbors)
        exact = ExactAdvection()(ctx, inp.pos, inp.vel)
        nmae = normalized_mae(fields["advection_acceleration"], exact)
    if "pressure_unclamped" in fields and "pos_collided" in fields:
        nf = inp.n_fluid
        pos, vel = inp.pos.clone(), inp.vel.clone()
        pos[:nf], vel[:nf] = fields["pos_collided"], fields["vel_collided"]
        at_pressure = ParticleState(pos=pos, vel=vel, ptype=inp.ptype, params=inp.params, check=False)
        ctx = exact_context(at_pressure, settings, constants, neighbors)
        residual = ppe_relative_residual(ctx, fields["pressure_unclamped"])
    return nmae, residual


def run_model(
    cfg: DictConfig, simulator: Simulator, state: ParticleState, out: Path, one_step: bool
) -> dict[str, Any]:
    """Roll the model out into ``out`` (rollout.h5) and collect its one-step errors per stored frame.

    Returns:
        ``complete``, ``stop_reason``, ``steps`` done, ``timing`` (median time per step and per stage as
        ``task=simulate`` reports them, and ``steps_total_s``, the wall time of all steps done) and
        per-frame ``step``, ``advection_nmae`` and ``ppe_relative_residual`` lists.
    """
    settings = SolverSettings.from_config(cfg.solver)
    guard = Guard(float(cfg.solver.guard.max_courant), int(cfg.solver.guard.check_every))
    nf = state.n_fluid
    writer = TrajectoryWriter(
        out,
        nf,
        state.pos[nf:].cpu().numpy(),
        state.ptype[nf:].cpu().numpy(),
        run_attributes(state, cfg, simulator.name, str(cfg.scene.name), int(cfg.write_every)),
    )
    probe = _StepProbe(simulator, record=one_step)
    constants = mps_constants(state, settings)
    neighbors = mps_neighbor_list(state, settings)  # one list for every frame: it rebuilds only as needed
    result: dict[str, Any] = {"step": [], "advection_nmae": [], "ppe_relative_residual": []}

    def on_frame(s: ParticleState) -> None:
        nmae, res = _one_step_errors(probe, settings, constants, neighbors) if one_step else (math.nan,) * 2
        result["step"].append(s.step)
        result["advection_nmae"].append(nmae)
        result["ppe_relative_residual"].append(res)

    complete, stop_reason, record = True, "", {"step_seconds": []}
    try:
        _, record = rollout(
            probe,
            state,
            int(cfg.steps),
            guard=guard,
            writer=writer,
            write_every=int(cfg.write_every),
            on_frame=on_frame,
            progress=bool(cfg.progress),
        )
    except RolloutError as err:  # the model blew up: evaluate what it wrote
        complete, stop_reason = False, str(err)
        record = getattr(err, "record", record)
        log.warning("model %s stopped: %s", simulator.name, err)
    except BaseException as err:
        writer.close(complete=False, stop_reason=f"{type(err).__name__}: {err}")
        raise
    for k, v in simulator.attributes().items():
        writer.group.attrs[k] = v
    writer.close(complete=complete, stop_reason=stop_reason)
    record.setdefault("stage_seconds", {})
    record.setdefault("info", {})
    timing = {**_timing_summary(record), "steps_total_s": float(sum(record["step_seconds"]))}
    return {
        **result,
        "complete": complete,
        "stop_reason": stop_reason,
        "steps": len(record["step_seconds"]),
        "timing": timing,
    }


# ------------------------------------------------------------------------------------------- comparison
@dataclass
class _Trajectory:
    """An open rollout file, read frame by frame (a long run need not fit in memory)."""

    file: h5py.File
    steps: list[int]
    times: list[float]
    boundary_position: np.ndarray
    boundary_type: np.ndarray
    attrs: dict[str, Any]

    @classmethod
    def open(cls, path: Path) -> _Trajectory:
        f = open_lagfluid_file(path)
        g = f["00000"]
        dt = float(g.attrs["dt"])
        times = [float(t) for t in g["time"][()]]
        return cls(
            f,
            [round(t / dt) for t in times],
            times,
            g["boundary_position"][()],
            g["boundary_type"][()],
            dict(g.attrs),
        )

    @property
    def l0(self) -> float:
        """Particle spacing (m)."""
        return float(self.attrs["l0"])

    @property
    def surface_offset(self) -> float:
        """Where the boundary surface lies in the built scenes' coordinates: half a spacing inside (m)."""
        return 0.5 * self.l0

    def frame(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        g = self.file["00000"]
        return g["position"][index], g["velocity"][index], g["pressure"][index]


def _field(
    traj: _Trajectory, pos: np.ndarray, vel: np.ndarray, settings: SolverSettings, n0: float
) -> FieldMetrics:
    """Density error and divergence of a stored frame (fluid + static boundary), in float64."""
    nf = pos.shape[0]
    all_pos = torch.from_numpy(np.concatenate([pos, traj.boundary_position]).astype(np.float64))
    all_vel = torch.zeros_like(all_pos)
    all_vel[:nf] = torch.from_numpy(vel.astype(np.float64))
    ptype = torch.cat(
        [torch.full((nf,), int(ParticleType.FLUID)), torch.from_numpy(traj.boundary_type.astype(np.int64))]
    )
    l0, dim = float(traj.attrs["l0"]), int(traj.attrs.get("dim", 3))
    return field_metrics(
        all_pos,
        all_vel,
        ptype,
        n0,
        settings.re_density * l0,
        settings.re_gradient * l0,
        settings.surface_beta,
        dim,
        settings.neighbor_backend,
    )


def _common_frames(model: _Trajectory, ref: _Trajectory) -> list[tuple[int, int]]:
    """``(model frame, reference frame)`` index pairs stored at the same time (the model's dt may differ).

    A model frame matches when its time lies on the reference's step grid (to 1e-6 of a reference step)
    and the reference stored that step.
    """
    dt_ref = float(ref.attrs["dt"])
    ref_index = {s: i for i, s in enumerate(ref.steps)}
    pairs = []
    for i, t in enumerate(model.times):
        s = round(t / dt_ref)
        if abs(t - s * dt_ref) <= 1e-6 * dt_ref and s in ref_index:
            pairs.append((i, ref_index[s]))
    return pairs


def compare(model_path: Path, reference_path: Path, settings: SolverSettings) -> dict[str, Any]:
    """Per-frame metrics of the model's rollout against the reference's, at the times both stored.

    The model may run at another dt or particle spacing than the reference (``evaluate.reference``): frames
    are matched by time, each rollout's density error uses its own spacing's ``n0``, its kinetic energy its
    own particle mass, and the Chamfer distance is taken in the boundary surface's frame (see the module
    doc); the position MSE is NaN when the particle counts differ (no correspondence).

    Returns:
        ``{"step", "time_s", "chamfer_mm", "position_mse_m2", "kinetic_energy_rel_error"}`` lists and
        ``density_error``, ``velocity_divergence_per_s``, ``kinetic_energy_J`` as ``{"model", "reference"}``.
    """
    model, ref = _Trajectory.open(model_path), _Trajectory.open(reference_path)
    try:
        dim = int(ref.attrs.get("dim", 3))
        n0 = {id(t): lattice_constants(t.l0, settings, dim).n0 for t in (model, ref)}
        mass = {id(t): float(t.attrs["density"]) * t.l0**dim for t in (model, ref)}
        # zero when the spacings agree: then positions are compared exactly as stored
        shift = np.float32(model.surface_offset - ref.surface_offset)
        out: dict[str, Any] = {
            k: [] for k in ("step", "time_s", "chamfer_mm", "position_mse_m2", "kinetic_energy_rel_error")
        }
        pairs = {k: {"model": [], "reference": []} for k in ("density_error", "velocity_divergence_per_s")}
        pairs["kinetic_energy_J"] = {"model": [], "reference": []}
        for i, j in _common_frames(model, ref):
            mp, mv, _ = model.frame(i)
            rp, rv, _ = ref.frame(j)
            out["step"].append(model.steps[i])
            out["time_s"].append(model.times[i])
            out["chamfer_mm"].append(1e3 * chamfer_distance(mp - shift if shift else mp, rp))
            out["position_mse_m2"].append(position_mse(mp, rp) if mp.shape == rp.shape else math.nan)
            e_model, e_ref = kinetic_energy(mv, mass[id(model)]), kinetic_energy(rv, mass[id(ref)])
            pairs["kinetic_energy_J"]["model"].append(e_model)
            pairs["kinetic_energy_J"]["reference"].append(e_ref)
            out["kinetic_energy_rel_error"].append(relative_error(e_model, e_ref))
            for who, traj, p, v in (("model", model, mp, mv), ("reference", ref, rp, rv)):
                m = _field(traj, p, v, settings, n0[id(traj)])
                pairs["density_error"][who].append(m.density_error)
                pairs["velocity_divergence_per_s"][who].append(m.velocity_divergence)
        return {**out, **pairs}
    finally:
        model.file.close()
        ref.file.close()


def _finite_or_none(value: Any) -> Any:
    """JSON has no NaN/inf: undefined values are written as null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_none(v) for v in value]
    return value


# ------------------------------------------------------------------------------------------- figures
def plot_errors(path: Path, frames: dict[str, Any], title: str) -> Path:
    """Paper Fig. 4: every per-frame metric against time, model (and MPS where both have one)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(frames["time_s"])
    # Fixed margins rather than a layout engine: constrained layout measured ~2 s per figure here.
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5))
    fig.subplots_adjust(left=0.06, right=0.99, bottom=0.08, top=0.93, wspace=0.28, hspace=0.3)
    model_style, ref_style = {"color": "C0", "label": "model"}, {"color": "k", "ls": "--", "label": "MPS"}

    def both(ax: Any, key: str, ylabel: str) -> None:
        ax.plot(t, frames[key]["model"], **model_style)
        ax.plot(t, frames[key]["reference"], **ref_style)
        ax.set_ylabel(ylabel)
        ax.legend()

    def single(ax: Any, values: list[float], ylabel: str, label: str, log_scale: bool = False) -> None:
        y = np.asarray(values, dtype=float)
        ax.plot(t, y, marker="." if len(t) < 30 else None, label=label)
        ax.set_ylabel(ylabel)
        if log_scale and np.any(np.isfinite(y) & (y > 0)):
            ax.set_yscale("log")

    single(axes[0, 0], frames["chamfer_mm"], "Chamfer distance to MPS (mm)", "model -> MPS")
    both(axes[0, 1], "density_error", "density error")
    both(axes[0, 2], "velocity_divergence_per_s", "velocity divergence (1/s)")
    single(axes[1, 0], frames["position_mse_m2"], "position MSE to MPS (m$^2$)", "model", log_scale=True)
    both(axes[1, 1], "kinetic_energy_J", "fluid kinetic energy (J)")
    ax = axes[1, 2]
    single(ax, frames["advection_nmae"], "one-step error", "advection nMAE (eq. 32)", log_scale=True)
    single(ax, frames["ppe_relative_residual"], "one-step error", "PPE residual (eq. 31)", log_scale=True)
    ax.legend()
    for ax in axes.flat:
        ax.set_xlabel("time (s)")
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_pressure_slice(
    path: Path,
    model_path: Path,
    reference_path: Path,
    options: EvaluateOptions,
    title: str,
) -> dict[str, Any]:
    """Paper Fig. 6: pressure on a vertical slab through the tank, model and MPS, one colour scale.

    The frame is the common stored frame nearest ``options.slice_time`` (the middle one when None); the slab
    holds the particles within ``slice_width / 2`` l0 of the plane ``slice_axis = slice_position``.

    Returns:
        Where the slice is: ``time_s``, ``axis``, ``position_m``, ``width_l0``, ``particles`` per panel.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    model, ref = _Trajectory.open(model_path), _Trajectory.open(reference_path)
    try:
        l0 = max(model.l0, ref.l0)  # the coarser spacing: a slab that holds a layer of both rollouts
        common = _common_frames(model, ref)
        if not common:
            raise RolloutError(f"{model_path} and {reference_path} store no frame at the same time")
        if options.slice_time is None:
            i_model, i_ref = common[len(common) // 2]
        else:
            i_model, i_ref = min(common, key=lambda ij: abs(model.times[ij[0]] - options.slice_time))
        time_s = model.times[i_model]
        axis = _AXES[options.slice_axis]
        across = 1 - axis  # the other horizontal axis is drawn left to right, z up
        if options.slice_position is None:
            first = model.frame(0)[0][:, axis].astype(np.float64)
            centre = first[np.argmin(np.abs(first - first.mean()))]  # a particle layer, not between two
        else:
            centre = options.slice_position
        half = 0.5 * options.slice_width * l0
        panels = []
        for name, traj, index in (("model", model, i_model), ("MPS", ref, i_ref)):
            pos, _, p = traj.frame(index)
            inside = np.abs(pos[:, axis] - centre) < half
            panels.append((name, pos[inside], p[inside]))
        bnd = ref.boundary_position
        walls = bnd[(np.abs(bnd[:, axis] - centre) < half) & (ref.boundary_type == int(ParticleType.WALL))]
        pmax = max((float(p.max()) for _, _, p in panels if p.size), default=0.0) or 1.0
        fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharex=True, sharey=True)
        fig.subplots_adjust(left=0.07, right=0.88, bottom=0.12, top=0.86, wspace=0.08)
        sc = None
        for ax, (name, pos, p) in zip(axes, panels, strict=True):
            ax.scatter(walls[:, across], walls[:, 2], s=6, c="0.8", marker="s", linewidths=0)
            sc = ax.scatter(pos[:, across], pos[:, 2], s=10, c=p, cmap="jet", vmin=0.0, vmax=pmax, marker="s")
            ax.set_title(f"{name}, t = {time_s:.3f} s ({len(p)} particles)")
            ax.set_aspect("equal")
            ax.set_xlabel("xyz"[across] + " (m)")
        axes[0].set_ylabel("z (m)")
        fig.colorbar(sc, cax=fig.add_axes((0.9, 0.15, 0.015, 0.68)), label="pressure (Pa)")
        fig.suptitle(f"{title}: pressure on the slab |{options.slice_axis} - {centre:.3f} m| < {half:.3f} m")
        fig.savefig(path, dpi=110)
        plt.close(fig)
        return {
            "time_s": time_s,
            "step": model.steps[i_model],
            "axis": options.slice_axis,
            "position_m": float(centre),
            "width_l0": options.slice_width,
            "particles": {name: len(p) for name, _, p in panels},
        }
    finally:
        model.file.close()
        ref.file.close()


# ------------------------------------------------------------------------------------------- the task
def _summaries(frames: dict[str, Any], horizons: tuple[int, ...]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in frames.items():
        if key in ("step", "time_s"):
            continue
        if isinstance(value, dict):
            out[key] = {who: summarize(v, finite_only=True) for who, v in value.items()}
        else:
            out[key] = summarize(value, finite_only=True)
    out["position_mse_horizons_m2"] = mse_horizons(frames["step"], frames["position_mse_m2"], horizons)
    return out


def evaluate(cfg: DictConfig) -> dict[str, Any]:
    """``task=evaluate``: roll out ``cfg.model`` and MPS from ``cfg.scene``, compare, write the outputs.

    Returns:
        The content of ``metrics.json`` (with NaN where JSON has null).

    Raises:
        LagfluidError: bad configuration, an unknown model, missing weights, or an MPS reference that
            stopped (a model that stops is recorded, not raised).
    """
    start = time.perf_counter()
    torch.manual_seed(int(cfg.seed))
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    options = EvaluateOptions.from_config(cfg.evaluate)
    steps, write_every = int(cfg.steps), int(cfg.write_every)
    if steps < 1 or write_every < 1:
        raise ConfigError(f"task=evaluate needs steps >= 1 and write_every >= 1, got {steps}, {write_every}")
    if torch.device(str(cfg.device)).type == "cuda" and not torch.cuda.is_available():
        raise RolloutError(
            f"device={cfg.device} was asked for, but torch sees no CUDA device; use device=cpu"
        )
    out_dir = Path(cfg.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for name in OUTPUTS:  # a failed run must not leave an earlier run's outputs looking like its own
        (out_dir / name).unlink(missing_ok=True)

    # Model first: an unknown model or missing weights fail before a possibly long reference run.
    state = build_initial_state(cfg)
    simulator = build_simulator(cfg)
    reference_path, reused, key = reference_rollout(cfg, options)
    model_path = out_dir / "rollout.h5"
    run = run_model(cfg, simulator, state, model_path, options.one_step)

    settings = SolverSettings.from_config(cfg.solver)
    frames = compare(model_path, reference_path, settings)
    for name in ("advection_nmae", "ppe_relative_residual"):
        by_step = dict(zip(run["step"], run[name], strict=True))
        frames[name] = [by_step.get(s, math.nan) for s in frames["step"]]

    slice_info = None
    if options.figures:
        title = f"{simulator.name} vs MPS on {cfg.scene.name}"
        plot_errors(out_dir / "error_vs_time.png", frames, title)
        slice_path = out_dir / "pressure_slice.png"
        slice_info = plot_pressure_slice(slice_path, model_path, reference_path, options, title)
    metrics = {
        "task": "evaluate",
        "model": simulator.name,
        "scene": str(cfg.scene.name),
        "complete": run["complete"],
        "stop_reason": run["stop_reason"],
        "steps_requested": steps,
        "steps": run["steps"],
        "frames_compared": len(frames["step"]),
        "dt": float(state.params.dt),
        "write_every": write_every,
        "device": str(cfg.device),
        "dtype": str(cfg.dtype),
        "particles": {"fluid": state.n_fluid, "boundary": state.num_particles - state.n_fluid},
        "summary": _summaries(frames, options.horizons),
        "frames": frames,
        "pressure_slice": slice_info,
        "timing": run["timing"],
        "reference": {
            "path": str(reference_path),
            "reused": reused,
            "overrides": options.reference,
            "key_hash": key_hash(key),
            "key": key,
        },
        "simulator": simulator.attributes(),
        "config": OmegaConf.to_yaml(cfg, resolve=True),
        "version": lagfluid.__version__,
        "git_commit": git_commit(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "wall_time_total_s": time.perf_counter() - start,
    }
    tmp = out_dir / "metrics.json.part"
    tmp.write_text(json.dumps(_finite_or_none(metrics), indent=2))
    os.replace(tmp, out_dir / "metrics.json")
    summary = metrics["summary"]
    log.info(
        "wrote %s: %s vs MPS, %d frames, Chamfer mean %.3f mm, density error mean %.4f (MPS %.4f)",
        out_dir,
        simulator.name,
        len(frames["step"]),
        summary["chamfer_mm"]["mean"],
        summary["density_error"]["model"]["mean"],
        summary["density_error"]["reference"]["mean"],
    )
    return metrics
