"""What ``task=generate`` makes, read and checked once from the composed config: :class:`DataSpec`."""

from __future__ import annotations

import hashlib
import json
import logging
import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from lagfluid.data.layout import (
    SAMPLES_FORMAT_VERSION,
    SPLITS,
)
from lagfluid.errors import LagfluidError
from lagfluid.physics.settings import solver_identity
from lagfluid.state import SceneParams
from lagfluid.tasks.config import run_device, scene_params
from lagfluid.tasks.generate.policy import policy_identity

log = logging.getLogger(__name__)


def _range(name: str, value: Any, positive: bool) -> tuple[float, float]:
    lo, hi = (float(v) for v in value)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi) or (positive and lo <= 0):
        raise LagfluidError(
            f"{name} must be [low, high] with low <= high{' and low > 0' if positive else ''}"
        )
    return lo, hi


def draw(rng: np.random.Generator, lo: float, hi: float, log_uniform: bool) -> float:
    """One value in ``[lo, hi]``: log-uniform or uniform."""
    if log_uniform:
        return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
    return float(rng.uniform(lo, hi))


@dataclass(frozen=True)
class DataSpec:
    """Everything ``task=generate`` needs, read and checked once from the composed config.

    Attributes:
        name: profile name.
        out_dir: dataset directory.
        num_scenes: number of scenes.
        steps: solver steps per scene.
        sample_every: k: frames and samples every k-th step.
        next_steps: K: also store the fluid positions of the K solver steps after each sample (0: none).
        seed: scene k is built with ``seed + k``.
        scene_index: only this scene (multirun), or None for all.
        splits: fraction of the scenes per split.
        builder: scene builder name.
        scene_options: builder options shared by every scene (``seed`` is set per scene when the scene
            takes one).
        params: physical parameters before the per-scene materials.
        materials: ``vary``, ``gravity`` and ``viscosity`` ranges, ``log_uniform``.
        collision: collision-system settings.
        solver: the ``solver`` config as a plain dict.
        dtype: floating dtype of the simulation.
        device: torch device.
        policy: None when the MPS solver moves the particles; else what moves them in an on-policy dataset
            (``data.policy=model``: the model, its stages, its network files' hashes;
            :mod:`lagfluid.tasks.generate.policy`).
        on_fluid_leaving: ``"error"``: an MPS scene stopped by a fluid particle leaving the domain fails;
            ``"keep"``: it is kept as a shorter scene (the steps before the stop). Non-finite values and the
            Courant limit always fail.
    """

    name: str
    out_dir: Path
    num_scenes: int
    steps: int
    sample_every: int
    next_steps: int
    seed: int
    scene_index: int | None
    splits: dict[str, float]
    builder: str
    scene_options: dict[str, Any]
    params: SceneParams
    materials: dict[str, Any]
    collision: dict[str, Any]
    solver: dict[str, Any]
    dtype: torch.dtype
    device: torch.device
    policy: dict[str, Any] | None = None
    on_fluid_leaving: str = "error"

    @classmethod
    def from_config(cls, cfg: DictConfig) -> DataSpec:
        """Read ``cfg.data``, ``cfg.scene``, ``cfg.solver`` and the top-level overrides."""
        data = OmegaConf.to_container(cfg.data, resolve=True)
        num_scenes, steps, every = int(cfg.num_scenes), int(cfg.steps), int(data["sample_every"])
        for key, value in (("num_scenes", num_scenes), ("steps", steps), ("data.sample_every", every)):
            if value < 1:
                raise LagfluidError(f"{key} must be >= 1, got {value}")
        next_steps = int(data.get("next_steps") or 0)
        if next_steps < 0:
            raise LagfluidError(f"data.next_steps must be >= 0, got {next_steps}")
        seed = int(data["seed"])
        if seed < 0:
            raise LagfluidError(f"data.seed must be >= 0, got {seed}")
        index = data.get("scene_index")
        if index is not None and not 0 <= int(index) < num_scenes:
            raise LagfluidError(f"data.scene_index must be in [0, {num_scenes}), got {index}")
        on_leaving = str(data.get("on_fluid_leaving") or "error")
        if on_leaving not in ("error", "keep"):
            raise LagfluidError(f"data.on_fluid_leaving must be 'error' or 'keep', got {on_leaving!r}")
        splits = {k: float(v) for k, v in (data.get("splits") or {}).items()}
        if set(splits) - set(SPLITS) or any(v < 0 for v in splits.values()) or splits.get("train", 0) <= 0:
            raise LagfluidError(
                f"data.splits must map {', '.join(SPLITS)} to fractions >= 0 (train > 0), got {splits}"
            )
        materials = dict(data["materials"])
        _range("data.materials.gravity", materials["gravity"], positive=materials["log_uniform"])
        _range("data.materials.viscosity", materials["viscosity"], positive=materials["log_uniform"])
        collision = dict(data["collision"])
        if int(collision["num_systems"]) < 0 or int(collision["steps"]) < 1:
            raise LagfluidError("data.collision needs num_systems >= 0 and steps >= 1")
        if len(collision["block"]) != 3 or min(int(b) for b in collision["block"]) < 1:
            raise LagfluidError(f"data.collision.block must be 3 positive ints, got {collision['block']}")
        _range("data.collision.spacing", collision["spacing"], positive=True)
        _range("data.collision.speed", collision["speed"], positive=True)
        scene = OmegaConf.to_container(cfg.scene, resolve=True)
        options = {k: v for k, v in scene.items() if k not in ("name", "builder", "params")}
        options.update(data.get("scene_options") or {})
        params = scene_params(cfg)
        if cfg.dt is None and data.get("dt") is not None:
            params = params.with_overrides(dt=float(data["dt"]))
        dtype = {"float32": torch.float32, "float64": torch.float64}.get(cfg.dtype)
        if dtype is None:
            raise LagfluidError(f"unknown dtype '{cfg.dtype}'; available: float32, float64")
        return cls(
            name=str(data["name"]),
            out_dir=Path(data["out_dir"]),
            num_scenes=num_scenes,
            steps=steps,
            sample_every=every,
            next_steps=next_steps,
            seed=seed,
            scene_index=None if index is None else int(index),
            splits=splits,
            builder=str(cfg.scene.get("builder") or cfg.scene.name),
            scene_options=options,
            params=params,
            materials=materials,
            collision=collision,
            solver=OmegaConf.to_container(cfg.solver, resolve=True),
            dtype=dtype,
            device=run_device(cfg),
            policy=policy_identity(cfg),
            on_fluid_leaving=on_leaving,
        )

    @property
    def num_samples(self) -> int:
        """Samples per scene: one at every k-th step before the last, S = ceil(steps / k)."""
        return -(-self.steps // self.sample_every)

    def scene_setup(self, index: int) -> tuple[dict[str, Any], SceneParams, int]:
        """Options, physical parameters (materials drawn when they vary) and seed of scene ``index``."""
        seed = self.seed + index
        options = dict(self.scene_options)
        if "seed" in options:
            options["seed"] = seed
        params = self.params
        if self.materials["vary"]:
            rng = np.random.default_rng([seed, 1])  # a stream of its own: the scene draws from seed alone
            m = self.materials
            g = draw(rng, *m["gravity"], m["log_uniform"])
            nu = draw(rng, *m["viscosity"], m["log_uniform"])
            direction = np.asarray(params.gravity, dtype=np.float64)
            norm = float(np.linalg.norm(direction))
            direction = direction / norm if norm > 0 else np.array([0.0, 0.0, -1.0])
            params = replace(params, gravity=tuple(float(v) for v in g * direction), viscosity=nu)
        return options, params, seed

    def fingerprint(self, index: int) -> str:
        """Hash of everything that determines the content of scene ``index``."""
        options, params, seed = self.scene_setup(index)
        # The guard and the (exact) neighbour backend do not change what a finished file holds.
        solver = {k: v for k, v in solver_identity(self.solver).items() if k not in ("guard", "neighbors")}
        content = {
            "builder": self.builder,
            "options": options,
            "params": asdict(params),
            "seed": seed,
            "steps": self.steps,
            "sample_every": self.sample_every,
            "solver": solver,
            "collision": self.collision,
            "dtype": str(self.dtype),
            "samples_format": SAMPLES_FORMAT_VERSION,
        }
        if self.next_steps:  # only then: the files of datasets without them keep their fingerprints
            content["next_steps"] = self.next_steps
        if self.policy is not None:  # likewise: solver datasets keep theirs
            content["policy"] = self.policy
        return hashlib.sha256(json.dumps(content, sort_keys=True, default=str).encode()).hexdigest()[:16]
