"""From a composed Hydra config to the objects of a run, shared by the tasks.

The initial state (its parameters: :func:`lagfluid.scenes.scene_params`), the simulator (through the
registry, checked against the :class:`~lagfluid.models.simulator.Simulator` contract and run at its own time
step), the provenance attributes every output file carries, and the per-job output folder of a Hydra
multirun.
"""

from __future__ import annotations

import logging
import re
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

import lagfluid
from lagfluid.errors import ConfigError
from lagfluid.models.exact_after import with_exact_after
from lagfluid.models.simulator import Simulator, check_simulator
from lagfluid.registry import check_scene_name, get_simulator_factory
from lagfluid.rollout import Guard
from lagfluid.scenes import build_scene, scene_builder, scene_params, trajectory_history
from lagfluid.state import ParticleState, parse_dtype

log = logging.getLogger(__name__)


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


# top-level keys every task reads as whole numbers, with their smallest valid value
_WHOLE_NUMBERS = {"steps": 0, "seed": 0, "write_every": 1, "num_scenes": 1}


def check_run_numbers(cfg: DictConfig) -> None:
    """Refuse a top-level ``steps``, ``seed``, ``write_every``, ``num_scenes`` or ``dt`` of the wrong kind.

    ``steps=abc`` would otherwise fail deep inside a task; every task checks these first (``dispatch``).

    Raises:
        ConfigError: naming the key and the value.
    """
    for key, least in _WHOLE_NUMBERS.items():
        value = cfg.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < least:
            raise ConfigError(f"{key} must be a whole number >= {least}, got {value!r}")
    dt = cfg.get("dt")
    if dt is not None and (isinstance(dt, bool) or not isinstance(dt, (int, float)) or not dt > 0):
        raise ConfigError(f"dt must be a time step > 0 in s (or null: the scene's), got {dt!r}")


def apply_threads(cfg: DictConfig) -> None:
    """Give torch ``cfg.threads`` intra-op threads; ``null`` keeps torch's default (every core).

    Raises:
        ConfigError: ``threads`` that is not a whole number >= 1 (``0`` or ``-1`` would silently mean all).
    """
    threads = cfg.get("threads")
    if threads is None:
        return
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise ConfigError(f"threads must be a whole number >= 1 (or null: every core), got {threads!r}")
    torch.set_num_threads(threads)


def run_dtype(cfg: DictConfig) -> torch.dtype:
    """The floating dtype of ``cfg.dtype`` (:func:`lagfluid.state.parse_dtype`)."""
    return parse_dtype(cfg.dtype)


def run_device(cfg: DictConfig) -> torch.device:
    """The torch device of ``cfg.device``: ``cpu`` or ``cuda[:N]`` (what lagfluid's kernels are written for).

    Raises:
        ConfigError: not a device string, another device type (``mps``, ``meta``), or CUDA asked for where
            torch sees none.
    """
    try:
        device = torch.device(str(cfg.device))
    except RuntimeError as err:
        raise ConfigError(f"unknown device '{cfg.device}'; use device=cpu or device=cuda[:N]") from err
    if device.type not in ("cpu", "cuda"):
        raise ConfigError(f"device={cfg.device} is not supported; use device=cpu or device=cuda[:N]")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device={cfg.device} was asked for, but torch sees no CUDA device; use device=cpu")
    return device


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
        # the domain, so that a run started from this file (scene=trajectory) keeps the same guard
        "bounds": None if state.bounds is None else state.bounds.detach().cpu().numpy().astype(np.float64),
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
    builder = scene_builder(cfg)
    check_scene_name(builder)
    dtype = run_dtype(cfg)
    scene = OmegaConf.to_container(cfg.scene, resolve=True)
    options = {k: v for k, v in scene.items() if k not in ("name", "builder", "params")}
    state = build_scene(builder, scene_params(cfg), dtype=dtype, **options)
    return state.to(device=run_device(cfg))


def check_run_memory(cfg: DictConfig, state: ParticleState, simulator: Simulator, also: float = 0.0) -> None:
    """Refuse a CPU run whose estimated peak memory exceeds the memory available now, in one line.

    Called once the particles are built, before the simulator's first neighbour search (its ``reset``): a
    scene too large is refused naming the estimate, the memory available and the scene keys to shrink,
    instead of being killed by the OS (and other jobs with it) later. The estimate is the simulator's
    (:func:`lagfluid.memory.memory_needed`); a CUDA run is not estimated (calibrated on the CPU only).

    Args:
        cfg: the run's config (the scene's name and keys, for the message).
        state: the initial state.
        simulator: the run's simulator.
        also: bytes the task needs besides the rollout (``task=evaluate``'s exact one-step errors).

    Raises:
        SceneError: the estimate exceeds the available memory.
    """
    from lagfluid.memory import memory_needed
    from lagfluid.scenes.validation import check_memory, shrink_advice

    if state.device.type != "cpu":
        return
    files = cfg.scene.get("path") or cfg.scene.get("container")  # a file scene's file, a mesh scene's tank
    check_memory(
        memory_needed(simulator, state) + also,
        f"a rollout of model {simulator.name} ({state.n_fluid:,} fluid of {state.num_particles:,} particles)",
        f"scene '{cfg.scene.name}'" + (f" ({files})" if files else ""),
        shrink_advice(cfg.scene.keys()),
    )


def build_simulator(cfg: DictConfig) -> Simulator:
    """The simulator named by ``cfg.model.name``, checked against the Simulator contract.

    With ``cfg.model.exact_after`` on, it is followed by exact MPS stages after each step
    (:mod:`lagfluid.models.exact_after`), whatever the model.
    """
    name = str(cfg.model.name)
    return with_exact_after(check_simulator(get_simulator_factory(name)(cfg), name), cfg)


def at_simulator_time_step(state: ParticleState, simulator: Simulator, cfg: DictConfig) -> ParticleState:
    """``state`` with the time step the simulator steps by: its own ``dt`` when it declares one.

    Raises:
        ConfigError: ``dt=`` was set on the command line to another value than the model's own.
    """
    own = simulator.dt
    if own is None or own == state.params.dt:
        return state
    if cfg.get("dt") is not None:
        raise ConfigError(
            f"model '{simulator.name}' steps by its own dt={own} s (it was trained so); "
            f"dt={cfg.dt} cannot change that: drop dt= from the command line"
        )
    log.info("model %s steps by its own dt=%g s (scene: %g s)", simulator.name, own, state.params.dt)
    return ParticleState(
        pos=state.pos,
        vel=state.vel,
        ptype=state.ptype,
        params=state.params.with_overrides(dt=float(own)),
        pressure=state.pressure,
        time=state.time,
        step=state.step,
        bounds=state.bounds,
        check=False,
    )


def run_guard(cfg: DictConfig, simulator: Simulator) -> Guard:
    """The rollout guard of a run: ``solver.guard``, with the Courant limit the simulator states, if any."""
    limit = simulator.max_courant
    return Guard(
        float(cfg.solver.guard.max_courant if limit is None else limit), int(cfg.solver.guard.check_every)
    )


def initial_history(cfg: DictConfig, simulator: Simulator) -> list[ParticleState]:
    """The earlier states ``simulator.reset`` gets: frames before ``scene.frame`` for ``scene=trajectory``.

    Args:
        cfg: the run's config.
        simulator: the run's simulator; it gets ``min(history_length, t)`` frames ``t-H .. t-1`` (oldest
            first) of the trajectory file when the scene starts at its frame ``t``.

    Returns:
        the history (on ``cfg.device`` in ``cfg.dtype``, at the simulator's time step); empty for a scene
        built from scratch or a simulator without history.

    Raises:
        ConfigError: the file's frames are not spaced by the simulator's time step (its own ``dt``, or the
            scene's); the message names both spacings.
        SceneError: those frames are not uniformly spaced, or the file or frame is bad.
    """
    if scene_builder(cfg) != "trajectory" or simulator.history_length == 0:
        return []
    params = scene_params(cfg)
    dt = float(simulator.dt) if simulator.dt is not None else params.dt
    history = trajectory_history(
        cfg.scene.path,
        int(cfg.scene.frame),
        simulator.history_length,
        dt,
        params.with_overrides(dt=dt),
        run_dtype(cfg),
    )
    device = run_device(cfg)
    return [s.to(device=device) for s in history]


def folder_name(overrides: str) -> str:
    """``k1=v1,k2=v2`` as a file name: path separators and awkward characters become ``_``, cut at 120."""
    return re.sub(r"[^A-Za-z0-9=.,+_-]", "_", overrides)[:120]


def job_folder(num: int, override_dirname: str) -> str:
    """The folder of multirun job ``num`` under ``out_dir``: its number and the overrides that made it.

    ``override_dirname`` is Hydra's ``k1=v1,k2=v2`` of the job (:func:`folder_name`; the number keeps
    folders unique when names are cut).
    """
    name = folder_name(override_dirname)
    return f"{num}_{name}" if name else str(num)


def multirun_out_dir(cfg: DictConfig) -> Path | None:
    """``<out_dir>/<job folder>`` when ``cfg`` is a job of a Hydra multirun, else None.

    Every job of a sweep resolves the same ``out_dir`` unless it happens to interpolate what the sweep
    varies; one folder per job keeps one job's ``rollout.h5`` from replacing another's. ``task=train`` is
    the exception for ``stage``: the trainables of one model write files of their own names into one
    folder (``model.weights=<folder>`` loads them together), so jobs that differ only in ``stage`` share
    ``<out_dir>/<the other overrides>`` (``out_dir`` itself when there are none).
    """
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if not HydraConfig.initialized():
        return None
    hydra_cfg = HydraConfig.get()
    if hydra_cfg.mode != RunMode.MULTIRUN:
        return None
    out_dir = Path(str(cfg.out_dir))
    if cfg.task != "train":
        return out_dir / job_folder(int(hydra_cfg.job.num), str(hydra_cfg.job.override_dirname))
    exclude = {*hydra_cfg.job.config.override_dirname.exclude_keys, "stage"}
    others = sorted(o for o in hydra_cfg.overrides.task if o.split("=", 1)[0].lstrip("+~") not in exclude)
    return out_dir / folder_name(",".join(others)) if others else out_dir
