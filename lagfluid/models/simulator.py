"""The interface every simulator implements.

MPS included, so that one rollout loop, one metrics module and one benchmark harness measure them all on
equal terms.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from lagfluid.state import ParticleState


@runtime_checkable
class Simulator(Protocol):
    """A time stepper for particle states.

    Attributes:
        name: registry name, written into every output.
        last_timings: seconds per named stage of the last :meth:`step` (e.g. ``neighbors``, ``advection``,
            ``collision``, ``pressure_assembly``, ``pressure_solve``, ``correction``).
        last_info: per-step diagnostics of the last step (e.g. ``ppe_iterations``, ``ppe_residual``).
    """

    name: str

    @property
    def last_timings(self) -> dict[str, float]:
        """Seconds per stage of the last step."""
        ...

    last_info: dict[str, float]

    def reset(self, state: ParticleState) -> None:
        """Prepare for a new rollout starting at ``state`` (per-scene constants, neighbour lists)."""
        ...

    def step(self, state: ParticleState) -> ParticleState:
        """Return the state one time step ``state.params.dt`` later; never modifies ``state``."""
        ...

    def attributes(self) -> dict[str, Any]:
        """Scalars worth storing with a rollout (reference densities, parameter counts, ...)."""
        ...
