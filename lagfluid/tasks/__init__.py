"""The tasks ``python -m lagfluid.run task=<name>`` runs, with their config and output handling.

Each ``task=<name>`` is ``lagfluid/tasks/<name>`` (a module or a folder): :mod:`~lagfluid.tasks.simulate`,
:mod:`~lagfluid.tasks.generate`, :mod:`~lagfluid.tasks.train`, :mod:`~lagfluid.tasks.evaluate`,
:mod:`~lagfluid.tasks.export`. Beside them, what those tasks share or own: a run's setup from its config
(:mod:`~lagfluid.tasks.config`), its output files and locks (:mod:`~lagfluid.tasks.outputs`,
:mod:`~lagfluid.tasks.locks`), ``resume=true`` (:mod:`~lagfluid.tasks.simulate_resume`), training's rounds
(:mod:`~lagfluid.tasks.onpolicy_rounds`, :mod:`~lagfluid.tasks.dagger_rounds`,
:mod:`~lagfluid.tasks.dagger_eval`), torchrun (:mod:`~lagfluid.tasks.distributed`) and the multirun timer
Hydra calls back (:mod:`~lagfluid.tasks.multirun_timer`). The commands stay at ``lagfluid/``'s root:
``python -m lagfluid.run`` and ``python -m lagfluid.retrain``.

The tasks import every layer below them and nothing imports a task but the commands (and the benchmarks):
``tests/test_layers.py`` checks it (docs/architecture.md#layers).
"""
