"""Plant known bugs one at a time, run the test that must catch each, revert: CAUGHT or MISSED.

The bugs that once went unnoticed (issue 17, item 6) and a few since.

``python tests/plant_bugs.py [name fragment ...]`` from the repository root prints CAUGHT or MISSED per bug;
the source file is restored whatever happens. Not collected by pytest (a tool to check the tests, not a test).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# (bug, file, what the code says, the planted line, the test that must fail)
PLANTS = [
    (
        "Verlet list rebuilt after a whole skin, not half",
        "lagfluid/neighbor_list.py",
        "moved.max() > 0.5 * self.skin",
        "moved.max() > 1.0 * self.skin",
        "tests/test_mps.py::test_verlet_list_rebuilds_before_two_particles_can_close_a_skin",
    ),
    (
        "guard ignores solver.guard.check_every",
        "lagfluid/rollout.py",
        "if write or done % guard.check_every == 0:",
        "if write:",
        "tests/test_mps.py::test_guard_checks_every_k_steps_and_every_written_frame",
    ),
    (
        "Courant number off by 2x",
        "lagfluid/rollout.py",
        "courant = speed * state.params.dt / state.params.l0",
        "courant = 0.5 * speed * state.params.dt / state.params.l0",
        "tests/test_mps.py::test_guard_names_step_particle_and_value_on_blow_up",
    ),
    (
        "training resume does not restore the weights",
        "lagfluid/train.py",
        '        net.load_state_dict(ckpt["state_dict"])',
        "        pass  # planted",
        "tests/test_fgn.py::test_a_resumed_training_ends_with_the_uninterrupted_runs_weights",
    ),
    (
        "training resume does not restore the Adam state",
        "lagfluid/train.py",
        '        optimizer.load_state_dict(ckpt["optimizer"])',
        "        pass  # planted",
        "tests/test_fgn.py::test_a_resumed_training_ends_with_the_uninterrupted_runs_weights",
    ),
    (
        "density error without its absolute value",
        "lagfluid/metrics.py",
        "density_error=float((n[interior] / n0 - 1.0).abs().mean())",
        "density_error=float((n[interior] / n0 - 1.0).mean())",
        "tests/test_metrics.py::test_density_error_averages_compression_and_expansion_as_magnitudes",
    ),
    (
        "kinetic energy of a run at another l0 with the reference's particle mass",
        "lagfluid/evaluate/compare.py",
        "kinetic_energy(mv, mass[id(model)])",
        "kinetic_energy(mv, mass[id(ref)])",
        "tests/test_metrics.py::test_kinetic_energy_of_runs_at_two_spacings_uses_each_runs_particle_mass",
    ),
    (
        "torchrun ranks do not average their gradients",
        "lagfluid/distributed.py",
        "        dist.all_reduce(p.grad)\n        p.grad /= size",
        "        pass  # planted",
        "tests/test_distributed.py::test_two_processes_follow_one_process_with_the_same_global_batch",
    ),
    (
        "compiled cell search keeps pairs at exactly r",
        "lagfluid/_pair_kernels_numba.py",
        "if j != i and _squared_distance(pos, j, i) < bound2:",
        "if j != i and _squared_distance(pos, j, i) <= bound2:",
        "tests/test_neighbors.py::test_pairs_at_exactly_the_radius_are_not_neighbours",
    ),
    # exact stages after an end-to-end step (model.exact_after, issue 35)
    (
        "exact_after: GNS's velocity history keeps the uncorrected step",
        "baselines/gns/simulator.py",
        "        self._velocities = torch.cat([self._velocities[:, :-1], displacement.unsqueeze(1)], dim=1)",
        "        pass  # planted",
        "tests/test_exact_after.py::test_gns_history_after_a_corrected_step_is_the_corrected_displacement",
    ),
    (
        "exact_after: the collision moves velocities but not positions",
        "lagfluid/physics/stages.py",
        "            pos[:nf] = integrate.collide(pos[:nf], v_star, v_new, dt)",
        "            pass  # planted",
        "tests/test_exact_after.py::test_exact_collision_after_a_step_is_the_collision_rule_applied_directly",
    ),
    (
        "exact_after: the relaxation factor is ignored",
        "lagfluid/physics/stages.py",
        "                acc_p = relaxation * acc_p",
        "                pass  # planted",
        "tests/test_exact_after.py::test_mps_pressure_after_a_step_lowers_a_compressed_blocks_density_error",
    ),
    (
        "exact_after: the stages also rewrite GNS's MPS warm-start frames",
        "lagfluid/models/exact_after.py",
        'self._ran = bool(getattr(self.model, "last_step_learned", True))',
        "self._ran = True",
        "tests/test_exact_after.py::test_gns_history_after_a_corrected_step_is_the_corrected_displacement",
    ),
    (
        "exact_after: the run is named as the plain model",
        "lagfluid/models/exact_after.py",
        "        self.name = options.label(model.name)",
        "        self.name = model.name",
        "tests/test_exact_after.py::test_labels_reach_rollout_and_metrics",
    ),
    (
        "exact_after: a resumed run takes the stages' constants from the checkpoint's state",
        "lagfluid/models/exact_after.py",
        "            self.exact.constants = MPSConstants(n0, n0_lap, lam)",
        "            pass  # planted",
        "tests/test_exact_after.py::test_a_stopped_gns_with_exact_stages_resumes_bit_for_bit",
    ),
    (
        "exact_after: a relaxation above 1 passes",
        "lagfluid/models/exact_after.py",
        "if not (_is_number(w) and 0 < w <= 1):",
        "if not (_is_number(w) and 0 < w):",
        "tests/test_exact_after.py::test_a_bad_exact_after_is_one_config_error_naming_it",
    ),
]


def main(only: list[str]) -> int:
    """Plant, test, revert each bug (those whose name contains a fragment of ``only``); 1 if one is missed."""
    missed = 0
    for name, path, code, planted, test in PLANTS:
        if only and not any(o in name for o in only):
            continue
        source = REPO / path
        text = source.read_text()
        if code not in text:
            print(f"STALE: {name}: {path} no longer says {code!r}")
            missed += 1
            continue
        source.write_text(text.replace(code, planted))
        try:
            done = subprocess.run(
                [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", test],
                cwd=REPO,
                capture_output=True,
                text=True,
                env={**os.environ, "OMP_NUM_THREADS": "1"},
            )
        finally:
            source.write_text(text)
        caught = done.returncode != 0
        missed += not caught
        print(f"{'CAUGHT' if caught else 'MISSED'}: {name}: {test}", flush=True)
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
