"""The split-step scheme, written once, with pluggable stage implementations.

One step (paper A.1 eqs. 11-18 and A.2 eqs. 24-28; authors' code for the position updates)::

    a      = advection(x^n, v^n)              exact: nu lap(v) + g           learned: AdvectionNet
    v*     = v^n + a dt ;  x* = x^n + v* dt
    v**    = collision(x*, v*)                exact: collision rule         learned: CollisionNet
    x**    = x* + (v** - v*) dt
    p      = pressure(x**, v**)               exact: PPE + CG               learned: PressureNet
    p      = max(p, 0)                        (negative-pressure clamp)
    a_p    = -grad_min(p) / rho               MPS minimum-pressure gradient, always exact
    v^n+1  = v** + a_p dt ;  x^n+1 = x** + a_p dt^2

The updates and their inverses (the training targets) are :mod:`lagfluid.integrate`'s, so one-step
training and rollout agree by construction; the position update of the correction follows the authors'
code (``x += a_p dt^2``), not the paper's eq. 28 (see there).

Only fluid particles move; boundary rows are static and never integrated.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Protocol

import torch
from torch import Tensor

from lagfluid import integrate, pair_kernels
from lagfluid.errors import ConfigError
from lagfluid.neighbor_list import Graph, VerletNeighborList
from lagfluid.neighbors import edge_vectors
from lagfluid.physics import operators as ops
from lagfluid.state import ParticleState, ParticleType, SceneParams

# Solver keys added after datasets and reference rollouts were first made, each with the value that
# reproduces the behaviour from before it existed. Content hashes (dataset fingerprints, the evaluation's
# reference key) leave a key out at that value, so files made before it existed keep matching: a dataset
# generated earlier resumes instead of being refused as "another configuration".
NEUTRAL_SOLVER_KEYS: dict[str, Any] = {"pressure_gradient": "minimum", "source_density_reference_dt": None}


def solver_identity(solver: dict[str, Any]) -> dict[str, Any]:
    """``solver`` (a plain config dict) less the :data:`NEUTRAL_SOLVER_KEYS` that hold their neutral value."""
    neutral = NEUTRAL_SOLVER_KEYS
    return {k: v for k, v in solver.items() if not (k in neutral and v == neutral[k])}


# (config group, key) -> (SolverSettings field, type)
_NESTED_KEYS: dict[tuple[str, str], tuple[str, type]] = {
    ("ppe", "method"): ("ppe_method", str),
    ("ppe", "tol"): ("ppe_tol", float),
    ("ppe", "tol_mode"): ("ppe_tol_mode", str),
    ("ppe", "maxiter"): ("ppe_maxiter", int),
    ("ppe", "warm_start"): ("ppe_warm_start", bool),
    ("neighbors", "backend"): ("neighbor_backend", str),
    ("neighbors", "skin_fraction"): ("neighbor_skin_fraction", float),
    ("neighbors", "wall_hops"): ("wall_hops", int),
}


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
    neighbor_skin_fraction: float = 0.3
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
        if not self.neighbor_skin_fraction >= 0:
            raise bad("neighbors.skin_fraction", self.neighbor_skin_fraction, ">= 0")
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


def neighbor_list(settings: SolverSettings, cutoff: float) -> VerletNeighborList:
    """A fresh Verlet list at ``cutoff`` (m) with the settings' skin fraction, backend and wall hops."""
    return VerletNeighborList(
        cutoff, settings.neighbor_skin_fraction * cutoff, settings.neighbor_backend, settings.wall_hops
    )


def read_info(info: dict[str, float | Tensor]) -> dict[str, float]:
    """``info`` as numbers, its 0-d tensors read in one transfer (on CUDA one host synchronisation)."""
    tensors = {k: v for k, v in info.items() if isinstance(v, Tensor)}
    if not tensors:
        return dict(info)
    values = torch.stack([v.detach().to(torch.float64) for v in tensors.values()]).tolist()
    return {**info, **dict(zip(tensors, values, strict=True))}


class StageTimer:
    """Seconds per named stage of the last step.

    On the CPU wall-clock time; on CUDA the time between two events the stream records around the block:
    no host synchronisation inside the step (a synchronisation per stage would stall the device at every
    stage boundary). :meth:`read` waits for the last event, after the step.
    """

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._events: list[tuple[str, Any, Any]] = []  # (name, start, end) CUDA events not yet read

    def reset(self) -> None:
        """Forget the last step's times."""
        self.seconds = {}
        self._events = []

    @contextmanager
    def __call__(self, name: str, device: torch.device) -> Iterator[None]:
        """Time the ``with`` block and add it to ``seconds[name]``."""
        if device.type == "cuda":
            stream = torch.cuda.current_stream(device)  # that device's, whichever device is current
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record(stream)
            try:
                yield
            finally:
                end.record(stream)
                self._events.append((name, start, end))
            return
        start_s = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - start_s

    def read(self) -> dict[str, float]:
        """Seconds per stage so far (reading CUDA's events: waits for the device to reach the last one)."""
        for name, start, end in self._events:
            end.synchronize()
            self.seconds[name] = self.seconds.get(name, 0.0) + start.elapsed_time(end) / 1e3
        self._events = []
        return dict(self.seconds)


@dataclass
class SplitStepFields:
    """The intermediates of one split step: the inputs and labels of one-step training samples (paper A.2).

    Fluid rows (N_fluid, 3) unless noted; ``None`` where the stage that makes a field did not run.

    Attributes:
        advection_acceleration: ``a`` of the advection stage.
        pos_star, vel_star: ``x*``, ``v*`` after advection (the collision stage's input).
        pos_collided, vel_collided: ``x**``, ``v**`` after collision (the pressure stage's input).
        pressure_unclamped: (N,) the pressure stage's output before the ``p >= 0`` clamp.
        number_density: (N,) ``n`` at ``x**`` (radius ``re_density``), from the pressure stage.
        free_surface: (N,) bool, ``n < beta n0``.
        ppe_solved: (N,) bool, the pressure unknowns (non-dummy, not on the free surface).
    """

    advection_acceleration: Tensor | None = None
    pos_star: Tensor | None = None
    vel_star: Tensor | None = None
    pos_collided: Tensor | None = None
    vel_collided: Tensor | None = None
    pressure_unclamped: Tensor | None = None
    number_density: Tensor | None = None
    free_surface: Tensor | None = None
    ppe_solved: Tensor | None = None


_FIELD_NAMES = frozenset(f.name for f in dataclasses.fields(SplitStepFields))


@dataclass
class _Anchor:
    """A graph at the full cutoff and the positions it was filtered at (:meth:`StepContext.graph`).

    Attributes:
        src: the positions tensor it was asked about; ``version`` its ``_version`` then.
        pos: (N, 3) a copy of those positions (``src`` may since have been updated in place).
        graph: every pair within the cutoff at ``pos``.
        fluid_only: whether its targets are the fluid only (else also the walls within reach).
    """

    src: Tensor
    version: int
    pos: Tensor
    graph: Graph
    fluid_only: bool

    def at(self, pos: Tensor) -> bool:
        """True when ``pos`` is the very tensor the graph was filtered at, unmodified since."""
        return pos is self.src and pos._version == self.version

    def moved(self, pos: Tensor, n_fluid: int) -> float:
        """The largest distance a fluid particle moved from the anchor's positions to ``pos``, m."""
        return float((pos[:n_fluid] - self.pos[:n_fluid]).norm(dim=1).max()) if n_fluid else 0.0


@dataclass
class StepContext:
    """What every stage of one step may read: the state at ``x^n``, settings, constants and neighbours.

    Attributes:
        state: the state at the start of the step (``x^n``, ``v^n``).
        settings: scheme coefficients.
        constants: reference densities.
        neighbors: the Verlet list; ask it for graphs through :meth:`graph`.
        timer: per-stage timings of this step.
        info: per-step diagnostics a stage wants reported (PPE iterations, residual, ...): numbers, or 0-d
            tensors read after the step, all in one transfer (:func:`read_info`).
        fields: the step's intermediates, kept only when the step was asked to record them (dataset
            generation, one-step errors); stages add theirs with :meth:`record` (or :meth:`record_label`).
    """

    state: ParticleState
    settings: SolverSettings
    constants: MPSConstants
    neighbors: VerletNeighborList
    timer: StageTimer
    info: dict[str, float | Tensor] = field(default_factory=dict)
    fields: SplitStepFields | None = None
    _anchors: list[_Anchor] = field(default_factory=list)  # full-cutoff graphs, newest first (see graph)
    _within: dict[tuple[float, bool], Graph] = field(default_factory=dict)
    _labelled: set[str] = field(default_factory=set)  # fields a stage recorded with record_label

    @property
    def params(self) -> SceneParams:
        """Physical parameters of the scene."""
        return self.state.params

    @property
    def n_fluid(self) -> int:
        """Number of fluid particles (the first rows)."""
        return self.state.n_fluid

    def radius(self, factor: float) -> float:
        """A radius given in l0, in metres."""
        return factor * self.params.l0

    def record(self, **arrays: Tensor) -> None:
        """Keep arrays of this step as :class:`SplitStepFields` when the step records them (else no-op).

        Raises:
            ConfigError: a name that is not a field of :class:`SplitStepFields` (a stage's typo).
        """
        unknown = set(arrays) - _FIELD_NAMES
        if unknown:
            raise ConfigError(f"unknown step field(s) {sorted(unknown)}; declared: {sorted(_FIELD_NAMES)}")
        if self.fields is not None:
            for name, value in arrays.items():
                if name not in self._labelled:
                    setattr(self.fields, name, value.detach().clone())

    def record_label(self, **arrays: Tensor) -> None:
        """Like :meth:`record`, but later records of these fields in this step leave them as they are.

        For a stage that moves the particles by one rule and labels the step by another: the step then
        records the stage's output under the same name (on-policy datasets, :mod:`lagfluid.generate.policy`).
        """
        self.record(**arrays)
        self._labelled.update(arrays)

    def graph(self, pos: Tensor, factor: float, fluid_targets_only: bool = False) -> Graph:
        """All pairs within ``factor * l0`` at positions ``pos`` (N, 3), sorted by target.

        Targets are the fluid particles and the walls within reach of the fluid, or only the fluid with
        ``fluid_targets_only`` (then the wall rows cost nothing).

        Exact, and cheap when possible: a graph at the full cutoff is filtered from the Verlet list once per
        set of positions and kept as an *anchor* (the newest, and the newest with wall targets); stages at
        the same positions slice theirs from it, and a smaller radius ``r`` at *nearby* positions (every
        fluid particle moved at most ``d`` since) is derived from it by taking its pairs within ``r + 2d``
        and recomputing their distances (:meth:`_derive`). The split step hands its last anchor to the next
        step, so a step of FGN filters the Verlet list once (at ``x**``) and derives the rest.
        """
        radius = self.radius(factor)
        nf = self.n_fluid
        key = (radius, fluid_targets_only)
        with self.timer("neighbors", pos.device):
            newest = self._anchors[0] if self._anchors else None
            # Same tensor object, not modified since: identity, not the data pointer, which a freed
            # temporary's successor can reuse. An all-target graph serves both requests.
            if newest is not None and newest.at(pos) and newest.fluid_only <= fluid_targets_only:
                if key not in self._within:  # stages at one set of positions share sub-graphs
                    every = self._within.get((radius, False))
                    if fluid_targets_only and every is not None:
                        # Sorted by target: the fluid-target graph is a prefix (a slice, no pass).
                        self._within[key] = every.into_first(nf)
                    else:
                        full = newest.graph
                        sub = full.into_first(nf) if fluid_targets_only and not newest.fluid_only else full
                        self._within[key] = sub.within(radius)
                return self._within[key]
            for anchor in self._anchors:
                if (anchor.fluid_only and not fluid_targets_only) or radius >= anchor.graph.radius:
                    continue  # (the second: no displacement is small enough, so none is measured)
                moved = anchor.moved(pos, nf)
                if radius + 2.0 * moved < anchor.graph.radius:
                    derived = self._derive(pos, anchor, radius, moved, fluid_targets_only)
                    if derived is not None:
                        return derived
            full = self.neighbors.graph(pos, self.state.ptype, self.neighbors.cutoff, fluid_targets_only)
            anchor = _Anchor(pos, pos._version, pos.clone(), full, fluid_targets_only)
            # the newest first, and the newest all-target one behind it when this one has fluid targets only
            older = [a for a in self._anchors if not a.fluid_only][:1] if fluid_targets_only else []
            self._anchors = [anchor, *older]
            self._within = {key: full.within(radius)}
            return self._within[key]

    def _derive(
        self, pos: Tensor, anchor: _Anchor, radius: float, moved: float, fluid_only: bool
    ) -> Graph | None:
        """Every pair within ``radius`` at ``pos`` from the ``anchor`` graph; None when it cannot tell.

        Every fluid particle has moved at most ``moved`` from the anchor's positions, and
        ``radius + 2 moved < anchor.graph.radius``. A pair closer than ``radius`` now was closer than
        ``radius + 2 moved`` then (boundaries are static), so it is in the anchor: one pass over those pairs
        replaces a pass over the Verlet candidates. Fluid-target requests always can. All-target ones need
        an all-target anchor, and the walls that are targets now (those within ``wall_hops`` hops of the
        fluid *now*, see :mod:`lagfluid.neighbor_list`) to be among its targets, or to have no edge within
        ``radius``; walls that stopped being targets are dropped.
        """
        full = anchor.graph
        nf = self.n_fluid
        if fluid_only:
            near = full.into_first(nf).within(radius + 2.0 * moved)
            mask = None
        else:
            active = self.neighbors.wall_targets(pos, self.state.ptype)
            mask = None
            if active is not None:
                then = torch.zeros_like(active)  # the walls that were targets: full's rows after the fluid's
                then[full.edge_index[1, full.into_first(nf).edge_index.shape[1] :]] = True
                # A wall newly within reach of the fluid has no row in the anchor. It has no fluid within
                # radius now (it would have been within radius + moved < cutoff then), so it matters only
                # if two boundary particles can be closer than radius.
                newly = bool((active & ~then).any())
                if newly and radius > self.neighbors.closest_static_pair():
                    return None
                mask = active
                mask[:nf] = True
            near = full.within(radius + 2.0 * moved)
        if pair_kernels.applies(pos):
            return Graph(*pair_kernels.pairs_within(pos, [near.edge_index], radius, [mask]), radius)
        rel, dist = edge_vectors(pos, near.edge_index)
        keep = dist < radius
        if mask is not None:
            keep &= mask.index_select(0, near.edge_index[1])
        return Graph(near.edge_index, rel, dist, radius).select(keep)


class AdvectionStage(Protocol):
    """Body force and viscosity: returns the advection acceleration ``a`` (N_fluid, 3)."""

    def __call__(self, ctx: StepContext, pos: Tensor, vel: Tensor) -> Tensor:
        """Acceleration of the fluid particles at ``(x^n, v^n)`` (full (N, 3) arrays)."""
        ...

    def radii(self, settings: SolverSettings, params: SceneParams) -> tuple[float, ...]:
        """Radii (in l0) this stage asks the step context for: the neighbour list covers the largest."""
        ...


class CollisionStage(Protocol):
    """Short-range repulsion: returns corrected fluid velocities ``v**`` (N_fluid, 3)."""

    def __call__(self, ctx: StepContext, pos: Tensor, vel: Tensor) -> Tensor:
        """Corrected fluid velocities at ``(x*, v*)`` (full (N, 3) arrays)."""
        ...

    def radii(self, settings: SolverSettings, params: SceneParams) -> tuple[float, ...]:
        """Radii (in l0) this stage asks the step context for: the neighbour list covers the largest."""
        ...


class PressureStage(Protocol):
    """Pressure projection: returns the pressure (N,) of every particle at ``(x**, v**)``."""

    def __call__(self, ctx: StepContext, pos: Tensor, vel: Tensor) -> Tensor:
        """Pressure of all particles (zero where not computed)."""
        ...

    def radii(self, settings: SolverSettings, params: SceneParams) -> tuple[float, ...]:
        """Radii (in l0) this stage asks the step context for: the neighbour list covers the largest."""
        ...


def stage_cutoff(
    settings: SolverSettings,
    params: SceneParams,
    advection: AdvectionStage | None,
    collision: CollisionStage | None,
    pressure: PressureStage | None,
) -> float:
    """Largest radius (in l0) a split step with these stages searches for this scene: its neighbour cutoff.

    Every stage reports its radii with ``radii(settings, params)`` (the stage protocols); a pressure stage
    adds the correction's ``re_gradient``. FGN needs
    2.1 l0 where MPS needs 3.1 l0 (the Laplacian): a list at 2.1 + skin holds ~2.6x fewer candidate pairs
    to filter every step.

    Args:
        settings: scheme coefficients and radii.
        params: the scene's physical parameters (a stage's radii may depend on them, e.g. viscosity).
        advection: the advection stage, ``None`` when skipped.
        collision: the collision stage, ``None`` when skipped.
        pressure: the pressure stage, ``None`` when skipped.
    """
    needed: list[float] = [settings.re_gradient] if pressure is not None else []
    for stage in (advection, collision, pressure):
        if stage is None:
            continue
        needed += list(stage.radii(settings, params))
    return max(needed, default=settings.re_collision)


class SplitStepSimulator:
    """The advect -> collide -> project -> correct scheme with any mix of exact and learned stages.

    Implements :class:`lagfluid.models.simulator.Simulator`: it steps by the scene's ``dt`` (``dt = None``),
    needs no history (each step reads ``x^n, v^n`` only) and has no trainable parameters of its own
    (learned-stage simulators override :attr:`parameters`).

    Args:
        name: simulator name (written into outputs).
        settings: scheme coefficients.
        advection, collision, pressure: stage implementations; ``None`` skips the stage.
    """

    dt: float | None = None
    history_length: int = 0
    max_courant: float | None = None  # the run's solver.guard.max_courant

    def __init__(
        self,
        name: str,
        settings: SolverSettings,
        advection: AdvectionStage | None,
        collision: CollisionStage | None,
        pressure: PressureStage | None,
    ) -> None:
        self.name = name
        self.settings = settings
        self.advection = advection
        self.collision = collision
        self.pressure = pressure
        self.constants: MPSConstants | None = None
        self.neighbors: VerletNeighborList | None = None
        self.timer = StageTimer()
        self._info: dict[str, float | Tensor] = {}  # the last step's diagnostics (see last_info)
        self.last_fields: SplitStepFields | None = None
        # The last step's graph at x**, kept for the next step when it starts from that step's output:
        # (the returned positions, their version, the step context's cached graph).
        self._carried: tuple[Tensor, Tensor, int, list[_Anchor]] | None = None

    # ------------------------------------------------------------------ Simulator interface
    @property
    def parameters(self) -> int:
        """Trainable parameters of the stages: 0 for the exact scheme."""
        return 0

    def reset(self, state: ParticleState, history: Sequence[ParticleState] = ()) -> None:
        """Compute the per-scene constants and a fresh neighbour list for ``state``.

        ``history`` (earlier states) is accepted as every simulator's is and not needed: the scheme is
        one-step.
        """
        self.constants = scene_constants(state, self.settings)
        self.neighbors = neighbor_list(self.settings, self.cutoff(state.params) * state.params.l0)
        self._carried = None

    def memory_needed(self, state: ParticleState) -> float:
        """Bytes a rollout from ``state`` needs (:func:`lagfluid.memory.rollout_bytes`).

        The Verlet list's candidate pairs at the cutoff plus skin dominate, for MPS and FGN alike (115-190 and
        117 B per pair measured over runs that rebuild the list).
        """
        from lagfluid.memory import DEFAULT_BYTES_PER_PAIR, rollout_bytes

        params = state.params
        radius = self.cutoff(params) * (1 + self.settings.neighbor_skin_fraction) * params.l0
        return rollout_bytes(state, radius, DEFAULT_BYTES_PER_PAIR)

    def cutoff(self, params: SceneParams) -> float:
        """Largest radius (in l0) the configured stages use for this scene: the neighbour list's cutoff.

        See :func:`stage_cutoff`.
        """
        return stage_cutoff(self.settings, params, self.advection, self.collision, self.pressure)

    @property
    def last_info(self) -> dict[str, float]:
        """Diagnostics of the last step (``info`` of its :class:`StepContext`).

        Its 0-d tensors are read at the first access, after the step: on CUDA the read then waits for
        nothing, where inside the step it would stall the queue.
        """
        self._info = read_info(self._info)
        return dict(self._info)

    @property
    def last_timings(self) -> dict[str, float]:
        """Seconds per stage of the last step (``neighbors`` includes the candidate-list filtering)."""
        return self.timer.read()

    def attributes(self) -> dict[str, Any]:
        """Constants worth storing with a rollout."""
        if self.constants is None:
            return {}
        return {"n0": self.constants.n0, "n0_lap": self.constants.n0_lap, "lambda": self.constants.lam}

    @torch.no_grad()
    def step(self, state: ParticleState, *, record: bool = False) -> ParticleState:
        """Advance ``state`` by one time step ``state.params.dt``; returns a new state.

        With ``record`` the step also leaves its intermediates in ``last_fields`` (a
        :class:`SplitStepFields`; else ``last_fields`` is None): the inputs and labels of the one-step
        training samples (paper A.2) and of the one-step errors of ``task=evaluate``.
        """
        if self.constants is None or self.neighbors is None:
            self.reset(state)
        self.timer.reset()
        builds = self.neighbors.builds
        ctx = StepContext(
            state,
            self.settings,
            self.constants,
            self.neighbors,
            self.timer,
            fields=SplitStepFields() if record else None,
        )
        carried = self._carried
        if carried is not None and carried[0] is state.pos and carried[1] is state.ptype:
            if state.pos._version == carried[2]:  # the last step's output, untouched: its x** graph is
                ctx._anchors = carried[3]  # x** is a few um from x^n: x^n's graphs derive from its graph
        nf, dt, device = state.n_fluid, state.params.dt, state.device
        # Updated in place row-slice by row-slice: the step context's graph cache keys on this tensor.
        pos, vel = state.pos.clone(), state.vel.clone()

        if self.advection is not None:
            acc = self.advection(ctx, pos, vel)
            with self.timer("advection", device):
                pos[:nf], vel[:nf] = integrate.advect(pos[:nf], vel[:nf], acc, dt)
            ctx.record(advection_acceleration=acc)
        else:
            pos[:nf] = integrate.drift(pos[:nf], vel[:nf], dt)
        ctx.record(pos_star=pos[:nf], vel_star=vel[:nf])

        if self.collision is not None:
            self.collide(ctx, pos, vel)
        ctx.record(pos_collided=pos[:nf], vel_collided=vel[:nf])

        pressure = torch.zeros_like(state.pressure)
        if self.pressure is not None:
            pressure = self.project(ctx, pos, vel)

        ctx.info["list_rebuilds"] = float(self.neighbors.builds - builds)
        self._info = ctx.info
        self.last_fields = ctx.fields
        self._carried = (pos, state.ptype, pos._version, ctx._anchors) if ctx._anchors else None
        return ParticleState(
            pos=pos,
            vel=vel,
            ptype=state.ptype,
            params=state.params,
            pressure=pressure,
            time=state.time + dt,
            step=state.step + 1,
            bounds=state.bounds,
            check=False,
            fluid_count=nf,
        )

    def collide(self, ctx: StepContext, pos: Tensor, vel: Tensor) -> None:
        """The collision stage and its update, in place on the fluid rows of ``pos``, ``vel`` (N, 3).

        ``v** = collision(x*, v*)``, ``x** = x* + (v** - v*) dt`` (:func:`lagfluid.integrate.collide`).
        """
        nf, dt = ctx.n_fluid, ctx.params.dt
        v_star = vel[:nf].clone()
        v_new = self.collision(ctx, pos, vel)
        with self.timer("collision", pos.device):
            pos[:nf] = integrate.collide(pos[:nf], v_star, v_new, dt)
            vel[:nf] = v_new

    def project(self, ctx: StepContext, pos: Tensor, vel: Tensor, relaxation: float = 1.0) -> Tensor:
        """The pressure stage, the clamp and the correction, in place on ``pos``, ``vel`` (N, 3).

        ``a_p = -grad_min(p) / rho``, ``v += w a_p dt``, ``x += w a_p dt^2``
        (:func:`lagfluid.integrate.correct`) with the relaxation factor ``w`` (1: the scheme's step;
        :mod:`lagfluid.models.exact_after` may scale it).

        Returns:
            (N,) the pressure the stage solved for (clamped at 0 when the settings say so), before ``w``.
        """
        nf, dt = ctx.n_fluid, ctx.params.dt
        pressure = self.pressure(ctx, pos, vel)
        ctx.record(pressure_unclamped=pressure)
        g_grad = self.gradient_graph(ctx, pos)
        with self.timer("correction", pos.device):
            if self.settings.clamp_negative_pressure:
                pressure = pressure.clamp_min(0.0)
            acc_p = self.pressure_acceleration(ctx, pos, pressure, g_grad)
            if relaxation != 1.0:
                acc_p = relaxation * acc_p
            pos[:nf], vel[:nf] = integrate.correct(pos[:nf], vel[:nf], acc_p, dt)
        return pressure

    @torch.no_grad()
    def exact_stages(
        self, state: ParticleState, warm_pressure: Tensor, iterations: int = 1, relaxation: float = 1.0
    ) -> ParticleState:
        """The configured collision and pressure stages alone on ``state``'s positions and velocities.

        No advection and no drift: ``state`` is where another scheme's step ended (an end-to-end network,
        :mod:`lagfluid.models.exact_after`). Each of the ``iterations`` applies the collision stage (if any)
        and then the pressure projection (if any) with the relaxation factor ``relaxation``, by
        :meth:`collide` and :meth:`project`, the step's own updates; the PPE's source term uses
        ``state.params.dt``. Time and step count stay ``state``'s.

        Args:
            state: the state to correct (its ``pressure`` is returned unchanged when no pressure stage runs).
            warm_pressure: (N,) the PPE's warm start (the last solved pressure); later iterations start
                from the one before.
            iterations: how many times to apply the stages (>= 1).
            relaxation: ``w`` in (0, 1] of the pressure correction.

        Returns:
            The corrected state; its pressure is the last solve's (or ``state.pressure``).
        """
        if self.constants is None or self.neighbors is None:
            self.reset(state)
        self.timer.reset()
        builds, nf = self.neighbors.builds, state.n_fluid
        pos, vel, pressure = state.pos.clone(), state.vel.clone(), warm_pressure
        anchors: list[_Anchor] = []  # graphs carried from one iteration to the next (derived, exact)
        info: dict[str, float | Tensor] = {}
        for _ in range(iterations):
            at = dataclasses.replace(state, pos=pos, vel=vel, pressure=pressure, check=False, fluid_count=nf)
            ctx = StepContext(at, self.settings, self.constants, self.neighbors, self.timer)
            ctx._anchors = anchors
            if self.collision is not None:
                self.collide(ctx, pos, vel)
            if self.pressure is not None:
                pressure = self.project(ctx, pos, vel, relaxation)
            anchors, info = ctx._anchors, ctx.info
        info["list_rebuilds"] = float(self.neighbors.builds - builds)
        self._info, self.last_fields, self._carried = info, None, None
        return dataclasses.replace(
            state,
            pos=pos,
            vel=vel,
            pressure=pressure if self.pressure is not None else state.pressure,
            check=False,
            fluid_count=nf,
        )

    def gradient_graph(self, ctx: StepContext, pos: Tensor) -> Graph:
        """Edges into fluid particles within ``re_gradient``, dummy sources included."""
        return ctx.graph(pos, self.settings.re_gradient, fluid_targets_only=True)

    def pressure_acceleration(self, ctx: StepContext, pos: Tensor, pressure: Tensor, graph: Graph) -> Tensor:
        """``-grad p / rho`` on the fluid particles (N_fluid, 3), over :meth:`gradient_graph`.

        ``settings.pressure_gradient``: ``minimum`` (the authors' minimum-pressure gradient) or ``corrected``
        (:func:`lagfluid.physics.operators.corrected_pressure_gradient`). Dummy particles carry no pressure
        and are left out: in the gradient they would pose as the neighbourhood minimum p = 0.
        """
        with_pressure = ctx.state.ptype != ParticleType.DUMMY
        radius, n0 = ctx.radius(self.settings.re_gradient), self.constants.n0
        common = {"dim": ctx.params.dim, "num_nodes": ctx.n_fluid}
        if self.settings.pressure_gradient == "minimum":
            grad = ops.min_pressure_gradient(
                pos,
                graph.edge_index,
                pressure,
                radius,
                n0,
                geometry=graph.geometry,
                sources=with_pressure,
                **common,
            )
        else:
            g = graph.select(with_pressure.index_select(0, graph.edge_index[0]))
            grad = ops.corrected_pressure_gradient(
                pos, g.edge_index, pressure, radius, n0, geometry=g.geometry, **common
            )
        return -grad / ctx.params.density
