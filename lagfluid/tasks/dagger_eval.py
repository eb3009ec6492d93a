"""What each DAgger round bought: the model's rollout of the dam, complete or the step the guard stopped it.

After each round of :mod:`lagfluid.tasks.dagger_rounds` (and for its starting weights, round 0),
``task=simulate`` rolls the round's weights out on ``train.dagger.dam_scene`` (``dam``, the scene every model
stops on) for ``train.dagger.dam_steps`` steps (125 of GNS's 8 ms: the 1 s dam), exactly as
``python -m lagfluid.run model=gns scene=dam model.weights=<round folder>`` would, into
``<out_dir>/dagger/round<k>/dam/`` (``rollout.h5``, ``metrics.json``, ``preview.png``). Its result is kept in
``dam.json`` there (a rerun with the same weights, scene and steps skips the rollout) and every round's
in ``<out_dir>/dagger/dam.csv``: ``round, complete, steps, steps_requested, stop_reason, density_error_mean,
weights``.
"""

from __future__ import annotations

import copy
import csv
import io
import json
import logging
import os
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict

from lagfluid.errors import ConfigError, RolloutError
from lagfluid.plugin_configs import CONF_DIR
from lagfluid.tasks.outputs import write_json

log = logging.getLogger(__name__)

COLUMNS = ("round", "complete", "steps", "steps_requested", "stop_reason", "density_error_mean", "weights")


def scene_config(name: str) -> DictConfig:
    """The ``scene=<name>`` group config of ``conf/scene/`` (its ``defaults`` from the same group merged).

    Raises:
        ConfigError: no such scene file.
    """
    folder = CONF_DIR / "scene"
    path = folder / f"{name}.yaml"
    if not path.is_file():
        names = ", ".join(sorted(p.stem for p in folder.glob("*.yaml")))
        raise ConfigError(f"train.dagger.dam_scene={name}: no such scene; available: {names}")
    node = OmegaConf.load(path)
    defaults = [str(d) for d in node.pop("defaults", None) or []]
    merged = OmegaConf.create()
    for entry in defaults if "_self_" in defaults else [*defaults, "_self_"]:  # Hydra: _self_ last if absent
        merged = OmegaConf.merge(merged, node if entry == "_self_" else scene_config(entry))
    return merged


def _rollout_config(cfg: DictConfig, weights: Path, scene: str, steps: int, out: Path) -> DictConfig:
    """``cfg`` as ``task=simulate model.weights=<weights> scene=<scene> steps=<steps> out_dir=<out>``."""
    ev = copy.deepcopy(cfg)
    with open_dict(ev):
        ev.task = "simulate"
        ev.scene = scene_config(scene)
        ev.steps = steps
        ev.dt = None  # the model's own
        ev.model.weights = str(weights)
        ev.out_dir = str(out)
        ev.resume = False
        ev.export = None
    return ev


def dam_result(cfg: DictConfig, k: int, weights: Path, scene: str, steps: int, out: Path) -> dict[str, Any]:
    """Round ``k``'s rollout of ``scene`` with the weights in ``weights`` (cached in ``out/dam.json``)."""
    record = out / "dam.json"
    if record.is_file():
        kept = json.loads(record.read_text())
        if (kept["weights"], kept["scene"], kept["steps_requested"]) == (str(weights), scene, steps):
            return kept
    from lagfluid.tasks.simulate import simulate

    try:
        metrics = simulate(_rollout_config(cfg, weights, scene, steps, out))
    except RolloutError:  # the guard's stop is the result: metrics.json says where and why
        metrics = json.loads((out / "metrics.json").read_text())
    result = {
        "round": k,
        "complete": bool(metrics["complete"]),
        "steps": int(metrics["steps"]),
        "steps_requested": steps,
        "stop_reason": str(metrics["stop_reason"]),
        "density_error_mean": (metrics.get("density_error") or {}).get("mean"),
        "weights": str(weights),
        "scene": scene,
    }
    tmp = record.with_name(record.name + ".part")
    write_json(tmp, result)
    os.replace(tmp, record)
    how = (
        "complete"
        if result["complete"]
        else f"stopped after {result['steps']} steps ({result['stop_reason']})"
    )
    log.info("DAgger round %d: %s, %d steps: %s", k, scene, steps, how)
    return result


def write_summary(path: Path, results: list[dict[str, Any]]) -> None:
    """``dam.csv``: one row per round's result (:data:`COLUMNS`), written atomically."""
    text = io.StringIO()
    writer = csv.DictWriter(text, COLUMNS, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    writer.writerows(results)
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(text.getvalue())
    os.replace(tmp, path)
