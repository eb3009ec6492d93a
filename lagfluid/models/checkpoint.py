"""Network checkpoints: one file per network, tensors and plain values only.

A checkpoint is a ``dict`` saved with :func:`torch.save` that :func:`torch.load` reads back with
``weights_only=True`` (no pickled code is ever executed)::

    format        "lagfluid-network"
    version       1
    kind          "advection" | "collision" | "pressure"
    options       the network's constructor options (so the file rebuilds its own architecture)
    state_dict    weights and normalisation statistics (the Standardizer buffers)
    step          training iterations done
    meta          free-form provenance: data, training profile, time, package version, ...
    optimizer, scheduler   (training checkpoints only) to resume exactly

Writes are atomic: a temporary file in the same directory, then a rename.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch
from torch import nn

from lagfluid.errors import LagfluidError
from lagfluid.models.fgn import AdvectionNet, CollisionNet, PressureNet

CHECKPOINT_FORMAT = "lagfluid-network"
KINDS = ("advection", "collision", "pressure")
_NODE_NET_KEYS = ("width", "layers", "act", "aggregation", "encoder_hidden", "decoder_hidden")


class CheckpointError(LagfluidError):
    """A checkpoint that is missing, unreadable, of another format or of another network."""


def build_network(kind: str, options: dict[str, Any]) -> nn.Module:
    """A fresh network of ``kind`` from its options (the ``model.<kind>`` config node as a dict)."""
    opts = {k: v for k, v in dict(options).items() if v is not None}
    try:
        if kind == "collision":
            return CollisionNet(**opts)
        net_opts = {k: opts.pop(k) for k in _NODE_NET_KEYS if k in opts}
        if kind == "advection":
            return AdvectionNet(**opts, **net_opts)
        if kind == "pressure":
            return PressureNet(**opts, **net_opts)
    except TypeError as err:  # an unknown option name
        raise CheckpointError(f"invalid options for the {kind} network: {err}") from err
    raise CheckpointError(f"unknown network kind '{kind}'; available: {', '.join(KINDS)}")


def save_checkpoint(path: str | os.PathLike, payload: dict[str, Any]) -> None:
    """Write ``payload`` (see the module doc) atomically to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    torch.save({"format": CHECKPOINT_FORMAT, "version": 1, **payload}, tmp)
    os.replace(tmp, path)


def network_payload(net: nn.Module, kind: str, options: dict[str, Any], step: int, meta: dict) -> dict:
    """The checkpoint fields of a network (no optimizer state)."""
    return {
        "kind": kind,
        "options": dict(options),
        "state_dict": {k: v.detach().cpu() for k, v in net.state_dict().items()},
        "step": int(step),
        "meta": dict(meta),
    }


def read_checkpoint(path: str | os.PathLike, kind: str | None = None) -> dict[str, Any]:
    """Load a checkpoint dict (``weights_only=True``), checking its format and, if given, its kind.

    Raises:
        CheckpointError: missing file, unreadable or foreign content, or another kind of network.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises many types for corrupt or foreign files
        raise CheckpointError(f"cannot read checkpoint {path}: {type(err).__name__}: {err}") from err
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT or ckpt.get("version") != 1:
        raise CheckpointError(
            f"{path} is not a lagfluid network checkpoint (format {CHECKPOINT_FORMAT!r} v1)"
        )
    if kind is not None and ckpt.get("kind") != kind:
        raise CheckpointError(f"{path} holds a {ckpt.get('kind')!r} network, expected {kind!r}")
    return ckpt


def load_network(path: str | os.PathLike, kind: str | None = None) -> tuple[nn.Module, dict[str, Any]]:
    """Rebuild the network saved in ``path`` with its own options and weights.

    Returns:
        The network (CPU, eval mode) and the checkpoint dict.
    """
    ckpt = read_checkpoint(path, kind)
    net = build_network(ckpt["kind"], ckpt["options"])
    try:
        net.load_state_dict(ckpt["state_dict"])
    except RuntimeError as err:
        raise CheckpointError(f"{path}: weights do not fit its own options: {err}") from err
    return net.eval(), ckpt


def export_weights(run_dir: str | os.PathLike, dest_dir: str | os.PathLike) -> list[Path]:
    """Copy the three networks of a training run without optimizer and RNG state (shipping size).

    ``python -m lagfluid.models.checkpoint RUN_DIR DEST_DIR`` does the same from the shell.
    """
    written = []
    for kind in KINDS:
        ckpt = read_checkpoint(Path(run_dir) / f"{kind}.pt", kind)
        keep = {k: ckpt[k] for k in ("kind", "options", "state_dict", "step", "meta")}
        save_checkpoint(Path(dest_dir) / f"{kind}.pt", keep)
        written.append(Path(dest_dir) / f"{kind}.pt")
    return written


if __name__ == "__main__":
    import sys

    if len(sys.argv) != 3:
        sys.exit("usage: python -m lagfluid.models.checkpoint RUN_DIR DEST_DIR")
    for path in export_weights(sys.argv[1], sys.argv[2]):
        sys.stdout.write(f"{path} ({path.stat().st_size / 1e3:.0f} kB)\n")
