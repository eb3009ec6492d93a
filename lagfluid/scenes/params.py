"""A run's scene parameters from its composed config: what ``scene=`` and ``dt=`` ask for.

Model-neutral and task-free: the tasks build their scenes with it, and a plugin whose simulator factory
needs the scene's time step (GNS sizes an untrained network's statistics by it) takes it from
:mod:`lagfluid.zoo`.
"""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from lagfluid.errors import SceneError
from lagfluid.scenes.trajectory import trajectory_params
from lagfluid.state import SceneParams

__all__ = ["scene_builder", "scene_params"]


def scene_builder(cfg: DictConfig) -> str:
    """The builder of ``cfg.scene`` (:data:`lagfluid.scenes.SCENES`): ``scene.builder``, else its name."""
    return str(cfg.scene.get("builder") or cfg.scene.name)


def scene_params(cfg: DictConfig) -> SceneParams:
    """Physical parameters from ``cfg.scene.params`` with the top-level ``dt`` override applied.

    For ``scene=trajectory`` a null parameter (the config's default) is the trajectory file's value: the
    command-line ``dt=`` wins over ``scene.params.X``, which wins over the file.
    """
    raw = OmegaConf.to_container(cfg.scene.get("params", {}) or {}, resolve=True)
    if scene_builder(cfg) == "trajectory":
        if OmegaConf.is_missing(cfg.scene, "path") or cfg.scene.path is None:
            raise SceneError("scene=trajectory needs scene.path=<a lagfluid trajectory file (.h5)>")
        raw = {**trajectory_params(cfg.scene.path), **{k: v for k, v in raw.items() if v is not None}}
    if "gravity" in raw:
        try:  # a vector; a scalar (scene.params.gravity=9.8) would fail inside SceneParams' checks
            raw["gravity"] = tuple(float(v) for v in raw["gravity"])
        except (TypeError, ValueError):
            raise SceneError(
                "scene.params.gravity must be a vector [gx, gy, gz] in m/s^2, e.g. [0, 0, -9.81]; "
                f"got {raw['gravity']!r}"
            ) from None
    return SceneParams(**raw).with_overrides(dt=cfg.dt)
