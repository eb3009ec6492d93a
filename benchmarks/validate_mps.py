"""Physical validation of the MPS ground-truth solver against analytic answers and experiments.

``python -m benchmarks.validate_mps [--quick]`` runs six checks and writes ``benchmarks/results/
validate_mps.md`` and ``.csv`` (``validate_mps_quick.*`` with ``--quick``) plus PNG figures next to them,
with provenance (date, machine, versions, git commit, command, runtime). Every check prints PASS/FAIL
(or INFO) with the measured number and the criterion; the exit status is 1 when any check fails.

1. hydrostatic pressure of a resting column (slope of p(z) in the interior vs rho g, bottom pressure);
2. free fall without walls (exact discrete kinematics, first-order error vs x0 + g t^2/2, p = 0);
3. mass conservation (fluid count constant, no fluid particle beyond the inner wall layers, every run);
4. density error and velocity divergence of the resting tank (``lagfluid.metrics``) vs the paper's
   MPS ground-truth values (FGN Table 1: density error 0.038, divergence 0.019);
5. the authors' dam collapse (``dam_col_4k.npz``, 300 steps of 2 ms): no leak, no blow-up, PPE converged,
   surge front vs Martin & Moyce (1952) and Koshizuka & Oka (1996);
6. dt robustness: a small dam at dt = 1, 2, 4 ms.

The solver is run as the project runs it (``conf/solver/mps.yaml``, scene dtype float32), never tuned here;
``--profile NAME`` validates another solver profile (``conf/solver/NAME.yaml``, e.g. ``mps_corrected``) and
``--solver key=value ...`` a configured variant (e.g. ``pressure_gradient=corrected``), each into its own
report (``validate_mps_mps_corrected.*``, ``validate_mps_pressure_gradient_corrected.*``).
"""

from __future__ import annotations

import argparse
import csv
import functools
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig, OmegaConf

from benchmarks.provenance import markdown, provenance
from lagfluid.errors import RolloutError
from lagfluid.metrics import field_metrics
from lagfluid.models.mps_simulator import build_mps
from lagfluid.physics.stages import SolverSettings, lattice_constants
from lagfluid.rollout import Guard, rollout
from lagfluid.run import CONF_DIR
from lagfluid.scenes import build_scene
from lagfluid.state import ParticleState, ParticleType, SceneParams

RESULTS = Path(__file__).resolve().parent / "results"
AUTHORS_DAM = Path(__file__).resolve().parents[1] / ".." / "shared" / "reference" / "fgn_original" / "grids"
AUTHORS_DAM = AUTHORS_DAM / "dam_col_4k.npz"
PAPER_DENSITY_ERROR, PAPER_DIVERGENCE = 0.038, 0.019  # FGN Table 1, MPS ground truth

# Surge front Z = x/a vs T = t sqrt(2g/a) for a column of height 2a ("n^2 = 2"), digitised from
# Martin & Moyce (1952), Phil. Trans. R. Soc. A 244, 312-324, Fig. 3, and from Koshizuka & Oka (1996),
# Nucl. Sci. Eng. 123, 421-434 (their experiment, height 2L). Values as tabulated in PySPH
# (pysph/examples/db_exp_data.py).
MARTIN_MOYCE_A2250 = np.array(  # a = 2.25 in
    [
        [0.832, 1.217], [1.219, 1.474], [1.997, 2.292], [2.547, 2.995], [3.345, 4.134],
        [4.034, 4.944], [4.418, 5.881], [5.091, 6.980], [5.685, 7.945], [6.306, 8.966],
        [6.822, 9.986], [7.439, 10.963], [8.031, 11.977], [8.633, 13.005], [9.237, 13.970],
    ]
)  # fmt: skip
MARTIN_MOYCE_A1125 = np.array(  # a = 1.125 in
    [
        [0.849, 1.245], [1.212, 1.443], [1.602, 1.884], [2.283, 2.689], [2.950, 3.728],
        [3.598, 4.528], [3.905, 4.999], [4.592, 5.841], [4.961, 6.271], [5.316, 6.717],
    ]
)  # fmt: skip
KOSHIZUKA_OKA = np.array(
    [
        [0.0, 1.000], [0.381, 1.111], [0.769, 1.252], [1.153, 1.505], [1.537, 1.892],
        [1.935, 2.241], [2.323, 2.615], [2.719, 3.003], [3.096, 3.624],
    ]
)  # fmt: skip
FRONT_DEVIATION_LIMIT = 0.30  # gross deviation from Martin & Moyce (mean |Z/Z_ref - 1|) fails the check


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


# ------------------------------------------------------------------------------ 1 + 4: resting column
def check_hydrostatic(
    quick: bool, settings: SolverSettings, figdir: Path, suffix: str
) -> tuple[list[Check], RunLog]:
    n = 6 if quick else 10
    settle_s = 0.3 if quick else 1.0
    window_s = 0.1
    state = build_scene("dam", fluid_size=[n, n, 2 * n], tank_size=[n + 1, n + 1], wall_height=2 * n + 2)
    nf, l0, dt_, rho = state.n_fluid, state.params.l0, state.params.dt, state.params.density
    g = -state.params.gravity[2]
    steps, window = round(settle_s / dt_), round(window_s / dt_)
    print(
        f"[1] hydrostatic: {n}x{n}x{2 * n} column ({nf} fluid), {steps} steps, fit window {window}",
        flush=True,
    )
    acc = {"p": np.zeros(nf), "z": np.zeros(nf), "pw": None, "k": 0, "slopes": [], "derr": [], "div": []}
    floor = (state.ptype == ParticleType.WALL) & (state.pos[:, 2].abs() < 0.1 * l0)
    sim = make_sim()

    def fit(z: np.ndarray, p: np.ndarray, ztop: float) -> tuple[float, float]:
        sel = (z > 3.5 * l0) & (z < ztop - 2.5 * l0)
        slope, icpt = np.polyfit(z[sel], p[sel], 1)
        return float(slope), float(icpt)

    def on_step(s: ParticleState, log: RunLog) -> None:
        v = s.vel[:nf].double().norm(dim=1).numpy()
        log.add("t", s.time)
        log.add("vmax", v.max())
        log.add("vmean", v.mean())
        if s.step > steps - window:
            z, p = s.pos[:nf, 2].double().numpy(), s.pressure[:nf].double().numpy()
            ztop = float(np.sort(z)[-n * n :].mean())
            acc["slopes"].append(fit(z, p, ztop)[0])
            acc["p"] += p
            acc["z"] += z
            pw = s.pressure[floor].double().numpy()
            acc["pw"] = pw if acc["pw"] is None else acc["pw"] + pw
            acc["k"] += 1
            if s.step % 10 == 0 or s.step == steps:
                de, dv = metrics_of(s, settings)
                acc["derr"].append(de)
                acc["div"].append(dv)

    final, log = monitored_rollout(sim, state, steps, "hydrostatic", on_step)
    k = max(acc["k"], 1)
    z, p, pw = acc["z"] / k, acc["p"] / k, (acc["pw"] if acc["pw"] is not None else np.zeros(1)) / k
    ztop = float(np.sort(z)[-n * n :].mean())
    slope, icpt = fit(z, p, ztop)
    zf, pf = final.pos[:nf, 2].double().numpy(), final.pressure[:nf].double().numpy()
    slope_last = fit(zf, pf, float(np.sort(zf)[-n * n :].mean()))[0]
    ratio = -slope / (rho * g)
    bottom = z < 1.5 * l0
    p_bot, p_bot_ref = float(p[bottom].mean()), rho * g * (ztop - float(z[bottom].mean()))
    pw_mean, pw_ref = float(pw.mean()), rho * g * ztop
    zero_level = -icpt / slope
    vmax, vmean = log.series["vmax"], log.series["vmean"]
    w = slice(-window, None)
    out = [
        Check(
            "1 hydrostatic",
            f"slope -dp/dz / (rho g), interior {3.5:g} l0 < z < z_top - 2.5 l0, p averaged over the last "
            f"{window_s:g} s of {settle_s:g} s",
            f"{ratio:.4f} (per-frame fits {-np.mean(acc['slopes']) / (rho * g):.4f} "
            f"+- {np.std(acc['slopes']) / (rho * g):.4f}; last frame {-slope_last / (rho * g):.4f})",
            "|ratio - 1| <= 0.10",
            status(abs(ratio - 1) <= 0.10),
        ),
        Check(
            "1 hydrostatic",
            "bottom fluid layer p / rho g (z_top - z), z_top = mean top-layer height",
            f"{p_bot / p_bot_ref:.4f} ({p_bot:.0f} Pa vs {p_bot_ref:.0f} Pa)",
            "|ratio - 1| <= 0.10",
            status(abs(p_bot / p_bot_ref - 1) <= 0.10),
        ),
        Check(
            "1 hydrostatic",
            "floor wall (inner layer, z = 0) p / rho g z_top",
            f"{pw_mean / pw_ref:.4f} ({pw_mean:.0f} Pa vs {pw_ref:.0f} Pa; "
            f"min {pw.min():.0f}, max {pw.max():.0f})",
            "|ratio - 1| <= 0.10",
            status(abs(pw_mean / pw_ref - 1) <= 0.10),
        ),
        Check(
            "1 hydrostatic",
            "zero-pressure level of the fit vs top layer; column top sinking",
            f"fit p = 0 at z = {zero_level / l0:.2f} l0; top layer at {ztop / l0:.2f} l0 "
            f"(initially {2 * n:.2f} l0)",
            "informative",
            "INFO",
        ),
        Check(
            "1 hydrostatic",
            "residual |v| in the last window: max / mean (m/s)",
            f"{max(vmax[w]):.4f} / {np.mean(vmean[w]):.4f} (at 0.1 s: {vmax[round(0.1 / dt_)]:.4f} / "
            f"{vmean[round(0.1 / dt_)]:.4f}; Courant max {log.courant_max:.3f})",
            "informative (a resting column should stay well below 0.01 sqrt(g h))",
            "INFO",
        ),
        Check(
            "1 hydrostatic",
            "growth of the residual motion: mean |v| in the last window / in the window half-way",
            f"{np.mean(vmean[w]) / max(np.mean(vmean[steps // 2 - window : steps // 2]), 1e-30):.2f} "
            f"({np.mean(vmean[steps // 2 - window : steps // 2]):.4f} -> {np.mean(vmean[w]):.4f} m/s)",
            "informative (> 1: the motion still grows; a fluid at rest stays at rest)",
            "INFO",
        ),
        Check(
            "1 hydrostatic",
            "PPE converged every step",
            f"{int(sum(1 for c in log.ppe_converged if c))}/{len(log.ppe_converged)} "
            f"(iterations median {np.median(log.ppe_iterations or [math.nan]):.0f})",
            "all, and run completed",
            status(not log.error and all(log.ppe_converged) and len(log.ppe_converged) == steps),
        ),
    ]
    derr, div = float(np.mean(acc["derr"])), float(np.mean(acc["div"]))
    derr_max, div_max = float(np.max(acc["derr"])), float(np.max(acc["div"]))
    resting = [
        Check(
            "4 resting tank",
            f"density error mean|n/n0 - 1| (interior), mean over the last {window_s:g} s",
            f"{derr:.4f} (max {derr_max:.4f})",
            f"<= {PAPER_DENSITY_ERROR / 4:.4f} (1/4 of the paper's MPS value {PAPER_DENSITY_ERROR})",
            status(derr_max <= PAPER_DENSITY_ERROR / 4),
        ),
        Check(
            "4 resting tank",
            f"velocity divergence mean|div v| (1/s, interior), mean over the last {window_s:g} s",
            f"{div:.4f} (max {div_max:.4f})",
            f"<= {PAPER_DIVERGENCE} (the paper's MPS value on the dam collapse)",
            status(div_max <= PAPER_DIVERGENCE),
        ),
    ]
    plot_hydrostatic(
        figdir / f"validate_mps_hydrostatic{suffix}.png", z, p, ztop, rho, g, slope, icpt, l0, log
    )
    return out + resting, log


def plot_hydrostatic(
    path: Path, z: np.ndarray, p: np.ndarray, ztop: float, rho: float, g: float, slope: float, icpt: float,
    l0: float, log: RunLog,
) -> None:  # fmt: skip
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.5))
    depth = ztop - z
    interior = (z > 3.5 * l0) & (z < ztop - 2.5 * l0)
    ax.scatter(depth[~interior], p[~interior], s=4, c="0.6", label="fluid (excluded from fit)")
    ax.scatter(depth[interior], p[interior], s=4, c="C0", label="fluid (fit)")
    d = np.linspace(0, depth.max(), 50)
    ax.plot(d, rho * g * d, "k-", label=r"$\rho g\,(z_{top}-z)$")
    ax.plot(d, slope * (ztop - d) + icpt, "C3--", label=f"fit: slope = {-slope / (rho * g):.3f} $\\rho g$")
    ax.set_xlabel("depth below the top layer (m)")
    ax.set_ylabel("pressure (Pa), time-averaged")
    ax.legend(fontsize=8)
    ax.set_title("resting column: p vs depth")
    t = np.array(log.series["t"])
    bx.semilogy(t, log.series["vmax"], label="max |v|")
    bx.semilogy(t, log.series["vmean"], label="mean |v|")
    bx.set_xlabel("t (s)")
    bx.set_ylabel("|v| (m/s)")
    bx.set_title("residual velocity of the 'resting' column")
    bx.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ------------------------------------------------------------------------------------- 2: free fall
def check_free_fall(quick: bool) -> list[Check]:
    out = []
    n, steps = (6, 25) if quick else (8, 100)
    for dtype, tol in ((torch.float64, 1e-9), (torch.float32, 1e-4)):
        axes = [torch.arange(n, dtype=torch.float64) * 0.05 for _ in range(3)]
        pos = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        vel = torch.tensor([0.3, 0.0, 0.0], dtype=torch.float64).expand_as(pos).clone()
        state = ParticleState.from_arrays(
            pos, vel, torch.ones(len(pos), dtype=torch.long), SceneParams(), dtype=dtype
        )
        dt_, g = state.params.dt, state.params.gravity[2]
        print(f"[2] free fall: {n}^3 block, {steps} steps, {dtype}", flush=True)
        final, log = monitored_rollout(make_sim(), state, steps, f"free fall {dtype}")
        t = steps * dt_
        x0 = state.pos.double()
        xf, vf = final.pos.double(), final.vel.double()
        z_disc = x0[:, 2] + g * dt_ * dt_ * steps * (steps + 1) / 2
        err_disc = max(
            float((xf[:, 2] - z_disc).abs().max()),
            float((vf[:, 2] - g * t).abs().max()),
            float((xf[:, 0] - x0[:, 0] - 0.3 * t).abs().max()),
            float((xf[:, 1] - x0[:, 1]).abs().max()),
        )
        err_cont = float((xf[:, 2] - x0[:, 2] - 0.5 * g * t * t).abs().max())
        first_order = abs(0.5 * g * dt_ * t)
        pmax = float(final.pressure.abs().max())
        name = str(dtype).replace("torch.", "")
        out += [
            Check(
                "2 free fall",
                f"{name}: max error vs discrete kinematics (x, z, v_z) after {steps} steps",
                f"{err_disc:.2e} m (or m/s)",
                f"<= {tol:g}",
                status(err_disc <= tol and not log.error),
            ),
            Check(
                "2 free fall",
                f"{name}: error vs x0 + g t^2/2 at t = {t:g} s, / (g dt t / 2) (first order)",
                f"{err_cont:.3e} m = {err_cont / first_order:.5f} x g dt t/2",
                "ratio within 1e-3 of 1",
                status(abs(err_cont / first_order - 1) <= 1e-3),
            ),
            Check(
                "2 free fall",
                f"{name}: max |p| at the last step",
                f"{pmax:.2e} Pa",
                "<= 1e-6 Pa",
                status(pmax <= 1e-6),
            ),
        ]
    return out


# ------------------------------------------------------------------------------- 5 + 6: dam collapse
def front_of(s: ParticleState, lo: np.ndarray, l0: float) -> tuple[float, float]:
    """(99th percentile, max) of the x of fluid particles within 2 l0 of the floor, from the inner wall."""
    x = s.pos[: s.n_fluid].double().numpy()
    near = x[:, 2] - lo[2] < 2.0 * l0
    if not near.any():
        return math.nan, math.nan
    xs = x[near, 0] - lo[0]
    return float(np.percentile(xs, 99)), float(xs.max())


def dam_run(
    state: ParticleState, steps: int, name: str, settings: SolverSettings, metrics_every: int = 10
) -> tuple[RunLog, float, float]:
    """Roll out a dam collapse, recording the front every step; returns the log, a and the column height."""
    lo, _ = inner_box(state)
    l0 = state.params.l0
    x0 = state.pos[: state.n_fluid].double().numpy()
    a = float(x0[:, 0].max() - lo[0])  # column width: wall surface (l0/2) to the column's volume edge
    h = float(x0[:, 2].max() - lo[2])

    def on_step(s: ParticleState, log: RunLog) -> None:
        f99, fmax = front_of(s, lo, l0)
        log.add("t", s.time)
        log.add("front_p99", f99)
        log.add("front_max", fmax)
        if s.step % metrics_every == 0 and s.step:
            de, dv = metrics_of(s, settings)
            log.add("density_error", de)
            log.add("divergence", dv)

    _, log = monitored_rollout(make_sim(), state, steps, name, on_step)
    return log, a, h


def front_deviation(
    T: np.ndarray, Z: np.ndarray, ref: np.ndarray, z_limit: float
) -> tuple[float, float, int]:
    """Mean and max of Z(T_ref)/Z_ref - 1 over reference points inside our time range, before the far wall."""
    devs = []
    for tr, zr in ref:
        if tr <= T[-1] and tr > 0:
            zi = float(np.interp(tr, T, Z))
            if zi < z_limit:
                devs.append(zi / zr - 1.0)
    if not devs:
        return math.nan, math.nan, 0
    d = np.array(devs)
    return float(d.mean()), float(d[np.argmax(np.abs(d))]), len(d)


def check_authors_dam(quick: bool, settings: SolverSettings, figdir: Path, suffix: str) -> tuple[
    list[Check], RunLog | None, dict[str, Any]
]:  # fmt: skip
    if not AUTHORS_DAM.exists():
        note = f"skipped: {AUTHORS_DAM} not found (../shared absent)"
        print(f"[5] {note}", flush=True)
        return [Check("5 authors' dam", "run", note, "file present", "INFO")], None, {}
    steps = 60 if quick else 300
    state = build_scene("file", path=str(AUTHORS_DAM))
    print(
        f"[5] authors' dam: {state.n_fluid} fluid / {state.num_particles} particles, {steps} steps",
        flush=True,
    )
    log, a, h = dam_run(state, steps, "authors' dam", settings)
    lo, hi = inner_box(state)
    g = -state.params.gravity[2]
    t = np.array(log.series["t"])
    T = t * math.sqrt(2 * g / a)
    Z99 = np.array(log.series["front_p99"]) / a
    Zmax = np.array(log.series["front_max"]) / a
    z_wall = (hi[0] - lo[0]) / a
    z_limit = z_wall - 4 * state.params.l0 / a  # compare only before the front reaches the far wall
    out = [
        Check(
            "5 authors' dam",
            f"run completed ({steps} steps, dt {state.params.dt})",
            log.error or f"yes, {log.steps_done} steps in {log.wall_s:.0f} s",
            "no guard stop",
            status(not log.error and log.steps_done == steps),
        ),
        Check(
            "5 authors' dam",
            "fluid beyond the inner wall layers (any step) / below the floor's inner layer",
            f"{log.outside_max} / {log.below_floor_max}; closest approach to a wall plane "
            f"{log.min_clearance:.3f} l0",
            "0 / 0",
            status(log.outside_max == 0 and log.below_floor_max == 0),
        ),
        Check(
            "5 authors' dam",
            "max Courant number max|v| dt / l0; non-finite steps",
            f"{log.courant_max:.3f}; {log.nonfinite_steps}",
            "< 0.5; 0",
            status(log.courant_max < 0.5 and log.nonfinite_steps == 0),
        ),
        Check(
            "5 authors' dam",
            "PPE converged (abs tol 1e-6, <= 200 it)",
            f"{int(sum(1 for c in log.ppe_converged if c))}/{len(log.ppe_converged)} steps, iterations "
            f"median {np.median(log.ppe_iterations):.0f}, max {max(log.ppe_iterations):.0f}",
            "every step",
            status(len(log.ppe_converged) == steps and all(log.ppe_converged)),
        ),
    ]
    if "density_error" in log.series:
        out.append(
            Check(
                "5 authors' dam",
                "density error / divergence (1/s), mean (max) over every 10th step",
                f"{np.mean(log.series['density_error']):.4f} ({np.max(log.series['density_error']):.4f}) / "
                f"{np.mean(log.series['divergence']):.4f} ({np.max(log.series['divergence']):.4f})",
                f"informative; paper's MPS ground truth {PAPER_DENSITY_ERROR} / {PAPER_DIVERGENCE}",
                "INFO",
            )
        )
    mm_mean, mm_max, mm_n = front_deviation(T, Z99, MARTIN_MOYCE_A2250, z_limit)
    mm1_mean, mm1_max, mm1_n = front_deviation(T, Z99, MARTIN_MOYCE_A1125, z_limit)
    ko_mean, ko_max, ko_n = front_deviation(T, Z99, KOSHIZUKA_OKA, z_limit)
    ritter = 1.0 + 2.0 * T * math.sqrt(h / (2 * a))  # shallow-water front x = a + 2 sqrt(g h) t
    above_ritter = int((Zmax > ritter + 1e-9).sum())
    gross = bool(mm_n) and abs(mm_mean) > FRONT_DEVIATION_LIMIT
    out += [
        Check(
            "5 authors' dam",
            f"surge front Z = x_99/a vs Martin & Moyce n^2=2, a=2.25 in ({mm_n} points, T <= {T[-1]:.2f}, "
            f"Z < {z_limit:.2f})",
            f"mean {mm_mean:+.1%}, largest {mm_max:+.1%}",
            f"|mean| <= {FRONT_DEVIATION_LIMIT:.0%} (else gross)",
            ("FAIL" if gross else "INFO") if mm_n else "INFO (run too short to compare)",
        ),
        Check(
            "5 authors' dam",
            f"surge front vs Martin & Moyce a=1.125 in ({mm1_n} points) / Koshizuka & Oka 1996 ({ko_n})",
            f"mean {mm1_mean:+.1%} (largest {mm1_max:+.1%}) / mean {ko_mean:+.1%} (largest {ko_max:+.1%})",
            "informative",
            "INFO",
        ),
        Check(
            "5 authors' dam",
            "front (max x near the floor) above the shallow-water (Ritter) front Z = 1 + 2T sqrt(h/2a)",
            f"{above_ritter} of {len(T)} steps",
            "0",
            status(above_ritter == 0),
        ),
    ]
    info = {"T": T, "Z99": Z99, "Zmax": Zmax, "t": t, "a": a, "h": h, "z_wall": z_wall, "ritter": ritter}
    return out, log, info


def check_dt(quick: bool, settings: SolverSettings) -> tuple[list[Check], list[RunLog], dict[str, Any]]:
    fluid, tank = ([6, 4, 12], [25, 5]) if quick else ([8, 4, 16], [33, 5])
    t_end = 0.2 if quick else 0.4
    curves: dict[str, Any] = {}
    logs, out = [], []
    for dt_ in (0.001, 0.002, 0.004):
        state = build_scene("dam", SceneParams(dt=dt_), fluid_size=fluid, tank_size=tank)
        steps = round(t_end / dt_)
        print(f"[6] small dam {fluid} in {tank}, dt {dt_}, {steps} steps", flush=True)
        log, a, _h = dam_run(state, steps, f"small dam dt={dt_}", settings, metrics_every=10**9)
        logs.append(log)
        g = -state.params.gravity[2]
        t = np.array(log.series["t"])
        curves[dt_] = (t * math.sqrt(2 * g / a), np.array(log.series["front_p99"]) / a)
        out.append(
            Check(
                "6 dt robustness",
                f"dt = {dt_ * 1e3:g} ms: completed, PPE converged, Courant max",
                f"{'yes' if not log.error and log.steps_done == steps else 'NO: ' + log.error}, "
                f"{int(sum(1 for c in log.ppe_converged if c))}/{len(log.ppe_converged)}, "
                f"{log.courant_max:.3f}",
                "completed, all converged, < 0.5",
                status(
                    not log.error
                    and log.steps_done == steps
                    and all(log.ppe_converged)
                    and log.courant_max < 0.5
                ),
            )
        )
    T_ref, Z_ref = curves[0.001]
    for dt_ in (0.002, 0.004):
        T, Z = curves[dt_]
        n = min(len(T), len(T_ref))
        if n == 0:
            continue
        Tc = T[(T <= T_ref[-1])]
        Zc = Z[: len(Tc)]
        zr = np.interp(Tc, T_ref, Z_ref)
        dev = np.abs(Zc / zr - 1)
        out.append(
            Check(
                "6 dt robustness",
                f"front Z(T) at dt = {dt_ * 1e3:g} ms vs dt = 1 ms, max relative difference "
                f"(T <= {Tc[-1]:.2f})",
                f"{dev.max():.1%} (at T = {Tc[np.argmax(dev)]:.2f}); at the end {dev[-1]:.1%}",
                "informative (<= 10% expected)",
                "INFO",
            )
        )
    return out, logs, curves


def plot_front(path: Path, info: dict[str, Any], curves: dict[float, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2 if curves else 1, figsize=(11 if curves else 6, 4.5), squeeze=False)
    ax = axes[0, 0]
    if info:
        T = info["T"]
        ax.plot(T, info["Z99"], "C0-", label="lagfluid MPS, 99th pct. x near floor")
        ax.plot(T, info["Zmax"], "C0:", label="lagfluid MPS, max x near floor")
        ax.plot(T, info["ritter"], "k--", lw=0.8, label="shallow water (Ritter) 1 + 2T")
        ax.axhline(info["z_wall"], color="0.5", lw=0.8, label="far wall")
    ax.plot(*MARTIN_MOYCE_A2250.T, "s", mfc="none", c="C3", label="Martin & Moyce 1952, a = 2.25 in")
    ax.plot(*MARTIN_MOYCE_A1125.T, "^", mfc="none", c="C1", label="Martin & Moyce 1952, a = 1.125 in")
    ax.plot(*KOSHIZUKA_OKA.T, "o", mfc="none", c="C2", label="Koshizuka & Oka 1996 (exp.)")
    tmax = float(info["T"][-1]) if info else 4.0
    ax.set_xlim(0, tmax * 1.05)
    ax.set_ylim(0.8, (info["z_wall"] if info else 4.0) + 0.5)
    ax.set_xlabel(r"$T = t\sqrt{2g/a}$")
    ax.set_ylabel(r"$Z = x_{front}/a$")
    ax.set_title("authors' dam collapse (a = 0.5 m, h = 2a): surge front")
    ax.legend(fontsize=7)
    if curves:
        bx = axes[0, 1]
        for dt_, (T, Z) in curves.items():
            bx.plot(T, Z, label=f"dt = {dt_ * 1e3:g} ms")
        bx.plot(*MARTIN_MOYCE_A2250.T, "s", mfc="none", c="C3", label="Martin & Moyce, a = 2.25 in")
        bx.set_xlim(0, max(T[-1] for T, _ in curves.values()) * 1.05)
        bx.set_ylim(0.8, max(float(np.nanmax(Z)) for _, Z in curves.values()) + 0.3)
        bx.set_xlabel(r"$T$")
        bx.set_ylabel(r"$Z$")
        bx.set_title("small dam: dt robustness")
        bx.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ------------------------------------------------------------------------------------------- 3: mass
def check_mass(logs: list[RunLog]) -> list[Check]:
    out = []
    for log in logs:
        counts = sorted(log.fluid_counts)
        walled = log.inner_lo is not None
        ok = counts == [log.n_fluid] and log.nonfinite_steps == 0 and (not walled or log.outside_max == 0)
        out.append(
            Check(
                "3 mass",
                f"{log.name}: fluid count over {log.steps_done} steps; fluid beyond the inner wall layers",
                f"{counts} (start {log.n_fluid}); "
                + (
                    f"max {log.outside_max} outside, closest approach {log.min_clearance:.2f} l0"
                    if walled
                    else "no walls"
                ),
                "constant; 0 outside; finite",
                status(ok),
            )
        )
    return out


# ----------------------------------------------------------------------------------------- report
def run_provenance(runtime: float, load_before: float) -> dict[str, str]:
    return provenance(
        "benchmarks.validate_mps",
        load_before,
        runtime=f"{runtime:.0f} s ({runtime / 60:.1f} min)",
        solver=solver_description(),
    )


def solver_description() -> str:
    """The profile and overrides every run used, for the report."""
    name = SOLVER_PROFILE[0]
    text = f"conf/solver/{name}.yaml"
    if name == "mps":
        text += " (authors' coefficients, n0 from the ideal lattice)"
    if SOLVER_OVERRIDES:
        dotted = OmegaConf.to_container(OmegaConf.create(SOLVER_OVERRIDES))
        text += " with " + ", ".join(f"{k}={v}" for k, v in _dotted_items(dotted))
    return text + ", scene dtype float32"


def _dotted_items(tree: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    """``{"ppe": {"tol": 1e-8}}`` -> ``[("ppe.tol", 1e-8)]``, as ``--solver`` takes them."""
    items: list[tuple[str, Any]] = []
    for key, value in tree.items():
        if isinstance(value, dict):
            items += _dotted_items(value, f"{prefix}{key}.")
        else:
            items.append((f"{prefix}{key}", value))
    return items


def write_report(checks: list[Check], prov: dict[str, str], stem: Path, extra: str) -> None:
    stem.parent.mkdir(parents=True, exist_ok=True)
    lines = ["| check | quantity | measured | criterion | status |", "|---|---|---|---|:---:|"]
    for c in checks:
        lines.append(f"| {c.check} | {c.quantity} | {c.measured} | {c.criterion} | **{c.status}** |")
    n_fail = sum(c.status == "FAIL" for c in checks)
    notes = markdown(prov)
    stem.with_suffix(".md").write_text(
        "# MPS solver: physical validation\n\n"
        f"{notes}\n\n**{n_fail} check(s) failed** of {sum(c.status != 'INFO' for c in checks)} pass/fail "
        "checks (INFO rows are informative).\n\n" + "\n".join(lines) + "\n\n" + extra
    )
    with stem.with_suffix(".csv").open("w", newline="") as f:
        for k, v in prov.items():
            f.write(f"# {k}: {v}\n")
        w = csv.writer(f)
        w.writerow(["check", "quantity", "measured", "criterion", "status"])
        for c in checks:
            w.writerow([c.check, c.quantity, c.measured, c.criterion, c.status])


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="reduced sizes and durations (< ~3 min)")
    parser.add_argument("--out", type=Path, default=None, help="path stem for .md/.csv (default results/)")
    parser.add_argument(
        "--profile",
        default="mps",
        metavar="NAME",
        help="solver profile conf/solver/NAME.yaml, e.g. mps_corrected (default mps, the authors' scheme; "
        "report results/validate_mps_<NAME>... unless mps)",
    )
    parser.add_argument(
        "--solver",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="overrides of the profile for every run, e.g. pressure_gradient=corrected "
        "(default report: results/validate_mps_<key>_<value>...)",
    )
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    SOLVER_PROFILE[0] = args.profile
    SOLVER_OVERRIDES.clear()
    SOLVER_OVERRIDES.update(OmegaConf.to_container(OmegaConf.from_dotlist(args.solver)))
    variant = "" if args.profile == "mps" else "_" + args.profile
    variant += "".join("_" + item.replace("=", "_").replace(".", "_") for item in args.solver)
    suffix = ("_quick" if args.quick else "") + variant
    stem = args.out or RESULTS / f"validate_mps{suffix}"
    figdir = stem.parent
    figdir.mkdir(parents=True, exist_ok=True)
    settings = SolverSettings.from_config(solver_config())
    start, load_before = time.perf_counter(), os.getloadavg()[0]
    checks: list[Check] = []
    logs: list[RunLog] = []
    timings: dict[str, float] = {}

    t0 = time.perf_counter()
    hydro, hlog = check_hydrostatic(args.quick, settings, figdir, suffix)
    logs.append(hlog)
    timings["hydrostatic + resting tank"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    free = check_free_fall(args.quick)
    timings["free fall"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    dam, dlog, info = check_authors_dam(args.quick, settings, figdir, suffix)
    if dlog is not None:
        logs.append(dlog)
    timings["authors' dam"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    dtc, dlogs, curves = check_dt(args.quick, settings)
    logs += dlogs
    timings["dt robustness"] = time.perf_counter() - t0
    plot_front(figdir / f"validate_mps_dam_front{suffix}.png", info, curves)

    checks = [c for c in hydro if c.check.startswith("1")] + free + check_mass(logs)
    checks += [c for c in hydro if c.check.startswith("4")] + dam + dtc
    for c in checks:
        print(f"{c.status:4s}  {c.check}: {c.quantity}: {c.measured}  [{c.criterion}]")

    extra = "## Timings\n\n" + "\n".join(f"- {k}: {v:.0f} s" for k, v in timings.items()) + "\n"
    if info:
        extra += "\n## Surge front of the authors' dam (99th percentile of x within 2 l0 of the floor)\n\n"
        extra += f"a = {info['a']:.3f} m, h = {info['h']:.3f} m (h/a = {info['h'] / info['a']:.2f}).\n\n"
        extra += "| t (s) | T | Z (p99) | Z (max) |\n|---:|---:|---:|---:|\n"
        every = max(1, round(0.05 / (info["t"][1] - info["t"][0]))) if len(info["t"]) > 1 else 1
        for i in range(0, len(info["t"]), every):
            row = (info["t"][i], info["T"][i], info["Z99"][i], info["Zmax"][i])
            extra += "| {:.3f} | {:.3f} | {:.3f} | {:.3f} |\n".format(*row)
    extra += (
        "\n## Notes on the criteria\n\n"
        "- Hydrostatic: the column starts on an exact lattice at rest; 1 s (0.3 s with --quick) is several "
        "times the gravity-wave crossing time 2 L / sqrt(g h) ~ 0.35 s, and the pressure is averaged "
        "over the last 0.1 s to remove the step-to-step MPS pressure noise. The free-surface layer and the "
        "two below it, and the three layers next to the floor, are left out of the fit.\n"
        "- Resting tank: 'near zero' is set against the paper's MPS ground-truth values on the dam collapse "
        "(FGN Table 1: density error 0.038, divergence 0.019): a fluid at rest must be at least as "
        "incompressible as a violent flow. The paper's divergence may not be defined exactly as ours (their "
        "released divergence kernel has a defect, FGN_ORIGINAL.md item 8); the density error is comparable.\n"
        "- Surge front: x is measured from the inner wall layer (x = 0) to the 99th percentile of the fluid "
        "particles within 2 l0 of the floor, Z = x / a with a the initial column width (particle centre to "
        "particle centre, so Z(0) = 1); only reference points before the front reaches the far wall count. "
        "Martin & Moyce's fronts lag most simulations by ~10% (finite gate-removal time, bed friction); a "
        "deviation above 30% fails the check, and a front ahead of the shallow-water (Ritter) front "
        "x = a + 2 sqrt(g h) t is impossible and fails it too.\n"
    )
    extra += (
        f"\n## Figures\n\n- `validate_mps_hydrostatic{suffix}.png`: p vs depth (time-averaged) with rho g "
        "depth; residual velocity of the resting column vs time\n"
        f"- `validate_mps_dam_front{suffix}.png`: surge front Z vs T against Martin & Moyce (1952), "
        "Koshizuka & Oka (1996) and the shallow-water bound; dt robustness of the small dam\n"
    )
    runtime = time.perf_counter() - start
    write_report(checks, run_provenance(runtime, load_before), stem, extra)
    n_fail = sum(c.status == "FAIL" for c in checks)
    print(f"{n_fail} check(s) failed; runtime {runtime:.0f} s; report {stem.with_suffix('.md')}")
    return 1 if n_fail else 0


if __name__ == "__main__":
    sys.exit(main())
