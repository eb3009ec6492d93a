"""Checks 1 and 4: hydrostatic pressure, residual motion and metrics of a resting column, and its figure."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from benchmarks.validate_mps.common import (
    PAPER_DENSITY_ERROR,
    PAPER_DIVERGENCE,
    Check,
    RunLog,
    make_sim,
    metrics_of,
    monitored_rollout,
    status,
)
from lagfluid.physics.settings import SolverSettings
from lagfluid.scenes import build_scene
from lagfluid.state import ParticleState, ParticleType


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
