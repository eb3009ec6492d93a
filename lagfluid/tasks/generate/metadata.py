"""A dataset's ``metadata.json``: splits, counts, statistics of the train split, provenance."""

from __future__ import annotations

import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

import lagfluid
from lagfluid.data.layout import (
    DATASET_FORMAT,
    METADATA_FILE,
    SAMPLES_FORMAT_VERSION,
    SPLITS,
    read_scene_info,
    scene_path,
    split_of,
)
from lagfluid.data.statistics import STATISTICS, dataset_statistics
from lagfluid.physics.settings import SolverSettings
from lagfluid.tasks.config import git_commit
from lagfluid.tasks.generate.spec import DataSpec

log = logging.getLogger(__name__)


def write_json_atomic(path: Path, content: dict[str, Any]) -> None:
    """Write atomically: a per-process temporary file, then rename (parallel jobs may race here)."""
    tmp = path.with_name(f"{path.name}.{os.getpid()}.part")
    tmp.write_text(json.dumps(content, indent=2))
    os.replace(tmp, path)


def write_metadata(spec: DataSpec, generation_seconds: float | None = None) -> dict[str, Any]:
    """Write ``metadata.json`` for the scenes ``0 .. num_scenes-1`` (all must be finished); returns it."""
    infos = [read_scene_info(scene_path(spec.out_dir, k)) for k in range(spec.num_scenes)]
    splits = split_of(spec.num_scenes, spec.splits)
    rel = [str(i.path.relative_to(spec.out_dir)) for i in infos]
    first = infos[0].attrs
    settings = SolverSettings.from_config(spec.solver)
    l0, dim = float(first["l0"]), int(first["dim"])
    bounds = [i.attrs["bounds"] for i in infos if not isinstance(i.attrs.get("bounds"), str)]
    box = None
    if bounds:
        lo = np.min([np.asarray(b)[0] for b in bounds], axis=0)
        hi = np.max([np.asarray(b)[1] for b in bounds], axis=0)
        box = [[float(a), float(b)] for a, b in zip(lo, hi, strict=True)]
    counts = {}
    for split in SPLITS:
        members = [i for i, s in zip(infos, splits, strict=True) if s == split]
        counts[split] = {
            "scenes": len(members),
            "frames": sum(i.frames for i in members),
            "advection_samples": sum(i.samples for i in members),
            "pressure_samples": sum(i.samples for i in members),
            "collision_samples": sum(i.collision_samples for i in members),
        }
    train = [i.path for i, s in zip(infos, splits, strict=True) if s == "train"]
    stats = dataset_statistics(train)
    seconds = [float(i.attrs.get("wall_time_s", 0.0)) for i in infos]
    meta = {
        "format": DATASET_FORMAT,
        "format_version": 1,
        "samples_format_version": SAMPLES_FORMAT_VERSION,
        "name": spec.name,
        "num_scenes": spec.num_scenes,
        "steps": spec.steps,
        "sample_every": spec.sample_every,
        "next_steps": spec.next_steps,
        "write_every": spec.sample_every,
        "sequence_length": infos[0].frames,
        "dt": float(first["dt"]),
        "dim": dim,
        "l0": l0,
        "bounds": box,
        "periodic_boundary_conditions": [False] * dim,
        "default_connectivity_radius": settings.re_laplacian * l0,
        "default_connectivity_radius_note": "re_laplacian * l0: the largest radius of the MPS operators",
        "radii_l0": {
            "density": settings.re_density,
            "gradient": settings.re_gradient,
            "laplacian": settings.re_laplacian,
            "collision": settings.re_collision,
        },
        "n0": float(first["n0"]),
        "n0_lap": float(first["n0_lap"]),
        "lambda": float(first["lambda"]),
        "statistics_split": "train",
        "statistics_features": STATISTICS,
        **stats,
        "splits": {split: [r for r, s in zip(rel, splits, strict=True) if s == split] for split in SPLITS},
        "counts": counts,
        "scenes": [
            {
                "index": k,
                "file": rel[k],
                "split": splits[k],
                "seed": int(i.attrs["seed"]),
                "gravity": [float(g) for g in i.attrs["gravity"]],
                "viscosity": float(i.attrs["viscosity"]),
                "n_fluid": i.n_fluid,
                "n_boundary": i.n_boundary,
                "frames": i.frames,
                "samples": i.samples,
                "collision_samples": i.collision_samples,
                "wall_time_s": seconds[k],
                "step_time_median_s": float(i.attrs.get("step_time_median_s", math.nan)),
                # a shorter scene (a policy's stop, or MPS's with data.on_fluid_leaving=keep): where and why
                **(
                    {
                        "stopped_at_step": int(i.attrs["stopped_at_step"]),
                        "stop_reason": str(i.attrs["stop_reason"]),
                    }
                    if "stopped_at_step" in i.attrs
                    else {}
                ),
            }
            for k, i in enumerate(infos)
        ],
        "scene": {"builder": spec.builder, "options": spec.scene_options},
        "materials": spec.materials,
        "collision": spec.collision,
        "solver": spec.solver,
        "model": "mps" if spec.policy is None else spec.policy["model"],
        # an on-policy dataset's (lagfluid.tasks.generate.policy): what moved the particles
        **({"policy": spec.policy} if spec.policy is not None else {}),
        "version": lagfluid.__version__,
        "git_commit": git_commit(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "generation_time_s": sum(seconds),
        "generation_run_time_s": generation_seconds,
    }
    write_json_atomic(spec.out_dir / METADATA_FILE, meta)
    return meta
