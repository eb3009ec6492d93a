"""Hydra for the tables: composing a row's config in-process, the row files, and building overrides."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig

from lagfluid.errors import ConfigError
from lagfluid.plugin_configs import group_options
from lagfluid.run import CONF_DIR, _register_plugin_configs


def compose_config(overrides: Sequence[str]) -> DictConfig:
    """The lagfluid config for ``overrides`` (as ``python -m lagfluid.run`` composes it, plugins included)."""
    _register_plugin_configs()  # as lagfluid.run.main does: model=<plugin> composes without a model file
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def experiment_names() -> list[str]:
    """Every option of Hydra's ``experiment`` group (``conf/experiment/``, registered nodes, plugins' files).

    A plugin's config folder (``lagfluid.configs``) is on the search path when a row composes, but the
    loader of the compose API does not list its files: they are added from the folders themselves.
    """
    _register_plugin_configs()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        names = set(GlobalHydra.instance().config_loader().get_group_options("experiment"))
    return sorted(names | set(group_options("experiment", CONF_DIR)))


def row_file(name: str) -> str | None:
    """``name`` when ``experiment=<name>`` exists (the row is defined there), else None."""
    return name if name in experiment_names() else None


def steps_in(duration: float, dt: float, what: str) -> int:
    """``duration / dt`` as a whole number of steps.

    Raises:
        ConfigError: ``duration`` is not a multiple of ``dt`` (frames would not fall on common times).
    """
    n = round(duration / dt)
    if n < 1 or abs(n * dt - duration) > 1e-9 * max(1.0, duration):
        raise ConfigError(f"{what}: {duration} s is not a whole number of steps of dt = {dt} s")
    return n


def hydra_value(value: Any) -> str:
    """A Python value as a Hydra override value (nested dicts and lists, null)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, dict):
        return "{" + ",".join(f"{k}:{hydra_value(v)}" for k, v in value.items()) + "}"
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(hydra_value(v) for v in value) + "]"
    return repr(value) if isinstance(value, float) else str(value)


def coarsened_scene(scene: DictConfig, factor: int) -> dict[str, Any]:
    """The same physical dam at ``factor`` times the particle spacing: ``{l0, fluid_size, tank_size}``.

    The built scenes put the inner wall layers on x, y, z = 0 and ``tank_size * l0``, and a particle stands
    for a cube of side l0, so the fluid fills ``fluid_size * l0`` and the tank's inner surfaces are
    ``(tank_size - 1) * l0`` apart. Keeping both (and the wall height, ``2 * fluid_size[2]`` by default)
    gives the same physical scene, shifted by ``(factor - 1) * l0 / 2``, which :mod:`lagfluid.tasks.evaluate`
    undoes when it compares runs at different spacings.

    Raises:
        ConfigError: the scene has no ``fluid_size``/``tank_size`` (not a dam), or they do not divide.
    """
    if "fluid_size" not in scene or "tank_size" not in scene:
        raise ConfigError(f"scene {scene.name} has no fluid_size/tank_size: its resolution cannot be changed")
    fluid, tank = list(scene.fluid_size), list(scene.tank_size)
    if (
        scene.get("wall_height") is not None
        or any(f % factor for f in fluid)
        or any((t - 1) % factor for t in tank)
    ):
        raise ConfigError(
            f"scene {scene.name} (fluid_size {fluid}, tank_size {tank}, "
            f"wall_height {scene.get('wall_height')})"
            f" cannot be coarsened by {factor}: fluid_size and tank_size - 1 must be multiples of it"
        )
    return {
        "l0": float(scene.params.l0) * factor,
        "fluid_size": [f // factor for f in fluid],
        "tank_size": [(t - 1) // factor + 1 for t in tank],
    }
