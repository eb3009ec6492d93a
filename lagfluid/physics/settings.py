"""Settings of the split-step scheme (``conf/solver``) and its reference densities n0, n0_lap, lambda.

:class:`SolverSettings` holds the coefficients of the scheme and of the exact stages; :class:`MPSConstants`
the reference densities of the undisturbed fluid, from the ideal lattice or the initial frame
(``settings.n0_from``). Both are plain values: checkpoints and rollouts store their numbers, never these
classes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from lagfluid.errors import ConfigError
from lagfluid.neighbors.verlet import VerletNeighborList
from lagfluid.physics import operators as ops
from lagfluid.state import ParticleState

# Solver keys added after datasets and reference rollouts were first made, each with the value that
# reproduces the behaviour from before it existed. Content hashes (dataset fingerprints, the evaluation's
# reference key) leave a key out at that value, so files made before it existed keep matching: a dataset
# generated earlier resumes instead of being refused as "another configuration".
NEUTRAL_SOLVER_KEYS: dict[str, Any] = {"pressure_gradient": "minimum", "source_density_reference_dt": None}


def solver_identity(solver: dict[str, Any]) -> dict[str, Any]:
    """``solver`` (a plain config dict) less the :data:`NEUTRAL_SOLVER_KEYS` that hold their neutral value."""
    neutral = NEUTRAL_SOLVER_KEYS
    return {k: v for k, v in solver.items() if not (k in neutral and v == neutral[k])}


# Lists at least this long (in l0: MPS's 3.1) take the smaller automatic skin (SolverSettings.skin_fraction).
AUTO_SKIN_LARGE_CUTOFF = 3.0

# (config group, key) -> (SolverSettings field, type)
_NESTED_KEYS: dict[tuple[str, str], tuple[str, type]] = {
    ("ppe", "method"): ("ppe_method", str),
    ("ppe", "tol"): ("ppe_tol", float),
    ("ppe", "tol_mode"): ("ppe_tol_mode", str),
    ("ppe", "maxiter"): ("ppe_maxiter", int),
    ("ppe", "warm_start"): ("ppe_warm_start", bool),
    ("neighbors", "backend"): ("neighbor_backend", str),
    ("neighbors", "skin_fraction"): ("neighbor_skin_fraction", lambda v: _skin_setting(v)),
    ("neighbors", "wall_hops"): ("wall_hops", int),
}


def _skin_setting(value: object) -> float | None:
    """``solver.neighbors.skin_fraction`` as a number, or None for ``auto`` (SolverSettings.skin_fraction)."""
    if value == "auto":
        return None
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ConfigError(f"solver.neighbors.skin_fraction must be >= 0 or auto, got {value!r}") from None


def _is_number(value: object) -> bool:
    """A real number, not a bool (YAML's ``true`` would otherwise pass as 1)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


@dataclass(frozen=True)
class SolverSettings:
    """Coefficients of the scheme and the exact stages; radii as multiples of ``l0``.

    Built from ``conf/solver/*.yaml`` with :meth:`from_config`; defaults are the authors' values.
    """

    re_density: float = 2.1
    re_gradient: float = 2.1
    re_laplacian: float = 3.1
    re_collision: float = 0.92
    restitution: float = 0.2
    surface_beta: float = 0.97
    source_divergence: float = 0.8
    source_density: float = 0.2
    source_density_reference_dt: float | None = None
    clamp_negative_pressure: bool = True
    pressure_gradient: str = "minimum"
    n0_from: str = "lattice"
    ppe_method: str = "auto"
    ppe_tol: float = 1.0e-6
    ppe_tol_mode: str = "abs"
    ppe_maxiter: int = 200
    ppe_warm_start: bool = True
    neighbor_backend: str = "auto"
    neighbor_skin_fraction: float | None = None  # None: auto, see skin_fraction
    wall_hops: int | None = 2

    def __post_init__(self) -> None:
        from lagfluid.neighbors import BACKENDS

        def bad(key: str, value: object, expected: str) -> ConfigError:
            return ConfigError(f"solver.{key} must be {expected}, got {value!r}")

        for name in ("re_density", "re_gradient", "re_laplacian", "re_collision"):
            if not getattr(self, name) > 0:
                raise bad(name, getattr(self, name), "> 0")
        choices = {
            "n0_from": (self.n0_from, ("lattice", "initial")),
            "pressure_gradient": (self.pressure_gradient, ("minimum", "corrected")),
            "ppe.tol_mode": (self.ppe_tol_mode, ("abs", "rel")),
            "ppe.method": (self.ppe_method, ("auto", "scipy_cg", "torch_cg", "pyamg")),
            "neighbors.backend": (self.neighbor_backend, ("auto", *BACKENDS)),
        }
        for key, (value, allowed) in choices.items():
            if value not in allowed:
                raise bad(key, value, "one of " + ", ".join(allowed))
        if self.wall_hops is not None and not (isinstance(self.wall_hops, int) and self.wall_hops >= 1):
            raise bad("neighbors.wall_hops", self.wall_hops, "an integer >= 1 or null (every wall)")
        skin = self.neighbor_skin_fraction
        if skin is not None and not (_is_number(skin) and skin >= 0):
            raise bad("neighbors.skin_fraction", skin, ">= 0 or auto")
        if not (self.ppe_tol > 0 and self.ppe_maxiter >= 1):
            raise bad("ppe.tol / ppe.maxiter", (self.ppe_tol, self.ppe_maxiter), "> 0 / >= 1")
        if not 0 < self.surface_beta <= 1:
            raise bad("surface_beta", self.surface_beta, "in (0, 1]")
        for key in ("source_divergence", "source_density"):
            if not _is_number(getattr(self, key)) or getattr(self, key) < 0:
                raise bad(key, getattr(self, key), "a number >= 0")
        ref_dt = self.source_density_reference_dt
        if ref_dt is not None and not (_is_number(ref_dt) and math.isfinite(ref_dt) and ref_dt > 0):
            raise bad("source_density_reference_dt", ref_dt, "a finite time step > 0 (s) or null")

    def skin_fraction(self, cutoff_l0: float) -> float:
        """The Verlet skin as a fraction of a list's cutoff ``cutoff_l0`` (in l0): the setting, or auto.

        Auto is the fastest measured over the whole flowing second (quiet machine, alternated): 0.15 for a
        list at the Laplacian's 3.1 l0 (MPS and the hybrids that solve the PPE; 7 % faster than 0.3 at 10k,
        ``benchmarks/results/whole_run_mps_dam_medium.md``), 0.3 for the learned stages' 2.1 l0 (FGN;
        4 % faster than 0.15 and 10 % than 0.5 at 40k, ``benchmarks/results/whole_run_fgn_dam_large.md``).
        The skin changes no result: the lists are exact and keep their pair order (MPS's 1 s dam is
        bit-identical at 0.15 and 0.3).
        """
        if self.neighbor_skin_fraction is not None:
            return self.neighbor_skin_fraction
        return 0.15 if cutoff_l0 >= AUTO_SKIN_LARGE_CUTOFF else 0.3

    def density_source_weight(self, dt: float) -> float:
        """Weight of the PPE source's density term ``(n - n0)/(dt^2 n0)`` at time step ``dt`` (s).

        ``source_density_reference_dt`` null (the authors): ``source_density`` whatever ``dt``, i.e. the
        solve removes that fraction of the density error *per step*; its pressure scales as ``1/dt^2`` while
        the particle-scale density noise does not shrink, so a smaller ``dt`` makes a resting fluid noisier
        (see benchmarks/results/resting_variants.md, the dt = 1 ms table). Set to a time step ``dt_ref``
        (s), the weight is ``min(1, source_density (dt/dt_ref)^2)``: the density error relaxes on the fixed
        physical time ``dt_ref / sqrt(source_density)`` whatever ``dt``; the cap: one step cannot correct
        more than all of it.
        """
        if self.source_density_reference_dt is None:
            return self.source_density
        return min(1.0, self.source_density * (dt / self.source_density_reference_dt) ** 2)

    def ppe_source_weights(self, dt: float) -> dict[str, float]:
        """Keyword weights ``gamma_div``, ``gamma_density`` of ``ppe.ppe_source`` at time step ``dt``."""
        return {"gamma_div": self.source_divergence, "gamma_density": self.density_source_weight(dt)}

    @classmethod
    def from_config(cls, cfg: Any) -> SolverSettings:
        """Build from a ``solver`` config node (an ``omegaconf.DictConfig`` or a plain dict)."""
        plain = {k: cfg[k] for k in cls.__dataclass_fields__ if k in cfg}
        # Nested keys present in the config; absent ones keep the dataclass defaults (one source of truth).
        # The casts matter: YAML reads 1e-6 (no dot) as a string.
        for (group, key), (name, cast) in _NESTED_KEYS.items():
            node = cfg.get(group) or {}
            if key in node and node[key] is not None:
                plain[name] = cast(node[key])
            elif key in node:  # an explicit null, e.g. neighbors.wall_hops: null
                plain[name] = None
        return cls(**plain)


@dataclass(frozen=True)
class MPSConstants:
    """Reference number densities of the undisturbed fluid.

    Attributes:
        n0: number density at radius ``re_density`` (dimensionless).
        n0_lap: number density at radius ``re_laplacian``.
        lam: the Laplacian model's lambda, m^2.
    """

    n0: float
    n0_lap: float
    lam: float


def lattice_constants(l0: float, settings: SolverSettings, dim: int = 3) -> MPSConstants:
    """n0, n0_lap and lambda of an interior site of the ideal simple-cubic (square, 2-D) lattice.

    Using the lattice instead of the initial frame makes the constants independent of the scene (a thin
    fluid sheet has no interior particle), so models trained on one scene transfer to another.
    """
    reach = math.ceil(max(settings.re_density, settings.re_laplacian)) + 1
    axis = torch.arange(-reach, reach + 1, dtype=torch.float64)
    grids = torch.meshgrid(*([axis] * dim), indexing="ij")
    offsets = torch.stack([g.flatten() for g in grids], dim=1) * l0
    pos = torch.cat([torch.zeros(1, dim, dtype=torch.float64), offsets[offsets.norm(dim=1) > 0]])
    if dim == 2:
        pos = torch.cat([pos, torch.zeros(pos.shape[0], 1, dtype=torch.float64)], dim=1)
    src = torch.arange(1, pos.shape[0])
    edge_index = torch.stack([src, torch.zeros_like(src)])
    centre = torch.zeros(pos.shape[0], dtype=torch.bool)
    centre[0] = True
    re_n, re_lap = settings.re_density * l0, settings.re_laplacian * l0
    n0 = float(ops.number_density(pos, edge_index, re_n, num_nodes=pos.shape[0])[0])
    n0_lap, lam = ops.laplacian_lambda(pos, edge_index, re_lap, centre)
    return MPSConstants(n0=n0, n0_lap=float(n0_lap), lam=float(lam))


def initial_constants(state: ParticleState, settings: SolverSettings) -> MPSConstants:
    """n0, n0_lap, lambda as the authors compute them: the maximum over the initial fluid."""
    l0 = state.params.l0
    nl = VerletNeighborList(settings.re_laplacian * l0, 0.0, settings.neighbor_backend)
    g_lap = nl.graph(state.pos, state.ptype, settings.re_laplacian * l0)
    g_n = g_lap.within(settings.re_density * l0)
    n = ops.number_density(state.pos, g_n.edge_index, settings.re_density * l0, num_nodes=state.num_particles)
    n0 = float(ops.reference_density(n, state.fluid_mask))
    n0_lap, lam = ops.laplacian_lambda(
        state.pos, g_lap.edge_index, settings.re_laplacian * l0, state.fluid_mask
    )
    return MPSConstants(n0=n0, n0_lap=float(n0_lap), lam=float(lam))


def scene_constants(state: ParticleState, settings: SolverSettings) -> MPSConstants:
    """``n0``, ``n0_lap``, ``lambda`` per ``settings.n0_from``: the lattice's or the initial fluid's."""
    if settings.n0_from == "lattice":
        return lattice_constants(state.params.l0, settings, state.params.dim)
    return initial_constants(state, settings)
