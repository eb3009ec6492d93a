"""Assembly of the MPS pressure Poisson equation (PPE) on the solved set: :func:`assemble_ppe`.

**The system.** The MPS Laplacian model (radius ``re = 3.1 l0``, kernel ``w = re/r - 1``) is
``lap(p)_i = sum_j c_ij (p_j - p_i)`` with ``c_ij = 2d/(lambda n0_lap) * w_ij`` (the per-edge
``coef`` the caller passes, see ``operators.laplacian_weights``). The unknowns are the pressures
of the *solved set* (non-free-surface fluid and wall particles). With ``A = -(1/rho) L``::

    A_ii =  (1/rho) * sum_{j in N(i), j solved or free surface} c_ij
    A_ij = -(1/rho) * c_ij                      (j solved, j != i)

Which neighbours count, and why (the standard MPS choice, e.g. Koshizuka's reference code
``setMatrix``):

* **Free-surface neighbours** are Dirichlet particles, ``p_j = 0``: the term ``c_ij (0 - p_i)``
  survives and lands on the diagonal only. A row next to the surface is therefore *strictly*
  diagonally dominant, and that excess is what makes the matrix nonsingular (an irreducibly
  diagonally dominant M-matrix, hence SPD) on every connected component touching the surface.
* **Dummy neighbours** are not part of the pressure problem at all (they only complete the wall
  particles' number density): neither diagonal nor off-diagonal. A row whose missing
  neighbours are dummies keeps zero row sum, i.e. a homogeneous Neumann-like wall.
* **Solved neighbours** give the usual symmetric off-diagonal pair; rows without Dirichlet
  neighbours sum to zero (``A @ const = 0`` there: the Laplacian is consistent).

Which particle is which is told by two masks: ``solve_mask`` (unknowns) and ``dirichlet_mask``
(free-surface particles, ``p = 0``); a neighbour in neither (dummy) is ignored. The Dirichlet
mask is a required argument on purpose: defaulting it to "every non-solved particle" would
silently put dummy particles on the diagonal.

**Isolated clusters.** A connected component of the solved set with no Dirichlet neighbour (a
fully enclosed blob, a patch of wall particles cut off from the fluid, two surface-free drops
that touch) has zero row sums throughout: its block of ``A`` is singular (pressure defined only
up to a constant). The remedy is the standard MPS one (Koshizuka's reference code,
``checkBoundaryCondition`` + ``increaseDiagonalTerm``): **the diagonal of every row in such a
component is doubled**. That block becomes strictly diagonally dominant, hence SPD, and CG
converges on it as fast as elsewhere; the pressure it yields is bounded and of the right order
(a compressed enclosed blob still gets positive pressure). A tiny shift ``eps * A_ii`` would
also remove the singularity but leaves a condition number ~1/eps, so CG needs far more
iterations on that block; pinning one particle to ``p = 0`` depends on which particle is picked.
The factor is configurable (``isolated_diagonal_factor``); the flagged rows are returned.

On the CPU the solver's own graphs (``check=False``) are assembled by the compiled kernels of
:mod:`lagfluid.physics.ppe._numba` (one pass per row instead of ~20 torch passes; see
``benchmarks/results/ppe.md``); everywhere else by torch operations. Both give the same arrays.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from types import ModuleType
from typing import Literal

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import connected_components
from torch import Tensor

from lagfluid.neighbors import pair_kernels
from lagfluid.neighbors.pair_kernels import backend_for

logger = logging.getLogger(__name__)


@dataclass
class PPESystem:
    """The assembled PPE on the solved set.

    Attributes:
        matrix: (K, K) torch sparse CSR ``A = -(1/rho) L`` restricted to the solved set, diagonal
            stored explicitly, columns sorted within rows; on the device and in the dtype of
            ``coef``.
        index: (K,) int64, solved-set position -> particle index (increasing).
        isolated: (K,) bool, rows in connected components with no Dirichlet (free-surface)
            neighbour; their diagonal was multiplied by ``isolated_diagonal_factor``.
        num_particles: N, the number of particles the masks were given for.
        n_isolated_components: number of such components.
    """

    matrix: Tensor
    index: Tensor
    isolated: Tensor
    num_particles: int
    n_isolated_components: int = 0

    @property
    def num_unknowns(self) -> int:
        """K, the number of solved particles."""
        return int(self.index.numel())

    def diagonal(self) -> Tensor:
        """(K,) the diagonal of ``matrix``."""
        return _csr_diagonal(self.matrix)

    def gather(self, values: Tensor) -> Tensor:
        """Restrict a per-particle array (N, ...) to the solved set (K, ...)."""
        if values.shape[0] != self.num_particles:
            raise ValueError(f"values must have {self.num_particles} rows, got shape {tuple(values.shape)}")
        return values[self.index.to(values.device)]

    def scatter(self, p: Tensor, fill: float = 0.0) -> Tensor:
        """Expand a solved-set array (K,) to all particles (N,), ``fill`` elsewhere (p = 0 default)."""
        if p.shape != (self.num_unknowns,):
            raise ValueError(f"p must have shape ({self.num_unknowns},), got {tuple(p.shape)}")
        out = torch.full((self.num_particles,), fill, dtype=p.dtype, device=p.device)
        out[self.index.to(p.device)] = p
        return out

    def to_scipy(self) -> sp.csr_matrix:
        """The matrix as a float64 SciPy CSR matrix (copied to the CPU)."""
        return _to_scipy(self.matrix)


def _csr_diagonal(matrix: Tensor) -> Tensor:
    crow, col, val = matrix.crow_indices(), matrix.col_indices(), matrix.values()
    k = matrix.shape[0]
    rows = torch.repeat_interleave(torch.arange(k, device=val.device), torch.diff(crow))
    on_diag = col.long() == rows
    return torch.zeros(k, dtype=val.dtype, device=val.device).index_add_(0, rows[on_diag], val[on_diag])


def _to_scipy(matrix: Tensor) -> sp.csr_matrix:
    crow = matrix.crow_indices().cpu().numpy()
    col = matrix.col_indices().cpu().numpy()
    val = matrix.values().detach().cpu().numpy().astype(np.float64, copy=False)
    out = sp.csr_matrix((val, col, crow), shape=tuple(matrix.shape))
    out.has_sorted_indices = True
    return out


def _index_dtype(nnz: int) -> torch.dtype:
    # int32 indices halve index traffic in SpMV (the solve is bandwidth-bound) and are what
    # SciPy/PyAMG use natively; int64 only when the system is too large for them.
    return torch.int32 if nnz < 2**31 - 1 else torch.int64


# ---------------------------------------------------------------------------------------------- assembly
def assemble_ppe(
    edge_index: Tensor,
    coef: Tensor,
    solve_mask: Tensor,
    density: float,
    *,
    dirichlet_mask: Tensor,
    isolated_diagonal_factor: float = 2.0,
    components: Literal["auto", "scipy", "torch"] = "auto",
    check: bool = True,
) -> PPESystem:
    """Assemble ``A = -(1/rho) L`` on the solved set as a sparse CSR matrix (vectorised, no loops).

    ``A_ii = (1/rho) sum_j c_ij`` over neighbours j that are solved or Dirichlet (free surface);
    ``A_ij = -(1/rho) c_ij`` for solved j; neighbours in neither mask (dummy) are ignored. Rows of
    components without any Dirichlet neighbour get their diagonal multiplied by
    ``isolated_diagonal_factor`` (standard MPS remedy, see the module docstring).

    Args:
        edge_index: (2, E) int64, row 0 = source j (neighbour), row 1 = target i (centre); every
            ordered pair within the Laplacian radius, no self loops, no duplicates. Edges whose
            target is not solved are ignored, so a graph with extra receivers is fine.
        coef: (E,) per-edge Laplacian coefficients ``2d/(lambda n0_lap) * w_ij`` (>= 0, finite).
        solve_mask: (N,) bool, the unknowns: non-free-surface fluid and wall particles.
        density: fluid density rho (> 0).
        dirichlet_mask: (N,) bool, free-surface particles (``p = 0``); must not overlap
            ``solve_mask``. Particles in neither mask (dummy) take no part.
        isolated_diagonal_factor: diagonal multiplier for components with no Dirichlet
            neighbour (>= 1; Koshizuka's reference code uses 2; 1 disables the remedy and leaves
            those blocks singular).
        components: how such components are found: ``"scipy"`` (``connected_components`` on the
            CPU), ``"torch"`` (reachability from the Dirichlet-coupled rows by repeated sparse
            products, stays on the device), ``"auto"`` (scipy on CPU, torch elsewhere).
        check: validate the inputs (shapes, ranges, finiteness, self loops, symmetry). The solver passes
            False for the graphs of its own neighbour list, which hold all of this by construction and
            are sorted by target, then source (also trusted then: unsorted edges are only sorted, and
            duplicates only rejected, with ``check=True``).

    Returns:
        The :class:`PPESystem` (matrix, index map, isolated-row flags).

    Raises:
        ValueError: on inconsistent shapes, dtypes, masks or values (naming the argument), or
            when the edges between solved particles are not symmetric.
    """
    if check:
        _check_assembly_inputs(
            edge_index, coef, solve_mask, dirichlet_mask, density, isolated_diagonal_factor
        )
    device = coef.device
    solve_mask, dirichlet_mask = solve_mask.to(device), dirichlet_mask.to(device)
    edge_index = edge_index.to(device)
    assemble = backend_for("ppe_assembly", coef)
    return assemble(
        edge_index, coef, solve_mask, dirichlet_mask, density, isolated_diagonal_factor, components, check
    )


def _assemble_torch(
    edge_index: Tensor,
    coef: Tensor,
    solve_mask: Tensor,
    dirichlet_mask: Tensor,
    density: float,
    isolated_diagonal_factor: float,
    components: str,
    check: bool,
) -> PPESystem:
    """:func:`assemble_ppe` in torch operations (any device, differentiable), the arguments on one device."""
    device, dtype = coef.device, coef.dtype
    n = int(solve_mask.numel())
    index = torch.nonzero(solve_mask).flatten()
    k = int(index.numel())
    pos_of = torch.full((n,), -1, dtype=torch.long, device=device)
    pos_of.index_copy_(0, index, torch.arange(k, device=device))
    # Per particle: 2 solved, 1 Dirichlet, 0 neither (one gather per edge tells both).
    role = solve_mask.to(torch.int8) * 2 + dirichlet_mask.to(torch.int8)

    # Edges into solved particles count; zero weights (r == re exactly) couple nothing. Per-edge masks
    # over the whole edge list rather than compacting it first: fewer gathers (index_select rather than
    # x[idx] throughout: advanced indexing is slower on the CPU, see benchmarks/results/ppe.md).
    src_role = role.index_select(0, edge_index[0])
    live = solve_mask.index_select(0, edge_index[1]) & (coef > 0)
    c = coef * (1.0 / float(density))
    # Diagonal: every solved or free-surface neighbour (dummy neighbours take no part); adding the
    # masked edges as exact zeros leaves each row's sum what it is.
    diag = torch.zeros(n, dtype=dtype, device=device)
    diag.index_add_(0, edge_index[1], c.masked_fill(~live | (src_role == 0), 0.0))
    diag = diag.index_select(0, index)
    # A row is Dirichlet-coupled when it has a free-surface neighbour (with positive weight).
    coupled = torch.zeros(n, dtype=torch.bool, device=device)
    coupled[edge_index[1][live & (src_role == 1)]] = True
    coupled = coupled.index_select(0, index)

    off_sel = torch.nonzero(live & (src_role == 2)).flatten()
    rows = pos_of.index_select(0, edge_index[1].index_select(0, off_sel))
    cols = pos_of.index_select(0, edge_index[0].index_select(0, off_sel))
    off = c.index_select(0, off_sel).neg_()
    # Symmetry of the solved-solved edge set (cheap necessary check: in-degree == out-degree).
    if check and rows.numel():
        if not torch.equal(torch.bincount(rows, minlength=k), torch.bincount(cols, minlength=k)):
            raise ValueError(
                "edge_index is not symmetric on the solved set: every pair of solved particles within the "
                "radius must appear in both directions (is a solved particle missing as a receiver?)"
            )
    if check:
        rows, cols, off = _sort_edges(rows, cols, off, k)
    counts = torch.bincount(rows, minlength=k)
    crow_off = torch.zeros(k + 1, dtype=torch.long, device=device)
    torch.cumsum(counts, 0, out=crow_off[1:])

    # Isolated components: no Dirichlet neighbour anywhere in the component -> singular block. (The
    # pattern without the diagonal has the same components.)
    isolated, n_iso = _isolated_rows(crow_off, cols, coupled, k, components)
    diag = _final_diagonal(diag, isolated, n_iso, density, isolated_diagonal_factor)
    idt = _index_dtype(int(rows.numel()) + k)
    if device.type == "cpu" and not (off.requires_grad or diag.requires_grad):
        matrix = _csr_plus_diagonal_scipy(crow_off, cols, off, diag, k, idt)
    else:
        crow, col, val, _ = _csr_with_diagonal(rows, cols, off, diag, k)
        matrix = torch.sparse_csr_tensor(crow.to(idt), col.to(idt), val, (k, k), check_invariants=False)
    return PPESystem(
        matrix=matrix, index=index, isolated=isolated, num_particles=n, n_isolated_components=n_iso
    )


def _final_diagonal(diag: Tensor, isolated: Tensor, n_iso: int, density: float, factor: float) -> Tensor:
    """The diagonal (K,) after the remedies for isolated components and empty rows."""
    # A solved particle with no non-dummy neighbour has an all-zero row; give it a typical diagonal
    # (p_i = b_i / A_ii, as if it had a full neighbourhood at p = 0) rather than a singular matrix.
    empty = diag <= 0
    any_empty = bool(empty.any())
    fill = 0.0
    if any_empty:
        positive = diag[~empty]
        fill = float(positive.median()) if positive.numel() else 1.0 / float(density)
    if n_iso:
        diag = torch.where(isolated, diag * factor, diag)
        logger.debug(
            "PPE: %d rows in %d components without a free-surface neighbour", int(isolated.sum()), n_iso
        )
    if any_empty:
        diag = diag.masked_fill(empty, fill)
        logger.warning(
            "PPE: %d solved particles have no fluid/wall/free-surface neighbour; diagonal set to %.3e",
            int(empty.sum()),
            fill,
        )
    return diag


_NUMBA = "lagfluid.physics.ppe._numba"


def _ppe_kernels() -> ModuleType | None:
    return pair_kernels.load(_NUMBA)


def _assemble_compiled(
    edge_index: Tensor,
    coef: Tensor,
    solve_mask: Tensor,
    dirichlet_mask: Tensor,
    density: float,
    factor: float,
    components: str,
    check: bool,
) -> PPESystem:
    """:func:`assemble_ppe` for trusted CPU input (sorted by target, then source) in compiled passes.

    The same matrix as the torch assembly (``tests/test_ppe.py`` compares them) from one pass per solved
    row, instead of ~20 torch passes over the edge list plus SciPy's ``connected_components`` (several
    times faster per step: see ``benchmarks/results/ppe.md``). Input to check (``check=True``) and a
    chosen ``components`` go to the torch body.
    """
    if check or components != "auto":
        return _assemble_torch(
            edge_index, coef, solve_mask, dirichlet_mask, density, factor, components, check
        )
    kern = _ppe_kernels()
    pair_kernels.set_threads()
    n = int(solve_mask.numel())
    index = torch.nonzero(solve_mask).flatten()
    k = int(index.numel())
    pos_of = torch.full((n,), -1, dtype=torch.long)
    pos_of.index_copy_(0, index, torch.arange(k))
    role = (solve_mask.to(torch.int8) * 2 + dirichlet_mask.to(torch.int8)).numpy()
    dst = edge_index[1].contiguous().numpy()
    idx = index.numpy()
    edge_start = np.searchsorted(dst, idx, side="left")  # edges are sorted by target
    edge_stop = np.searchsorted(dst, idx, side="right")
    src, c = edge_index[0].contiguous().numpy(), coef.detach().contiguous().numpy()
    inv_rho = c.dtype.type(1.0 / float(density))  # as torch multiplies a float32 tensor by a Python float
    diag = np.empty(k, dtype=c.dtype)
    coupled = np.empty(k, dtype=np.bool_)
    counts = np.zeros(k + 1, dtype=np.int64)
    kern.count_rows(src, c, role, edge_start, edge_stop, inv_rho, diag, coupled, counts)
    crow = np.cumsum(counts)
    nnz = int(crow[-1])
    np_idx = np.int32 if _index_dtype(nnz) == torch.int32 else np.int64
    col = np.empty(nnz, dtype=np_idx)
    val = np.empty(nnz, dtype=c.dtype)
    diag_at = np.empty(k, dtype=np.int64)
    kern.fill_rows(src, c, role, pos_of.numpy(), edge_start, edge_stop, inv_rho, crow, col, val, diag_at)
    isolated, n_iso = _isolated_rows(
        torch.from_numpy(crow), torch.from_numpy(col), torch.from_numpy(coupled), k
    )
    diag_t = _final_diagonal(torch.from_numpy(diag), isolated, n_iso, density, factor)
    val[diag_at] = diag_t.numpy()
    matrix = torch.sparse_csr_tensor(
        torch.from_numpy(crow.astype(np_idx)),
        torch.from_numpy(col),
        torch.from_numpy(val),
        (k, k),
        check_invariants=False,
    )
    return PPESystem(
        matrix=matrix,
        index=index,
        isolated=isolated,
        num_particles=n,
        n_isolated_components=n_iso,
    )


def _check_assembly_inputs(
    edge_index: Tensor,
    coef: Tensor,
    solve_mask: Tensor,
    dirichlet_mask: Tensor,
    density: float,
    factor: float,
) -> None:
    if not isinstance(edge_index, Tensor) or edge_index.dim() != 2 or edge_index.shape[0] != 2:
        raise ValueError(
            f"edge_index must be a (2, E) tensor, got {getattr(edge_index, 'shape', type(edge_index))}"
        )
    if edge_index.dtype not in (torch.int64, torch.int32):
        raise ValueError(f"edge_index must be an integer tensor, got {edge_index.dtype}")
    e = edge_index.shape[1]
    if not isinstance(coef, Tensor) or coef.shape != (e,):
        raise ValueError(
            f"coef must have shape ({e},) to match edge_index, got {getattr(coef, 'shape', None)}"
        )
    if not coef.is_floating_point():
        raise ValueError(f"coef must be floating point, got {coef.dtype}")
    for name, mask in (("solve_mask", solve_mask), ("dirichlet_mask", dirichlet_mask)):
        if not isinstance(mask, Tensor) or mask.dim() != 1 or mask.dtype != torch.bool:
            raise ValueError(f"{name} must be a (N,) bool tensor, got {getattr(mask, 'dtype', type(mask))}")
    n = solve_mask.numel()
    if dirichlet_mask.numel() != n:
        raise ValueError(f"dirichlet_mask has {dirichlet_mask.numel()} entries, solve_mask has {n}")
    if bool((solve_mask & dirichlet_mask.to(solve_mask.device)).any()):
        raise ValueError("solve_mask and dirichlet_mask overlap: a particle is either solved or at p = 0")
    if not (math.isfinite(density) and density > 0):
        raise ValueError(f"density must be finite and > 0, got {density!r}")
    if not (math.isfinite(factor) and factor >= 1.0):
        raise ValueError(f"isolated_diagonal_factor must be finite and >= 1, got {factor!r}")
    if e:
        lo, hi = int(edge_index.min()), int(edge_index.max())
        if lo < 0 or hi >= n:
            raise ValueError(f"edge_index entries must lie in [0, {n}), found range [{lo}, {hi}]")
        if not bool(torch.isfinite(coef).all()):
            raise ValueError("coef contains NaN or Inf")
        if bool((coef < 0).any()):
            raise ValueError("coef must be >= 0 (Laplacian weights 2d/(lambda n0) * (re/r - 1) for r < re)")
        if bool((edge_index[0] == edge_index[1]).any()):
            raise ValueError("edge_index contains self loops")


def _sort_edges(rows: Tensor, cols: Tensor, vals: Tensor, k: int) -> tuple[Tensor, Tensor, Tensor]:
    """Order the off-diagonal entries by (row, col) and reject duplicates.

    Neighbour lists in CSR order (by centre, then neighbour) are already sorted; filtering and the
    monotone renumbering keep them so, and the O(E) check spares the sort.
    """
    key = rows * k + cols
    if key.numel() > 1 and not bool((key[1:] > key[:-1]).all()):
        key, perm = torch.sort(key)
        rows, cols, vals = rows[perm], cols[perm], vals[perm]
        if bool((key[1:] == key[:-1]).any()):
            raise ValueError("edge_index contains duplicate edges")
    return rows, cols, vals


def _csr_plus_diagonal_scipy(
    crow: Tensor, cols: Tensor, off: Tensor, diag: Tensor, k: int, idt: torch.dtype
) -> Tensor:
    """CSR of the (row, col)-sorted off-diagonal entries plus the diagonal, merged by SciPy (CPU only).

    The same arrays as :func:`_csr_with_diagonal`, from one O(nnz) C++ pass (``csr_plus_csr`` on canonical
    inputs) instead of a dozen torch passes (see ``benchmarks/results/ppe.md``).
    """
    np_idx = np.int32 if idt == torch.int32 else np.int64
    off_sp = sp.csr_matrix(
        (off.numpy(), cols.numpy().astype(np_idx, copy=False), crow.numpy().astype(np_idx, copy=False)),
        shape=(k, k),
    )
    off_sp.has_canonical_format = True  # sorted and duplicate-free (_sort_edges)
    diag_sp = sp.csr_matrix(
        (diag.numpy(), np.arange(k, dtype=np_idx), np.arange(k + 1, dtype=np_idx)), shape=(k, k)
    )
    diag_sp.has_canonical_format = True
    merged = off_sp + diag_sp
    return torch.sparse_csr_tensor(
        torch.from_numpy(merged.indptr.astype(np_idx, copy=False)),
        torch.from_numpy(merged.indices.astype(np_idx, copy=False)),
        torch.from_numpy(merged.data),
        (k, k),
        check_invariants=False,
    )


def _csr_with_diagonal(
    rows: Tensor, cols: Tensor, off: Tensor, diag: Tensor, k: int
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Merge (row, col)-sorted off-diagonal entries and an explicit diagonal into CSR arrays (O(nnz)).

    Returns ``(crow, col, val, pos_diag)`` (int64 indices; ``pos_diag[r]`` is where ``A_rr`` is stored).
    """
    device = diag.device
    counts = torch.bincount(rows, minlength=k)
    crow = torch.zeros(k + 1, dtype=torch.long, device=device)
    crow[1:] = torch.cumsum(counts + 1, 0)
    # Entry e of row r moves past the r diagonals of earlier rows, and past its own row's diagonal
    # when col > r; the diagonal of row r sits after that row's entries with col < r.
    pos_off = torch.arange(rows.numel(), device=device) + rows + (cols > rows).long()
    pos_diag = crow[:-1] + torch.bincount(rows[cols < rows], minlength=k)
    nnz = rows.numel() + k
    col = torch.empty(nnz, dtype=torch.long, device=device)
    val = torch.empty(nnz, dtype=diag.dtype, device=device)
    col.index_copy_(0, pos_off, cols)
    val.index_copy_(0, pos_off, off)
    col.index_copy_(0, pos_diag, torch.arange(k, device=device))
    val.index_copy_(0, pos_diag, diag)
    return crow, col, val, pos_diag


def _isolated_rows(
    crow: Tensor, col: Tensor, coupled: Tensor, k: int, components: str = "auto"
) -> tuple[Tensor, int]:
    """Rows of connected components (graph: the matrix pattern) that contain no coupled row.

    Components are labelled on the CPU by the compiled search (``auto``, with Numba) or SciPy's
    ``connected_components`` (``scipy``, or ``auto`` without Numba); on other devices by sparse products.
    """
    if components not in ("auto", "scipy", "torch"):
        raise ValueError(f"components must be 'auto', 'scipy' or 'torch', got {components!r}")
    if k == 0:
        return coupled.clone(), 0
    if components == "scipy" or (components == "auto" and coupled.device.type == "cpu"):
        label = backend_for("component_labels", crow, col, compiled=components == "auto")
        labels = label(crow.cpu().numpy(), col.cpu().numpy(), k)
        has_dirichlet = np.bincount(labels, weights=coupled.cpu().numpy()) > 0
        iso_np = ~has_dirichlet[labels]
        n_iso = int(np.unique(labels[iso_np]).size)
        return torch.from_numpy(iso_np).to(coupled.device), n_iso
    # Device path: grow the set reachable from the coupled rows one hop per sparse product; the
    # number of rounds is the graph distance to the surface (tens for real scenes).
    pattern = torch.sparse_csr_tensor(
        crow, col, torch.ones(col.numel(), device=coupled.device), (k, k), check_invariants=False
    )
    reached = coupled.clone()
    frontier = reached.float()
    while bool(frontier.any()):
        new = ((pattern @ frontier) > 0) & ~reached
        reached |= new
        frontier = new.float()
    iso = ~reached
    n_iso = _count_components_torch(crow, col, iso) if bool(iso.any()) else 0
    return iso, n_iso


def _component_labels_compiled(crow: np.ndarray, col: np.ndarray, k: int) -> np.ndarray:
    """(K,) the connected component of each row of a symmetric (K, K) CSR pattern, by a compiled search."""
    return _ppe_kernels().component_labels(crow, col)


def _component_labels_scipy(crow: np.ndarray, col: np.ndarray, k: int) -> np.ndarray:
    """:func:`_component_labels_compiled` by SciPy's ``connected_components`` (the same components).

    Its labels may be numbered otherwise; only which rows share a label is used.
    """
    graph = sp.csr_matrix((np.ones(col.size, dtype=np.int8), col, crow), shape=(k, k))
    # The pattern is symmetric, so strong components are the components (and need no transpose).
    return connected_components(graph, directed=True, connection="strong")[1]


def _count_components_torch(crow: Tensor, col: Tensor, mask: Tensor) -> int:
    """Number of connected components among the ``mask`` rows (a closed set), by min-label propagation."""
    k = mask.numel()
    rows = torch.repeat_interleave(torch.arange(k, device=mask.device), torch.diff(crow))
    keep = mask[rows]
    r, c = rows[keep], col[keep].long()
    label = torch.arange(k, device=mask.device)
    while True:  # one hop per round: as many rounds as the widest isolated component is across
        new = label.scatter_reduce(0, r, label[c], reduce="amin", include_self=True)
        if torch.equal(new, label):
            break
        label = new
    return int(torch.unique(label[mask]).numel())


pair_kernels.register("ppe_assembly", compiled=_assemble_compiled, torch=_assemble_torch, module=_NUMBA)
pair_kernels.register(
    "component_labels", compiled=_component_labels_compiled, torch=_component_labels_scipy, module=_NUMBA
)
