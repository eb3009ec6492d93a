"""The MPS reference rollout of an evaluation: its key, its cache, and computing it."""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path
from typing import Any

import h5py
import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

import lagfluid
from lagfluid.data.store import TrajectoryFileError, open_lagfluid_file
from lagfluid.errors import ConfigError, RolloutError
from lagfluid.physics.settings import solver_identity
from lagfluid.plugin_configs import CONF_DIR
from lagfluid.tasks.config import scene_params
from lagfluid.tasks.evaluate.options import EvaluateOptions
from lagfluid.tasks.locks import lock_path, wait_for_lock
from lagfluid.tasks.simulate import simulate

log = logging.getLogger(__name__)


def _file_digest(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def reference_key(cfg: DictConfig) -> dict[str, Any]:
    """What the MPS reference rollout depends on: the resolved scene, solver, dt, steps, output and precision.

    Also the lagfluid version (a release may change the solver) and, for ``scene=file``, the SHA-256 of the
    grid file (the same path may hold another grid later).
    """
    scene = OmegaConf.to_container(cfg.scene, resolve=True)
    key: dict[str, Any] = {
        "scene": scene,
        "solver": solver_identity(OmegaConf.to_container(cfg.solver, resolve=True)),
        "dt": scene_params(cfg).dt,
        "steps": int(cfg.steps),
        "write_every": int(cfg.write_every),
        "dtype": str(cfg.dtype),
        "device": torch.device(str(cfg.device)).type,  # CPU and CUDA runs differ in round-off
        "lagfluid_version": lagfluid.__version__,
    }
    path = scene.get("path") if isinstance(scene, dict) else None
    if path and Path(str(path)).is_file():
        key["scene_file_sha256"] = _file_digest(Path(str(path)))
    return key


def _key_json(key: dict[str, Any]) -> str:
    return json.dumps(key, sort_keys=True, default=str)


def key_hash(key: dict[str, Any]) -> str:
    """12 hex digits of the SHA-256 of the key's canonical JSON (the cache folder's suffix)."""
    return hashlib.sha256(_key_json(key).encode()).hexdigest()[:12]


def expected_frames(steps: int, write_every: int) -> int:
    """Frames a complete rollout stores: ``0, k, 2k, ...`` and the last step."""
    return steps // write_every + 1 + (1 if steps % write_every else 0)


def cached_reference_problem(path: Path, key: dict[str, Any], frames: int) -> str | None:
    """Why the file at ``path`` cannot serve as the reference for ``key``, or None when it can."""
    try:
        f = open_lagfluid_file(path, "reference rollout")
    except TrajectoryFileError as err:
        return str(err)
    with f:
        if "00000" not in f:
            return f"{path} has no trajectory group"
        g = f["00000"]
        if not bool(g.attrs.get("complete", False)):
            return f"{path} is incomplete ({g.attrs.get('stop_reason', '')})"
        if g.attrs.get("model") != "mps":
            return f"{path} was made by model {g.attrs.get('model')!r}, not mps"
        if g.attrs.get("reference_key") != _key_json(key):
            return f"{path} was made with another configuration"
        if g["time"].shape[0] != frames or g["position"].shape[0] != frames:
            return f"{path} holds {g['time'].shape[0]} frames, {frames} expected"
        for name, item in g.items():  # read every chunk: a damaged one must not fail every later run
            if isinstance(item, h5py.Dataset):
                try:
                    item[...]
                except (OSError, RuntimeError) as err:
                    return f"{path} has an unreadable dataset {name} ({err})"
    return None


def reference_settings(cfg: DictConfig, overrides: dict[str, Any]) -> DictConfig:
    """The run's config with ``overrides`` (``evaluate.reference``) merged over it: what the reference uses.

    Raises:
        ConfigError: an override names a key the config does not have (struct mode).
    """
    if not overrides:
        return cfg
    merged = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    OmegaConf.set_struct(merged, True)
    try:
        return OmegaConf.merge(merged, overrides)
    except OmegaConfBaseException as err:  # an unknown key or a bad type: name the bad value
        raise ConfigError(f"evaluate.reference={overrides!r} does not fit the config: {err}") from err


def reference_config(cfg: DictConfig, out_dir: Path) -> DictConfig:
    """``cfg`` with ``model=mps`` and ``task=simulate`` writing to ``out_dir`` (struct mode kept)."""
    plain = OmegaConf.to_container(cfg, resolve=True)
    plain["model"] = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "model" / "mps.yaml"), resolve=True)
    plain["task"] = "simulate"
    plain["out_dir"] = str(out_dir)
    ref = OmegaConf.create(plain)
    OmegaConf.set_struct(ref, True)
    return ref


def reference_rollout(cfg: DictConfig, options: EvaluateOptions) -> tuple[Path, bool, dict[str, Any]]:
    """The MPS reference rollout for ``cfg``: reused from the cache when valid, else computed.

    Returns:
        The path of its ``rollout.h5``, whether it was reused, and its key.

    Raises:
        RolloutError: the MPS run stopped (guard); the message says how.
    """
    cfg = reference_settings(cfg, options.reference)
    key = reference_key(cfg)
    folder = options.reference_dir / f"{cfg.scene.name}-{key_hash(key)}"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "rollout.h5"
    frames = expected_frames(int(cfg.steps), int(cfg.write_every))
    # One evaluation computes a reference, the others with its key wait for it (the log says for whom); not
    # the folder's own lock, which the reference's task=simulate takes.
    with wait_for_lock(lock_path(folder, "reference"), "evaluate", f"the MPS reference in {folder}"):
        if options.reuse_reference:
            problem = cached_reference_problem(path, key, frames) if path.exists() else "none cached"
            if problem is None:
                log.info("reusing the MPS reference %s", path)
                return path, True, key
            log.info("computing the MPS reference in %s (%s)", folder, problem)
        try:
            simulate(reference_config(cfg, folder))
        except RolloutError as err:
            raise RolloutError(f"the MPS reference stopped, nothing to compare with: {err}") from err
        # Stamped only after a complete run: a file without it (a crash in between) is never reused.
        with h5py.File(path, "a") as f:
            f["00000"].attrs["reference_key"] = _key_json(key)
    return path, False, key
