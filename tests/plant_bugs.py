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
        "lagfluid/neighbors/verlet.py",
        ".norm(dim=1).max() > 0.5 * self.skin",
        ".norm(dim=1).max() > 1.0 * self.skin",
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
        "lagfluid/tasks/train.py",
        '        self.net.load_state_dict(ckpt["state_dict"])',
        "        pass  # planted",
        "tests/test_fgn.py::test_a_resumed_training_ends_with_the_uninterrupted_runs_weights",
    ),
    (
        "training resume does not restore the Adam state",
        "lagfluid/tasks/train.py",
        '        self.optimizer.load_state_dict(ckpt["optimizer"])',
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
        "lagfluid/tasks/evaluate/compare.py",
        "kinetic_energy(mv, mass[id(model)])",
        "kinetic_energy(mv, mass[id(ref)])",
        "tests/test_metrics.py::test_kinetic_energy_of_runs_at_two_spacings_uses_each_runs_particle_mass",
    ),
    (
        "torchrun ranks do not average their gradients",
        "lagfluid/tasks/distributed.py",
        "        dist.all_reduce(p.grad)\n        p.grad /= size",
        "        pass  # planted",
        "tests/test_distributed.py::test_two_processes_follow_one_process_with_the_same_global_batch",
    ),
    (
        "compiled cell search keeps pairs at exactly r",
        "lagfluid/neighbors/_numba.py",
        "if j != i and _squared_distance(pos, j, i) < bound2:",
        "if j != i and _squared_distance(pos, j, i) <= bound2:",
        "tests/test_neighbors.py::test_pairs_at_exactly_the_radius_are_not_neighbours",
    ),
    # GNS and CConv by value (issue 34)
    (
        "GNS edge vector sign flipped",
        "baselines/gns/graph.py",
        "rel = (x.index_select(0, src) - x.index_select(0, dst)) / radius",
        "rel = (x.index_select(0, dst) - x.index_select(0, src)) / radius",
        "tests/test_gns_values.py::test_the_training_step_feeds_the_hand_graphs_node_and_edge_features",
    ),
    (
        "GNS boundary-type feature zeroed",
        "baselines/gns/graph.py",
        "net.type_features(boundary).to(pos.dtype),",
        "net.type_features(torch.zeros_like(boundary)).to(pos.dtype),",
        "tests/test_gns_values.py::test_the_training_step_feeds_the_hand_graphs_node_and_edge_features",
    ),
    (
        "GNS noise-corrected target using the wrong frame",
        "baselines/gns/trainable.py",
        "target_next = target_next + noise[:, -1]",
        "target_next = target_next + noise[:, -2]",
        "tests/test_gns_values.py::test_the_noisy_target_corrects_for_the_noise_of_the_last_input_frame",
    ),
    (
        "GNS pushforward starting from the last frame",
        "baselines/gns/trainable.py",
        "end = frames.shape[1] - unroll",
        "end = frames.shape[1]",
        "tests/test_gns_values.py::test_the_pushforward_starts_unroll_frames_before_the_last",
    ),
    (
        "CConv window exponent 3 -> 2",
        "baselines/cconv/conv.py",
        "return torch.clamp((1 - r_sqr) ** 3, 0, 1)",
        "return torch.clamp((1 - r_sqr) ** 2, 0, 1)",
        "tests/test_cconv_values.py::test_the_layer_is_the_direct_sum_over_the_neighbours",
    ),
    # datasets and python -m lagfluid.data.convert (issue 34)
    (
        "converted LagrangeBench bounds transposed",
        "lagfluid/data/convert.py",
        '"bounds": containing.T.tolist(),',
        '"bounds": containing.tolist(),',
        "tests/test_convert.py::test_a_converted_dataset_is_read_by_lagrangebench_conventions",
    ),
    (
        "converted LagrangeBench bounds are the fluid's domain, the walls outside them",
        "lagfluid/data/convert.py",
        "    containing = _containing_bounds(data)\n",
        "    containing = data.bounds if data.bounds is not None else _bounds_of(data)\n",
        "tests/test_convert.py::test_a_converted_dataset_is_read_by_lagrangebench_conventions",
    ),
    (
        "converted set's way back takes LagrangeBench's bounds for the fluid's domain",
        "lagfluid/data/convert.py",
        'box = meta.get("domain_bounds") or meta.get("bounds")',
        'box = meta.get("bounds")',
        "tests/test_convert.py::test_a_lagrangebench_dataset_back_to_ours_keeps_the_trajectories",
    ),
    (
        "convert removes a user's DST.part",
        "lagfluid/data/convert.py",
        "if part.is_symlink() or not marker.is_file():",
        "if part.is_symlink():",
        "tests/test_convert.py::test_convert_removes_no_part_folder_but_its_own",
    ),
    (
        "convert leaves its marker in DST",
        "lagfluid/data/convert.py",
        "        (part / PART_MARKER).unlink()",
        "        pass  # planted",
        "tests/test_convert.py::test_convert_removes_no_part_folder_but_its_own",
    ),
    (
        "a failed conversion leaves its DST.part",
        "lagfluid/data/convert.py",
        "shutil.rmtree(part, ignore_errors=True)  # made by this run",
        "pass  # made by this run",
        "tests/test_convert.py::test_what_cannot_convert_is_named",
    ),
    (
        "no warning for trajectories shorter than LagrangeBench's windows",
        "lagfluid/data/convert.py",
        "short = {s: n for s, n in frames.items() if n < need[s]}",
        "short = {}",
        "tests/test_convert.py::test_lagrangebench_limits_are_warned_at_convert_time",
    ),
    (
        "no warning for particles outside LagrangeBench's cells",
        "lagfluid/data/convert.py",
        "    if axes:",
        "    if False:",
        "tests/test_convert.py::test_lagrangebench_limits_are_warned_at_convert_time",
    ),
    (
        "a truncated LagrangeBench train.h5 gives a traceback",
        "lagfluid/data/convert.py",
        "except OSError as err:  # h5py",
        "except KeyError as err:  # h5py",
        "tests/test_convert.py::test_broken_metadata_and_files_are_one_line",
    ),
    (
        "metadata.json without l0 or splits gives a KeyError",
        "lagfluid/data/layout.py",
        "require_keys(meta, path, METADATA_KEYS)",
        "None",
        "tests/test_data.py::test_metadata_without_a_key_it_needs_is_named",
    ),
    # metrics, previews, task=export and the training log (issue 34)
    (
        "ParaView number_density always from frame 0",
        "lagfluid/tasks/export/vtk.py",
        "number_density_ratio(pos, boundary, btype, l0, dim, settings)",
        'number_density_ratio(g["position"][0], boundary, btype, l0, dim, settings)',
        "tests/test_export.py::test_the_number_density_of_each_frame_is_that_frames_own",
    ),
    (
        "divergence metric abs(mean) instead of mean(abs)",
        "lagfluid/metrics.py",
        "velocity_divergence=float(div[interior].abs().mean())",
        "velocity_divergence=float(div[interior].mean().abs())",
        "tests/test_metrics.py::test_velocity_divergence_averages_expansion_and_compression_as_magnitudes",
    ),
    (
        "previews colour by pressure whatever the simulator predicts",
        "lagfluid/viz.py",
        'return "pressure" if getattr(simulator, "predicts_pressure", True) else "speed"',
        'return "pressure"',
        "tests/test_export.py::test_a_preview_colours_by_pressure_only_for_a_simulator_that_predicts_it",
    ),
    (
        "the preview of a run the guard stopped does not say so",
        "lagfluid/tasks/simulate.py",
        'title = stopped_title(f"{simulator.name} on {cfg.scene.name}", stop_reason, by_guard)',
        'title = f"{simulator.name} on {cfg.scene.name}"',
        "tests/test_export.py::test_a_run_stopped_by_the_guard_says_so_on_its_preview",
    ),
    (
        "kinetic-energy error relative to each frame's reference energy",
        "lagfluid/metrics.py",
        "return (err / peak).tolist()",
        "return (err / b).tolist()",
        "tests/test_metrics.py::test_kinetic_energy_error_is_relative_to_the_references_peak_not_to_each_frame",
    ),
    (
        "metrics.json holds simulator.networks as JSON text",
        "lagfluid/models/fgn/simulator.py",
        'return {**super().attributes(), "networks": self.networks}',
        'return {**super().attributes(), "networks": __import__("json").dumps(self.networks)}',
        "tests/test_fgn.py::test_metrics_json_holds_the_networks_as_an_object_not_json_text",
    ),
    (
        "a resumed training forgets the losses since the last logged row",
        "lagfluid/tasks/train.py",
        'window = [float(v) for v in ckpt.get("loss_window", [])]',
        "window = []",
        "tests/test_fgn.py::test_a_resumed_trainings_loss_log_is_the_uninterrupted_runs[checkpoint-between-rows]",
    ),
    (
        "a training rerun without a checkpoint appends to the old loss log",
        "lagfluid/tasks/train.py",
        "        if self.main:\n            _start_csv(self.csv_path, self.step)",
        "        if self.main and self.step > 0:\n            _start_csv(self.csv_path, self.step)",
        "tests/test_fgn.py::test_a_resumed_trainings_loss_log_is_the_uninterrupted_runs[before-the-first-checkpoint]",
    ),
    (
        "a failed ParaView export leaves its half-written folder",
        "lagfluid/tasks/export/vtk.py",
        "        shutil.rmtree(part, ignore_errors=True)\n        raise",
        "        raise",
        "tests/test_export.py::test_a_damaged_frame_is_named_and_the_last_export_stays_whole",
    ),
    (
        "a damaged frame in an export is a raw h5py traceback",
        "lagfluid/data/store.py",
        "    except (OSError, RuntimeError) as err:  # h5py",
        "    except RuntimeError as err:  # h5py",
        "tests/test_export.py::test_a_damaged_frame_is_named_and_the_last_export_stays_whole",
    ),
    (
        "task=export makes a runs/export/<model>-<scene> folder of its own",
        "lagfluid/conf/config.yaml",
        "dir: ${lagfluid.if_task:${task},export,.,${out_dir}}",
        "dir: ${out_dir}",
        "tests/test_export.py::test_cli_export_of_a_damaged_run_is_one_line_and_makes_no_folder_of_its_own",
    ),
    # issue 34 (output folders, locks, stored precision, resume)
    (
        "resume accepting a changed write_every",
        "lagfluid/tasks/simulate_resume.py",
        '"threads", "checkpoint_every_s", "out_dir")',
        '"threads", "checkpoint_every_s", "out_dir", "write_every")',
        "tests/test_simulate_resume.py::test_resume_refuses_other_settings_and_a_folder_without_a_checkpoint",
    ),
    (
        "simulate skips its out_dir lock",
        "lagfluid/tasks/simulate.py",
        '    with hold_outputs(out_dir, "simulate"):',
        "    if True:  # planted",
        "tests/test_run_lock.py::test_a_second_simulate_into_a_held_out_dir_is_refused_by_name_and_touches_nothing",
    ),
    (
        "Hydra writes .hydra/ into an out_dir another run holds",
        "lagfluid/tasks/locks.py",
        "            check_out_dir(folder)\n",
        "            pass  # planted\n",
        "tests/test_run_lock.py::test_a_second_simulate_into_a_held_out_dir_is_refused_by_name_and_touches_nothing",
    ),
    (
        "export skips its lock",
        "lagfluid/tasks/export/__init__.py",
        '    with hold_outputs(path.parent, "export", what="run"):',
        "    if True:  # planted",
        "tests/test_run_lock.py::test_every_task_that_writes_takes_its_lock",
    ),
    (
        "a killed run's lock taken over without a word",
        "lagfluid/tasks/locks.py",
        "    if left:\n        log.warning(",
        "    if False:\n        log.warning(",
        "tests/test_run_lock.py::test_a_lock_left_by_a_killed_run_is_taken_over_and_logged",
    ),
    (
        "a held MPS reference lock waits without a log line",
        "lagfluid/tasks/locks.py",
        '        log.info("waiting for %s: %s holds its lock", what, _holder(path))',
        "        pass  # planted",
        "tests/test_run_lock.py::test_an_evaluation_waiting_for_a_held_reference_says_for_what_and_whom",
    ),
    (
        "a run without a rollout publishes over the earlier run's files",
        "lagfluid/tasks/outputs.py",
        "    if not part_path(out_dir / names[0]).exists():",
        "    if False:",
        "tests/test_run_lock.py::test_a_run_that_wrote_no_rollout_leaves_the_earlier_files_alone",
    ),
    (
        "a float64 run stores float32 positions",
        "lagfluid/tasks/simulate.py",
        "            dtype=stored_dtype(state),",
        "            dtype=np.float32,",
        "tests/test_store.py::test_a_float64_run_far_from_the_origin_stores_its_exact_positions",
    ),
    (
        "evaluate stores a float64 model rollout as float32",
        "lagfluid/tasks/evaluate/model_run.py",
        "        dtype=stored_dtype(state),",
        '        dtype="float32",',
        "tests/test_store.py::test_a_float64_run_far_from_the_origin_stores_its_exact_positions",
    ),
    (
        "Ctrl-C before the first periodic checkpoint saves none",
        "lagfluid/tasks/simulate.py",
        "            checkpoint.save_latest()",
        "            pass  # planted",
        "tests/test_simulate_resume.py::test_ctrl_c_before_the_first_periodic_checkpoint_saves_one_and_resumes",
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
        "lagfluid/tasks/simulate.py",
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
        "lagfluid/tasks/train.py",
        "        check_export_to(cfg.export_to)",
        "        pass  # planted",
        "tests/test_train.py::test_export_to_an_existing_file_is_refused_before_the_training",
    ),
    (
        "an evaluation the guard stopped exits 0",
        "lagfluid/tasks/evaluate/task.py",
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
        "lagfluid/neighbors/pair_kernels.py",
        "    if where and not _announced:",
        "    if False:",
        "tests/test_progress.py::test_a_cold_kernel_cache_is_announced_once_before_compiling",
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
        "lagfluid/physics/scheme.py",
        "            pos[:nf] = integrate.collide(pos[:nf], v_star, v_new, dt)",
        "            pass  # planted",
        "tests/test_exact_after.py::test_exact_collision_after_a_step_is_the_collision_rule_applied_directly",
    ),
    (
        "exact_after: the relaxation factor is ignored",
        "lagfluid/physics/scheme.py",
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
    # train.max_seconds and benchmarks/gpu_train.sh (issue 35, item 6)
    (
        "train.max_seconds ignored",
        "lagfluid/tasks/train.py",
        "return not last and self.deadline is not None and time.monotonic() >= self.deadline",
        "return False",
        "tests/test_train.py::test_max_seconds_stops_after_a_checkpoint_and_the_same_command_continues_exactly",
    ),
    (
        "a training stopped by train.max_seconds loses the iterations since its last checkpoint",
        "lagfluid/tasks/train.py",
        "if step % int(tcfg.checkpoint_every) == 0 or last or stopped:",
        "if step % int(tcfg.checkpoint_every) == 0 or last:",
        "tests/test_train.py::test_max_seconds_stops_after_a_checkpoint_and_the_same_command_continues_exactly",
    ),
    (
        "the next trainable starts after train.max_seconds stopped one",
        "lagfluid/tasks/train.py",
        'if summaries[-1].get("stopped"):',
        "if False:",
        "tests/test_train.py::test_max_seconds_stops_after_a_checkpoint_and_the_same_command_continues_exactly",
    ),
    (
        "gpu_train.sh brings back the checkpoints with their optimizer state",
        "benchmarks/gpu_train.sh",
        "export_weights(run, out, kinds=[kind])",
        'shutil.copyfile(run / f"{kind}.pt", out / f"{kind}.pt")',
        "tests/test_gpu_train.py::test_each_network_comes_back_loadable_with_its_loss_log_and_stopped_by_the_cap",
    ),
    (
        "gpu_train.sh overwrites a file of the same name in OUT",
        "benchmarks/gpu_train.sh",
        'if [ -e "$out/$name" ]; then',
        'if [ -e "$out/$name.planted" ]; then',
        "tests/test_gpu_train.py::test_an_out_that_holds_one_of_its_files_is_refused_untouched",
    ),
    # DAgger for end-to-end models (issue 35, item 3: GNS trained on its own mistakes)
    (
        "dagger: MPS starts from the model's explicit velocity, not its frames' difference",
        "lagfluid/tasks/generate/expert.py",
        "    vel[:nf] = velocity_from_positions(before.pos[:nf], after.pos[:nf], after.params.dt)",
        "    vel[:nf] = after.vel[:nf]",
        "tests/test_dagger.py::test_mps_label_of_a_free_fall_is_the_integrator_inverse_of_mps_substeps",
    ),
    (
        "dagger: MPS label one solver step short of the model's step",
        "lagfluid/tasks/generate/expert.py",
        "    for _ in range(substeps):\n        state = expert.step(state)",
        "    for _ in range(substeps - 1):\n        state = expert.step(state)",
        "tests/test_dagger.py::test_mps_label_of_a_free_fall_is_the_integrator_inverse_of_mps_substeps",
    ),
    (
        "dagger: the MPS warm-start frames labelled as the model's",
        "lagfluid/tasks/generate/expert.py",
        '        if not getattr(sim, "last_step_learned", True):',
        "        if False:",
        "tests/test_dagger.py::test_each_round_rolls_out_the_previous_rounds_weights_and_mps_labels_their_states",
    ),
    (
        "dagger: every k-th own frame counted from the 2nd",
        "lagfluid/tasks/generate/expert.py",
        "        if (learned - 1) % every:",
        "        if learned % every:",
        "tests/test_dagger.py::test_start_from_skips_the_one_step_training_and_every_k_labels_every_kth_own_frame",
    ),
    (
        "dagger: a guard stop keeps one frame too many",
        "lagfluid/tasks/generate/expert.py",
        '            stopped = {"stopped_after_frame": int(last.step), "stop_reason": str(err)}',
        '            stopped = {"stopped_after_frame": int(last.step) + 1, "stop_reason": str(err)}',
        "tests/test_dagger.py::test_a_rollout_stopped_by_the_models_guard_keeps_the_frames_and_labels_before",
    ),
    (
        "dagger: round k fine-tunes on round k's data alone",
        "lagfluid/tasks/dagger_rounds.py",
        "for j in range(1, k + 1)]",
        "for j in range(k, k + 1)]",
        "tests/test_dagger.py::test_round_k_fine_tunes_from_round_k_minus_1_on_the_original_data_and_rounds_1_to_k",
    ),
    (
        "dagger: every round fine-tunes from the start weights",
        "lagfluid/tasks/dagger_rounds.py",
        "            tuned.train.init_from = str(previous)",
        "            tuned.train.init_from = str(start)",
        "tests/test_dagger.py::test_round_k_fine_tunes_from_round_k_minus_1_on_the_original_data_and_rounds_1_to_k",
    ),
    (
        "dagger: windows without enough frames before their label",
        "lagfluid/data/expert_windows.py",
        "(frames >= self.first) & (frames < info.frames)",
        "(frames >= 0) & (frames < info.frames)",
        "tests/test_dagger.py::test_a_dagger_window_is_the_models_frames_and_its_target_the_inverse_of_mps_answer",
    ),
    (
        "dagger: GNS reads a DAgger dataset as a solver trajectory",
        "lagfluid/data/expert_windows.py",
        "    if is_expert_dataset(load_metadata(root)):",
        "    if False:",
        "tests/test_dagger.py::test_a_dagger_window_is_the_models_frames_and_its_target_the_inverse_of_mps_answer",
    ),
    (
        "dagger: a measured dam rollout is run again on a rerun",
        "lagfluid/tasks/dagger_eval.py",
        "== (str(weights), scene, steps):",
        "== (None, None, None):",
        "tests/test_dagger.py::test_each_rounds_dam_rollout_is_measured_and_a_rerun_redoes_nothing",
    ),
    (
        "dagger: start_from still trains in out_dir first",
        "lagfluid/tasks/train.py",
        "    for name in [] if from_elsewhere else names:",
        "    for name in [] if False else names:",
        "tests/test_dagger.py::test_start_from_skips_the_one_step_training_and_every_k_labels_every_kth_own_frame",
    ),
    # GNS's first edge layer applied by parts (issue 35, item 3): the same function as the concatenated form
    (
        "GNS edge layer: the receiver's projection gathered by the sender",
        "baselines/gns/network.py",
        "receiver = F.linear(x, w[:, L : 2 * L]).index_select(0, edge_index[1])",
        "receiver = F.linear(x, w[:, L : 2 * L]).index_select(0, edge_index[0])",
        "tests/test_gns.py::test_the_shipped_weights_roll_out_the_same_with_the_concatenated_edge_layer",
    ),
    (
        "GNS edge layer: the sender projected by the receiver's column block",
        "baselines/gns/network.py",
        "sender = F.linear(x, w[:, 2 * L :])",
        "sender = F.linear(x, w[:, L : 2 * L])",
        "tests/test_gns.py::test_edge_update_applied_by_parts_is_the_concatenated_mlp_in_value_and_gradient",
    ),
    (
        "GNS edge layer: the first layer's bias left out",
        "baselines/gns/network.py",
        "F.linear(e, w[:, :L], first.bias)",
        "F.linear(e, w[:, :L])",
        "tests/test_gns.py::test_edge_update_by_parts_in_float32_is_the_concatenated_form_to_rounding",
    ),
    (
        "GNS edge layer: no gradient reaches the receiver's column block (same forward)",
        "baselines/gns/network.py",
        "receiver = F.linear(x, w[:, L : 2 * L])",
        "receiver = F.linear(x, w[:, L : 2 * L].detach())",
        "tests/test_gns.py::test_the_networks_loss_gradients_by_parts_equal_the_concatenated_forms",
    ),
    # CConv fine-tuned from DeepLagrangianFluids' weights (issue 35, item 2)
    (
        "cconv fine-tune: the rollout ignores the checkpoint's axes",
        "baselines/cconv/simulator.py",
        '        AXES[view["axes"]],',
        "        torch.eye(3),",
        "tests/test_cconv.py::test_a_fine_tuned_checkpoint_rolls_out_as_it_was_trained",
    ),
    (
        "cconv fine-tune: the training leaves the walls' normals unweighted",
        "baselines/cconv/trainable.py",
        "        points, normals = points @ rotation.T, self.surface_weight * normals @ rotation.T",
        "        points, normals = points @ rotation.T, normals @ rotation.T",
        "tests/test_cconv.py::test_a_fine_tuned_checkpoint_rolls_out_as_it_was_trained",
    ),
    (
        "cconv fine-tune: DLF's 9.81 kept instead of the data's gravity",
        "baselines/cconv/trainable.py",
        '        net.gravity.copy_(torch.tensor([float(g) for g in self.options["gravity"]]))',
        "        pass",
        "tests/test_cconv.py::test_fine_tuning_starts_from_dlfs_weights_with_the_datas_gravity",
    ),
    (
        "cconv fine-tune: the random turn is about a horizontal axis",
        "baselines/cconv/trainable.py",
        "            turn = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)",
        "            turn = torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=torch.float64)",
        "tests/test_cconv.py::test_a_turn_about_gravity_keeps_gravity_and_turns_the_horizontal",
    ),
    (
        "cconv fine-tune: validation batches turned at random as training's",
        "baselines/cconv/trainable.py",
        "turn=net.training)",
        "turn=True)",
        "tests/test_cconv.py::test_a_fine_tuned_checkpoint_rolls_out_as_it_was_trained",
    ),
    (
        "training range: a recorded range keeps every quantity (GNS/CConv warn about the data's dt)",
        "lagfluid/models/training_range.py",
        '        return {key: list(value) for key, value in meta["range"].items() if key in quantities}',
        '        return dict(meta["range"])',
        "tests/test_data.py::test_a_recorded_training_range_keeps_only_the_quantities_asked_for",
    ),
    (
        "threads: Numba's pool started inside the first kernel (threads=1 runs on every core)",
        "lagfluid/neighbors/pair_kernels.py",
        "    parallel._launch_threads()  # a no-op once started\n    torch.set_num_threads(threads)",
        "    pass",
        "tests/test_pair_kernels.py::test_the_first_compiled_search_keeps_torchs_thread_count",
    ),
    # benchmarks.unseen_obstacles: scenes no model trained on (issue 35)
    (
        "unseen_obstacles: the dam_cone tank lower than its open top (a lid over the fluid)",
        "benchmarks/unseen_obstacles.py",
        '"container": _box([0, 0, 0], [2.0, 1.0, 1.8]),',
        '"container": _box([0, 0, 0], [2.0, 1.0, 1.0]),',
        "tests/test_unseen_obstacles.py::test_every_scene_is_small_with_obstacles_in_reach_and_no_lid",
    ),
    (
        "unseen_obstacles: the mesh folder's digest ignores the obstacles (a stale MPS reference reused)",
        "benchmarks/unseen_obstacles.py",
        'b"".join(blobs[k] for k in sorted(blobs))',
        'b"".join(blobs[k] for k in ("container", "fluid"))',
        "tests/test_unseen_obstacles.py::test_mesh_folders_are_named_by_their_geometry",
    ),
    (
        "unseen_obstacles: a derived exact row labelled as the plain model",
        "benchmarks/unseen_obstacles.py",
        "label = ExactAfterOptions(collision=True, pressure=True).label(plain.label)",
        "label = plain.label",
        "tests/test_unseen_obstacles.py::test_rows_take_the_tables_labels_and_a_missing_one_is_skipped",
    ),
    (
        "unseen_obstacles: missing weights fail the benchmark instead of skipping the row",
        "benchmarks/unseen_obstacles.py",
        "    except MissingWeightsError as err:",
        "    except KeyError as err:",
        "tests/test_unseen_obstacles.py::test_a_row_whose_weights_are_missing_is_skipped_not_run",
    ),
    (
        "unseen_obstacles: a row with metrics.json is run again",
        "benchmarks/unseen_obstacles.py",
        "    if not metrics_path.is_file():\n        print(",
        "    if True:\n        print(",
        "tests/test_unseen_obstacles.py::test_a_row_with_metrics_is_read_not_rerun_and_its_columns_are_its_numbers",
    ),
    (
        "unseen_obstacles: the wall approach's second share is below 0.8 l0, not 0.7",
        "benchmarks/unseen_obstacles.py",
        "{s['< 0.7 l0']}",
        "{s['< 0.8 l0']}",
        "tests/test_unseen_obstacles.py::test_a_row_with_metrics_is_read_not_rerun_and_its_columns_are_its_numbers",
    ),
    # GNS: the statistics and windows of the training (issue 35, why the trained GNS never completes the dam)
    (
        "GNS statistics skip frame t (history, then t+1)",
        "baselines/gns/trainable.py",
        "[_trajectory_history(item), item.pos[fluid].unsqueeze(1), item.y.unsqueeze(1)], dim=1",
        "[_trajectory_history(item), item.y.unsqueeze(1)], dim=1",
        "tests/test_gns.py::test_the_statistics_are_of_the_frames_the_targets_are_made_of",
    ),
    (
        "GNS statistics count the copies of frame 0 that pad an early window",
        "baselines/gns/trainable.py",
        "else item.history[:, item.history.shape[1] - int(before) :]",
        "else item.history",
        "tests/test_gns.py::test_the_statistics_are_of_the_frames_the_targets_are_made_of",
    ),
    (
        "GNS windows start at H + K, not at the warm start's H",
        "baselines/gns/trainable.py",
        'trajectory_windows(data_dir, "train", history=frames, first=first, stride=stride)',
        'trajectory_windows(data_dir, "train", history=frames, first=None, stride=stride)',
        "tests/test_gns.py::test_the_windows_start_at_the_first_frame_a_warm_started_rollout_steps_from",
    ),
    (
        "GNS pushforward unrolls from the copies of frame 0",
        "baselines/gns/trainable.py",
        "unroll = min(self._draw_unroll(int(net.trained_batches)), self._most_unroll(batch))",
        "unroll = self._draw_unroll(int(net.trained_batches))",
        "tests/test_gns.py::test_the_windows_start_at_the_first_frame_a_warm_started_rollout_steps_from",
    ),
    # the design document in the repository, docs/architecture.md (issue 36, item 5)
    (
        "a docstring points to the design document outside the repository again",
        "lagfluid/integrate.py",
        "One integrator, outside the models (``docs/architecture.md#conventions``, convention 5;",
        "DESIGN convention 5 (",
        "tests/test_docs.py::test_nothing_points_to_a_design_document_outside_the_repository",
    ),
    (
        "the architecture document names a file that is not there (a module moved, the document not)",
        "docs/architecture.md",
        "(`VerletNeighborList`, `lagfluid/neighbors/verlet.py`)",
        "(`VerletNeighborList`, `lagfluid/neighbors/verlet_list.py`)",
        "tests/test_docs.py::test_every_path_in_the_architecture_document_exists",
    ),
    (
        "a pointer cites a section the architecture document does not have",
        "lagfluid/data/layout.py",
        "``docs/architecture.md#layers``",
        "``docs/architecture.md#the-layers``",
        "tests/test_docs.py::test_every_anchor_pointing_into_the_architecture_document_exists",
    ),
    # issue 36: the plugin surface lagfluid.zoo, the layer table, import circles
    (
        "a baseline imports FGN's networks module, not the zoo",
        "baselines/gns/network.py",
        "from lagfluid.zoo import ConfigError, Standardizer\n",
        "from lagfluid.models.fgn.networks import Standardizer\nfrom lagfluid.zoo import ConfigError\n",
        "tests/test_layers.py::test_imports_point_one_way",
    ),
    (
        "GNS takes scene_params from the task module lagfluid.tasks.config again",
        "baselines/gns/simulator.py",
        "    scene_params,\n    semi_implicit_euler,\n)\n",
        "    semi_implicit_euler,\n)\nfrom lagfluid.tasks.config import scene_params\n",
        "tests/test_layers.py::test_imports_point_one_way",
    ),
    (
        "the test plugin imports lagfluid.state directly",
        "tests/plugins/tinymlp/model.py",
        "from lagfluid.zoo import (\n    ParticleState,\n",
        "from lagfluid.state import ParticleState\nfrom lagfluid.zoo import (\n",
        "tests/test_layers.py::test_imports_point_one_way",
    ),
    (
        "the checkpoint <-> training_range circle put back (a function-level import)",
        "lagfluid/models/training_range.py",
        "    lines = []\n",
        "    from lagfluid.models.checkpoint import read_checkpoint  # noqa: F401\n\n    lines = []\n",
        "tests/test_layers.py::test_no_import_circles",
    ),
    (
        "a layer table pattern that names no module",
        "tests/test_layers.py",
        '"rollout": ("lagfluid.rollout",),',
        '"rollout": ("lagfluid.rollout", "lagfluid.rollouts.*"),',
        "tests/test_layers.py::test_every_pattern_names_a_module",
    ),
    (
        "the layer table lists data above scenes, which imports it",
        "tests/test_layers.py",
        '    "scenes": ("lagfluid.scenes", "lagfluid.scenes.*"),\n'
        '    "data": ("lagfluid.data", "lagfluid.data.*"),\n',
        '    "data": ("lagfluid.data", "lagfluid.data.*"),\n'
        '    "scenes": ("lagfluid.scenes", "lagfluid.scenes.*"),\n',
        "tests/test_layers.py::test_every_layer_has_its_rule_and_imports_only_layers_below_it",
    ),
    (
        "a name of lagfluid.zoo missing from its docstring",
        "lagfluid/zoo.py",
        "    ``pair_bytes``           the bytes of the neighbour pairs alone\n",
        "",
        "tests/test_zoo.py::test_every_name_of_the_surface_is_in_its_docstring_and_in_the_readme",
    ),
    (
        "make_mlp keeps a bias under LayerNorm (state_dict keys change)",
        "lagfluid/models/layers.py",
        "bias=not layer_norm",
        "bias=True",
        "tests/test_zoo.py::test_the_shared_layers_keep_their_state_dict_keys",
    ),
    # issue 36, benchmarks vs studies: a moved study's old path, a non-atomic results writer
    (
        "README runs a moved study by its old path",
        "README.md",
        "`python -m benchmarks.studies.resting_variants` measures",
        "`python -m benchmarks.resting_variants` measures",
        "tests/test_benchmarks_layout.py::test_every_benchmark_the_documents_run_exists",
    ),
    (
        "write_atomic writes in place, not beside (a failure mid-write destroys the old results)",
        "benchmarks/provenance.py",
        'tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")',
        "tmp = path",
        "tests/test_provenance.py::test_a_failure_mid_write_leaves_the_old_results_intact",
    ),
    # issue 35, session 7: GNS's frame interval (train.frame_stride), DAgger's refusal of it, gpu_day.sh
    (
        "stride windows: the history taken from consecutive stored frames, not every s-th",
        "lagfluid/data/datasets.py",
        "np.arange(t - self.history * s, t + after * s + 1, s)",
        "np.arange(t - (self.history + after) - 1, t + after * s + 1)[-(self.history + 1 + after) :]",
        "tests/test_gns.py::test_trajectory_windows_with_a_frame_stride_take_every_other_stored_frame",
    ),
    (
        "stride windows: the frame spacing not scaled by the stride",
        "lagfluid/data/datasets.py",
        'frame_dt=torch.tensor([float(a["dt"]) * every * self.stride], dtype=torch.float32),',
        'frame_dt=torch.tensor([float(a["dt"]) * every], dtype=torch.float32),',
        "tests/test_gns.py::test_trajectory_windows_with_a_frame_stride_take_every_other_stored_frame",
    ),
    (
        "GNS's trainable ignores train.frame_stride",
        "baselines/gns/trainable.py",
        "frames, first, stride = self.history + max(self.unrolls), self.history, self.frame_stride",
        "frames, first, stride = self.history + max(self.unrolls), self.history, 1",
        "tests/test_gns.py::test_train_frame_stride_reaches_the_windows_and_a_bad_one_is_refused",
    ),
    (
        "DAgger rounds accept a frame stride (refused only after round 1's rollouts)",
        "lagfluid/tasks/dagger_rounds.py",
        'if values["rounds"] and stride != 1:',
        "if False:",
        "tests/test_dagger.py::test_bad_dagger_settings_are_refused_before_anything_runs",
    ),
    (
        "gpu_day.sh writes into an OUT that holds an earlier day's files",
        "benchmarks/gpu_day.sh",
        'if [ -n "$(ls -A "$out")" ]; then',
        "if false; then",
        "tests/test_gpu_train.py::test_a_day_into_an_out_that_holds_files_is_refused_untouched",
    ),
    # issue 36, item 4: the Trainer's parts on their own
    (
        "trainer: the identity always lists the schedule (every older checkpoint's fingerprint changes)",
        "lagfluid/tasks/train.py",
        "        if self.milestones or self.adam_eps != 1e-8:",
        "        if True:",
        "tests/test_train.py::test_the_trainers_identity_holds_the_optional_settings_only_when_set",
    ),
    (
        "trainer: a checkpoint of other settings is resumed",
        "lagfluid/tasks/train.py",
        'if meta.get("fingerprint") != self.fingerprint:',
        "if False:",
        "tests/test_train.py::test_a_checkpoint_of_other_settings_is_refused_in_one_line_and_kept",
    ),
    (
        "trainer: train.max_seconds stops a run on its last iteration too",
        "lagfluid/tasks/train.py",
        "return not last and self.deadline is not None and time.monotonic() >= self.deadline",
        "return self.deadline is not None and time.monotonic() >= self.deadline",
        "tests/test_train.py::test_the_stop_rules_are_all_iterations_and_max_seconds_after_any_iteration_but_the_last",
    ),
    (
        "trainer: an iteration steps at the next iteration's learning rate",
        "lagfluid/tasks/train.py",
        "step, self.iterations, float(tcfg.lr_start)",
        "step + 1, self.iterations, float(tcfg.lr_start)",
        "tests/test_train.py::test_one_iteration_is_one_adam_step_at_its_rate_logged_and_saved_for_the_resume",
    ),
    (
        "trainer: a logged row's losses are averaged into the next row too",
        "lagfluid/tasks/train.py",
        "        self.window = []\n",
        "        pass  # planted\n",
        "tests/test_train.py::test_one_iteration_is_one_adam_step_at_its_rate_logged_and_saved_for_the_resume",
    ),
    (
        "trainer: a checkpoint leaves out the losses since the last logged row",
        "lagfluid/tasks/train.py",
        "loss_window=list(self.window)",
        "loss_window=[]",
        "tests/test_train.py::test_one_iteration_is_one_adam_step_at_its_rate_logged_and_saved_for_the_resume",
    ),
    # issue 36, item 2: backends chosen once (pair_kernels.backend_for), each kernel's two bodies
    (
        "backends: the dispatch always picks the torch body (the compiled kernels never run)",
        "lagfluid/neighbors/pair_kernels.py",
        "        return kernel.compiled\n",
        "        return kernel.torch\n",
        "tests/test_kernel_dispatch.py::test_cpu_float32_and_float64_take_the_compiled_body_where_numba_is",
    ),
    (
        "backends: the dispatch sends float16 to the compiled kernels (written for float32 and float64)",
        "lagfluid/neighbors/pair_kernels.py",
        "and (t.dtype in _COMPILED_FLOATS or not t.dtype.is_floating_point)",
        "and True",
        "tests/test_kernel_dispatch.py::test_other_devices_dtypes_and_autograd_take_the_torch_body",
    ),
    (
        "backends: the dispatch sends tensors that need a gradient to the compiled kernels",
        "lagfluid/neighbors/pair_kernels.py",
        "and not (t.requires_grad and torch.is_grad_enabled())",
        "and True",
        "tests/test_kernel_dispatch.py::test_other_devices_dtypes_and_autograd_take_the_torch_body",
    ),
    (
        "backends: the torch body of select_below keeps the pairs at exactly the radius",
        "lagfluid/neighbors/pair_kernels.py",
        "    index = torch.nonzero(dist < radius).flatten()\n",
        "    index = torch.nonzero(dist <= radius).flatten()\n",
        "tests/test_kernel_dispatch.py::test_both_bodies_give_the_worked_out_numbers[select_below]",
    ),
    (
        "backends: the min-pressure gradient registered with its bodies swapped (autograd would reach Numba)",
        "lagfluid/physics/operators.py",
        '"min_pressure_gradient", compiled=_min_gradient_compiled, torch=_min_gradient_torch,',
        '"min_pressure_gradient", compiled=_min_gradient_torch, torch=_min_gradient_compiled,',
        "tests/test_operators.py::test_compiled_min_pressure_gradient_equals_the_torch_operations",
    ),
    (
        "backends: the compiled number density hands every graph to its torch body",
        "lagfluid/physics/operators.py",
        "    if rows is None:\n        return _number_density_torch(",
        "    if True:\n        return _number_density_torch(",
        "tests/test_operators.py::test_compiled_number_density_equals_the_torch_operations",
    ),
    # issue 36, item 1: folders by layer (lagfluid/tasks/, lagfluid/neighbors/) in the layer table
    (
        "layers: the table lists tasks/ module by module again (a new task module falls in no layer)",
        "tests/test_layers.py",
        '    "tasks": ("lagfluid.tasks", "lagfluid.tasks.*"),',
        '    "tasks": ("lagfluid.tasks", "lagfluid.tasks.train", "lagfluid.tasks.simulate"),',
        "tests/test_layers.py::test_the_table_states_folders",
    ),
    (
        "layers: the neighbour search imports the physics (a search that reaches up)",
        "lagfluid/neighbors/verlet.py",
        "from lagfluid.state import ParticleType\n",
        "from lagfluid.physics.operators import kernel\nfrom lagfluid.state import ParticleType\n",
        "tests/test_layers.py::test_imports_point_one_way",
    ),
    (
        "layers: a task imports the command module lagfluid.run",
        "lagfluid/tasks/outputs.py",
        "from lagfluid.data.store import ",
        "from lagfluid.run import CONF_DIR\nfrom lagfluid.data.store import ",
        "tests/test_layers.py::test_imports_point_one_way",
    ),
    # the Verlet list's split search: the boundary indexed once per scene (issue 37)
    (
        "Verlet list searches against a stale boundary index after the walls moved",
        "lagfluid/neighbors/verlet.py",
        "if static is None or not static.matches(pos, walls, n_fluid, self.list_radius):",
        "if static is None:",
        "tests/test_pair_kernels.py::test_static_boundary_is_indexed_once_and_again_when_the_walls_change",
    ),
    (
        "split search keeps a pair at exactly the list radius",
        "lagfluid/neighbors/_numba.py",
        "if acc < bound2 and order[k] != skip[r]:",
        "if acc <= bound2 and order[k] != skip[r]:",
        "tests/test_pair_kernels.py::test_split_search_gives_the_candidates_of_brute_force_and_of_one_cell_list",
    ),
    (
        "split search drops a fluid-wall pair (each fluid row's last boundary source)",
        "lagfluid/neighbors/_numba.py",
        "out_j[o + k] = fb_buf[fb_slots[i] + k] + n_fluid",
        "out_j[o + k] = fb_buf[fb_slots[i] + max(k - 1, 0)] + n_fluid",
        "tests/test_pair_kernels.py::test_split_search_gives_the_candidates_of_brute_force_and_of_one_cell_list",
    ),
    (
        "split search reads source positions without the cell permutation",
        "lagfluid/neighbors/pair_kernels.py",
        "self._sorted_pos = np.ascontiguousarray(self._args[0][self._args[2]])",
        "self._sorted_pos = np.ascontiguousarray(self._args[0])",
        "tests/test_pair_kernels.py::test_split_search_gives_the_candidates_of_brute_force_and_of_one_cell_list",
    ),
    (
        "split search's fluid rows transposed with the chunks in reverse order (sources not ascending)",
        "lagfluid/neighbors/pair_kernels.py",
        "cursor = np.cumsum(hist, axis=0) - hist + f_off[:-1]",
        "cursor = np.cumsum(hist[::-1], axis=0)[::-1] - hist + f_off[:-1]",
        "tests/test_pair_kernels.py::test_fluid_rows_come_sorted_from_the_transpose_whatever_the_chunks",
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
        # pytest exits 1 when a test failed; 2, 4 or 5 (an error, a node id that does not exist, no test
        # collected) mean the test never judged the plant: an ERROR, counted as missed
        verdict = {0: "MISSED", 1: "CAUGHT"}.get(done.returncode, f"ERROR (pytest exit {done.returncode})")
        missed += verdict != "CAUGHT"
        print(f"{verdict}: {name}: {test}", flush=True)
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
