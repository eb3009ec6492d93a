"""The model's rollout of an evaluation, with the one-step errors of the steps that made its stored frames.

A one-step error compares what a stage of the model returned with the exact stage *at the same input*
(paper Table 4): the rollout's ``on_step`` hook hands over the state before the step and the step's declared
intermediates (:class:`~lagfluid.physics.step_context.SplitStepFields`); a simulator without such stages (an
end-to-end model) has none and its one-step errors are NaN.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from lagfluid.data.store import TrajectoryWriter, stored_dtype
from lagfluid.errors import RolloutError
from lagfluid.metrics import normalized_mae
from lagfluid.models.simulator import Simulator
from lagfluid.neighbors.verlet import VerletNeighborList
from lagfluid.physics.mps import ExactAdvection
from lagfluid.physics.reference import exact_context, mps_constants, mps_neighbor_list, ppe_relative_residual
from lagfluid.physics.settings import MPSConstants, SolverSettings
from lagfluid.physics.step_context import SplitStepFields
from lagfluid.rollout import rollout
from lagfluid.state import ParticleState
from lagfluid.tasks.config import run_attributes, run_guard
from lagfluid.tasks.simulate import timing_summary

log = logging.getLogger(__name__)


def one_step_errors(
    before: ParticleState,
    fields: Any,
    settings: SolverSettings,
    constants: MPSConstants,
    neighbors: VerletNeighborList,
) -> tuple[float, float]:
    """Advection nMAE (eq. 32) and PPE relative residual (eq. 31) of one step (NaN where not applicable).

    Args:
        before: the state the step started from.
        fields: the step's recorded intermediates; only :class:`SplitStepFields` carry stage outputs.
        settings: the exact MPS stages' settings.
        constants: their constants for this scene.
        neighbors: a neighbour list kept across calls (exact at any positions; rebuilds as needed).
    """
    nmae = residual = math.nan
    if not isinstance(fields, SplitStepFields):
        return nmae, residual
    if fields.advection_acceleration is not None:
        ctx = exact_context(before, settings, constants, neighbors)
        exact = ExactAdvection()(ctx, before.pos, before.vel)
        nmae = normalized_mae(fields.advection_acceleration, exact)
    if fields.pressure_unclamped is not None and fields.pos_collided is not None:
        nf = before.n_fluid
        pos, vel = before.pos.clone(), before.vel.clone()
        pos[:nf], vel[:nf] = fields.pos_collided, fields.vel_collided
        at_pressure = ParticleState(pos=pos, vel=vel, ptype=before.ptype, params=before.params, check=False)
        ctx = exact_context(at_pressure, settings, constants, neighbors)
        residual = ppe_relative_residual(ctx, fields.pressure_unclamped)
    return nmae, residual


def run_model(
    cfg: DictConfig,
    simulator: Simulator,
    state: ParticleState,
    out: Path,
    one_step: bool,
    history: Sequence[ParticleState] = (),
    reset: bool = True,
) -> dict[str, Any]:
    """Roll the model out into ``out`` (rollout.h5) and collect its one-step errors per stored frame.

    With ``reset`` the rollout first calls ``simulator.reset(state, history)`` (``history``:
    :func:`lagfluid.tasks.config.initial_history`); pass False when the caller has reset it already.

    Returns:
        ``complete``, ``stop_reason``, ``steps`` done, ``timing`` (median time per step and per stage as
        ``task=simulate`` reports them, and ``steps_total_s``, the wall time of all steps done) and
        per-frame ``step``, ``advection_nmae`` and ``ppe_relative_residual`` lists (the frames whose step
        recorded intermediates).
    """
    settings = SolverSettings.from_config(cfg.solver)
    guard = run_guard(cfg, simulator)
    steps, write_every = int(cfg.steps), int(cfg.write_every)
    nf = state.n_fluid
    writer = TrajectoryWriter(
        out,
        nf,
        state.pos[nf:].cpu().numpy(),
        state.ptype[nf:].cpu().numpy(),
        run_attributes(state, cfg, simulator.name, str(cfg.scene.name), write_every),
        dtype=stored_dtype(state),
    )
    constants = mps_constants(state, settings)
    neighbors = mps_neighbor_list(state, settings)  # one list for every frame: it rebuilds only as needed
    result: dict[str, Any] = {"step": [], "advection_nmae": [], "ppe_relative_residual": []}
    first = state.step

    def makes_stored_frame(s: ParticleState) -> bool:
        # the same frames the rollout stores: k = 1..steps with k % write_every == 0, and the last
        k = s.step - first + 1
        return k % write_every == 0 or k == steps

    def on_step(before: ParticleState, after: ParticleState, fields: Any) -> None:
        if fields is None:
            return
        nmae, res = one_step_errors(before, fields, settings, constants, neighbors)
        result["step"].append(after.step)
        result["advection_nmae"].append(nmae)
        result["ppe_relative_residual"].append(res)

    complete, stop_reason, record = True, "", {"step_seconds": []}
    try:
        _, record = rollout(
            simulator,
            state,
            steps,
            guard=guard,
            write_every=write_every,
            on_frame=writer.append_state,
            on_step=on_step if one_step else None,
            # Recording copies the intermediates: only when the one-step errors need them, so that timed
            # runs (evaluate.one_step=false) measure the simulator alone.
            record_when=makes_stored_frame if one_step else None,
            history=history,
            progress=bool(cfg.progress),
            reset=reset,
        )
    except RolloutError as err:  # the model blew up: evaluate what it wrote
        complete, stop_reason = False, str(err)
        record = getattr(err, "record", record)
        log.warning("model %s stopped: %s", simulator.name, err)
    except BaseException as err:
        writer.close(complete=False, stop_reason=f"{type(err).__name__}: {err}")
        raise
    writer.set_attributes(simulator.attributes())
    writer.close(complete=complete, stop_reason=stop_reason)
    record.setdefault("stage_seconds", {})
    record.setdefault("info", {})
    timing = {**timing_summary(record), "steps_total_s": float(sum(record["step_seconds"]))}
    return {
        **result,
        "complete": complete,
        "stop_reason": stop_reason,
        "steps": len(record["step_seconds"]),
        "timing": timing,
    }
