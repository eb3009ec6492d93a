"""Physical validation of the MPS ground-truth solver against analytic answers and experiments.

``python -m benchmarks.validate_mps [--quick]`` runs six checks and writes ``benchmarks/results/
validate_mps.md`` and ``.csv`` (``validate_mps_quick.*`` with ``--quick``) plus PNG figures next to them,
with provenance (date, machine, versions, git commit, command, runtime). Every check prints PASS/FAIL
(or INFO) with the measured number and the criterion; the exit status is 1 when any check fails.

1. hydrostatic pressure of a resting column (slope of p(z) in the interior vs rho g, bottom pressure);
2. free fall without walls (exact discrete kinematics, first-order error vs x0 + g t^2/2, p = 0);
3. mass conservation (fluid count constant, no fluid particle beyond the inner wall layers, every run);
4. density error and velocity divergence of the resting tank (``lagfluid.metrics``) vs the paper's
   MPS ground-truth values (FGN Table 1: density error 0.038, divergence 0.019);
5. the authors' dam collapse (``dam_col_4k.npz``, 300 steps of 2 ms): no leak, no blow-up, PPE converged,
   surge front vs Martin & Moyce (1952) and Koshizuka & Oka (1996);
6. dt robustness: a small dam at dt = 1, 2, 4 ms.

The solver is run as the project runs it (``conf/solver/mps.yaml``, scene dtype float32), never tuned here;
``--profile NAME`` validates another solver profile (``conf/solver/NAME.yaml``, e.g. ``mps_corrected``) and
``--solver key=value ...`` a configured variant (e.g. ``pressure_gradient=corrected``), each into its own
report (``validate_mps_mps_corrected.*``, ``validate_mps_pressure_gradient_corrected.*``).

Modules, one job each: :mod:`~benchmarks.validate_mps.common` (the report row, the run log, the solver
under test, the monitored rollout, the metrics), :mod:`~benchmarks.validate_mps.hydrostatic` (checks 1 and
4), :mod:`~benchmarks.validate_mps.free_fall` (check 2), :mod:`~benchmarks.validate_mps.mass` (check 3),
:mod:`~benchmarks.validate_mps.dam` (checks 5 and 6), :mod:`~benchmarks.validate_mps.report` (provenance and
the .md/.csv files), :mod:`~benchmarks.validate_mps.cli` (the command line).
"""
