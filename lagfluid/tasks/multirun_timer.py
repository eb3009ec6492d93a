"""A Hydra callback that records a multirun's total wall time: ``<sweep dir>/multirun_time.json``.

Registered in ``conf/config.yaml`` (``hydra.callbacks``), so every ``python -m lagfluid.run -m ...`` writes
it; the retrain-everything sweep (``python -m lagfluid.retrain``) reports its total this way. The file
holds the start and end (UTC, ISO 8601), ``wall_s``, the command-line overrides and the sweeper's own
parameters (the jobs' overrides are in each job's ``.hydra/overrides.yaml``). Written atomically once
every job has returned; a sweep stopped by a failing job writes none.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import time
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger(__name__)

FILE_NAME = "multirun_time.json"


def _now() -> str:
    return dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")


class MultirunTimer(Callback):
    """Times a Hydra multirun from ``on_multirun_start`` to ``on_multirun_end`` (main process)."""

    def __init__(self) -> None:
        self._t0: float | None = None
        self._started = ""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Start the clock."""
        self._t0, self._started = time.perf_counter(), _now()

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Write ``multirun_time.json`` into the sweep directory and log the total."""
        if self._t0 is None:
            return
        wall = time.perf_counter() - self._t0
        hydra_cfg = config.hydra
        sweep_dir = Path(str(hydra_cfg.sweep.dir))
        params = hydra_cfg.sweeper.get("params") or {}
        record = {
            "started": self._started,
            "finished": _now(),
            "wall_s": round(wall, 1),
            "overrides": list(hydra_cfg.overrides.task),
            "sweeper_params": OmegaConf.to_container(params, resolve=True) if params else {},
        }
        sweep_dir.mkdir(parents=True, exist_ok=True)
        path = sweep_dir / FILE_NAME
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(record, indent=2) + "\n")
        os.replace(tmp, path)
        log.info("multirun finished in %.0f s (%.1f min): %s", wall, wall / 60, path)
