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
    # issue 34, what the command line tells a user (memory, Ctrl-C, keys, --help, export_to, exit status, ETA)
    (
        "memory estimate per fluid particle, not per neighbour pair",
        "lagfluid/memory.py",
        "    return bytes_per_pair * neighbour_pairs(state.pos.detach().cpu().numpy(), fluid, radius)",
        "    return bytes_per_pair * float(fluid.sum())",
        "tests/test_memory.py::test_the_estimate_is_the_calibrated_bytes_per_pair_and_grows_with_the_fluid",
    ),
    (
        "pair estimate without the sphere's share of the 27-cell block",
        "lagfluid/memory.py",
        "share = (4.0 / 3.0) * np.pi * radius**3 / (27.0 * side**3)",
        "share = (4.0 / 3.0) * np.pi * radius**3 / (8.0 * side**3)",
        "tests/test_memory.py::test_neighbour_pairs_counts_the_lattice_points_of_each_receivers_sphere",
    ),
    (
        "simulate runs without the memory check",
        "lagfluid/simulate.py",
        "    check_run_memory(cfg, state, simulator)  # before the first neighbour search",
        "    pass  # planted",
        "tests/test_memory.py::test_a_rollout_too_large_for_the_memory_left_is_refused_before_the_first_search",
    ),
    (
        "a mesh too large gets the dam's keys as advice",
        "lagfluid/scenes/mesh.py",
        'ADVICE = shrink_advice(("container", "fluid", "obstacles", "scale"))',
        'ADVICE = shrink_advice(("fluid_size", "tank_size", "wall_height"))',
        "tests/test_mesh_scene.py::test_meshes_too_large_for_memory_point_to_scene_scale_not_to_keys_mesh_lacks",
    ),
    (
        "Ctrl-C exits 1 instead of 130",
        "lagfluid/run.py",
        "sys.exit(128 + (signal.SIGTERM if isinstance(err, Terminated) else signal.SIGINT))",
        "sys.exit(1)",
        "tests/test_cli.py::test_ctrl_c_is_one_line_naming_how_to_continue_and_exit_status_130",
    ),
    (
        "a misspelt key is left to Hydra's +key advice",
        "lagfluid/run.py",
        'if sep and not key.startswith(("++", "~", "-")):',
        'if sep and key.startswith("+") and not key.startswith(("++", "~", "-")):',
        "tests/test_cli.py::test_a_misspelt_key_names_the_closest_keys_not_hydras_plus_advice",
    ),
    (
        "--help shows Hydra's own group list (no plugins)",
        "lagfluid/conf/config.yaml",
        "      ${lagfluid.config_groups:}",
        "      $APP_CONFIG_GROUPS",
        "tests/test_cli.py::test_help_lists_every_model_and_train_profile_plugins_included",
    ),
    (
        "export_to checked only after the training",
        "lagfluid/train.py",
        "        check_export_to(cfg.export_to)",
        "        pass  # planted",
        "tests/test_train.py::test_export_to_an_existing_file_is_refused_before_the_training",
    ),
    (
        "an evaluation the guard stopped exits 0",
        "lagfluid/evaluate/task.py",
        '    if not metrics["complete"]:',
        "    if False:",
        "tests/test_cli.py::test_a_guard_stop_is_an_error_under_simulate_and_evaluate_alike",
    ),
    (
        "the rollout's ETA counts the first (compiling) step",
        "lagfluid/rollout.py",
        "                bar.restart_clock()",
        "                pass  # planted",
        "tests/test_progress.py::test_a_rollout_restarts_the_eta_clock_after_its_first_step",
    ),
    (
        "the log line's rate keeps the first step",
        "lagfluid/progress.py",
        "        self.start_n, self.start = self.n, time.perf_counter()",
        "        pass  # planted",
        "tests/test_progress.py::test_the_log_lines_eta_starts_after_the_first_step",
    ),
    (
        "the bar's smoothed rate keeps the first step",
        "lagfluid/progress.py",
        "        self.reset(self.total)  # a fresh clock and fresh rate averages, at a count of 0",
        "        pass  # planted",
        "tests/test_progress.py::test_the_bars_eta_starts_after_the_first_step",
    ),
    (
        "a cold kernel cache compiles in silence",
        "lagfluid/pair_kernels.py",
        "    if where and not _announced:",
        "    if False:",
        "tests/test_progress.py::test_a_cold_kernel_cache_is_announced_once_before_compiling",
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
