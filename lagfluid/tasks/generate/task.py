"""``task=generate``: the missing scenes (or one, in a multirun), then ``metadata.json``."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import Any

from omegaconf import DictConfig

from lagfluid.data.layout import (
    METADATA_FILE,
    SPLITS,
    scene_path,
    split_counts,
)
from lagfluid.errors import LagfluidError
from lagfluid.tasks.config import apply_threads
from lagfluid.tasks.generate.metadata import write_metadata
from lagfluid.tasks.generate.scene import generate_scene, scene_done
from lagfluid.tasks.generate.spec import DataSpec
from lagfluid.tasks.locks import hold_outputs

log = logging.getLogger(__name__)


def generate(cfg: DictConfig) -> dict[str, Any] | None:
    """``task=generate``: make the missing scenes (or only ``data.scene_index``), then ``metadata.json``.

    Returns:
        the metadata once every scene is there, else None (other multirun jobs are still working).

    Raises:
        LagfluidError: bad settings, a scene file from another configuration, or scenes stopped by the guard
            (named; the others are still generated).
    """
    apply_threads(cfg)
    spec = DataSpec.from_config(cfg)
    if "seed" not in spec.scene_options:
        log.warning(
            "scene '%s' takes no seed: every scene starts alike (use scene=random for the paper's data)",
            spec.builder,
        )
    split_counts(spec.num_scenes, spec.splits)  # fail on impossible splits before hours of simulation
    start = time.perf_counter()
    todo: Sequence[int] = range(spec.num_scenes) if spec.scene_index is None else [spec.scene_index]
    log.info(
        "generating %s of %d scenes (%d steps, samples every %d) into %s",
        "all" if spec.scene_index is None else f"scene {spec.scene_index}",
        spec.num_scenes,
        spec.steps,
        spec.sample_every,
        spec.out_dir,
    )
    scenes = scene_path(spec.out_dir, 0).parent
    # each scene is locked, not the folder: a multirun's jobs (data.scene_index) make theirs side by side
    with hold_outputs(scenes, "generate", [scene_path(spec.out_dir, k).stem for k in todo], "data.out_dir"):
        return _generate_scenes(cfg, spec, todo, start)


def _generate_scenes(
    cfg: DictConfig, spec: DataSpec, todo: Sequence[int], start: float
) -> dict[str, Any] | None:
    """:func:`generate` once its scenes ``todo`` are locked: they, then ``metadata.json`` if all are there."""
    failed = []
    for k in todo:
        path = scene_path(spec.out_dir, k)
        if scene_done(path, spec.fingerprint(k)):
            log.info("scene %d: %s is done, skipped", k, path)
            continue
        try:
            generate_scene(cfg, spec, k)
        except LagfluidError as err:
            if spec.scene_index is not None:
                raise
            log.error("%s", err)
            failed.append(str(err))
    if failed:
        raise LagfluidError(f"{len(failed)} scene(s) failed: " + " | ".join(failed))
    missing = [
        k for k in range(spec.num_scenes) if not scene_done(scene_path(spec.out_dir, k), spec.fingerprint(k))
    ]
    if missing:
        log.info("metadata.json waits for scenes %s (other jobs, or rerun task=generate)", missing)
        return None
    meta = write_metadata(spec, time.perf_counter() - start)
    log.info(
        "wrote %s: %d scenes (%s), %d advection/pressure and %d collision training samples",
        spec.out_dir / METADATA_FILE,
        spec.num_scenes,
        ", ".join(f"{s} {meta['counts'][s]['scenes']}" for s in SPLITS),
        meta["counts"]["train"]["advection_samples"],
        meta["counts"]["train"]["collision_samples"],
    )
    return meta
