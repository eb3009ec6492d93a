"""The paper's tables and figures, and the speed/accuracy trade-off, regenerated from real runs.

Usage::

    python -m benchmarks.tables                  # full profile (prints its estimated runtime first)
    python -m benchmarks.tables --quick          # reduced profile, < 5 min; writes tables_quick_* files
    python -m benchmarks.tables --quick --readme --weights runs/train/fgn-cpu --threads 1
    python -m benchmarks.tables --only table2 tradeoff
    python -m benchmarks.tables --quick --simulators gns_unroll   # one model's rows beside MPS and FGN

``--simulators KEY ...`` runs only those simulators' rows beside MPS and FGN in Tables 1-3, 5 and the
trade-off (what a plugin's author checks a model with; Table 4, Fig. 5 and the trade-off's MPS variants run
as always) and writes them under their own prefix (``tables_quick_gns_unroll_*``, the keys in the tables'
order), never over the whole zoo's files or the README.

Every row is a Hydra experiment file (``conf/experiment/<name>.yaml``: ``python -m lagfluid.run
experiment=table3_dam_fgn`` runs that row alone at the full profile); this script composes them in-process
(Hydra's compose API) and runs them one after another in one process, so every timing is taken under the
same conditions. A profile adds overrides (scene, steps, frames, dt) to each row; every row's complete
override list is written beside its numbers. Accuracy rows run ``task=evaluate``
(:mod:`lagfluid.tasks.evaluate`: the model and the MPS reference from the same initial state, metrics per
stored frame), so every number comes from :mod:`lagfluid.metrics`.

The simulators compared are the registered ones plus their row files (``table2_<key>``,
``table3_<case>_<key>``, each with a ``table: {label, order, weights, note}`` block; a key appears in the
tables it has row files for, so a key with only ``table2_<key>`` is a timing row): adding a simulator is a
registry entry and its row files, nothing here (:mod:`benchmarks.tables.simulators`).

Modules, one job each: :mod:`~benchmarks.tables.simulators` (which simulators, their labels),
:mod:`~benchmarks.tables.profiles` (full and quick sizes, runtime estimate), :mod:`~benchmarks.tables.config`
(composing rows, overrides), :mod:`~benchmarks.tables.bench` (running rows once each),
:mod:`~benchmarks.tables.rows` (CSV rows and table cells), :mod:`~benchmarks.tables.parts` (the five parts),
:mod:`~benchmarks.tables.plots` (figures), :mod:`~benchmarks.tables.report` (files, ``--only`` merges,
README), :mod:`~benchmarks.tables.cli` (the command line).

Parts (``--only``):

* ``table3`` (paper Tables 1 and 3): density error, divergence (mean/max over the frames) and Chamfer
  distance to MPS (mean/max, mm) on the dam collapse and the water fall, for every simulator; MPS
  is the "Ground truth" row (its own density error and divergence).
* ``table2``: trainable parameters, median time per step, neighbour search and the rest ("inference") at
  ~40k fluid particles (``scene=dam_large``), every simulator in this process; warm-up steps excluded,
  at least a simulator's ``history_length`` + 1 (its start-up, e.g. a warm start by MPS, is never timed);
  a row file may time fewer steps (``table.timing_steps``: a network too slow at that size).
* ``table4``: the advection net's normalised MAE (eq. 32) on held-out gravity and viscosity (paper: ten
  sequences, g in [1, 100] m/s^2, nu in [1e-4, 0.1] m^2/s) and the pressure net's PPE relative residual
  (eq. 31), mean +- standard deviation.
* ``table5``: the paper's aggregator ablation: FGN's node-focused nets with GCN, SAGE (mean) or no
  aggregation (``model=fgn_gcn``, ``fgn_sage``, ``fgn_mlp``, rows ``table5_<case>_<key>``) beside their
  reference, FGN with every net trained here (``fgn_trained_here``, the same recipe, ``train=table5``, and
  pressure net architecture), and Table 3's FGN and MPS rows, same metrics (shipped weights:
  ``lagfluid/weights/fgn_*``).
* ``fig5``: FGN's Chamfer distance to MPS against time for dt from 0.5 ms up, until the rollout guard stops
  a run (the largest dt that completes is reported).
* ``tradeoff``: wall seconds per simulated second against accuracy (Chamfer distance to the reference MPS,
  density error) for every simulator, hybrids, FGN at other dt, and MPS at looser PPE tolerances, larger
  dt and a coarser resolution; the Pareto front is marked (:mod:`benchmarks.pareto`).

Outputs (``benchmarks/results/``, prefix ``tables`` or ``tables_quick``): ``<prefix>_report.md`` (every
table, the provenance and each row's overrides), ``<prefix>_parts.json`` (the rendered parts, so that an
``--only`` rerun replaces its parts and keeps the others, each saying when it ran),
``<prefix>_{table3,table2,table4,table5,fig5,tradeoff}.csv``,
``<prefix>_{fig5,tradeoff}.png``, ``<prefix>_fig4_dam_fgn.png`` and ``<prefix>_fig6_dam_fgn.png`` (paper
Figs. 4 and 6 for FGN on the dam). The full profile also rewrites the README's results tables (between
``<!-- tables:start -->`` and ``<!-- tables:end -->``); ``--readme`` makes any profile do so. Rollouts
go to ``runs/tables/<profile>/`` and MPS references to ``runs/tables/reference/`` (not committed).
"""
