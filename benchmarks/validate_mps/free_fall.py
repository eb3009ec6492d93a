"""Check 2: free fall without walls against the exact discrete kinematics and x0 + g t^2/2."""

from __future__ import annotations

import torch

from benchmarks.validate_mps.common import Check, make_sim, monitored_rollout, status
from lagfluid.state import ParticleState, SceneParams


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
