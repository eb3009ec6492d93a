"""One rollout loop for every simulator: steps, the guard, timing, and hooks for what a task keeps.

The loop neither writes files nor computes metrics: the tasks (:mod:`lagfluid.tasks.simulate`,
:mod:`lagfluid.tasks.generate`, :mod:`lagfluid.tasks.evaluate`) pass ``on_frame`` (every stored frame: write
it, measure it) and ``on_step`` (every step, with the state before and after and, on the steps ``record_when``
picks, the simulator's declared intermediates: training samples, one-step errors).

The guard stops a run with a :class:`~lagfluid.errors.RolloutError` naming the step, the particle and the
value (NaN/inf, a fluid particle leaving the domain, a Courant number above the limit); the exception
carries what was measured up to then.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from statistics import median
from typing import Any

import torch

from lagfluid.errors import ConfigError, RolloutError
from lagfluid.models.simulator import Simulator
from lagfluid.progress import progress_bar
from lagfluid.state import ParticleState

StepHook = Callable[[ParticleState, ParticleState, Any], None]
"""``on_step(before, after, fields)``: called after every accepted step; ``fields`` is the simulator's
``last_fields`` on the steps ``record_when`` picked, else None."""


@dataclass(frozen=True)
class Guard:
    """Run-time checks of a rollout.

    Attributes:
        max_courant: largest allowed ``max|v| dt / l0``.
        check_every: check every k steps (the last step is always checked).
    """

    max_courant: float = 0.5
    check_every: int = 1

    def __post_init__(self) -> None:
        """Refuse settings that would divide by zero or never pass."""
        if (
            isinstance(self.check_every, bool)
            or not isinstance(self.check_every, int)
            or self.check_every < 1
        ):
            raise ConfigError(
                f"solver.guard.check_every must be a whole number >= 1, got {self.check_every!r}"
            )
        if not (isinstance(self.max_courant, (int, float)) and self.max_courant > 0):
            raise ConfigError(f"solver.guard.max_courant must be > 0, got {self.max_courant!r}")

    def check(self, state: ParticleState) -> None:
        """Raise :class:`RolloutError` when ``state`` is non-finite, outside its domain or too fast."""
        if self._passes(state):
            return
        nf, step = state.n_fluid, state.step
        for name, values in (("position", state.pos[:nf]), ("velocity", state.vel[:nf])):
            bad = ~torch.isfinite(values).all(dim=1)
            if bool(bad.any()):
                i = int(torch.nonzero(bad)[0, 0])
                raise RolloutError(
                    f"step {step}: fluid particle {i} has a non-finite {name} {values[i].tolist()} "
                    f"({int(bad.sum())} particles affected); the simulation blew up - try a smaller dt "
                    f"(now {state.params.dt})",
                    kind="non_finite",
                )
        outside = state.fluid_outside_bounds()
        if outside.numel():
            i = int(outside[0])
            raise RolloutError(
                f"step {step}: fluid particle {i} left the domain at {state.pos[i].tolist()} "
                f"(domain {state.bounds[0].tolist()} .. {state.bounds[1].tolist()}; "
                f"{outside.numel()} particles outside); check the walls of the scene or reduce dt "
                f"(now {state.params.dt})",
                kind="left_domain",
            )
        i = int(state.vel[:nf].norm(dim=1).argmax())
        speed = float(state.vel[i].double().norm())  # float64: |v| = 1e30 overflows float32 when squared
        courant = speed * state.params.dt / state.params.l0
        if courant > self.max_courant:
            start = " (the scene's initial velocity)" if step == 0 else ""
            raise RolloutError(
                f"step {step}: Courant number {courant:.3g} at fluid particle {i} "
                f"(|v| = {speed:.3g} m/s){start} exceeds solver.guard.max_courant={self.max_courant}; "
                f"reduce dt (now {state.params.dt}) "
                f"or raise the limit",
                kind="courant",
            )

    def _passes(self, state: ParticleState) -> bool:
        """True when ``state`` certainly passes :meth:`check`, from one read of the device.

        Each test of :meth:`check` would read the device on its own (on CUDA a host synchronisation each);
        a state that fails any (or comes close to the Courant limit) goes on to :meth:`check`'s tests, which
        name the particle.
        """
        nf = state.n_fluid
        if nf == 0:
            return True
        fluid_pos, fluid_vel = state.pos[:nf], state.vel[:nf]
        # At least float32 (a float16 norm is off by ~5e-4, more than the margin below). |v| overflows float32
        # for finite |v| > 1e19: inf then fails the Courant test below, and check's float64 speed decides.
        speed = fluid_vel.to(torch.promote_types(fluid_vel.dtype, torch.float32)).norm(dim=1).max()
        finite = torch.isfinite(fluid_pos).all() & torch.isfinite(fluid_vel).all()
        ok = finite & ~state.fluid_outside_mask().any()
        ok, max_speed = torch.stack([ok.to(speed.dtype), speed]).tolist()
        # A margin of 1e-6 relative: float32's norm and check's float64 one may differ in the last bits.
        return bool(ok) and max_speed * state.params.dt / state.params.l0 <= self.max_courant * (1 - 1e-6)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def rollout(
    simulator: Simulator,
    state: ParticleState,
    steps: int,
    *,
    guard: Guard | None = None,
    write_every: int = 1,
    on_frame: Callable[[ParticleState], None] | None = None,
    on_step: StepHook | None = None,
    record_when: Callable[[ParticleState], bool] | None = None,
    history: Sequence[ParticleState] = (),
    progress: bool = False,
    reset: bool = True,
    step_offset: int = 0,
    record: dict[str, Any] | None = None,
) -> tuple[ParticleState, dict[str, Any]]:
    """Advance ``state`` by ``steps`` steps of ``simulator``.

    Args:
        simulator: any :class:`Simulator`.
        state: initial state (frame 0, handed to ``on_frame`` first).
        steps: number of steps.
        guard: run-time checks (default :class:`Guard`); every state handed to ``on_frame`` is checked first.
        write_every: k: ``on_frame`` sees frames ``0, k, 2k, ...`` and the last one.
        on_frame: optional ``f(state)`` for every such frame (write it, measure it).
        on_step: optional :data:`StepHook` called after every accepted step.
        record_when: optional ``f(state) -> bool`` on the state a step starts from: ask the simulator to
            record that step's intermediates (handed to ``on_step``). None: never (timed runs stay clean).
        history: earlier states for ``simulator.reset`` (oldest first), e.g. frames before a trajectory's
            frame ``t`` when the rollout starts there.
        progress: show progress (a tqdm bar on a terminal, else a log line every 10 %).
        reset: call ``simulator.reset(state, history)`` first; pass False to continue a rollout in segments
            (warm neighbour list and PPE start).
        step_offset: steps a resumed run took before ``state``: its frames and guard checks fall on the
            same steps as one uninterrupted run's, and ``state`` (stored then) is not handed to ``on_frame``.
        record: the record to extend (a resumed run's so far); None: a new one. ``on_frame`` may read it.

    Returns:
        The final state and a record with per-step wall times, per-stage times and diagnostics. Any exception
        raised during the loop carries that record as ``err.record`` and the last state that passed the
        guard as ``err.state``.
    """
    guard = guard or Guard()
    if steps < 0:
        raise RolloutError(f"steps must be >= 0, got {steps}")
    if write_every < 1:
        raise RolloutError(f"write_every must be >= 1, got {write_every}")
    if record is None:
        record = {"step_seconds": [], "stage_seconds": {}, "info": {}}
    try:  # the start too: a Courant number far past the limit (|v| = 1e30) fails inside the first step
        guard.check(state)
    except RolloutError as err:
        err.record, err.state = record, state  # type: ignore[attr-defined]
        raise
    if reset:
        simulator.reset(state, history)

    bar = progress_bar(
        step_offset + steps, enabled=progress, initial=step_offset, desc=simulator.name, unit="step"
    )
    try:
        if on_frame is not None and step_offset == 0:
            on_frame(state)
        for k in range(1, steps + 1):
            keep_fields = record_when is not None and record_when(state)
            _sync(state.device)
            start = time.perf_counter()
            new = simulator.step(state, record=keep_fields)
            _sync(state.device)
            elapsed = time.perf_counter() - start
            done = step_offset + k
            write = done % write_every == 0 or k == steps
            if write or done % guard.check_every == 0:
                guard.check(new)
            # only steps whose result was accepted are counted
            record["step_seconds"].append(elapsed)
            for name, sec in simulator.last_timings.items():
                record["stage_seconds"].setdefault(name, []).append(sec)
            for name, value in simulator.last_info.items():
                record["info"].setdefault(name, []).append(value)
            if on_step is not None:
                on_step(state, new, simulator.last_fields if keep_fields else None)
            state = new
            if write and on_frame is not None:
                on_frame(state)
            bar.update(1)
            if k == 1:  # the first step compiled kernels (a fresh install) and built lists: not in the ETA
                bar.restart_clock()
            if k % 10 == 0:
                bar.set_postfix(ms_per_step=f"{1e3 * median(record['step_seconds'][-10:]):.0f}")
    except BaseException as err:
        err.record, err.state = record, state  # type: ignore[attr-defined]
        raise
    finally:
        bar.close()
    return state, record
