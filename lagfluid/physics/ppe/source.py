"""The right-hand side of the MPS pressure Poisson equation: :func:`ppe_source`."""

from __future__ import annotations

import math

from torch import Tensor


def ppe_source(
    div_v: Tensor,
    n: Tensor,
    n0: float,
    dt: float,
    gamma_div: float = 0.8,
    gamma_density: float = 0.2,
) -> Tensor:
    r"""Mixed PPE source term (after Lee et al. 2011), in the sign convention of :func:`assemble_ppe`.

    ``b_i = -gamma_div * div(v*)_i / dt + gamma_density * (n_i - n0) / (dt^2 n0)``  (units 1/s^2)

    Derivation for ``A p = b`` with ``A = -(1/rho) L`` (positive definite):

    * Velocity divergence: the correction ``v = v* - (dt/rho) grad p`` must make ``div v = 0``, so
      ``div v* - (dt/rho) lap p = 0``, i.e. ``-(1/rho) lap p = -div(v*)/dt``.
    * Number density: continuity ``Dn/Dt = -n div v`` over one step, asking the corrected motion to
      bring ``n*`` back to ``n0``: ``(n0 - n*)/(dt n0) = -div(v - v*) = (dt/rho) lap p``, i.e.
      ``-(1/rho) lap p = (n* - n0)/(dt^2 n0)``.

    Blending the two with weights 0.8/0.2 gives the formula above, which is the authors' code (MPS step
    item 5) verbatim: their right-hand side already belongs to the sign-flipped (positive definite)
    system. ``rho`` appears in ``A`` (the ``1/rho`` factor), not here. Check: a compressed region
    (``n > n0``, ``div v* < 0``) has ``b > 0``, and since ``A`` is an M-matrix (``A^{-1} >= 0``)
    its pressure is positive.

    Args:
        div_v: (N,) velocity divergence of the predicted velocity ``v*``, 1/s.
        n: (N,) particle number density at the predicted positions.
        n0: reference number density.
        dt: time step, s.
        gamma_div: weight of the divergence term.
        gamma_density: weight of the density-error term.

    Returns:
        (N,) source term ``b`` (restrict it to the solved set with :meth:`PPESystem.gather`).
    """
    if div_v.shape != n.shape:
        raise ValueError(
            f"div_v and n must have the same shape, got {tuple(div_v.shape)} and {tuple(n.shape)}"
        )
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be finite and > 0, got {dt!r}")
    if not (math.isfinite(n0) and n0 > 0):
        raise ValueError(f"n0 must be finite and > 0, got {n0!r}")
    return -gamma_div * div_v / dt + gamma_density * (n - n0) / (dt * dt * n0)
