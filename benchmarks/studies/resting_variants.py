"""Diagnostic for the resting column's spurious motion: the same column under solver variants.

    python -m benchmarks.studies.resting_variants [--steps 500] [--threads 2] [--only VARIANT ...]

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
weight making the column noisier as dt falls, and ``source_density_reference_dt`` undoing that; what is left
is fed mostly by the density term itself, which ``solver=mps_corrected`` slows (see docs/validation.md).

It prints its table; the committed runs (tables and commands) are in
``benchmarks/results/resting_variants.md``.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import torch
from omegaconf import OmegaConf

from benchmarks.validate_mps.common import make_sim, metrics_of, profile_config, solver_config
from lagfluid.errors import LagfluidError
from lagfluid.physics.settings import SolverSettings
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
    "corrected + re_laplacian 2.1 + reference dt 2 ms, dt 1 ms": {
        "pressure_gradient": "corrected",
        "re_laplacian": 2.1,
        "source_density_reference_dt": 0.002,
        "dt": 0.001,
    },
    "solver=mps_corrected": {"profile": "mps_corrected"},
    "solver=mps_corrected, dt 1 ms": {"profile": "mps_corrected", "dt": 0.001},
}
# ``dt`` is the scene's time step (default 2 ms); a variant at another dt runs the same physical time.
# ``profile``: the solver profile conf/solver/<profile>.yaml, as it is on disk.


def solver_overrides(variant: dict[str, Any]) -> dict[str, Any]:
    """The variant's overrides of conf/solver/mps.yaml (a ``profile`` expanded to what it changes)."""
    overrides = {k: v for k, v in variant.items() if k not in ("dt", "profile")}
    if "profile" in variant:
        authors, profile = profile_config("mps"), profile_config(variant["profile"])
        changed = {k: v for k, v in profile.items() if k != "name" and authors.get(k) != v}
        overrides = {**OmegaConf.to_container(OmegaConf.create(changed)), **overrides}
    return overrides


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--steps", type=int, default=500, help="steps at dt = 2 ms (other dt: the same time)")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--only", nargs="+", default=None, metavar="VARIANT", help="run only these rows (names)")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    n = 10
    print("| variant | mean abs(v) (m/s) | max abs(v) | density error | divergence (1/s) | wall s |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    unknown = sorted(set(args.only or ()) - set(VARIANTS))
    if unknown:
        ap.error(f"unknown variant(s) {unknown}; known: {list(VARIANTS)}")
    for name, variant in VARIANTS.items():
        if args.only is not None and name not in args.only:
            continue
        overrides = solver_overrides(variant)
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
