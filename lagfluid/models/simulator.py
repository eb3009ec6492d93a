"""The interface every simulator implements, MPS included.

One rollout loop (:func:`lagfluid.rollout.rollout`), one metrics module and one benchmark harness measure
every simulator on equal terms through it. A plugin (``baselines/``, a third-party package) implements it
and registers a factory in the ``lagfluid.simulators`` entry-point group; nothing else in lagfluid names it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

from lagfluid.errors import ConfigError
from lagfluid.state import ParticleState


@runtime_checkable
class Simulator(Protocol):
    """A time stepper for particle states.

    Attributes:
        name: registry name, written into every output.
        dt: the simulator's own time step in s (a model trained on frames ``k`` solver steps apart steps by
            that), or None to step by the scene's ``state.params.dt``. The rollout tasks run the scene at
            this ``dt`` and record it in every output.
        history_length: how many earlier states :meth:`reset` wants (0 for one-step schemes; GNS: 5).
        max_courant: the largest ``max|v| dt / l0`` the simulator is valid to, which the rollout guard
            enforces; None: the run's ``solver.guard.max_courant`` (the MPS solver's limit). A learned model
            stepping at a coarser ``dt`` than the solver's states its own (GNS's training frames reach 0.8).
        parameters: trainable parameters (0 for MPS); reported beside every timing.
        last_timings: seconds per named stage of the last :meth:`step` (e.g. ``neighbors``, ``advection``,
            ``pressure_solve``; an end-to-end model may report just ``network``).
        last_info: per-step diagnostics of the last step (e.g. ``ppe_iterations``, ``ppe_residual``).
        last_fields: the intermediates of the last step when it was asked to ``record`` them, as an
            instance of the simulator's own dataclass (``SplitStepFields`` for the split-step scheme);
            None otherwise.
    """

    name: str
    dt: float | None
    history_length: int
    max_courant: float | None

    @property
    def parameters(self) -> int:
        """Trainable parameters."""
        ...

    @property
    def last_timings(self) -> dict[str, float]:
        """Seconds per stage of the last step."""
        ...

    last_info: dict[str, float]
    last_fields: Any | None

    def reset(self, state: ParticleState, history: Sequence[ParticleState] = ()) -> None:
        """Prepare for a rollout starting at ``state``.

        Args:
            state: the first state (per-scene constants, neighbour lists are set up for it).
            history: up to ``history_length`` earlier states, oldest first, spaced by the simulator's time
                step (e.g. frames ``t-5 .. t-1`` of a trajectory when the rollout starts at frame ``t``);
                empty for a scene built from scratch, where the simulator decides what it assumes.
        """
        ...

    def step(self, state: ParticleState, *, record: bool = False) -> ParticleState:
        """Return the state one time step later; never modifies ``state``.

        Args:
            state: the state at ``t``.
            record: keep this step's intermediates in ``last_fields`` (costs copies; off for timed runs).
        """
        ...

    def attributes(self) -> dict[str, Any]:
        """Values worth storing with a rollout (reference densities, where the weights came from, ...).

        Numbers, strings, or dicts and lists of them: ``metrics.json`` holds them as they are, the rollout
        file's attributes hold a dict as its JSON text (HDF5 attributes have no dicts).
        """
        ...

    # Optional: ``predicts_pressure = False`` for a simulator whose states carry no pressure of its own (GNS,
    # CConv: zeros); pictures of its rollouts then colour the fluid by speed (lagfluid.viz.colour_field).
    # Without it a simulator is taken to predict pressure.

    # Optional, for a simulator that carries tensors from one step to the next beyond the state (GNS's
    # integrated velocity history), so that a resumed run (``resume=true``) continues bit for bit:
    #   rollout_memory() -> dict[str, Tensor]          after a step: what the next step needs
    #   restore_rollout_memory(state, memory) -> None  after reset(state, history): take it back
    # Without them a resumed run calls reset(state, history) with the states before the checkpoint.
    #
    # Optional, for the memory check before a CPU rollout (lagfluid.tasks.config.check_run_memory):
    #   memory_needed(state) -> float   peak bytes a rollout from state needs (lagfluid.memory.rollout_bytes
    #                                   with the simulator's neighbour radius and measured bytes per pair)
    # Without it the run is estimated as MPS is.
    #
    # Optional, for exact stages after the step (model.exact_after, lagfluid.models.exact_after):
    #   amend_last_step(before, after) -> None  the state step(before) returned was replaced by ``after``:
    #                                           update what the next step reads beyond the state (GNS:
    #                                           its velocity history); required with rollout_memory
    #   last_step_learned: bool                 False after a step that is not the model's own (GNS's MPS
    #                                           warm start): the stages leave it as it is; absent: True


_REQUIRED = (
    "name",
    "dt",
    "history_length",
    "max_courant",
    "parameters",
    "last_timings",
    "last_info",
    "last_fields",
)


def check_simulator(simulator: object, origin: str) -> Simulator:
    """Return ``simulator`` if it implements :class:`Simulator`, else raise naming what it lacks.

    Args:
        simulator: what a registered factory returned.
        origin: where it came from (the model name), for the message.

    Raises:
        ConfigError: a missing attribute or method, or a bad ``dt``/``history_length``/``max_courant``.
    """
    missing = [a for a in (*_REQUIRED, "reset", "step", "attributes") if not hasattr(simulator, a)]
    if missing:
        raise ConfigError(
            f"model '{origin}' built a {type(simulator).__name__} that lacks {', '.join(missing)} "
            "(see lagfluid.models.simulator.Simulator)"
        )
    dt, history = simulator.dt, simulator.history_length
    if dt is not None and not (isinstance(dt, (int, float)) and not isinstance(dt, bool) and dt > 0):
        raise ConfigError(f"model '{origin}': dt must be a time step > 0 (s) or None, got {dt!r}")
    limit = simulator.max_courant
    if limit is not None and not (
        isinstance(limit, (int, float)) and not isinstance(limit, bool) and limit > 0
    ):
        raise ConfigError(f"model '{origin}': max_courant must be a number > 0 or None, got {limit!r}")
    if not (isinstance(history, int) and history >= 0):
        raise ConfigError(f"model '{origin}': history_length must be an integer >= 0, got {history!r}")
    return simulator  # type: ignore[return-value]
