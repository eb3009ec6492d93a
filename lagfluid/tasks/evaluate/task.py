"""``task=evaluate``: the model and the reference rolled out, compared and written (see the package doc)."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

import lagfluid
from lagfluid.errors import ConfigError, RolloutError
from lagfluid.memory import exact_step_bytes
from lagfluid.models.simulator import Simulator
from lagfluid.physics.settings import SolverSettings
from lagfluid.state import ParticleState
from lagfluid.tasks.config import (
    apply_threads,
    at_simulator_time_step,
    build_initial_state,
    build_simulator,
    check_run_memory,
    git_commit,
    initial_history,
    run_device,
    scene_params,
)
from lagfluid.tasks.evaluate.compare import compare, summaries
from lagfluid.tasks.evaluate.figures import plot_errors, plot_pressure_slice
from lagfluid.tasks.evaluate.model_run import run_model
from lagfluid.tasks.evaluate.options import EvaluateOptions
from lagfluid.tasks.evaluate.reference import key_hash, reference_rollout
from lagfluid.tasks.export.animation import side_by_side
from lagfluid.tasks.locks import hold_outputs
from lagfluid.tasks.outputs import begin, part_path, publish, write_json
from lagfluid.viz import colour_field, stopped_title

log = logging.getLogger(__name__)

OUTPUTS = ("rollout.h5", "metrics.json", "error_vs_time.png", "pressure_slice.png", "side_by_side.gif")


def reference_overrides(
    cfg: DictConfig, options: EvaluateOptions, simulator: Simulator, state: ParticleState
) -> dict[str, Any]:
    """``evaluate.reference``, plus what a model stepping by its own dt needs: MPS over the same time.

    A model with its own ``dt`` (trained on frames several solver steps apart) is compared with MPS at the
    scene's dt; MPS then runs ``dt_model / dt_scene`` times the steps and stores frames as often in time.
    Settings the user gave in ``evaluate.reference`` win.

    Raises:
        ConfigError: the model's dt is not a whole multiple of the scene's.
    """
    overrides = dict(options.reference)
    own = simulator.dt
    if own is None:
        return overrides
    scene_dt = scene_params(cfg).dt
    ratio = float(own) / scene_dt
    if abs(ratio - round(ratio)) > 1e-6 * ratio or round(ratio) < 1:
        raise ConfigError(
            f"model '{simulator.name}' steps by dt={own} s, not a whole multiple of the scene's "
            f"{scene_dt} s; "
            "set evaluate.reference={dt: ..., steps: ..., write_every: ...} to say how MPS should run"
        )
    k = round(ratio)
    if k > 1:
        overrides.setdefault("steps", int(cfg.steps) * k)
        overrides.setdefault("write_every", int(cfg.write_every) * k)
    return overrides


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
    apply_threads(cfg)
    options = EvaluateOptions.from_config(cfg.evaluate)
    steps, write_every = int(cfg.steps), int(cfg.write_every)
    if steps < 1 or write_every < 1:
        raise ConfigError(f"task=evaluate needs steps >= 1 and write_every >= 1, got {steps}, {write_every}")
    run_device(cfg)
    # Model first: an unknown model or missing weights fail before a possibly long reference run, and
    # everything fails before out_dir is touched (its last outputs stay until new ones replace them).
    state = build_initial_state(cfg)
    simulator = build_simulator(cfg)
    state = at_simulator_time_step(state, simulator, cfg)
    history = initial_history(cfg, simulator)
    # before the first neighbour search; the one-step errors keep an exact MPS neighbour list beside the model
    check_run_memory(cfg, state, simulator, also=exact_step_bytes(state) if options.one_step else 0.0)
    simulator.reset(state, history)  # per-scene set-up can fail too: before the reference and out_dir
    options = replace(options, reference=reference_overrides(cfg, options, simulator, state))
    out_dir = Path(cfg.out_dir)
    with hold_outputs(out_dir, "evaluate"):  # before the reference: a second run is refused at once
        reference_path, reused, key = reference_rollout(cfg, options)
        begin(out_dir, OUTPUTS)
        model_path = part_path(out_dir / "rollout.h5")
        run = run_model(cfg, simulator, state, model_path, options.one_step, reset=False)
        reference = {
            "path": str(reference_path),
            "reused": reused,
            "overrides": options.reference,
            "key_hash": key_hash(key),
            "key": key,
        }
        try:
            metrics = _compare_and_write(cfg, options, simulator, state, run, model_path, reference)
            metrics["wall_time_total_s"] = time.perf_counter() - start
            write_json(part_path(out_dir / "metrics.json"), metrics)
        finally:  # whatever failed above, the folder holds one run's files
            publish(out_dir, OUTPUTS, run["complete"])
    summary = metrics["summary"]
    log.info(
        "wrote %s: %s vs MPS, %d frames, Chamfer mean %.3f mm, density error mean %.4f (MPS %.4f)",
        out_dir,
        simulator.name,
        len(metrics["frames"]["step"]),
        summary["chamfer_mm"]["mean"],
        summary["density_error"]["model"]["mean"],
        summary["density_error"]["reference"]["mean"],
    )
    return metrics


def evaluate_task(cfg: DictConfig) -> dict[str, Any]:
    """``task=evaluate`` from the command line: :func:`evaluate`, then a model the guard stopped is an error.

    :func:`evaluate` returns a stopped model's metrics (the benchmark tables record it as a row); the command
    exits non-zero for it, as ``task=simulate`` does for a guard stop, naming the stop in one line.

    Raises:
        RolloutError: the model was stopped by the rollout guard (its frames were evaluated and written).
    """
    metrics = evaluate(cfg)
    if not metrics["complete"]:
        raise RolloutError(
            f"model {metrics['model']} stopped after {metrics['steps']} of {metrics['steps_requested']} "
            f"steps: {metrics['stop_reason']} (the frames before the stop are evaluated in {cfg.out_dir})"
        )
    return metrics


def _compare_and_write(
    cfg: DictConfig,
    options: EvaluateOptions,
    simulator: Simulator,
    state: ParticleState,
    run: dict[str, Any],
    model_path: Path,
    reference: dict[str, Any],
) -> dict[str, Any]:
    """Compare the model's rollout with the reference and draw the figures: ``metrics.json``'s content."""
    out_dir, reference_path = model_path.parent, Path(reference["path"])
    steps, write_every = int(cfg.steps), int(cfg.write_every)

    settings = SolverSettings.from_config(cfg.solver)
    frames = compare(model_path, reference_path, settings)
    for name in ("advection_nmae", "ppe_relative_residual"):
        by_step = dict(zip(run["step"], run[name], strict=True))
        frames[name] = [by_step.get(s, math.nan) for s in frames["step"]]

    slice_info = None
    if options.figures:
        # a model stops only by the guard here (run_model); a model without pressure is shown by speed
        title = stopped_title(
            f"{simulator.name} vs MPS on {cfg.scene.name}", run["stop_reason"], by_guard=True
        )
        field = colour_field(simulator)
        try:
            plot_errors(part_path(out_dir / "error_vs_time.png"), frames, title)
            slice_path = part_path(out_dir / "pressure_slice.png")
            slice_info = plot_pressure_slice(slice_path, model_path, reference_path, options, title, field)
            side_by_side(model_path, reference_path, part_path(out_dir / "side_by_side.gif"), field)
        except Exception as err:  # the metrics matter more than the pictures
            for name in ("error_vs_time.png", "pressure_slice.png", "side_by_side.gif"):
                part_path(out_dir / name).unlink(missing_ok=True)
            log.warning("figures not written: %s: %s", type(err).__name__, err)
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
        "parameters": int(simulator.parameters),
        "summary": summaries(frames, options.horizons),
        "frames": frames,
        "pressure_slice": slice_info,
        "timing": run["timing"],
        "reference": reference,
        "simulator": simulator.attributes(),
        "config": OmegaConf.to_yaml(cfg, resolve=True),
        "version": lagfluid.__version__,
        "git_commit": git_commit(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    return metrics
