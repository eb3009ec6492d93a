"""Load the FGN authors' published weights (``fgn_original/checkpoints``) into our modules.

Their files are plain arrays named as in their ``state_dict`` (``adv_net.npz``, ``col_net.npz``,
``prs_net.npz``) plus the mean and variance of each standard scaler (``*.scalers.json``). Our modules
keep their layout (see :mod:`lagfluid.models.fgn.networks`), so loading is a rename table, checked
strictly: a missing, extra or mis-shaped array is an error naming it. Their architecture is
``conf/model/fgn_original.yaml`` (identity activations in the node networks: their ``nn.LeakyReLU(True)``
sets ``negative_slope=1``).

The directory is a config value (``model.weights``); the package ships their published networks in
``lagfluid/weights/fgn_original`` (MIT, with their licence and a model card), the default.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from lagfluid.models.checkpoint import CheckpointError, MissingWeightsError
from lagfluid.models.fgn.networks import build_network

FILES = {"advection": "adv_net", "collision": "col_net", "pressure": "prs_net"}
# Parts of their collision layer that their forward pass computes but never uses (the node update).
_UNUSED = re.compile(r"mp_layers\.\d+\.1\.(edge_mlp|node_linear2|msg_linear)\.")
_RENAMES = (
    (re.compile(r"^(mp_layers\.\d+\.1)\.node_mlp\."), r"\1.mlp."),
    (re.compile(r"^(mp_layers\.\d+\.1)\.node_linear1\."), r"\1.node_linear."),
)


def _their_arrays(kind: str, directory: Path) -> dict[str, np.ndarray]:
    path = directory / f"{FILES[kind]}.npz"
    if not path.is_file():
        raise MissingWeightsError(f"authors' {kind} weights not found: {path} (model.weights={directory})")
    try:
        with np.load(path) as data:
            return {k: data[k] for k in data.files}
    except Exception as err:
        raise CheckpointError(f"cannot read {path}: {type(err).__name__}: {err}") from err


_SCALERS = {"advection": ("vel_scaler", "acc_scaler"), "pressure": ("vel_scaler", "dns_scaler", "prs_scaler")}


def _scalers(kind: str, directory: Path) -> dict[str, dict[str, list[float]]]:
    path = directory / f"{FILES[kind]}.scalers.json"
    if kind == "collision":
        return {}  # their collision net takes raw m/s and has no scaler
    if not path.is_file():
        raise MissingWeightsError(f"authors' {kind} scalers not found: {path}")
    try:
        scalers = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise CheckpointError(f"{path}: not readable JSON ({type(err).__name__}: {err})") from None
    for name in _SCALERS[kind]:  # each {"mean": [...], "var": [...]} of finite numbers, var > 0
        entry = scalers.get(name) if isinstance(scalers, dict) else None
        try:
            mean, var = (np.asarray(entry[key], dtype=np.float64) for key in ("mean", "var"))  # type: ignore[index]
            fine = mean.shape == var.shape and mean.ndim == 1 and np.isfinite(mean).all() and (var > 0).all()
        except (TypeError, KeyError, ValueError):
            fine = False
        if not fine:
            raise CheckpointError(
                f'{path}: \'{name}\' must be {{"mean": [...], "var": [...]}} of finite numbers with var > 0, '
                f"got {str(entry)[:120]}"
            )
    return scalers


def _set(standardizer: nn.Module, scaler: dict[str, list[float]]) -> None:
    standardizer.set(scaler["mean"], np.sqrt(np.asarray(scaler["var"], dtype=np.float64)))


def original_state_dict(kind: str, net: nn.Module, directory: Path) -> dict[str, torch.Tensor]:
    """Their arrays renamed onto ``net``'s parameter names (node nets sit under ``net.``)."""
    state: dict[str, torch.Tensor] = {}
    for name, array in _their_arrays(kind, directory).items():
        if _UNUSED.search(name):
            continue
        for pattern, repl in _RENAMES:
            name = pattern.sub(repl, name)
        state[name if kind == "collision" else f"net.{name}"] = torch.from_numpy(np.asarray(array))
    return state


def load_original_network(kind: str, options: dict[str, Any], directory: str | os.PathLike) -> nn.Module:
    """Build ``kind`` with ``options`` (their sizes) and load their weights and scalers.

    Raises:
        CheckpointError: a missing file, or arrays that do not fit the configured architecture (the
            message names the parameters).
    """
    directory = Path(directory)
    net = build_network(kind, options)
    state = original_state_dict(kind, net, directory)
    own = net.state_dict()
    params = {k for k in own if not k.endswith((".mean", ".std"))}
    missing, extra = sorted(params - set(state)), sorted(set(state) - params)
    wrong = sorted(k for k in set(state) & params if tuple(state[k].shape) != tuple(own[k].shape))
    if missing or extra or wrong:
        raise CheckpointError(
            f"authors' {kind} weights in {directory} do not fit model.{kind}: missing {missing}, "
            f"unexpected {extra}, wrong shape {wrong}"
        )
    net.load_state_dict(state, strict=False)
    scalers = _scalers(kind, directory)
    if kind == "advection":
        _set(net.speed, scalers["vel_scaler"])
        _set(net.target, scalers["acc_scaler"])
    elif kind == "pressure":
        _set(net.speed, scalers["vel_scaler"])
        _set(net.density, scalers["dns_scaler"])
        _set(net.target, scalers["prs_scaler"])
    return net.eval()


# the trainables' statistics (meta["stats"]) and the standardizers that hold them, per network
_STAT_MODULES = {
    "advection": {"speed": "speed", "target": "target"},
    "pressure": {"speed": "speed", "density": "density", "target": "target"},
}
# What the authors' pressure net was trained on (their code, the paper's A.2: water, l0 = 0.05 m, dt = 2 ms,
# g = 9.8065 m/s^2): recorded so a rollout outside it warns (lagfluid/models/training_range.py), as for a
# net trained here. Their advection net's range of g and nu is not published: none is recorded.
_TRAINED_ON = {
    "pressure": {
        "dt": [0.002, 0.002],
        "l0": [0.05, 0.05],
        "gravity": [9.8065, 9.8065],
        "viscosity": [1e-06, 1e-06],
    }
}


def original_checkpoint(kind: str, options: dict[str, Any], directory: str | os.PathLike) -> dict[str, Any]:
    """The authors' ``kind`` network as a lagfluid checkpoint of ``model=fgn`` (fine-tuning, mixing).

    ``options``: their architecture (``conf/model/fgn_original.yaml``'s section ``kind``). The result is a
    :func:`~lagfluid.models.checkpoint.save_checkpoint` payload whose statistics are their scalers, so a
    ``train.init_from`` or ``train.onpolicy.start_from`` folder holding it fine-tunes their network, and
    ``model=fgn`` runs it (a checkpoint's own options win over the config's).

    Raises:
        CheckpointError: see :func:`load_original_network`; ``kind`` is their collision net, whose raw
            m/s encoding is not lagfluid's (``model.collision``): there is nothing to convert it to.
    """
    from lagfluid.models.checkpoint import network_payload

    if kind not in _STAT_MODULES:
        raise CheckpointError(
            f"the authors' {kind} net has no lagfluid checkpoint form; convert advection or pressure"
        )
    net = load_original_network(kind, options, directory)
    stats = {  # as the trainables' fit_statistics write them: scalars, or lists per component
        name: [getattr(net, module).mean.squeeze().tolist(), getattr(net, module).std.squeeze().tolist()]
        for name, module in _STAT_MODULES[kind].items()
    }
    meta = {"stats": stats, "converted_from": f"{Path(directory).name}/{FILES[kind]}.npz"}
    if kind in _TRAINED_ON:
        meta["range"] = _TRAINED_ON[kind]
    return network_payload(net, kind, options, 0, meta, model="fgn")


CONVERTIBLE = tuple(_STAT_MODULES)
"""The authors' networks that have a lagfluid checkpoint form (their collision net does not)."""


def write_checkpoints(directory: str | os.PathLike, out: str | os.PathLike | None = None) -> list[Path]:
    """Write ``<out>/advection.pt`` and ``pressure.pt``: the authors' nets in ``directory`` converted.

    ``out`` defaults to ``directory`` (the package ships them beside the arrays, the start of
    ``experiment=retrain_fgn``'s pressure net). Options: ``conf/model/fgn_original.yaml``.
    """
    import yaml

    from lagfluid.models.checkpoint import save_checkpoint

    conf = Path(__file__).resolve().parents[2] / "conf" / "model" / "fgn_original.yaml"
    options = yaml.safe_load(conf.read_text())
    out = Path(out or directory)
    written = []
    for kind in CONVERTIBLE:
        save_checkpoint(out / f"{kind}.pt", original_checkpoint(kind, options[kind], directory))
        written.append(out / f"{kind}.pt")
    return written


if __name__ == "__main__":  # python -m lagfluid.models.fgn.original lagfluid/weights/fgn_original
    import logging
    import sys

    if len(sys.argv) != 2:
        sys.exit("usage: python -m lagfluid.models.fgn.original DIR (their .npz and .scalers.json files)")
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        written = write_checkpoints(sys.argv[1])
    except CheckpointError as err:  # a folder without their files: the message, not a traceback
        sys.exit(str(err))
    for path in written:
        logging.getLogger(__name__).info("wrote %s", path)
