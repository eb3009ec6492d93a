"""Retrain every shipped learned model on the current dataset: ``python -m lagfluid.retrain [overrides]``.

One Hydra multirun over every ``experiment/retrain_*.yaml`` of the core and of the plugins (FGN, the
Table 5 ablations, GNS, CConv: each a ``task=train`` job with its shipped profile and an ``export_to`` of
its shipped weights' folder), one job after another (``hydra.launcher.n_jobs=1``: two torch trainings on
one CPU slow each other down). The sweep's total wall time lands in ``<sweep dir>/multirun_time.json``
(:mod:`lagfluid.tasks.multirun_timer`); each job's ``<name>_loss.csv`` has its own.

Extra arguments are Hydra overrides for every job (``data=paper``, ``threads=2``, ``device=cuda``); an
``experiment=a,b`` of your own picks a subset. Rerunning the same command resumes every job from its
checkpoints and skips the finished ones (then only re-exports). Run it from the repository root: the
``export_to`` folders are relative to it.

Why a module rather than ``-m 'experiment=glob(retrain_*)'``: Hydra's glob sweep only lists the primary
config path's options, not the plugins' folders (added through ``hydra.searchpath``), so GNS and CConv would
silently drop out.
"""

from __future__ import annotations

import shlex
import subprocess
import sys
from collections.abc import Sequence

PREFIX = "retrain_"


def retrain_experiments() -> list[str]:
    """Names of every ``retrain_*`` experiment (core and plugins), sorted."""
    from lagfluid.run import _group_names

    return [name for name in _group_names("experiment") if name.startswith(PREFIX)]


def retrain_arguments(overrides: Sequence[str]) -> list[str]:
    """The ``lagfluid.run`` arguments of the retrain sweep, with the user's ``overrides`` last."""
    chosen = any(arg.split("=", 1)[0].lstrip("+~") == "experiment" for arg in overrides)
    sweep = [] if chosen else [f"experiment={','.join(retrain_experiments())}"]
    return ["-m", *sweep, "hydra.launcher.n_jobs=1", *overrides]


def main() -> None:
    """Entry point of ``python -m lagfluid.retrain``: runs the sweep as ``python -m lagfluid.run -m ...``."""
    args = retrain_arguments(sys.argv[1:])
    sys.stderr.write(f"python -m lagfluid.run {shlex.join(args)}\n")
    # a child process: it starts without torch loaded, so threads=N reaches OpenMP (lagfluid.run.limit_openmp)
    sys.exit(subprocess.run([sys.executable, "-m", "lagfluid.run", *args], check=False).returncode)


if __name__ == "__main__":
    main()
