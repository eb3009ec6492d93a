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

Beside it: its settings and constants (:mod:`lagfluid.physics.settings`), what one step's stages share
(:mod:`lagfluid.physics.step_context`), the per-stage timer (:mod:`lagfluid.physics.timing`); the exact
stages are in :mod:`lagfluid.physics.mps`, FGN's learned ones in :mod:`lagfluid.models.fgn.learned_stages`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any, Protocol

import torch
from torch import Tensor

from lagfluid import integrate
from lagfluid.neighbors.verlet import Graph, VerletNeighborList
from lagfluid.physics import operators as ops
from lagfluid.physics.settings import MPSConstants, SolverSettings, scene_constants
from lagfluid.physics.step_context import GraphAnchor, SplitStepFields, StepContext, neighbor_list, read_info
from lagfluid.physics.timing import StageTimer
from lagfluid.state import ParticleState, ParticleType, SceneParams


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
        self._carried: tuple[Tensor, Tensor, int, list[GraphAnchor]] | None = None

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
        self.neighbors = neighbor_list(self.settings, self.cutoff(state.params), state.params.l0)
        self._carried = None

    def memory_needed(self, state: ParticleState) -> float:
        """Bytes a rollout from ``state`` needs (:func:`lagfluid.memory.rollout_bytes`).

        The Verlet list's candidate pairs at the cutoff plus skin dominate, for MPS and FGN alike (115-190 and
        117 B per pair measured over runs that rebuild the list).
        """
        from lagfluid.memory import DEFAULT_BYTES_PER_PAIR, rollout_bytes

        params = state.params
        cutoff = self.cutoff(params)
        radius = cutoff * (1 + self.settings.skin_fraction(cutoff)) * params.l0
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
                ctx.anchors = carried[3]  # x** is a few um from x^n: x^n's graphs derive from its graph
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
        self._carried = (pos, state.ptype, pos._version, ctx.anchors) if ctx.anchors else None
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
        anchors: list[GraphAnchor] = []  # graphs carried from one iteration to the next (derived, exact)
        info: dict[str, float | Tensor] = {}
        for _ in range(iterations):
            at = dataclasses.replace(state, pos=pos, vel=vel, pressure=pressure, check=False, fluid_count=nf)
            ctx = StepContext(at, self.settings, self.constants, self.neighbors, self.timer)
            ctx.anchors = anchors
            if self.collision is not None:
                self.collide(ctx, pos, vel)
            if self.pressure is not None:
                pressure = self.project(ctx, pos, vel, relaxation)
            anchors, info = ctx.anchors, ctx.info
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
