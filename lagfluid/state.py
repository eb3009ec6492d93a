"""Particle state and physical parameters shared by every simulator.

Conventions (every module relies on them):

* Particles are stored in one set of arrays, **sorted by type**: fluid first, then wall, then
  dummy. ``pos[:n_fluid]`` are the fluid particles; boundary particles (wall + dummy) follow and
  are static: simulators never integrate them.
* Particle types follow the authors' grid files: 1 = fluid, 2 = wall (takes part in the pressure
  solve), 3 = dummy (outer boundary layers that only complete the wall particles' neighbourhoods).
* Lengths are metres; ``l0`` is the initial particle spacing. Radii are configured as multiples of
  ``l0``. Gravity is a 3-vector (z is up by default, as in the authors' data).
"""

from __future__ import annotations

import math
from dataclasses import InitVar, dataclass, field, replace
from enum import IntEnum

import torch
from torch import Tensor

from lagfluid.errors import RolloutError, SceneError

__all__ = ["DTYPES", "ParticleState", "ParticleType", "SceneError", "SceneParams", "parse_dtype"]

DTYPES = {"float32": torch.float32, "float64": torch.float64}
"""The floating dtypes a run may use (``dtype=`` on the command line)."""


def parse_dtype(name: object) -> torch.dtype:
    """The torch dtype named ``name`` (``float32`` or ``float64``).

    Raises:
        RolloutError: any other name.
    """
    dtype = DTYPES.get(str(name))
    if dtype is None:
        raise RolloutError(f"unknown dtype '{name}'; available: {', '.join(DTYPES)}")
    return dtype


class ParticleType(IntEnum):
    """Particle type codes, identical to the ``ptype`` column of the authors' grid files."""

    FLUID = 1
    WALL = 2
    DUMMY = 3


@dataclass(frozen=True)
class SceneParams:
    """Physical and numerical parameters of a scene.

    Attributes:
        gravity: body force per unit mass, m/s^2, shape (3,).
        viscosity: kinematic viscosity nu, m^2/s.
        density: fluid density rho, kg/m^3.
        dt: time step, s.
        l0: initial particle spacing, m.
        dim: spatial dimension used by the MPS operators (the ``d`` in ``2d / (lambda n0)``).
    """

    gravity: tuple[float, float, float] = (0.0, 0.0, -9.8065)
    viscosity: float = 1.0e-6
    density: float = 1000.0
    dt: float = 0.002
    l0: float = 0.05
    dim: int = 3

    def __post_init__(self) -> None:
        if len(self.gravity) != 3 or not all(math.isfinite(g) for g in self.gravity):
            raise SceneError(f"gravity must be three finite numbers, got {self.gravity!r}")
        for name in ("viscosity",):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise SceneError(f"{name} must be finite and >= 0, got {value!r}")
        for name in ("density", "dt", "l0"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise SceneError(f"{name} must be finite and > 0, got {value!r}")
        if self.dim not in (2, 3):
            raise SceneError(f"dim must be 2 or 3, got {self.dim!r}")

    def with_overrides(self, **changes: object) -> SceneParams:
        """Return a copy with the given fields replaced (``None`` values are ignored)."""
        return replace(self, **{k: v for k, v in changes.items() if v is not None})


@dataclass
class ParticleState:
    """Positions, velocities, pressure and types of all particles at one instant.

    Attributes:
        pos: positions, shape (N, 3), float32 or float64.
        vel: velocities, shape (N, 3), same dtype; boundary rows stay zero.
        ptype: particle types, shape (N,), int64, sorted FLUID < WALL < DUMMY.
        pressure: pressure, shape (N,), same dtype as ``pos``.
        params: physical parameters.
        time: simulated time, s.
        step: number of steps taken since the initial state.
        bounds: optional axis-aligned domain, shape (2, 3) (lower, upper corner); a fluid particle
            outside it has left the domain.
        check: validate on construction (simulators pass False for the states they step to: the
            rollout guard checks those, once, with a message about the run rather than the scene).
        fluid_count: the number of FLUID rows of ``ptype`` when the caller knows it (a simulator stepping to a
            state with its predecessor's ``ptype``); None: counted here.
    """

    pos: Tensor
    vel: Tensor
    ptype: Tensor
    params: SceneParams = field(default_factory=SceneParams)
    pressure: Tensor | None = None
    time: float = 0.0
    step: int = 0
    bounds: Tensor | None = None
    check: InitVar[bool] = True
    fluid_count: InitVar[int | None] = None

    def __post_init__(self, check: bool, fluid_count: int | None) -> None:
        if self.pressure is None:
            self.pressure = torch.zeros(self.pos.shape[0], dtype=self.pos.dtype, device=self.pos.device)
        # Counted once, or handed over by the step that made this state: asked for in every stage, and on
        # CUDA each count is a host synchronisation. (ptype is never modified in place; a state with other
        # particles is a new state.)
        if fluid_count is None:
            fluid_count = int((self.ptype == ParticleType.FLUID).sum())
        self._n_fluid = fluid_count
        if check:
            self.validate()

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_arrays(
        cls,
        pos: Tensor,
        vel: Tensor,
        ptype: Tensor,
        params: SceneParams | None = None,
        bounds: Tensor | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> ParticleState:
        """Build a state from unsorted arrays, sorting particles by type (stable).

        Args:
            pos: (N, 3) positions.
            vel: (N, 3) velocities.
            ptype: (N,) types (1 fluid, 2 wall, 3 dummy).
            params: physical parameters (defaults: the authors' values).
            bounds: optional (2, 3) domain box.
            dtype: floating dtype of the state.
        """
        pos = torch.as_tensor(pos, dtype=dtype)
        vel = torch.as_tensor(vel, dtype=dtype)
        ptype = torch.as_tensor(ptype, dtype=torch.int64)
        if ptype.dim() != 1 or pos.shape[0] != ptype.shape[0]:
            raise SceneError(f"ptype must have shape (N,) with N={pos.shape[0]}, got {tuple(ptype.shape)}")
        order = torch.argsort(ptype, stable=True)
        if bounds is not None:
            bounds = torch.as_tensor(bounds, dtype=dtype)
        return cls(
            pos=pos[order], vel=vel[order], ptype=ptype[order], params=params or SceneParams(), bounds=bounds
        )

    # ------------------------------------------------------------------ views
    @property
    def num_particles(self) -> int:
        """Total number of particles N."""
        return int(self.pos.shape[0])

    @property
    def n_fluid(self) -> int:
        """Number of fluid particles (they are the first ``n_fluid`` rows)."""
        return self._n_fluid

    @property
    def fluid_mask(self) -> Tensor:
        """(N,) bool, True for fluid particles."""
        return self.ptype == ParticleType.FLUID

    @property
    def wall_mask(self) -> Tensor:
        """(N,) bool, True for wall particles."""
        return self.ptype == ParticleType.WALL

    @property
    def dummy_mask(self) -> Tensor:
        """(N,) bool, True for dummy particles."""
        return self.ptype == ParticleType.DUMMY

    @property
    def device(self) -> torch.device:
        """Device of the state's tensors."""
        return self.pos.device

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of the state's tensors."""
        return self.pos.dtype

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> ParticleState:
        """Return a copy on ``device`` with floating tensors cast to ``dtype``."""

        def move(t: Tensor | None, floating: bool = True) -> Tensor | None:
            if t is None:
                return None
            return t.to(device=device, dtype=dtype if floating else None)

        return replace(
            self,
            pos=move(self.pos),
            vel=move(self.vel),
            ptype=move(self.ptype, floating=False),
            pressure=move(self.pressure),
            bounds=move(self.bounds),
        )

    def clone(self) -> ParticleState:
        """Deep copy of the tensors."""
        return replace(
            self,
            pos=self.pos.clone(),
            vel=self.vel.clone(),
            ptype=self.ptype.clone(),
            pressure=self.pressure.clone() if self.pressure is not None else None,
            bounds=self.bounds.clone() if self.bounds is not None else None,
        )

    def advanced_fluid(
        self, fluid_pos: Tensor, fluid_vel: Tensor, dt: float, pressure: Tensor | None = None
    ) -> ParticleState:
        """This state ``dt`` later with the fluid rows replaced; the boundary never moves.

        What an end-to-end model's step returns (it predicts the fluid alone). Not validated (the rollout
        guard checks the states a simulator steps to).

        Args:
            fluid_pos: (Nf, 3) new fluid positions.
            fluid_vel: (Nf, 3) new fluid velocities.
            dt: the step, s.
            pressure: (N,) new pressure; None: zero (a model that predicts none).
        """
        nf = self.n_fluid
        pos, vel = self.pos.clone(), self.vel.clone()
        pos[:nf], vel[:nf] = fluid_pos.to(pos.dtype), fluid_vel.to(vel.dtype)
        return ParticleState(
            pos=pos,
            vel=vel,
            ptype=self.ptype,
            params=self.params,
            pressure=torch.zeros_like(self.pressure) if pressure is None else pressure,
            time=self.time + dt,
            step=self.step + 1,
            bounds=self.bounds,
            check=False,
            fluid_count=nf,
        )

    # ------------------------------------------------------------------ checks
    def validate(self) -> None:
        """Raise :class:`SceneError` naming the first inconsistency found."""
        n = self.pos.shape[0]
        if self.pos.dim() != 2 or self.pos.shape[1] != 3:
            raise SceneError(f"pos must have shape (N, 3), got {tuple(self.pos.shape)}")
        if not self.pos.is_floating_point():
            raise SceneError(f"pos must be floating point, got {self.pos.dtype}")
        if self.vel.shape != self.pos.shape:
            raise SceneError(f"vel must have shape {tuple(self.pos.shape)}, got {tuple(self.vel.shape)}")
        if self.ptype.shape != (n,):
            raise SceneError(f"ptype must have shape ({n},), got {tuple(self.ptype.shape)}")
        if self.pressure is not None and self.pressure.shape != (n,):
            raise SceneError(f"pressure must have shape ({n},), got {tuple(self.pressure.shape)}")
        valid = torch.isin(self.ptype, torch.tensor([int(t) for t in ParticleType], device=self.ptype.device))
        if not bool(valid.all()):
            bad = int(torch.nonzero(~valid)[0, 0])
            raise SceneError(
                f"unknown particle type {int(self.ptype[bad])} at particle {bad}; "
                "expected 1 (fluid), 2 (wall) or 3 (dummy)"
            )
        if n > 1 and bool((self.ptype[1:] < self.ptype[:-1]).any()):
            raise SceneError(
                "particles must be sorted fluid, wall, dummy; build states with ParticleState.from_arrays"
            )
        counted = int((self.ptype == ParticleType.FLUID).sum())
        if self.n_fluid != counted:
            raise SceneError(f"fluid_count {self.n_fluid} does not match ptype's {counted} FLUID rows")
        if self.n_fluid == 0:
            raise SceneError("the scene has no fluid particles")
        for name in ("pos", "vel"):
            t = getattr(self, name)
            finite = torch.isfinite(t).all(dim=1)
            if not bool(finite.all()):
                bad = int(torch.nonzero(~finite)[0, 0])
                raise SceneError(f"{name} of particle {bad} is not finite: {t[bad].tolist()}")
        if self.bounds is not None:
            if self.bounds.shape != (2, 3) or not bool((self.bounds[1] > self.bounds[0]).all()):
                raise SceneError(
                    f"bounds must be a (2, 3) box with upper > lower, got {self.bounds.tolist()}"
                )
            outside = self.fluid_outside_bounds()
            if outside.numel():
                i = int(outside[0])
                raise SceneError(
                    f"fluid particle {i} at {self.pos[i].tolist()} is outside the domain "
                    f"{self.bounds[0].tolist()} .. {self.bounds[1].tolist()}"
                )

    def fluid_outside_mask(self) -> Tensor:
        """(N_fluid,) bool: the fluid particles outside ``bounds`` (all False when no bounds are set)."""
        fluid = self.pos[: self.n_fluid]
        if self.bounds is None:
            return torch.zeros(fluid.shape[0], dtype=torch.bool, device=fluid.device)
        return ((fluid < self.bounds[0]) | (fluid > self.bounds[1])).any(dim=1)

    def fluid_outside_bounds(self) -> Tensor:
        """Indices (K,) of fluid particles outside ``bounds`` (empty when no bounds are set)."""
        return torch.nonzero(self.fluid_outside_mask()).flatten()
