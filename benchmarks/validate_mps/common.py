"""What every check shares: the report row, the run log, the solver under test and the monitored rollout."""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig, OmegaConf

from lagfluid.errors import RolloutError
from lagfluid.metrics import field_metrics
from lagfluid.models.mps_simulator import build_mps
from lagfluid.physics.settings import SolverSettings, lattice_constants
from lagfluid.rollout import Guard, rollout
from lagfluid.run import CONF_DIR
from lagfluid.state import ParticleState, ParticleType

RESULTS = Path(__file__).resolve().parents[1] / "results"
# the authors' grid, shipped beside this script with their MIT licence (authors/README.md)
AUTHORS_DAM = Path(__file__).resolve().parent / "authors" / "dam_col_4k.npz"
PAPER_DENSITY_ERROR, PAPER_DIVERGENCE = 0.038, 0.019  # FGN Table 1, MPS ground truth


@dataclass
class Check:
    """One line of the report. ``status`` is PASS, FAIL or INFO (informative, never fails the run)."""

    check: str
    quantity: str
    measured: str
    criterion: str
    status: str


@dataclass
class RunLog:
    """Per-step bookkeeping of one rollout: mass, leaks, Courant number, PPE, metrics, surge front."""

    name: str
    n_fluid: int
    inner_lo: np.ndarray | None  # inner wall planes (x, y, z); None without walls
    inner_hi: np.ndarray | None
    l0: float
    dt: float
    steps_done: int = 0
    fluid_counts: set[int] = field(default_factory=set)
    nonfinite_steps: int = 0
    outside_steps: int = 0
    outside_max: int = 0
    below_floor_max: int = 0
    min_clearance: float = math.inf  # l0, smallest distance of a fluid particle to an inner wall plane
    courant_max: float = 0.0
    ppe_converged: list[float] = field(default_factory=list)
    ppe_iterations: list[float] = field(default_factory=list)
    error: str = ""
    wall_s: float = 0.0
    series: dict[str, list[float]] = field(default_factory=dict)

    def add(self, key: str, value: float) -> None:
        """Append ``value`` to the time series ``key``."""
        self.series.setdefault(key, []).append(float(value))


# Set from ``--profile NAME`` and ``--solver key=value ...``: applied to every run of this process, under
# the per-call overrides.
SOLVER_PROFILE: list[str] = ["mps"]
SOLVER_OVERRIDES: dict[str, Any] = {}


def profile_config(name: str) -> DictConfig:
    """The solver profile ``conf/solver/<name>.yaml`` as Hydra composes it (its ``defaults`` resolved).

    Raises:
        SystemExit: no such profile (the message lists the available ones).
    """
    return _composed_profile(name).copy()  # a copy: callers merge into it


@functools.cache
def _composed_profile(name: str) -> DictConfig:
    # Cached: every simulator of a report asks for it, and composing the whole config is not free.
    available = sorted(p.stem for p in (CONF_DIR / "solver").glob("*.yaml"))
    if name not in available:
        raise SystemExit(f"unknown solver profile '{name}'; available: {', '.join(available)}")
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=[f"solver={name}"]).solver


def solver_config(**overrides: Any) -> Any:
    """The ``--profile`` (default ``mps``) with the ``--solver`` overrides, then ``overrides``."""
    return OmegaConf.merge(profile_config(SOLVER_PROFILE[0]), SOLVER_OVERRIDES, overrides)


def make_sim(**overrides: Any) -> Any:
    return build_mps(OmegaConf.create({"solver": solver_config(**overrides)}))


def inner_box(state: ParticleState) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Inner wall planes of an open box tank: the innermost wall layer on each side (z has no top).

    The number of wall layers is read off the floor (distinct wall z levels below the fluid).
    """
    walls = state.pos[state.ptype == ParticleType.WALL].double().numpy()
    if len(walls) == 0:
        return None, None
    l0 = state.params.l0
    zmin_fluid = float(state.pos[: state.n_fluid, 2].min())
    layers = len(np.unique(np.round(walls[walls[:, 2] < zmin_fluid, 2] / l0)))
    lo = walls.min(axis=0) + (layers - 1) * l0
    hi = walls.max(axis=0) - (layers - 1) * l0
    hi[2] = np.inf
    return lo, hi


def monitored_rollout(
    sim: Any,
    state: ParticleState,
    steps: int,
    name: str,
    on_step: Any = None,
    log_every: int = 50,
) -> tuple[ParticleState, RunLog]:
    """Roll out with the project's guard (Courant 0.5) and check mass / leaks after every step."""
    lo, hi = inner_box(state)
    nf, l0 = state.n_fluid, state.params.l0
    log = RunLog(name, nf, lo, hi, l0, state.params.dt)
    start = time.perf_counter()

    def on_frame(s: ParticleState) -> None:
        log.steps_done = s.step
        log.fluid_counts.add(int((s.ptype == ParticleType.FLUID).sum()))
        x = s.pos[:nf].double().numpy()
        v = s.vel[:nf].double().numpy()
        if not (np.isfinite(x).all() and np.isfinite(v).all()):
            log.nonfinite_steps += 1
        if lo is not None:
            out = ((x < lo) | (x > hi)).any(axis=1)
            log.outside_max = max(log.outside_max, int(out.sum()))
            log.outside_steps += int(out.any())
            log.below_floor_max = max(log.below_floor_max, int((x[:, 2] < lo[2]).sum()))
            gaps = np.concatenate([x - lo, (hi - x)[:, :2]], axis=1)
            log.min_clearance = min(log.min_clearance, float(gaps.min()) / l0)
        log.courant_max = max(log.courant_max, float(np.linalg.norm(v, axis=1).max()) * s.params.dt / l0)
        if on_step is not None:
            on_step(s, log)
        if s.step and s.step % log_every == 0:
            print(
                f"  [{name}] step {s.step}/{steps} t={s.time:.3f}s wall={time.perf_counter() - start:.0f}s "
                f"Courant_max={log.courant_max:.3f}",
                flush=True,
            )

    try:
        state, record = rollout(sim, state, steps, guard=Guard(max_courant=0.5), on_frame=on_frame)
    except RolloutError as err:
        log.error = str(err)
        record = getattr(err, "record", {"info": {}})
        state = getattr(err, "state", state)
        print(f"  [{name}] STOPPED: {err}", flush=True)
    log.ppe_converged = list(record["info"].get("ppe_converged", []))
    log.ppe_iterations = list(record["info"].get("ppe_iterations", []))
    log.wall_s = time.perf_counter() - start
    return state, log


def metrics_of(state: ParticleState, settings: SolverSettings) -> tuple[float, float]:
    """(density error, velocity divergence) of one frame, lagfluid.metrics definitions."""
    l0 = state.params.l0
    n0 = lattice_constants(l0, settings, state.params.dim).n0
    m = field_metrics(
        state.pos,
        state.vel,
        state.ptype,
        n0,
        settings.re_density * l0,
        settings.re_gradient * l0,
        settings.surface_beta,
        state.params.dim,
        settings.neighbor_backend,
    )
    return m.density_error, m.velocity_divergence


def status(ok: bool) -> str:
    return "PASS" if ok else "FAIL"
