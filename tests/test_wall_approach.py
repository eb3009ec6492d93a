"""benchmarks.wall_approach: distances from the fluid to the boundary particles, against a lattice."""

import numpy as np

from benchmarks.wall_approach import boundary_distances, summary

L0 = 0.05


def _lattice(n: int, z0: float) -> np.ndarray:
    axis = np.arange(n) * L0
    x, y, z = np.meshgrid(axis, axis, z0 + axis, indexing="ij")
    return np.stack([x, y, z], -1).reshape(-1, 3)


def test_a_block_resting_one_spacing_above_a_floor_is_one_l0_away():
    floor = _lattice(6, 0.0)
    floor = floor[floor[:, 2] == 0.0]  # one layer at z = 0
    fluid = _lattice(4, L0)  # from z = l0 up, above the floor's points
    sinking = fluid - np.array([0.0, 0.0, 0.6 * L0])  # the lowest layer 0.4 l0 above the floor
    trajectory = {"position": np.stack([fluid, sinking]), "boundary_position": floor}
    d = boundary_distances(trajectory, L0)
    assert d.shape == (2 * fluid.shape[0],)
    np.testing.assert_allclose(d[: fluid.shape[0]].min(), 1.0)
    np.testing.assert_allclose(d[fluid.shape[0] :].min(), 0.4)
    row = summary("x", d, 2)
    assert row["min"] == 0.4 and row["particle-frames"] == d.size
    assert float(row["< 0.5 l0"]) == 16 / d.size  # the sunk bottom layer, 4 x 4 particles
    assert float(row["< 0.8 l0"]) == 16 / d.size and float(row["< 0.7 l0"]) == 16 / d.size
