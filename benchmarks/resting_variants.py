"""Diagnostic for the resting column's spurious motion: the same column under solver variants.

    python -m benchmarks.resting_variants [--steps 500] [--threads 2]

A 10 x 10 x 20 fluid column at rest in its tank (the hydrostatic case of ``benchmarks.validate_mps``) is
rolled out for ``--steps`` steps (1 s at the default dt) with each variant of ``conf/solver/mps.yaml``
below; printed: mean and max |v| of the fluid at the end (a resting column should stay near 0) and the
density error and velocity divergence of the last frame (``lagfluid.metrics``).

What drives the motion (issue 3): the minimum-pressure gradient's repulsion, ``(p_i - p_min,i)`` ~ 2 rho g l0
under hydrostatic load, makes the simple-cubic lattice shear-unstable: a column displaced along gravity is
pushed further (~6.3 m/s^2 per l0, so an e-folding time of ~0.1 s at l0 = 0.05 m, as observed; see
``test_hydrostatic_column_shift_destabilises_the_minimum_gradient_only`` in ``tests/test_operators.py``).
``pressure_gradient: corrected`` removes that term for the part of the pressure a linear field explains and
slows the growth ~5x, a smaller ``re_laplacian`` further. The dt 1 ms rows show the authors' per-step density
weight making the column noisier as dt falls, and ``source_density_reference_dt`` (in
``solver=mps_corrected``) undoing that. What drives the slow growth left is open (see the README).
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import torch

from benchmarks.validate_mps import make_sim, metrics_of, solver_config
from lagfluid.errors import LagfluidError
from lagfluid.physics.stages import SolverSettings
from lagfluid.rollout import rollout
from lagfluid.scenes import build_scene
from lagfluid.state import SceneParams

DEFAULT_DT = SceneParams().dt

VARIANTS: dict[str, dict[str, Any]] = {
    "default (authors)": {},
    "surface_beta 0.95": {"surface_beta": 0.95},
    "surface_beta 0.99": {"surface_beta": 0.99},
    "no negative-pressure clamp": {"clamp_negative_pressure": False},
    "source: divergence only": {"source_divergence": 1.0, "source_density": 0.0},
    "source: 0.5 / 0.5": {"source_divergence": 0.5, "source_density": 0.5},
    "re_gradient 3.1": {"re_gradient": 3.1},
    "pressure_gradient corrected": {"pressure_gradient": "corrected"},
    "corrected + re_laplacian 2.1": {"pressure_gradient": "corrected", "re_laplacian": 2.1},
    "default (authors), dt 1 ms": {"dt": 0.001},
    "corrected + re_laplacian 2.1, dt 1 ms": {
        "pressure_gradient": "corrected",
        "re_laplacian": 2.1,
        "dt": 0.001,
    },
    "solver=mps_corrected, dt 1 ms": {
        "pressure_gradient": "corrected",
        "re_laplacian": 2.1,
        "source_density_reference_dt": 0.002,
        "dt": 0.001,
    },
}
# ``dt`` is the scene's time step (default 2 ms); a variant at another dt runs the same physical time.
# solver=mps_corrected at 2 ms is the "corrected + re_laplacian 2.1" row (its reference dt changes nothing
# there).


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--steps", type=int, default=500, help="steps at dt = 2 ms (other dt: the same time)")
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    n = 10
    print("| variant | mean abs(v) (m/s) | max abs(v) | density error | divergence (1/s) | wall s |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    for name, variant in VARIANTS.items():
        overrides = {k: v for k, v in variant.items() if k != "dt"}
        dt = variant.get("dt", DEFAULT_DT)
        state = build_scene(
            "dam",
            params=SceneParams(dt=dt),
            fluid_size=[n, n, 2 * n],
            tank_size=[n + 1, n + 1],
            wall_height=2 * n + 2,
        )
        start = time.perf_counter()
        try:
            final, _ = rollout(make_sim(**overrides), state, round(args.steps * DEFAULT_DT / dt))
        except LagfluidError as err:  # the rollout guard stopped it: say where
            print(f"| {name} | stopped: {str(err).splitlines()[0][:100]} | | | | |", flush=True)
            continue
        speed = final.vel[: state.n_fluid].double().norm(dim=1)
        density_error, divergence = metrics_of(final, SolverSettings.from_config(solver_config(**overrides)))
        print(
            f"| {name} | {float(speed.mean()):.4f} | {float(speed.max()):.3f} | {density_error:.4f} | "
            f"{divergence:.3f} | {time.perf_counter() - start:.0f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
