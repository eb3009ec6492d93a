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
