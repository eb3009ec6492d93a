"""Memory: the allocator settings of long simulations (:func:`keep_freed_memory`) and a rollout's estimate.

numpy is imported inside the functions: :mod:`lagfluid.run` imports this module before it has told OpenMP
how many threads to start (:func:`lagfluid.run.limit_openmp`).
"""

from __future__ import annotations

import ctypes
import logging
import os
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

    from lagfluid.state import ParticleState

log = logging.getLogger(__name__)

# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
_SETTINGS = {
    _M_MMAP_THRESHOLD: 32 << 20,  # glibc's largest: blocks up to 32 MiB come from the heap, not fresh mmap
    _M_TRIM_THRESHOLD: 1 << 30,  # keep up to 1 GiB of free heap instead of returning it after every step
    _M_TOP_PAD: 256 << 20,  # grow the heap in 256 MiB steps
}


def keep_freed_memory() -> bool:
    """Let glibc's malloc keep freed blocks for reuse instead of handing them back to the OS.

    A simulation step allocates and frees the same few hundred MB of tensors every step. By default glibc
    serves large blocks with fresh ``mmap`` pages and trims the heap after frees, so every step pays a page
    fault per 4 KiB it touches again (~40k per step at 40,000 particles); kept, FGN's step at 40,000 fluid
    particles went from 132 to 112 ms on 2 cores (``benchmarks/results/fgn_step_speed.md``). The price: the
    process keeps its peak memory until it ends. Called by the command-line entry points, not on import.

    Returns:
        True when applied; False off glibc or when the user set ``MALLOC_*`` variables (theirs win).
    """
    if not sys.platform.startswith("linux") or any(k.startswith("MALLOC_") for k in os.environ):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl or another libc: nothing to tune
        return False
    applied = all(mallopt(param, value) == 1 for param, value in _SETTINGS.items())
    log.debug("malloc keeps freed memory: %s", applied)
    return applied


def neighbour_pairs(pos: np.ndarray, receivers: np.ndarray, radius: float) -> float:
    """Estimated pairs ``(i, j)`` with ``i`` a receiver and ``|x_i - x_j| < radius``, without a search.

    Particles are counted in cells of side ``h >= radius``; each receiver's neighbours are estimated as the
    particles in its cell's 27-cell block times the sphere's share of the block, ``(4/3) pi r^3 / (27 h^3)``.
    On a lattice this is the sphere's volume in lattice cells (274 at 4.03 l0, for 257 lattice points; a dam's
    fluid has 232-251 candidates per particle, fewer at its free surface, and the estimate is within 4 % of
    those counts); a denser file gets proportionally more. O(N) memory: ``np.unique`` of one
    int64 key per particle, where a search would hold every pair.

    Args:
        pos: (N, 3) positions, m.
        receivers: (N,) bool, the particles whose neighbours count (the fluid).
        radius: m.

    Returns:
        the estimated number of pairs (the self pair included, as in a candidate list).
    """
    import itertools

    import numpy as np

    pos = np.asarray(pos, dtype=np.float64)
    if not receivers.any():
        return 0.0
    lower, span = pos.min(axis=0), np.ptp(pos, axis=0)
    side = float(radius)
    while np.prod(np.floor(span / side) + 3.0) > 2.0**62:  # a key per cell must fit int64: coarser cells
        side *= 2.0
    cells = np.floor((pos - lower) / side).astype(np.int64) + 1  # 1.. so that cell - 1 stays >= 0
    dims = cells.max(axis=0) + 2
    keys = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    occupied, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    block = np.zeros(len(occupied))
    for dx, dy, dz in itertools.product((-1, 0, 1), repeat=3):
        other = occupied + (dx * dims[1] + dy) * dims[2] + dz
        at = np.minimum(np.searchsorted(occupied, other), len(occupied) - 1)
        found = occupied[at] == other
        block[found] += counts[at[found]]
    share = (4.0 / 3.0) * np.pi * radius**3 / (27.0 * side**3)
    return float(block[inverse[np.asarray(receivers, dtype=bool)]].sum() * share)


RUN_BASE_BYTES = 300 << 20
"""A rollout's memory beyond its particles: the heap grown in 256 MiB steps (:func:`keep_freed_memory`), the
trajectory writer, frame metrics, the preview (matplotlib)."""
RUN_BYTES_PER_PARTICLE = 500
"""Per particle, fluid or boundary: the state, its copies in a step, the cell search's keys and order."""
DEFAULT_PAIR_RADIUS = 4.03
"""l0: a simulator without ``memory_needed`` is estimated as MPS is: its candidate list at 3.1 l0 + skin."""
DEFAULT_BYTES_PER_PAIR = 130.0
"""Bytes per candidate pair of the split-step scheme's Verlet list (MPS, FGN; see :func:`rollout_bytes`)."""


def pair_bytes(state: ParticleState, radius: float, bytes_per_pair: float) -> float:
    """``bytes_per_pair`` times the pairs (fluid, any particle) of ``state`` closer than ``radius`` (m)."""
    fluid = state.fluid_mask.detach().cpu().numpy()
    return bytes_per_pair * neighbour_pairs(state.pos.detach().cpu().numpy(), fluid, radius)


def rollout_bytes(state: ParticleState, radius: float, bytes_per_pair: float) -> float:
    """Peak memory a rollout of ``state`` needs beyond what the process holds before it (bytes, estimated).

    ``RUN_BASE_BYTES + RUN_BYTES_PER_PARTICLE * N + bytes_per_pair * P``, ``P`` the pairs of a fluid particle
    and any particle within ``radius`` (:func:`neighbour_pairs`). Where the numbers come from: peak RSS of
    ``task=simulate`` (``threads=1``) minus its RSS before the first step, on dams of 4,000 to 80,000 fluid
    particles (31k to 154k in all; ``scene.fluid_size`` / ``tank_size`` varied; a 1,000-fluid dam in a
    121 x 121 l0 tank for the boundary): MPS ~300 MB + 115-190 B per candidate pair at 4.03 l0 (its Verlet
    list: 3.1 l0 + 0.3 skin) over 45-60 steps, which rebuild the list once (324 MB at 4,000 fluid, 1.42 GB at
    40,000; 3 steps without a rebuild: 87 B per pair); FGN 117 B per pair at 2.73 l0 (2.1 l0 + skin); GNS and
    CConv in their simulators. The constants round those up: the estimates are 13-100 % above every run
    measured, the fixed part weighing most in small runs. Measured on the CPU: a CUDA run is not estimated.
    MPS's list now takes a 0.15 skin (3.57 l0, ``SolverSettings.skin_fraction``): at 40,000 fluid its run's
    max RSS fell by 239 MB (1.95 -> 1.71 GB, 45 steps, ``/usr/bin/time``), so ~1.18 GB there, 8 % below the
    estimate.

    Args:
        state: the initial state (fluid first).
        radius: m, the simulator's neighbour radius (with its Verlet skin).
        bytes_per_pair: the simulator's measured bytes per such pair.
    """
    fixed = RUN_BASE_BYTES + RUN_BYTES_PER_PARTICLE * state.num_particles
    return fixed + pair_bytes(state, radius, bytes_per_pair)


def memory_needed(simulator: object, state: ParticleState) -> float:
    """Bytes a rollout of ``simulator`` from ``state`` needs: its own ``memory_needed(state)`` or MPS's."""
    own = getattr(simulator, "memory_needed", None)
    if own is not None:
        return float(own(state))
    return rollout_bytes(state, DEFAULT_PAIR_RADIUS * state.params.l0, DEFAULT_BYTES_PER_PAIR)


def exact_step_bytes(state: ParticleState) -> float:
    """Bytes the exact MPS stages need beside a rollout (``task=evaluate``'s one-step errors), as MPS's."""
    return pair_bytes(state, DEFAULT_PAIR_RADIUS * state.params.l0, DEFAULT_BYTES_PER_PAIR)
