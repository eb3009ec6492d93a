"""Name -> simulator and name -> trainables registries.

Built-ins are named in this module; plugins (``baselines/`` and third-party packages) register through
the entry-point groups ``lagfluid.simulators`` and ``lagfluid.trainables``, so ``lagfluid`` never imports
them; :func:`register_simulator` and :func:`register_trainables` register in-process (tests). Scenes are
looked up in :data:`lagfluid.scenes.SCENES`.

Factories are called as ``factory(cfg)`` with the resolved Hydra config (an ``omegaconf.DictConfig``). A
simulator factory returns an object implementing :class:`lagfluid.models.simulator.Simulator`; a
trainables factory, registered under the model's name, returns ``{name: trainable}`` (each implementing
:class:`lagfluid.models.trainable.Trainable`), the networks ``task=train`` trains for that model.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from importlib import import_module, metadata
from typing import Any

from lagfluid.errors import LagfluidError

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "lagfluid.simulators"
TRAINABLES_GROUP = "lagfluid.trainables"

SimulatorFactory = Callable[[Any], Any]
TrainablesFactory = Callable[[Any], dict[str, Any]]

# Built-ins are named here as "module:attribute" and imported only when used, so importing the registry
# (e.g. to validate a command line) stays cheap.
_BUILTIN: dict[str, str] = {
    "mps": "lagfluid.models.mps_simulator:build_mps",
    "fgn": "lagfluid.models.fgn.simulator:build_split_step",
    "hybrid": "lagfluid.models.fgn.simulator:build_split_step",
    "fgn_original": "lagfluid.models.fgn.simulator:build_split_step",
    "fgn_trained_here": "lagfluid.models.fgn.simulator:build_split_step",
    "fgn_gcn": "lagfluid.models.fgn.simulator:build_split_step",
    "fgn_sage": "lagfluid.models.fgn.simulator:build_split_step",
    "fgn_mlp": "lagfluid.models.fgn.simulator:build_split_step",
}
_REGISTERED: dict[str, SimulatorFactory] = {}
# model=hybrid trains the same three networks as model=fgn (its config holds their options too); the
# Table 5 ablations train their advection and pressure nets, their reference fgn_trained_here its pressure
# net (model.trains).
_BUILTIN_TRAINABLES: dict[str, str] = {
    "fgn": "lagfluid.models.fgn.trainables:build_trainables",
    "hybrid": "lagfluid.models.fgn.trainables:build_trainables",
    "fgn_trained_here": "lagfluid.models.fgn.trainables:build_trainables",
    "fgn_gcn": "lagfluid.models.fgn.trainables:build_trainables",
    "fgn_sage": "lagfluid.models.fgn.trainables:build_trainables",
    "fgn_mlp": "lagfluid.models.fgn.trainables:build_trainables",
}
_REGISTERED_TRAINABLES: dict[str, TrainablesFactory] = {}


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


def _entry_points(group: str = ENTRY_POINT_GROUP) -> dict[str, metadata.EntryPoint]:
    return {ep.name: ep for ep in metadata.entry_points(group=group)}


class PluginError(LagfluidError):
    """A plugin's entry point that cannot be loaded; the message names the plugin, its group and target."""


def _load_entry_point(ep: metadata.EntryPoint) -> Any:
    """``ep.load()``, with a failure (a missing module, a typo in the target) named in one line."""
    try:
        return ep.load()
    except Exception as err:  # whatever the plugin's import raises
        raise PluginError(
            f"plugin '{ep.name}' ({ep.group} = {ep.value!r}) cannot be loaded: {type(err).__name__}: {err}"
        ) from err


def _load(target: str) -> Any:
    module, attr = target.split(":")
    return getattr(import_module(module), attr)


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
        return _load(_BUILTIN[name])
    eps = _entry_points()
    if name in eps:
        return _load_entry_point(eps[name])
    raise UnknownNameError(f"unknown model '{name}'; available: {', '.join(available_simulators())}")


def register_trainables(model: str) -> Callable[[TrainablesFactory], TrainablesFactory]:
    """Decorator registering a trainables ``factory`` for ``model`` (overrides built-ins and plugins)."""

    def wrap(factory: TrainablesFactory) -> TrainablesFactory:
        _REGISTERED_TRAINABLES[model] = factory
        return factory

    return wrap


def trainable_models() -> list[str]:
    """Sorted names of the models that have trainables (``task=train`` accepts them)."""
    return sorted(
        set(_BUILTIN_TRAINABLES) | set(_REGISTERED_TRAINABLES) | set(_entry_points(TRAINABLES_GROUP))
    )


def get_trainables_factory(model: str) -> TrainablesFactory:
    """Return the trainables factory of ``model``.

    Raises:
        UnknownNameError: ``model`` has no trainables (message lists the models that have).
    """
    if model in _REGISTERED_TRAINABLES:
        return _REGISTERED_TRAINABLES[model]
    if model in _BUILTIN_TRAINABLES:
        return _load(_BUILTIN_TRAINABLES[model])
    eps = _entry_points(TRAINABLES_GROUP)
    if model in eps:
        return _load_entry_point(eps[model])
    raise UnknownNameError(
        f"model '{model}' has nothing to train (task=train); models with trainables: "
        f"{', '.join(trainable_models())}"
    )


def get_trainables(model: str, cfg: Any) -> dict[str, Any]:
    """``{name: trainable}`` of ``model`` built from ``cfg`` (in the model's own order).

    Raises:
        UnknownNameError: ``model`` has no trainables.
        LagfluidError: the factory returned none.
    """
    trainables = dict(get_trainables_factory(model)(cfg))
    if not trainables:
        raise LagfluidError(f"model '{model}' registers no trainables")
    return trainables


def available_scenes() -> list[str]:
    """Sorted names of the declarative scenes."""
    from lagfluid.scenes import SCENES

    return sorted(SCENES)


def check_scene_name(name: str) -> None:
    """Raise :class:`UnknownNameError` when ``name`` is not a scene."""
    if name not in available_scenes():
        raise UnknownNameError(f"unknown scene '{name}'; available: {', '.join(available_scenes())}")
