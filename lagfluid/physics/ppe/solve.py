"""Solving the assembled PPE by preconditioned conjugate gradients: :func:`solve_ppe`, :func:`ppe_residual`.

``solve_ppe`` runs preconditioned CG (the authors: CG, absolute tolerance 1e-6, at most 200
iterations). Stopping is on the 2-norm of the unpreconditioned residual, ``||b - A p|| <= tol``
(``tol_mode="abs"``) or ``<= tol ||b||`` (``tol_mode="rel"``). The returned iterate is the last one:
CG's error in the energy norm ``||p - p*||_A`` decreases monotonically, so the last iterate is the best
one in the norm the method minimises. A solve that misses the tolerance is returned with
``converged=False`` and logged as a warning, never silently accepted.

Backends, one iteration each: ``scipy_cg`` (Jacobi CG in float64 on SciPy's SpMV), ``torch_cg`` (Jacobi CG
in torch on the CSR tensor, any device) and ``pyamg`` (SciPy CG with a smoothed-aggregation V-cycle; an
optional dependency). Jacobi is the default because the matrix changes every step, so an AMG setup is
paid every step and loses at the sizes measured; ``auto`` picks ``torch_cg`` on an accelerator and on a
CPU with two or more torch threads, ``scipy_cg`` on one (SciPy's SpMV is single-threaded). The
measurements behind both choices are in ``benchmarks/results/ppe.md``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from torch import Tensor

from lagfluid.physics.ppe.system import PPESystem, _csr_diagonal, _to_scipy

logger = logging.getLogger(__name__)

Method = Literal["auto", "scipy_cg", "pyamg", "torch_cg"]
TolMode = Literal["abs", "rel"]


def pyamg_available() -> bool:
    """Whether the optional PyAMG package (``pip install pyamg``) can be imported."""
    try:
        import pyamg  # noqa: F401
    except ImportError:
        return False
    return True


@dataclass(frozen=True)
class PPEInfo:
    """Outcome of a PPE solve.

    Attributes:
        iterations: CG iterations taken (0 when the initial guess already met the tolerance).
        residual: relative residual ``||A p - b|| / ||b||`` of the returned p (recomputed, not the
            solver's recursive estimate; the absolute norm when ``b = 0``).
        converged: whether the tolerance was met.
        method: the method that ran (``"scipy_cg"``, ``"pyamg"`` or ``"torch_cg"``).
    """

    iterations: int
    residual: float
    converged: bool
    method: str


def ppe_residual(
    A: PPESystem | Tensor | sp.spmatrix, p: Tensor | np.ndarray, b: Tensor | np.ndarray
) -> float:
    """Relative residual of the PPE (FGN eq. 31), ``||A p - b|| / ||b||`` in float64.

    Used to score learned pressure against the exact system. When ``b = 0`` the absolute norm
    ``||A p||`` is returned.

    Args:
        A: the system (a :class:`PPESystem`, a torch sparse CSR matrix or a SciPy sparse matrix).
        p: (K,) pressure on the solved set.
        b: (K,) right-hand side.
    """
    a_sp = _as_scipy(A)
    p_np, b_np = _as_f64_numpy(p, "p"), _as_f64_numpy(b, "b")
    k = a_sp.shape[0]
    if p_np.shape != (k,) or b_np.shape != (k,):
        raise ValueError(f"p and b must have shape ({k},), got {p_np.shape} and {b_np.shape}")
    r = _norm(a_sp @ p_np - b_np)
    bn = _norm(b_np)
    return float(r / bn) if bn > 0 else float(r)


def solve_ppe(
    A: PPESystem | Tensor | sp.spmatrix,
    b: Tensor | np.ndarray,
    x0: Tensor | np.ndarray | None = None,
    tol: float = 1e-6,
    maxiter: int = 200,
    method: Method = "auto",
    tol_mode: TolMode = "rel",
    compute_dtype: torch.dtype | None = torch.float64,
) -> tuple[Tensor | np.ndarray, PPEInfo]:
    """Solve ``A p = b`` by preconditioned conjugate gradients.

    Args:
        A: (K, K) SPD system from :func:`assemble_ppe` (or its ``matrix``, or a SciPy matrix).
        b: (K,) right-hand side on the solved set (e.g. ``system.gather(ppe_source(...))``).
        x0: (K,) initial guess, typically the previous step's pressure on the solved set (warm
            start); zeros when None.
        tol: tolerance on the residual 2-norm, see ``tol_mode``.
        maxiter: maximum number of CG iterations (the authors: 200).
        method: ``"scipy_cg"`` (SciPy CG, Jacobi preconditioner), ``"pyamg"`` (SciPy CG with a
            PyAMG smoothed-aggregation V-cycle preconditioner; optional dependency), ``"torch_cg"``
            (Jacobi-preconditioned CG in torch on the sparse CSR matrix), ``"auto"`` (``torch_cg``
            for tensors on an accelerator or on a CPU with >= 2 torch threads, else ``scipy_cg``: see
            ``benchmarks/results/ppe.md`` for the measurements).
        tol_mode: ``"abs"``: stop when ``||b - A p|| <= tol`` (the authors' choice, with tol=1e-6 and
            b in 1/s^2); ``"rel"``: when ``||b - A p|| <= tol * ||b||``.
        compute_dtype: dtype the torch iteration runs in. Default float64: the PPE's condition
            number grows like K^(2/3) and float32 CG stalls at a relative residual above the usual 1e-6
            (see ``benchmarks/results/ppe.md``). None runs in b's dtype (cheaper on a
            GPU when a looser tolerance suffices). The SciPy/PyAMG paths always run in float64.
            The result has b's dtype.

    Returns:
        ``(p, info)``: p (K,) with b's type, dtype and device; :class:`PPEInfo`.

    Raises:
        ValueError: on NaN/Inf in b or x0, a shape mismatch, or an unknown method or tol_mode.
    """
    if tol_mode not in ("abs", "rel"):
        raise ValueError(f"tol_mode must be 'abs' or 'rel', got {tol_mode!r}")
    if not (math.isfinite(tol) and tol >= 0):
        raise ValueError(f"tol must be finite and >= 0, got {tol!r}")
    if maxiter < 0:
        raise ValueError(f"maxiter must be >= 0, got {maxiter!r}")
    matrix = A.matrix if isinstance(A, PPESystem) else A
    if isinstance(matrix, Tensor):
        if matrix.layout != torch.sparse_csr:
            raise ValueError(f"A must be a sparse CSR tensor, got layout {matrix.layout}")
    elif not sp.issparse(matrix):
        raise ValueError(
            f"A must be a PPESystem, a torch sparse CSR tensor or a SciPy sparse matrix, got {type(A)}"
        )
    k = int(matrix.shape[0])
    if tuple(matrix.shape) != (k, k):
        raise ValueError(f"A must be square, got shape {tuple(matrix.shape)}")
    _check_vector(b, "b", k)
    if x0 is not None:
        _check_vector(x0, "x0", k)
    method = _resolve_method(method, matrix, b)

    as_torch = isinstance(b, Tensor)
    b64 = _as_f64_numpy(b, "b")
    bnorm = _norm(b64)
    if k == 0 or bnorm == 0.0:
        # Nothing to solve (no unknowns), or b = 0 whose solution is p = 0 exactly.
        p0 = torch.zeros_like(b) if as_torch else np.zeros_like(b)
        return p0, PPEInfo(iterations=0, residual=0.0, converged=True, method=method)
    threshold = tol * bnorm if tol_mode == "rel" else tol

    if method == "torch_cg":
        p, iters, rnorm = _solve_torch(matrix, b, x0, threshold, maxiter, compute_dtype)
        p = p.to(b.dtype)
    else:
        p64, iters, rnorm = _solve_scipy(matrix, b64, x0, threshold, maxiter, method)
        p = torch.from_numpy(p64).to(b.device, b.dtype) if as_torch else p64.astype(b.dtype, copy=False)

    # Judged by the true residual of the returned iterate, not the solver's recursive estimate.
    rel = rnorm / bnorm
    converged = bool(math.isfinite(rnorm) and rnorm <= threshold)
    if not converged:
        logger.warning(
            "PPE solve (%s) did not converge: relative residual %.3e (absolute %.3e; tolerance %.1e %s) "
            "after %d iterations (maxiter %d, K=%d)",
            method,
            rel,
            rnorm,
            tol,
            tol_mode,
            iters,
            maxiter,
            k,
        )
    return p, PPEInfo(iterations=int(iters), residual=float(rel), converged=converged, method=method)


def _check_vector(v: Tensor | np.ndarray, name: str, k: int) -> None:
    if not isinstance(v, (Tensor, np.ndarray)):
        raise ValueError(f"{name} must be a tensor or an array, got {type(v)}")
    if tuple(v.shape) != (k,):
        raise ValueError(f"{name} must have shape ({k},) to match A ({k} x {k}), got {tuple(v.shape)}")
    finite = bool(torch.isfinite(v).all()) if isinstance(v, Tensor) else bool(np.isfinite(v).all())
    if not finite:
        raise ValueError(f"{name} contains NaN or Inf")
    is_float = v.is_floating_point() if isinstance(v, Tensor) else np.issubdtype(v.dtype, np.floating)
    if not is_float:
        raise ValueError(f"{name} must be floating point, got {v.dtype}")


def _resolve_method(method: str, matrix: Tensor | sp.spmatrix, b: Tensor | np.ndarray) -> str:
    if method not in ("auto", "scipy_cg", "pyamg", "torch_cg"):
        raise ValueError(f"method must be 'auto', 'scipy_cg', 'pyamg' or 'torch_cg', got {method!r}")
    if method == "pyamg" and not pyamg_available():
        # Optional dependency: fall back to Jacobi CG (same tolerance, more iterations), loudly.
        logger.warning(
            "method='pyamg' requested but PyAMG is not installed (pip install pyamg); using scipy_cg"
        )
        method = "scipy_cg"
    if method == "torch_cg":
        if not (isinstance(matrix, Tensor) and isinstance(b, Tensor)):
            raise ValueError("method='torch_cg' needs A and b as torch tensors")
        if matrix.device != b.device:
            raise ValueError(f"A is on {matrix.device} but b is on {b.device}")
    if method != "auto":
        return method
    if isinstance(matrix, Tensor) and isinstance(b, Tensor) and b.device == matrix.device:
        if matrix.device.type != "cpu" or torch.get_num_threads() > 1:
            return "torch_cg"
    return "scipy_cg"


def _as_scipy(A: PPESystem | Tensor | sp.spmatrix) -> sp.csr_matrix:
    if isinstance(A, PPESystem):
        return A.to_scipy()
    if isinstance(A, Tensor):
        return _to_scipy(A)
    if sp.issparse(A):
        return sp.csr_matrix(A, dtype=np.float64)
    raise ValueError(
        f"A must be a PPESystem, a torch sparse CSR tensor or a SciPy sparse matrix, got {type(A)}"
    )


def _as_f64_numpy(v: Tensor | np.ndarray, name: str) -> np.ndarray:
    if isinstance(v, Tensor):
        return v.detach().cpu().double().numpy()
    if isinstance(v, np.ndarray):
        return v.astype(np.float64, copy=False)
    raise ValueError(f"{name} must be a tensor or an array, got {type(v)}")


def _solve_scipy(
    matrix: Tensor | sp.spmatrix,
    b64: np.ndarray,
    x0: Tensor | np.ndarray | None,
    threshold: float,
    maxiter: int,
    method: str,
) -> tuple[np.ndarray, int, float]:
    """SciPy CG (float64) with a Jacobi or PyAMG preconditioner; returns (x, iterations, ||b - A x||)."""
    a_sp = _as_scipy(matrix)
    x064 = None if x0 is None else _as_f64_numpy(x0, "x0")
    if method != "pyamg":
        x, iters = _pcg_jacobi(a_sp, b64, x064, threshold, maxiter)
        return x, iters, _norm(b64 - a_sp @ x)
    import pyamg

    # SA V-cycle with the default symmetric Gauss-Seidel smoother: an SPD preconditioner.
    ml = pyamg.smoothed_aggregation_solver(a_sp, symmetry="symmetric")
    precond = ml.aspreconditioner(cycle="V")
    iters = 0

    def count(_xk: np.ndarray) -> None:
        nonlocal iters
        iters += 1

    # SciPy stops when ||r|| < max(rtol ||b||, atol), r the unpreconditioned (recursive) residual.
    x, _ = spla.cg(a_sp, b64, x0=x064, rtol=0.0, atol=threshold, maxiter=maxiter, M=precond, callback=count)
    return x, iters, _norm(b64 - a_sp @ x)


def _dot(u: np.ndarray, v: np.ndarray) -> float:
    """``u . v`` without BLAS (see :func:`_pcg_jacobi`)."""
    return float(np.einsum("i,i->", u, v))


def _norm(v: np.ndarray) -> float:
    """2-norm without BLAS."""
    return math.sqrt(_dot(v, v))


def _pcg_jacobi(
    a: sp.csr_matrix, b: np.ndarray, x0: np.ndarray | None, threshold: float, maxiter: int
) -> tuple[np.ndarray, int]:
    """Jacobi-preconditioned CG in float64; stops when the residual 2-norm is ``<= threshold``.

    The same iteration as ``scipy.sparse.linalg.cg`` with a Jacobi preconditioner, written out so that
    the vector work is in place and uses no BLAS: OpenBLAS runs ``ddot`` (and so ``np.dot`` and
    ``np.linalg.norm``) on several threads above 10,000 entries, and on a loaded machine those threads
    wait on each other (an order of magnitude slower: see ``benchmarks/results/ppe.md``). The SpMV is
    SciPy's single-thread C++ ``csr_matvec``. When the recursive residual meets the tolerance the true
    one is checked, and the iteration restarts from it if it does not.

    Returns:
        ``(x, iterations)``.
    """
    inv_diag = 1.0 / a.diagonal()
    x = np.zeros_like(b) if x0 is None else np.array(x0, dtype=np.float64)
    r = b - a @ x if x0 is not None else b.copy()
    iters = 0
    if _norm(r) <= threshold:
        return x, iters
    z = inv_diag * r
    p = z.copy()
    rz = _dot(r, z)
    while iters < maxiter:
        q = a @ p
        pq = _dot(p, q)
        if not pq > 0:
            break  # breakdown (A not SPD on this Krylov space): reported by the caller's residual check
        alpha = rz / pq
        x += alpha * p
        r -= alpha * q
        iters += 1
        rnorm = _norm(r)
        if not math.isfinite(rnorm):
            break
        if rnorm <= threshold:
            r = b - a @ x  # the recursive residual drifts from b - A x: confirm, else restart from it
            if _norm(r) <= threshold:
                break
            np.multiply(inv_diag, r, out=z)
            p = z.copy()
            rz = _dot(r, z)
            continue
        np.multiply(inv_diag, r, out=z)
        rz_new = _dot(r, z)
        p *= rz_new / rz
        p += z
        rz = rz_new
    return x, iters


def _solve_torch(
    matrix: Tensor,
    b: Tensor,
    x0: Tensor | None,
    threshold: float,
    maxiter: int,
    dtype: torch.dtype | None,
) -> tuple[Tensor, int, float]:
    """Jacobi-preconditioned CG on a torch sparse CSR matrix, one host sync per iteration.

    Returns (x, iterations, ||b - A x|| evaluated in float64).
    """
    dtype = dtype or b.dtype
    a = _csr_as(matrix, dtype)
    bb = b.to(dtype)
    inv_diag = 1.0 / _csr_diagonal(a)
    if x0 is None:
        x = torch.zeros_like(bb)
        r = bb.clone()
    else:
        x = torch.as_tensor(x0, device=bb.device).to(dtype).clone()
        r = bb - a @ x
    iters = 0
    if float(torch.linalg.vector_norm(r)) > threshold:
        z = inv_diag * r
        p = z.clone()
        rz = torch.dot(r, z)
        while iters < maxiter:
            q = a @ p
            pq = torch.dot(p, q)
            alpha = torch.where(pq > 0, rz / pq, torch.zeros_like(pq))
            x.add_(alpha * p)
            r.sub_(alpha * q)
            iters += 1
            pq_f, rnorm = torch.stack([pq, torch.linalg.vector_norm(r)]).tolist()
            if not pq_f > 0 or not math.isfinite(rnorm):
                break  # breakdown (A not SPD on this Krylov space) or overflow: reported by the caller
            if rnorm <= threshold:
                # The recursive residual drifts from b - A x in low precision: confirm, else restart.
                r = bb - a @ x
                if float(torch.linalg.vector_norm(r)) <= threshold:
                    break
                z = inv_diag * r
                p = z.clone()
                rz = torch.dot(r, z)
                continue
            z = inv_diag * r
            rz_new = torch.dot(r, z)
            p = z + (rz_new / rz) * p
            rz = rz_new
    a64 = a if dtype == torch.float64 else _csr_as(matrix, torch.float64)
    rtrue = float(torch.linalg.vector_norm(b.double() - a64 @ x.double()))
    return x, iters, rtrue


def _csr_as(matrix: Tensor, dtype: torch.dtype) -> Tensor:
    if matrix.values().dtype == dtype:
        return matrix
    return torch.sparse_csr_tensor(
        matrix.crow_indices(),
        matrix.col_indices(),
        matrix.values().to(dtype),
        matrix.shape,
        check_invariants=False,
    )
