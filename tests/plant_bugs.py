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
    # issue 34 (output folders, locks, stored precision, resume)
    (
        "resume accepting a changed write_every",
        "lagfluid/simulate_resume.py",
        '"threads", "checkpoint_every_s", "out_dir")',
        '"threads", "checkpoint_every_s", "out_dir", "write_every")',
        "tests/test_simulate_resume.py::test_resume_refuses_other_settings_and_a_folder_without_a_checkpoint",
    ),
    (
        "simulate skips its out_dir lock",
        "lagfluid/simulate.py",
        '    with hold_outputs(out_dir, "simulate"):',
        "    if True:  # planted",
        "tests/test_run_lock.py::test_a_second_simulate_into_a_held_out_dir_is_refused_by_name_and_touches_nothing",
    ),
    (
        "Hydra writes .hydra/ into an out_dir another run holds",
        "lagfluid/locks.py",
        "            check_out_dir(folder)\n",
        "            pass  # planted\n",
        "tests/test_run_lock.py::test_a_second_simulate_into_a_held_out_dir_is_refused_by_name_and_touches_nothing",
    ),
    (
        "export skips its lock",
        "lagfluid/export/__init__.py",
        '    with hold_outputs(path.parent, "export", what="run"):',
        "    if True:  # planted",
        "tests/test_run_lock.py::test_every_task_that_writes_takes_its_lock",
    ),
    (
        "a killed run's lock taken over without a word",
        "lagfluid/locks.py",
        "    if left:\n        log.warning(",
        "    if False:\n        log.warning(",
        "tests/test_run_lock.py::test_a_lock_left_by_a_killed_run_is_taken_over_and_logged",
    ),
    (
        "a held MPS reference lock waits without a log line",
        "lagfluid/locks.py",
        '        log.info("waiting for %s: %s holds its lock", what, _holder(path))',
        "        pass  # planted",
        "tests/test_run_lock.py::test_an_evaluation_waiting_for_a_held_reference_says_for_what_and_whom",
    ),
    (
        "a run without a rollout publishes over the earlier run's files",
        "lagfluid/outputs.py",
        "    if not part_path(out_dir / names[0]).exists():",
        "    if False:",
        "tests/test_run_lock.py::test_a_run_that_wrote_no_rollout_leaves_the_earlier_files_alone",
    ),
    (
        "a float64 run stores float32 positions",
        "lagfluid/simulate.py",
        "            dtype=stored_dtype(state),",
        "            dtype=np.float32,",
        "tests/test_store.py::test_a_float64_run_far_from_the_origin_stores_its_exact_positions",
    ),
    (
        "evaluate stores a float64 model rollout as float32",
        "lagfluid/evaluate/model_run.py",
        "        dtype=stored_dtype(state),",
        '        dtype="float32",',
        "tests/test_store.py::test_a_float64_run_far_from_the_origin_stores_its_exact_positions",
    ),
    (
        "Ctrl-C before the first periodic checkpoint saves none",
        "lagfluid/simulate.py",
        "            checkpoint.save_latest()",
        "            pass  # planted",
        "tests/test_simulate_resume.py::test_ctrl_c_before_the_first_periodic_checkpoint_saves_one_and_resumes",
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
