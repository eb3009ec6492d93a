"""``task=evaluate``: a model against the MPS ground truth, rolled out from the same initial state.

``python -m lagfluid.run task=evaluate model=X scene=Y steps=N`` writes in ``out_dir``
(default ``runs/evaluate/<model>-<scene>``):

* ``rollout.h5``          the model's trajectory (the rollout format of :mod:`lagfluid.data.store`);
* ``metrics.json``        per-frame arrays of every metric, their summaries (mean and max over the run,
  position MSE at fixed horizons), the model's step timings (``timing``: median per step and stage, total)
  and provenance (config, reference file and whether it was reused);
* ``error_vs_time.png``   paper Fig. 4: Chamfer distance, density error, divergence, position MSE, kinetic
  energy and the one-step errors against time, model and MPS;
* ``pressure_slice.png``  paper Fig. 6: a vertical slice through the tank at one frame, model and MPS side
  by side on one colour scale.

**The reference.** MPS (``conf/model/mps.yaml``) with the run's scene, solver, dt, steps, write_every,
dtype and device is rolled out once by ``task=simulate`` into
``<evaluate.reference_dir>/<scene>-<hash>/`` (``rollout.h5``, ``metrics.json``, ``preview.png``), the hash
being that of the resolved key (:func:`reference_key`), which is also stored in the file as the attribute
``reference_key``. A later evaluation with the same key reuses the file only if it is readable, complete,
made by MPS, holds every frame and carries the same key; anything else (another dt, an interrupted run, a
file of another version) is recomputed, never silently used. A lock file serialises concurrent evaluations
of one reference (Hydra multiruns).

**Another reference.** ``evaluate.reference`` holds settings merged over the run's for the reference only
(null by default: the same settings), so a model run at other settings can be compared with MPS at the
defaults, e.g. ``dt=0.004 steps=250`` against ``evaluate.reference={dt:null,steps:500}``, or a coarser
``scene.params.l0`` against the default one. Frames are matched by *time*, not step number. Runs at
different particle spacings are compared in the frame of the boundary surface: the built scenes put the
inner wall layer on x, y, z = 0, so that surface lies half a spacing inside, at ``l0 / 2`` (each rollout
is shifted by ``-l0 / 2`` before the Chamfer distance); position MSE needs corresponding particles and is
NaN when the particle counts differ.

**Per frame** (frames ``0, k, 2k, ..., N`` with ``k = write_every``), :mod:`lagfluid.metrics`:

* ``chamfer_mm``: Chamfer distance model -> MPS (eq. 29) in mm;
* ``position_mse_m2``: LagrangeBench's position MSE per coordinate (particles keep their index);
* ``density_error``, ``velocity_divergence_per_s``: of the model and of MPS;
* ``kinetic_energy_J`` of both and
  ``kinetic_energy_error_rel_peak = |E_model(t) - E_MPS(t)| / max_s E_MPS(s)`` (relative to MPS's peak
  kinetic energy over the compared frames, not to ``E_MPS(t)``: the dam starts at rest);
* one-step errors of the model's step that produced the frame, against the exact stage at the same input
  (paper Table 4; null at frame 0, and for a stage the model does not have):
  ``advection_nmae`` (eq. 32, the advection acceleration against ``g + nu lap(v)``) and
  ``ppe_relative_residual`` (eq. 31, the pressure stage's output in the exact PPE at ``(x**, v**)``).

A model stopped by the rollout guard is a result, not a failure: what it wrote is evaluated and
``complete: false`` with the reason is recorded. A reference that stops is an error.
"""

from __future__ import annotations

from lagfluid.tasks.evaluate.compare import compare
from lagfluid.tasks.evaluate.options import EvaluateOptions
from lagfluid.tasks.evaluate.reference import (
    cached_reference_problem,
    expected_frames,
    key_hash,
    reference_key,
    reference_rollout,
    reference_settings,
)
from lagfluid.tasks.evaluate.task import evaluate

__all__ = [
    "EvaluateOptions",
    "cached_reference_problem",
    "compare",
    "evaluate",
    "expected_frames",
    "key_hash",
    "reference_key",
    "reference_rollout",
    "reference_settings",
]
