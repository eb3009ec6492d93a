"""What the stages of one split step share: the :class:`StepContext` and its graph caches.

The context holds the state at ``x^n``, the settings, constants, neighbour list and timer of the step, the
diagnostics its stages report and, when the step records them, its intermediates (:class:`SplitStepFields`).
Its graphs are cached on the identity of the positions tensor they were asked about (and its version, see
:meth:`StepContext.graph`): stages at one set of positions share them, nearby positions derive from them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import torch
from torch import Tensor

from lagfluid.errors import ConfigError
from lagfluid.neighbors.pair_kernels import backend_for
from lagfluid.neighbors.verlet import Graph, VerletNeighborList
from lagfluid.physics.settings import MPSConstants, SolverSettings
from lagfluid.physics.timing import StageTimer
from lagfluid.state import ParticleState, SceneParams


def neighbor_list(settings: SolverSettings, cutoff_l0: float, l0: float) -> VerletNeighborList:
    """A fresh Verlet list at ``cutoff_l0 * l0`` (m) with the settings' skin, backend and wall hops."""
    cutoff = cutoff_l0 * l0
    skin = settings.skin_fraction(cutoff_l0) * cutoff
    return VerletNeighborList(cutoff, skin, settings.neighbor_backend, settings.wall_hops)


def read_info(info: dict[str, float | Tensor]) -> dict[str, float]:
    """``info`` as numbers, its 0-d tensors read in one transfer (on CUDA one host synchronisation)."""
    tensors = {k: v for k, v in info.items() if isinstance(v, Tensor)}
    if not tensors:
        return dict(info)
    values = torch.stack([v.detach().to(torch.float64) for v in tensors.values()]).tolist()
    return {**info, **dict(zip(tensors, values, strict=True))}


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
class GraphAnchor:
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
        anchors: full-cutoff graphs, newest first (:meth:`graph`); the split step passes the last step's on
            to the next step when it starts from that step's output, unmodified.
    """

    state: ParticleState
    settings: SolverSettings
    constants: MPSConstants
    neighbors: VerletNeighborList
    timer: StageTimer
    info: dict[str, float | Tensor] = field(default_factory=dict)
    fields: SplitStepFields | None = None
    anchors: list[GraphAnchor] = field(default_factory=list)
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
        records the stage's output under the same name (on-policy datasets,
        :mod:`lagfluid.tasks.generate.policy`).
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
            newest = self.anchors[0] if self.anchors else None
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
            for anchor in self.anchors:
                if (anchor.fluid_only and not fluid_targets_only) or radius >= anchor.graph.radius:
                    continue  # (the second: no displacement is small enough, so none is measured)
                moved = anchor.moved(pos, nf)
                if radius + 2.0 * moved < anchor.graph.radius:
                    derived = self._derive(pos, anchor, radius, moved, fluid_targets_only)
                    if derived is not None:
                        return derived
            full = self.neighbors.graph(pos, self.state.ptype, self.neighbors.cutoff, fluid_targets_only)
            anchor = GraphAnchor(pos, pos._version, pos.clone(), full, fluid_targets_only)
            # the newest first, and the newest all-target one behind it when this one has fluid targets only
            older = [a for a in self.anchors if not a.fluid_only][:1] if fluid_targets_only else []
            self.anchors = [anchor, *older]
            self._within = {key: full.within(radius)}
            return self._within[key]

    def _derive(
        self, pos: Tensor, anchor: GraphAnchor, radius: float, moved: float, fluid_only: bool
    ) -> Graph | None:
        """Every pair within ``radius`` at ``pos`` from the ``anchor`` graph; None when it cannot tell.

        Every fluid particle has moved at most ``moved`` from the anchor's positions, and
        ``radius + 2 moved < anchor.graph.radius``. A pair closer than ``radius`` now was closer than
        ``radius + 2 moved`` then (boundaries are static), so it is in the anchor: one pass over those pairs
        replaces a pass over the Verlet candidates. Fluid-target requests always can. All-target ones need
        an all-target anchor, and the walls that are targets now (those within ``wall_hops`` hops of the
        fluid *now*, see :mod:`lagfluid.neighbors.verlet`) to be among its targets, or to have no edge within
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
        pairs_within = backend_for("pairs_within", pos)
        return Graph(*pairs_within(pos, [near.edge_index], radius, [mask]), radius)
