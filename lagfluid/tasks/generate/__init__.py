"""Dataset generation: the MPS solver on seeded scenes, one HDF5 file per scene, then ``metadata.json``.

``python -m lagfluid.run task=generate scene=random data=cpu [num_scenes=N] [steps=N]`` (profiles in
``conf/data/``: ``paper``, ``cpu``, ``tiny``) writes::

    DIR/                                 data.out_dir (default data/<profile>)
      scenes/scene_00007.h5              scene k, built with seed data.seed + k (layout below)
      metadata.json                      once every scene is there: splits, statistics, provenance

Each scene is independent, so Hydra multirun parallelises generation (joblib launcher)::

    python -m lagfluid.run -m task=generate scene=random data=cpu threads=1 'data.scene_index=range(0,12)'
    python -m lagfluid.run task=generate scene=random data=cpu     # finishes missing scenes, metadata

With ``data.scene_index`` set a job makes only that scene; the job that finds every scene present writes
``metadata.json`` (so a complete sweep needs no second command; the plain run is harmless and resumes).
``threads=1`` keeps each job on one core (the joblib launcher runs one job per core).

**Resume.** Frames and samples go to ``scene_00007.h5.part``; the file is renamed to ``scene_00007.h5``
(atomic) only when the scene is complete. A rerun skips finished scenes, regenerates missing ones and
overwrites leftover ``.part`` files, so an interrupted generation never duplicates or corrupts a scene.
Each file carries a *fingerprint* of everything that determines its content (scene options and seed,
physical parameters, steps, sampling, solver and collision settings); a finished file with another
fingerprint is an error rather than silently mixed into the dataset. A scene stopped by the rollout guard
(NaN, Courant number, a particle leaving the tank) is kept as ``scene_00007.failed.h5`` for inspection;
the other scenes still run and the generation then fails naming it. With ``data.on_fluid_leaving=keep``
(``data=paper``) a scene stopped by a fluid particle leaving the domain (a splash over the rim of the open
tank) is kept instead as a shorter scene, its ``stopped_at_step`` and ``stop_reason`` in the file and in
``metadata.json``: the authors' runs delete such particles and go on, a file of fixed particle count ends.

The scene-file layout is :mod:`lagfluid.data.layout`'s; the statistics in ``metadata.json`` are
:mod:`lagfluid.data.statistics`' and describe the data (a network's normalisation is fitted by its
trainable and lives in its checkpoint). Modules: :mod:`~lagfluid.tasks.generate.spec` (the settings),
:mod:`~lagfluid.tasks.generate.scene` (one scene file), :mod:`~lagfluid.tasks.generate.collision` (the
collision-only systems), :mod:`~lagfluid.tasks.generate.metadata` and :mod:`~lagfluid.tasks.generate.task`.
"""

from __future__ import annotations

from lagfluid.tasks.generate.collision import collision_system
from lagfluid.tasks.generate.metadata import write_metadata
from lagfluid.tasks.generate.scene import generate_scene
from lagfluid.tasks.generate.spec import DataSpec
from lagfluid.tasks.generate.task import generate

__all__ = ["DataSpec", "collision_system", "generate", "generate_scene", "write_metadata"]
