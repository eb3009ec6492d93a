"""Name -> simulator registry.

Built-in simulators register with :func:`register_simulator`; plugins (``baselines/`` and third-party
packages) register through the ``lagfluid.simulators`` entry-point group, so ``lagfluid`` never imports
them. Scenes are looked up in :data:`lagfluid.scenes.SCENES`.

A factory is called as ``factory(cfg)`` with the resolved Hydra config (an ``omegaconf.DictConfig``) and
returns an object implementing :class:`lagfluid.models.simulator.Simulator`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from importlib import import_module, metadata
from typing import Any

from lagfluid.errors import LagfluidError

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "lagfluid.simulators"

SimulatorFactory = Callable[[Any], Any]

# Built-ins are named here as "module:attribute" and imported only when used, so importing the registry
# (e.g. to validate a command line) stays cheap.
_BUILTIN: dict[str, str] = {
    "mps": "lagfluid.models.mps_simulator:build_mps",
    "fgn": "lagfluid.models.fgn_simulator:build_split_step",
    "hybrid": "lagfluid.models.fgn_simulator:build_split_step",
    "fgn_original": "lagfluid.models.fgn_simulator:build_split_step",
}
_REGISTERED: dict[str, SimulatorFactory] = {}


class UnknownNameError(LagfluidError, KeyError):
    """A model or scene name that is not registered; the message lists the available names."""

    def __str__(self) -> str:
        return str(self.args[0])


def register_simulator(name: str) -> Callable[[SimulatorFactory], SimulatorFactory]:
    """Decorator registering ``factory`` under ``name`` (overrides built-ins and plugins)."""

    def wrap(factory: SimulatorFactory) -> SimulatorFactory:
        _REGISTERED[name] = factory
        return factory

    return wrap


def _entry_points() -> dict[str, metadata.EntryPoint]:
    return {ep.name: ep for ep in metadata.entry_points(group=ENTRY_POINT_GROUP)}


def available_simulators() -> list[str]:
    """Sorted names of every simulator: built-in, registered in this process, or from plugins."""
    return sorted(set(_BUILTIN) | set(_REGISTERED) | set(_entry_points()))


def get_simulator_factory(name: str) -> SimulatorFactory:
    """Return the factory registered as ``name``.

    Raises:
        UnknownNameError: ``name`` is not registered (message lists the available names).
    """
    if name in _REGISTERED:
        return _REGISTERED[name]
    if name in _BUILTIN:
        module, attr = _BUILTIN[name].split(":")
        return getattr(import_module(module), attr)
    eps = _entry_points()
    if name in eps:
        return eps[name].load()
    raise UnknownNameError(f"unknown model '{name}'; available: {', '.join(available_simulators())}")


def available_scenes() -> list[str]:
    """Sorted names of the declarative scenes."""
    from lagfluid.scenes import SCENES

    return sorted(SCENES)


def check_scene_name(name: str) -> None:
    """Raise :class:`UnknownNameError` when ``name`` is not a scene."""
    if name not in available_scenes():
        raise UnknownNameError(f"unknown scene '{name}'; available: {', '.join(available_scenes())}")
