"""One rollout loop for every simulator: steps, guard, timing, writing.

``python -m lagfluid.run model=X scene=Y steps=N out_dir=DIR`` writes

* ``DIR/rollout.h5``   the trajectory (:mod:`lagfluid.data.store`),
* ``DIR/metrics.json`` counts, median wall time per step and per stage, density error and divergence,
* ``DIR/preview.png``  first, middle and last frame coloured by pressure.

The guard stops a run with a :class:`~lagfluid.errors.RolloutError` naming the step, the particle and the
value (NaN/inf, a fluid particle leaving the domain, a Courant number above the limit); what was written
up to then is kept and marked incomplete.
"""

from __future__ import annotations

import json
import logging
import math
import os
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from statistics import median
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

import lagfluid
from lagfluid.data.store import TrajectoryWriter
from lagfluid.errors import RolloutError
from lagfluid.metrics import field_metrics, summarize
from lagfluid.models.simulator import Simulator
from lagfluid.physics.stages import SolverSettings, lattice_constants
from lagfluid.registry import check_scene_name, get_simulator_factory
from lagfluid.scenes import build_scene
from lagfluid.state import ParticleState, ParticleType, SceneParams

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Guard:
    """Run-time checks of a rollout.

    Attributes:
        max_courant: largest allowed ``max|v| dt / l0``.
        check_every: check every k steps (the last step is always checked).
    """

    max_courant: float = 0.5
    check_every: int = 1

    def check(self, state: ParticleState) -> None:
        """Raise :class:`RolloutError` when ``state`` is non-finite, outside its domain or too fast."""
        nf, step = state.n_fluid, state.step
        for name, values in (("position", state.pos[:nf]), ("velocity", state.vel[:nf])):
            bad = ~torch.isfinite(values).all(dim=1)
            if bool(bad.any()):
                i = int(torch.nonzero(bad)[0, 0])
                raise RolloutError(
                    f"step {step}: fluid particle {i} has a non-finite {name} {values[i].tolist()} "
                    f"({int(bad.sum())} particles affected); the simulation blew up - try a smaller dt "
                    f"(now {state.params.dt})"
                )
        outside = state.fluid_outside_bounds()
        if outside.numel():
            i = int(outside[0])
            raise RolloutError(
                f"step {step}: fluid particle {i} left the domain at {state.pos[i].tolist()} "
                f"(domain {state.bounds[0].tolist()} .. {state.bounds[1].tolist()}; "
                f"{outside.numel()} particles outside); check the walls of the scene or reduce dt "
                f"(now {state.params.dt})"
            )
        speed = state.vel[:nf].norm(dim=1)
        i = int(speed.argmax())
        courant = float(speed[i]) * state.params.dt / state.params.l0
        if courant > self.max_courant:
            raise RolloutError(
                f"step {step}: Courant number {courant:.3f} at fluid particle {i} "
                f"(|v| = {float(speed[i]):.3g} m/s) "
                f"exceeds solver.guard.max_courant={self.max_courant}; reduce dt (now {state.params.dt}) "
                f"or raise the limit"
            )


def git_commit() -> str:
    """The current git commit of the source tree, or '' outside a repository."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=5,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return ""
    return out.stdout.strip() if out.returncode == 0 else ""


def scene_params(cfg: DictConfig) -> SceneParams:
    """Physical parameters from ``cfg.scene.params`` with the top-level ``dt`` override applied."""
    raw = OmegaConf.to_container(cfg.scene.get("params", {}) or {}, resolve=True)
    if "gravity" in raw:
        raw["gravity"] = tuple(float(g) for g in raw["gravity"])
    return SceneParams(**raw).with_overrides(dt=cfg.dt)


def run_attributes(
    state: ParticleState, cfg: DictConfig, model: str, scene: str, write_every: int
) -> dict[str, Any]:
    """Attributes every trajectory file carries: physical parameters and provenance (how it was made)."""
    params = state.params
    return {
        "model": model,
        "scene": scene,
        "dt": params.dt,
        "write_every": write_every,
        "l0": params.l0,
        "gravity": list(params.gravity),
        "viscosity": params.viscosity,
        "density": params.density,
        "dim": params.dim,
        "n_fluid": state.n_fluid,
        "config": OmegaConf.to_yaml(cfg, resolve=True),
        "version": lagfluid.__version__,
        "git_commit": git_commit(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


def build_initial_state(cfg: DictConfig) -> ParticleState:
    """The scene of ``cfg.scene``, on ``cfg.device`` in ``cfg.dtype``.

    ``cfg.scene.builder`` names the scene builder when a config reuses another scene's builder with other
    options (``dam_small`` is a ``dam``); otherwise the builder is ``cfg.scene.name``.
    """
    builder = cfg.scene.get("builder") or cfg.scene.name
    check_scene_name(builder)
    dtype = {"float32": torch.float32, "float64": torch.float64}.get(cfg.dtype)
    if dtype is None:
        raise RolloutError(f"unknown dtype '{cfg.dtype}'; available: float32, float64")
    scene = OmegaConf.to_container(cfg.scene, resolve=True)
    options = {k: v for k, v in scene.items() if k not in ("name", "builder", "params")}
    state = build_scene(builder, scene_params(cfg), dtype=dtype, **options)
    return state.to(device=torch.device(cfg.device))


def build_simulator(cfg: DictConfig) -> Simulator:
    """The simulator named by ``cfg.model.name``."""
    return get_simulator_factory(cfg.model.name)(cfg)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def rollout(
    simulator: Simulator,
    state: ParticleState,
    steps: int,
    *,
    guard: Guard | None = None,
    writer: TrajectoryWriter | None = None,
    write_every: int = 1,
    on_frame: Any = None,
    progress: bool = False,
    reset: bool = True,
) -> tuple[ParticleState, dict[str, Any]]:
    """Advance ``state`` by ``steps`` steps of ``simulator``.

    Args:
        simulator: any :class:`Simulator`.
        state: initial state (frame 0; written first when ``writer`` is given).
        steps: number of steps.
        guard: run-time checks (default :class:`Guard`); every state that is written is checked first.
        writer: optional trajectory writer; frames ``0, k, 2k, ...`` and the last one are written.
        write_every: k.
        on_frame: optional callback ``f(state)`` for every written frame (metrics).
        progress: show a tqdm progress bar.
        reset: call ``simulator.reset(state)`` first (per-scene constants, a fresh neighbour list); pass
            False to continue a rollout in segments (warm neighbour list and PPE start).

    Returns:
        The final state and a record with per-step wall times, per-stage times and diagnostics. Any exception
        raised during the loop carries that record as ``err.record`` and the last state that passed the
        guard as ``err.state``.
    """
    guard = guard or Guard()
    if steps < 0:
        raise RolloutError(f"steps must be >= 0, got {steps}")
    if write_every < 1:
        raise RolloutError(f"write_every must be >= 1, got {write_every}")
    if reset:
        simulator.reset(state)
    record: dict[str, Any] = {"step_seconds": [], "stage_seconds": {}, "info": {}}

    def emit(s: ParticleState) -> None:
        if writer is not None:
            nf = s.n_fluid
            writer.append(
                s.time,
                s.pos[:nf].detach().cpu().numpy(),
                s.vel[:nf].detach().cpu().numpy(),
                s.pressure[:nf].detach().cpu().numpy(),
            )
        if on_frame is not None:
            on_frame(s)

    bar = tqdm(total=steps, disable=not progress, desc=f"{simulator.name}", unit="step", dynamic_ncols=True)
    try:
        emit(state)
        for k in range(1, steps + 1):
            _sync(state.device)
            start = time.perf_counter()
            new = simulator.step(state)
            _sync(state.device)
            elapsed = time.perf_counter() - start
            write = k % write_every == 0 or k == steps
            if write or k % guard.check_every == 0:
                guard.check(new)
            # only steps whose result was accepted are counted
            record["step_seconds"].append(elapsed)
            for name, sec in simulator.last_timings.items():
                record["stage_seconds"].setdefault(name, []).append(sec)
            for name, value in simulator.last_info.items():
                record["info"].setdefault(name, []).append(value)
            state = new
            if write:
                emit(state)
            bar.update(1)
            if k % 10 == 0:
                bar.set_postfix(ms_per_step=f"{1e3 * median(record['step_seconds'][-10:]):.0f}")
    except BaseException as err:
        err.record, err.state = record, state  # type: ignore[attr-defined]
        raise
    finally:
        bar.close()
    return state, record


def _timing_summary(record: dict[str, Any]) -> dict[str, Any]:
    steps = record["step_seconds"]
    out: dict[str, Any] = {
        "time_per_step_median_s": median(steps) if steps else math.nan,
        "steps_per_second": 1.0 / median(steps) if steps else math.nan,
        "stage_median_s": {k: median(v) for k, v in record["stage_seconds"].items()},
    }
    info = record["info"]
    if "ppe_iterations" in info:
        it = info["ppe_iterations"]
        out["ppe"] = {
            "iterations_median": median(it),
            "iterations_max": max(it),
            "relative_residual_median": median(info["ppe_residual"]),
            "not_converged_steps": int(sum(1 for c in info["ppe_converged"] if not c)),
            "unknowns_median": median(info["ppe_unknowns"]),
        }
    return out


def simulate(cfg: DictConfig) -> dict[str, Any]:
    """``task=simulate``: roll out ``cfg.model`` on ``cfg.scene`` and write the three output files."""
    torch.manual_seed(int(cfg.seed))
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    if int(cfg.steps) < 0 or int(cfg.write_every) < 1:
        raise RolloutError(
            f"need steps >= 0 and write_every >= 1, got steps={cfg.steps}, write_every={cfg.write_every}"
        )
    out_dir = Path(cfg.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    # A failed run must not leave an earlier run's outputs looking like its own.
    for name in ("rollout.h5", "metrics.json", "preview.png"):
        (out_dir / name).unlink(missing_ok=True)
    device = torch.device(cfg.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise RolloutError(
            f"device={cfg.device} was asked for, but torch sees no CUDA device; use device=cpu"
        )
    state = build_initial_state(cfg)
    simulator = build_simulator(cfg)
    settings = SolverSettings.from_config(cfg.solver)
    guard = Guard(float(cfg.solver.guard.max_courant), int(cfg.solver.guard.check_every))
    params, nf = state.params, state.n_fluid
    n0 = lattice_constants(params.l0, settings, params.dim).n0
    attrs = run_attributes(state, cfg, simulator.name, str(cfg.scene.name), int(cfg.write_every))
    boundary = slice(nf, None)
    writer = TrajectoryWriter(
        out_dir / "rollout.h5",
        nf,
        state.pos[boundary].cpu().numpy(),
        state.ptype[boundary].cpu().numpy(),
        attrs,
    )
    density_errors: list[float] = []
    divergences: list[float] = []
    write_every = int(cfg.write_every)
    total_frames = int(cfg.steps) // write_every + 1 + (1 if int(cfg.steps) % write_every else 0)
    snapshots: dict[str, tuple[float, np.ndarray, np.ndarray]] = {}
    frame_counter = [0]

    def on_frame(s: ParticleState) -> None:
        m = field_metrics(
            s.pos,
            s.vel,
            s.ptype,
            n0,
            settings.re_density * params.l0,
            settings.re_gradient * params.l0,
            settings.surface_beta,
            params.dim,
            settings.neighbor_backend,
        )
        density_errors.append(m.density_error)
        divergences.append(m.velocity_divergence)
        # Keep only the first, middle and latest frame for the preview: O(1) memory for long runs.
        index, frame_counter[0] = frame_counter[0], frame_counter[0] + 1
        snap = (s.time, s.pos[:nf].cpu().numpy(), s.pressure[:nf].cpu().numpy())
        if index == 0:
            snapshots["first"] = snap
        if index == total_frames // 2:
            snapshots["middle"] = snap
        snapshots["last"] = snap

    stop_reason, complete = "", True
    record: dict[str, Any] = {"step_seconds": [], "stage_seconds": {}, "info": {}}
    start = time.perf_counter()
    try:
        _, record = rollout(
            simulator,
            state,
            int(cfg.steps),
            guard=guard,
            writer=writer,
            write_every=write_every,
            on_frame=on_frame,
            progress=bool(cfg.progress),
        )
    except BaseException as err:  # a guard stop, a bug, Ctrl-C: the file says the run is incomplete and why
        stop_reason = str(err) if isinstance(err, RolloutError) else f"{type(err).__name__}: {err}"
        complete = False
        record = getattr(err, "record", record)
        raise
    finally:
        for key, value in simulator.attributes().items():
            writer.group.attrs[key] = value
        writer.close(complete=complete, stop_reason=stop_reason)
        if snapshots:
            from lagfluid.viz import preview

            frames = [snapshots[k] for k in ("first", "middle", "last") if k in snapshots]
            frames = [f for i, f in enumerate(frames) if i == 0 or f[0] != frames[i - 1][0]]
            walls = state.pos[boundary][state.ptype[boundary] == ParticleType.WALL]
            preview(
                out_dir / "preview.png", frames, walls.cpu().numpy(), f"{simulator.name} on {cfg.scene.name}"
            )
        metrics = {
            "model": simulator.name,
            "scene": str(cfg.scene.name),
            "complete": complete,
            "stop_reason": stop_reason,
            "steps_requested": int(cfg.steps),
            "steps": len(record["step_seconds"]),
            "dt": params.dt,
            "device": str(cfg.device),
            "dtype": str(cfg.dtype),
            "particles": {
                "fluid": nf,
                "wall": int(state.wall_mask.sum()),
                "dummy": int(state.dummy_mask.sum()),
            },
            **_timing_summary(record),
            "density_error": summarize(density_errors),
            "velocity_divergence_per_s": summarize(divergences),
            "frames_evaluated": len(density_errors),
            "wall_time_total_s": time.perf_counter() - start,
            "simulator": simulator.attributes(),
            "version": lagfluid.__version__,
            "git_commit": attrs["git_commit"],
        }
        tmp = out_dir / "metrics.json.part"
        tmp.write_text(json.dumps(metrics, indent=2))
        os.replace(tmp, out_dir / "metrics.json")
    log.info(
        "wrote %s: %d steps, %.1f ms/step median, density error mean %.4f",
        out_dir,
        metrics["steps"],
        1e3 * metrics["time_per_step_median_s"],
        metrics["density_error"]["mean"],
    )
    return metrics
