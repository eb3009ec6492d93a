"""The range of scene parameters a network was trained on, and the warning when a rollout leaves it.

A learned stage extrapolates outside the time step, spacing, gravity and viscosity of its training data
(FGN at nu = 0.1 m^2/s, water-trained pressure net: 8x MPS's peak pressure, 4.5x its density error, with no
sign in the run). Every checkpoint records ``meta["range"]`` (``{quantity: [low, high]}``: the training
split's ``dt``, ``l0``, ``|g|``, ``nu``; a trainable that draws its own materials, FGN's advection net,
records those ranges); a simulator built from such checkpoints logs one warning per quantity outside.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from lagfluid.data.datasets import load_metadata
from lagfluid.state import SceneParams

log = logging.getLogger(__name__)

UNITS = {"dt": "s", "l0": "m", "gravity": "m/s^2", "viscosity": "m^2/s"}
_TOLERANCE = 1e-6  # relative: a value equal to a bound up to rounding is inside


def training_range(
    data_dirs: Sequence[str | Path], identity: Mapping[str, Any], quantities: Sequence[str] = tuple(UNITS)
) -> dict[str, list[float]]:
    """``{quantity: [low, high]}`` over the train splits of ``data_dirs`` (with resampled materials: theirs).

    Args:
        data_dirs: the datasets a network trained on (``data.out_dir`` and ``train.extra_data``).
        identity: the training run's identity (:func:`lagfluid.tasks.train.train_one`); ``materials`` with
            ``resample`` true replaces the scenes' gravity and viscosity by the drawn ranges.
        quantities: the ones that matter to the network (a trainable's ``range_quantities``: FGN's
            collision net learns from collision-only systems without gravity or viscosity).
    """
    values: dict[str, list[float]] = {key: [] for key in UNITS}
    for data_dir in data_dirs:
        meta = load_metadata(data_dir)
        values["dt"].append(float(meta["dt"]))
        values["l0"].append(float(meta["l0"]))
        for scene in meta.get("scenes", []):
            if scene.get("split") == "train":
                values["gravity"].append(math.hypot(*scene["gravity"]))
                values["viscosity"].append(float(scene["viscosity"]))
    ranges = {key: [min(v), max(v)] for key, v in values.items() if v}
    materials = identity.get("materials") or {}
    if materials.get("resample"):
        ranges["gravity"] = [float(g) for g in materials["gravity"]]
        ranges["viscosity"] = [float(n) for n in materials["viscosity"]]
    return {key: value for key, value in ranges.items() if key in quantities}


def range_from_checkpoint_meta(
    meta: Mapping[str, Any], quantities: Sequence[str] = tuple(UNITS)
) -> dict[str, list[float]] | None:
    """``meta["range"]``, else rebuilt from the run's recorded data folder and identity (None if gone).

    Only ``quantities`` are kept: a network that steps by its own time (GNS's frame, CConv's 20 ms) was
    trained on data of another solver dt, which its recorded range holds.
    """
    if meta.get("range"):
        return {key: list(value) for key, value in meta["range"].items() if key in quantities}
    data_dir, identity = meta.get("data_dir"), meta.get("identity")
    if not data_dir or not identity or not (Path(str(data_dir)) / "metadata.json").is_file():
        return None
    identity = json.loads(identity) if isinstance(identity, str) else dict(identity)
    extra = [d["dir"] for d in identity.get("extra_data", [])]
    return training_range([str(data_dir), *extra], identity, quantities)


def outside_range(
    ranges: Mapping[str, Sequence[float]], params: SceneParams
) -> dict[str, tuple[float, list[float]]]:
    """``{quantity: (scene value, [low, high])}`` for every quantity of ``params`` outside ``ranges``."""
    scene = {
        "dt": params.dt,
        "l0": params.l0,
        "gravity": math.hypot(*params.gravity),
        "viscosity": params.viscosity,
    }
    out = {}
    for key, (low, high) in ranges.items():
        value = scene.get(key)
        if value is not None and not (low * (1 - _TOLERANCE) <= value <= high * (1 + _TOLERANCE)):
            out[key] = (value, [low, high])
    return out


def range_warnings(model: str, networks: Mapping[str, Mapping[str, Any]], params: SceneParams) -> list[str]:
    """One line per quantity outside a network's training range: the value, the range, the network."""
    lines = []
    for kind, source in networks.items():
        for key, (value, (low, high)) in outside_range(source.get("range") or {}, params).items():
            span = f"{low:.3g}" if low == high else f"[{low:.3g}, {high:.3g}]"
            lines.append(
                f"model {model}: the {kind} network was trained on {key} {span} {UNITS[key]}; this scene has "
                f"{value:.3g}: expect larger errors than its model card states"
            )
    return lines


class RangeWarner:
    """Logs each line of :func:`range_warnings` once per simulator (a simulator is reset per rollout).

    Args:
        model: the model's name, for the message.
        networks: ``{network: {"range": {quantity: [low, high]}, ...}}`` (a network without a range is
            never warned about).
    """

    def __init__(self, model: str, networks: Mapping[str, Mapping[str, Any]]) -> None:
        self.model, self.networks = model, networks
        self._said: set[str] = set()

    def check(self, params: SceneParams) -> None:
        """Warn (once each) about the parameters of ``params`` outside a network's training range."""
        for line in range_warnings(self.model, self.networks, params):
            if line not in self._said:
                self._said.add(line)
                log.warning("%s", line)
