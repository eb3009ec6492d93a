"""``task=simulate``: roll a model out on a scene and write its outputs.

``python -m lagfluid.run model=X scene=Y steps=N out_dir=DIR`` writes

* ``DIR/rollout.h5``   the trajectory (:mod:`lagfluid.data.store`),
* ``DIR/metrics.json`` counts, median wall time per step and per stage, density error and divergence,
* ``DIR/preview.png``  first, middle and last frame coloured by pressure (by speed for a model that predicts
  none, :func:`lagfluid.viz.colour_field`); a stopped run's title says why.

Outputs are never lost: everything that can be checked before the first step is (dtype, device, scene,
model and weights) before any file in ``DIR`` is touched, and the new files replace the old ones together
when the run ends (:mod:`lagfluid.tasks.outputs`). A run the guard stopped is a result too (its files say
``complete: false`` and why); the last complete run's files it replaces are kept in ``DIR/previous/``.
"""

from __future__ import annotations

import logging
import math
import os
import time
from pathlib import Path
from statistics import median
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig

import lagfluid
from lagfluid.data.store import TrajectoryWriter, open_lagfluid_file, stored_dtype
from lagfluid.errors import RolloutError
from lagfluid.metrics import field_metrics, summarize
from lagfluid.models.simulator import Simulator
from lagfluid.physics.settings import SolverSettings, lattice_constants
from lagfluid.rollout import Guard, rollout
from lagfluid.state import ParticleState, ParticleType
from lagfluid.tasks.config import (
    apply_threads,
    at_simulator_time_step,
    build_initial_state,
    build_simulator,
    check_run_memory,
    initial_history,
    run_attributes,
    run_guard,
)
from lagfluid.tasks.locks import hold_outputs
from lagfluid.tasks.outputs import begin, part_path, publish, write_json
from lagfluid.tasks.simulate_resume import RolloutCheckpoint, run_settings
from lagfluid.viz import colour_field, field_values, stopped_title

log = logging.getLogger(__name__)

OUTPUTS = ("rollout.h5", "metrics.json", "preview.png")


def timing_summary(record: dict[str, Any]) -> dict[str, Any]:
    """Median and mean time per step and per stage, steps per second, list rebuilds and PPE statistics.

    The median is a typical step; the mean is what a whole rollout costs per step. They differ where some
    steps carry rare, costly work: a flowing 40k dam rebuilds its Verlet list every few steps, and FGN's mean
    step there is ~1.4x its median (``benchmarks/results/neighbors_notes.md``, the Verlet skin). So each
    stage has its mean beside its median, and ``list_rebuilds`` counts the steps' neighbour-list searches
    (for simulators that report them).
    """
    steps = record["step_seconds"]
    out: dict[str, Any] = {
        "time_per_step_median_s": median(steps) if steps else math.nan,
        "time_per_step_mean_s": sum(steps) / len(steps) if steps else math.nan,
        "steps_per_second": 1.0 / median(steps) if steps else math.nan,
        "stage_median_s": {k: median(v) for k, v in record["stage_seconds"].items()},
        "stage_mean_s": {k: sum(v) / len(v) for k, v in record["stage_seconds"].items() if v},
    }
    info = record["info"]
    if "list_rebuilds" in info:
        out["list_rebuilds"] = int(sum(info["list_rebuilds"]))
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


class _FrameMetrics:
    """Density error and divergence of every stored frame, and the three frames of the preview.

    The preview's values are ``field``'s (``pressure`` or ``speed``, :func:`lagfluid.viz.colour_field`).
    """

    def __init__(self, state: ParticleState, settings: SolverSettings, total_frames: int, field: str) -> None:
        params = state.params
        self.settings, self.params, self.field = settings, params, field
        self.n0 = lattice_constants(params.l0, settings, params.dim).n0
        self.total_frames = total_frames
        self.density_errors: list[float] = []
        self.divergences: list[float] = []
        self.snapshots: dict[str, tuple[float, np.ndarray, np.ndarray]] = {}
        self.count = 0

    def __call__(self, s: ParticleState) -> None:
        settings, params, nf = self.settings, self.params, s.n_fluid
        m = field_metrics(
            s.pos,
            s.vel,
            s.ptype,
            self.n0,
            settings.re_density * params.l0,
            settings.re_gradient * params.l0,
            settings.surface_beta,
            params.dim,
            settings.neighbor_backend,
        )
        self.density_errors.append(m.density_error)
        self.divergences.append(m.velocity_divergence)
        # Keep only the first, middle and latest frame for the preview: O(1) memory for long runs.
        index, self.count = self.count, self.count + 1
        values = field_values(self.field, s.vel[:nf].cpu().numpy(), s.pressure[:nf].cpu().numpy())
        snap = (s.time, s.pos[:nf].cpu().numpy(), values)
        if index == 0:
            self.snapshots["first"] = snap
        if index == self.total_frames // 2:
            self.snapshots["middle"] = snap
        self.snapshots["last"] = snap

    def state_dict(self) -> dict[str, Any]:
        """What a resumed run needs to go on (:mod:`lagfluid.tasks.simulate_resume`); arrays as tensors."""
        return {
            "density_errors": list(self.density_errors),
            "divergences": list(self.divergences),
            "count": self.count,
            "snapshots": {
                k: (t, torch.from_numpy(p), torch.from_numpy(q)) for k, (t, p, q) in self.snapshots.items()
            },
        }

    def load_state_dict(self, saved: dict[str, Any], state: ParticleState) -> None:
        """Restore :meth:`state_dict`'s values (the snapshots hold the same simulator's field)."""
        self.density_errors = list(saved["density_errors"])
        self.divergences = list(saved["divergences"])
        self.count = int(saved["count"])
        self.snapshots = {k: (float(t), p.numpy(), q.numpy()) for k, (t, p, q) in saved["snapshots"].items()}


def _reopen_partial_trajectory(out_dir: Path, frames: int) -> TrajectoryWriter:
    """The stopped run's trajectory, reopened after its first ``frames`` frames.

    A kill -9 leaves it as the writer's part file; Ctrl-C, SIGTERM or a guard stop published it as
    ``rollout.h5`` with ``complete=false`` (moved back to the part file here).
    """
    final = part_path(out_dir / "rollout.h5")
    partial = final.with_name(final.name + ".part")
    published = out_dir / "rollout.h5"
    if not partial.exists() and published.exists():
        with open_lagfluid_file(published) as f:
            complete = bool(f["00000"].attrs.get("complete", False))
        if complete:
            raise RolloutError(f"resume=true: {published} is a complete run; nothing to resume")
        os.replace(published, partial)
    if not partial.exists():
        raise RolloutError(f"resume=true: no partial trajectory in {out_dir} to continue")
    return TrajectoryWriter.reopen(final, frames)


def _write_preview(out_dir: Path, frames: _FrameMetrics, state: ParticleState, title: str) -> None:
    """``preview.png`` of the first, middle and last frame; a failure to draw it costs only the figure."""
    if not frames.snapshots:
        return
    from lagfluid.viz import preview

    shots = [frames.snapshots[k] for k in ("first", "middle", "last") if k in frames.snapshots]
    shots = [f for i, f in enumerate(shots) if i == 0 or f[0] != shots[i - 1][0]]
    nf = state.n_fluid
    walls = state.pos[nf:][state.ptype[nf:] == ParticleType.WALL]
    try:
        preview(part_path(out_dir / "preview.png"), shots, walls.cpu().numpy(), title, frames.field)
    except Exception as err:  # the rollout and its metrics matter more than the picture
        part_path(out_dir / "preview.png").unlink(missing_ok=True)
        log.warning("preview.png not written: %s: %s", type(err).__name__, err)


def simulate(cfg: DictConfig) -> dict[str, Any]:
    """``task=simulate``: roll out ``cfg.model`` on ``cfg.scene`` and write the three output files."""
    out_dir = Path(cfg.out_dir)
    run = SimulationRun(out_dir, cfg, *_set_up(cfg))  # touches no file yet
    with hold_outputs(out_dir, "simulate"):  # a second run into out_dir is refused, before it touches it
        return _simulate_in(run)


def _set_up(cfg: DictConfig) -> tuple[ParticleState, Simulator, SolverSettings, Guard]:
    """Everything that can fail before the first step, before ``out_dir`` is touched.

    Returns:
        The initial state at the simulator's time step, the simulator (reset on it), the solver settings and
        the run's guard.

    Raises:
        RolloutError: ``steps < 0`` or ``write_every < 1``; and whatever the checks of the export format,
            scene, model and weights, memory and the simulator's per-scene set-up raise.
    """
    torch.manual_seed(int(cfg.seed))
    apply_threads(cfg)
    if int(cfg.steps) < 0 or int(cfg.write_every) < 1:
        raise RolloutError(
            f"need steps >= 0 and write_every >= 1, got steps={cfg.steps}, write_every={cfg.write_every}"
        )
    if cfg.get("export") is not None:
        from lagfluid.tasks.export import check_format

        check_format(cfg.export)
    state = build_initial_state(cfg)
    simulator = build_simulator(cfg)
    state = at_simulator_time_step(state, simulator, cfg)
    history = initial_history(cfg, simulator)
    settings = SolverSettings.from_config(cfg.solver)
    guard = run_guard(cfg, simulator)
    check_run_memory(cfg, state, simulator)  # before the first neighbour search
    simulator.reset(state, history)  # per-scene set-up can fail too (a plugin's checks, the history)
    return state, simulator, settings, guard


def _simulate_in(run: SimulationRun) -> dict[str, Any]:
    """The run of :func:`simulate` once everything is checked and ``out_dir`` is locked; its metrics."""
    out_dir, cfg = run.out_dir, run.cfg
    metrics = run.roll(run.resume() if bool(cfg.resume) else run.start())
    log.info(
        "wrote %s: %d steps, %.1f ms/step median, density error mean %.4f",
        out_dir,
        metrics["steps"],
        1e3 * metrics["time_per_step_median_s"],
        metrics["density_error"]["mean"],
    )
    if cfg.get("export"):
        from lagfluid.tasks.export import export_rollout

        log.info("exported %s", export_rollout(out_dir / "rollout.h5", str(cfg.export), cfg))
    return metrics


class SimulationRun:
    """One ``task=simulate`` run in its locked ``out_dir``, from a fresh start or a stopped run's checkpoint.

    Its parts: :meth:`start` (a fresh trajectory file) or :meth:`resume` (the stopped run's state, history,
    record, frame metrics and trajectory), :meth:`roll` (the rollout with its hooks: :meth:`on_frame`, and the
    checkpoint's ``on_step``), :meth:`write_outputs` (trajectory closed, ``metrics.json`` of
    :meth:`metrics`, ``preview.png``, all published together whatever happened).
    """

    def __init__(
        self,
        out_dir: Path,
        cfg: DictConfig,
        state: ParticleState,
        simulator: Simulator,
        settings: SolverSettings,
        guard: Guard,
    ) -> None:
        """The run's frame metrics, resume checkpoint and an empty timing record; no file is touched yet."""
        self.out_dir, self.cfg, self.state, self.simulator, self.guard = out_dir, cfg, state, simulator, guard
        self.write_every = write_every = int(cfg.write_every)
        total_frames = int(cfg.steps) // write_every + 1 + (1 if int(cfg.steps) % write_every else 0)
        self.frames = _FrameMetrics(state, settings, total_frames, colour_field(simulator))
        self.checkpoint = RolloutCheckpoint(
            out_dir, run_settings(cfg), simulator.history_length, float(cfg.checkpoint_every_s)
        )
        self.checkpoint.memory = getattr(simulator, "rollout_memory", None)
        self.record: dict[str, Any] = {"step_seconds": [], "stage_seconds": {}, "info": {}}
        self.wall_before = 0.0  # the wall time of the run before a resume
        self.writer: TrajectoryWriter | None = None
        self.start_time, self.commit = 0.0, ""  # set when the rollout starts

    # ---------------------------------------------------------------------------------- start, resume
    def start(self) -> ParticleState:
        """A fresh run: the outputs begun, an old checkpoint removed, a new trajectory file; its start state.

        A trajectory start's state already counts the steps before its frame.
        """
        out_dir, state, nf = self.out_dir, self.state, self.state.n_fluid
        begin(out_dir, OUTPUTS)
        self.checkpoint.remove()
        cfg, name = self.cfg, self.simulator.name
        attrs = run_attributes(state, cfg, name, str(cfg.scene.name), self.write_every)
        boundary = slice(nf, None)
        self.writer = TrajectoryWriter(
            part_path(out_dir / "rollout.h5"),
            nf,
            state.pos[boundary].cpu().numpy(),
            state.ptype[boundary].cpu().numpy(),
            attrs,
            dtype=stored_dtype(state),
        )
        return state

    def resume(self) -> ParticleState:
        """``resume=true``: the stopped run's state, to go on from where its checkpoint left it.

        Restores the simulator's history (and a model's memory between steps), the checkpoint's window of
        states, the timing record, the wall time so far and the frame metrics, and reopens the trajectory
        after its stored frames (the constants stay the start's, see :mod:`lagfluid.tasks.simulate_resume`).

        Raises:
            RolloutError: no checkpoint or partial trajectory, other settings, or a run past ``steps``.
        """
        out_dir, cfg, state, simulator = self.out_dir, self.cfg, self.state, self.simulator
        checkpoint = self.checkpoint
        start_state, before, memory, written, extra = checkpoint.load(state)
        if start_state.step - state.step > int(cfg.steps):
            raise RolloutError(
                f"resume=true: the run in {out_dir} is at step {start_state.step - state.step}, past "
                f"steps={cfg.steps}"
            )
        if simulator.history_length:
            simulator.reset(start_state, before)
            if memory and hasattr(simulator, "restore_rollout_memory"):
                simulator.restore_rollout_memory(start_state, memory)
        for state_before in before:
            checkpoint.on_step(state_before, start_state, None)
        self.record, self.wall_before = extra["record"], float(extra["wall_time_s"])
        self.frames.load_state_dict(extra["frames"], start_state)
        self.writer = _reopen_partial_trajectory(out_dir, written)
        begin(out_dir, OUTPUTS[1:])
        log.info("resuming %s at step %d (%d frames stored)", out_dir, start_state.step, written)
        return start_state

    # ---------------------------------------------------------------------------------- the rollout
    def on_frame(self, s: ParticleState) -> None:
        """Hook of every stored frame: appended to the trajectory, measured, and checkpointed when due."""
        nf = self.state.n_fluid
        self.writer.append(
            s.time,
            s.pos[:nf].detach().cpu().numpy(),
            s.vel[:nf].detach().cpu().numpy(),
            s.pressure[:nf].detach().cpu().numpy(),
        )
        self.frames(s)
        extra = {
            "record": self.record,
            "frames": self.frames.state_dict(),
            "wall_time_s": self.wall_before + time.perf_counter() - self.start_time,
        }
        self.checkpoint.maybe_save(s, self.writer.frames, extra)

    def roll(self, start_state: ParticleState) -> dict[str, Any]:
        """The rollout from ``start_state`` to ``steps``, then the outputs whatever happened; the metrics.

        A guard stop, a bug or Ctrl-C is raised again after the outputs say the run is incomplete and why;
        Ctrl-C or SIGTERM first saves a checkpoint at the last frame (``resume=true`` continues from it).
        """
        cfg, state, checkpoint = self.cfg, self.state, self.checkpoint
        self.commit = str(self.writer.group.attrs.get("git_commit", ""))
        self.start_time = time.perf_counter()
        stop_reason, complete, by_guard = "", True, False
        try:
            _, self.record = rollout(
                self.simulator,
                start_state,
                int(cfg.steps) - (start_state.step - state.step),
                guard=self.guard,
                write_every=self.write_every,
                on_frame=self.on_frame,
                on_step=checkpoint.on_step,
                progress=bool(cfg.progress),
                reset=False,
                step_offset=start_state.step - state.step,
                record=self.record,
            )
        except BaseException as err:  # a guard stop, a bug, Ctrl-C: the files say the run is incomplete, why
            by_guard = isinstance(err, RolloutError)  # the guard's stop; else Ctrl-C, SIGTERM or a bug
            stop_reason = str(err) if by_guard else f"{type(err).__name__}: {err}"
            complete = False
            if isinstance(err, KeyboardInterrupt):  # Ctrl-C, SIGTERM: resume=true goes on from the last frame
                checkpoint.save_latest()
            self.record = getattr(err, "record", self.record)
            raise
        finally:
            metrics = self.write_outputs(complete, stop_reason, by_guard)
        return metrics

    # ---------------------------------------------------------------------------------- the outputs
    def write_outputs(self, complete: bool, stop_reason: str, by_guard: bool) -> dict[str, Any]:
        """Close the trajectory, write ``metrics.json`` and ``preview.png``, publish the three; the metrics.

        Whatever fails on the way, the folder holds one run's files (:func:`lagfluid.tasks.outputs.publish`).
        """
        cfg, simulator, out_dir = self.cfg, self.simulator, self.out_dir
        try:
            if complete:
                self.checkpoint.remove()
            self.writer.set_attributes(simulator.attributes())
            self.writer.close(complete=complete, stop_reason=stop_reason)
            metrics = self.metrics(complete, stop_reason)
            write_json(part_path(out_dir / "metrics.json"), metrics)
            title = stopped_title(f"{simulator.name} on {cfg.scene.name}", stop_reason, by_guard)
            _write_preview(out_dir, self.frames, self.state, title)
        finally:  # whatever failed above, the folder holds one run's files
            publish(out_dir, OUTPUTS, complete)
        return metrics

    def metrics(self, complete: bool, stop_reason: str) -> dict[str, Any]:
        """``metrics.json``: counts, timings, density error and divergence, the simulator, provenance."""
        cfg, state, simulator, frames = self.cfg, self.state, self.simulator, self.frames
        return {
            "model": simulator.name,
            "scene": str(cfg.scene.name),
            "complete": complete,
            "stop_reason": stop_reason,
            "steps_requested": int(cfg.steps),
            "steps": len(self.record["step_seconds"]),
            "dt": state.params.dt,
            "device": str(cfg.device),
            "dtype": str(cfg.dtype),
            "parameters": int(simulator.parameters),
            "particles": {
                "fluid": state.n_fluid,
                "wall": int(state.wall_mask.sum()),
                "dummy": int(state.dummy_mask.sum()),
            },
            **timing_summary(self.record),
            "density_error": summarize(frames.density_errors),
            "velocity_divergence_per_s": summarize(frames.divergences),
            "frames_evaluated": len(frames.density_errors),
            "wall_time_total_s": self.wall_before + time.perf_counter() - self.start_time,
            "simulator": simulator.attributes(),
            "version": lagfluid.__version__,
            "git_commit": self.commit,
        }
