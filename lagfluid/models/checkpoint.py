"""Network checkpoints: one file per trained network, tensors and plain values only.

A checkpoint is a ``dict`` saved with :func:`torch.save` that :func:`torch.load` reads back with
``weights_only=True`` (no pickled code is ever executed)::

    format        "lagfluid-network"
    version       1
    model         the model the network belongs to ("fgn"); files written before it existed have none and
                  are FGN's (:data:`LEGACY_MODEL`)
    kind          the trainable's name within its model ("advection" | "collision" | "pressure" for FGN)
    options       the network's constructor options (so the file rebuilds its own architecture)
    state_dict    weights and normalisation statistics (buffers)
    step          training iterations done
    meta          free-form provenance: data, training profile, time, package version, ...
    optimizer, rng, loss_window   (training checkpoints only) to resume exactly (loss_window: the losses
                  since the last row of the loss log)

This module knows no network: the model's trainable (or loader) rebuilds the network from ``options``.
Writes are atomic: a temporary file in the same directory, then a rename.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from lagfluid.errors import LagfluidError
from lagfluid.models.training_range import UNITS, range_from_checkpoint_meta

CHECKPOINT_FORMAT = "lagfluid-network"
LEGACY_MODEL = "fgn"
"""The model of a checkpoint without a ``model`` field (the shipped FGN weights predate the field)."""
_EXPORTED = ("model", "kind", "options", "state_dict", "step", "meta")


class CheckpointError(LagfluidError):
    """A checkpoint that is missing, unreadable, of another format or of another network."""


class MissingWeightsError(CheckpointError):
    """A model's weights file does not exist (nothing to read): the tables skip such a row, naming it."""


def save_checkpoint(path: str | os.PathLike, payload: dict[str, Any]) -> None:
    """Write ``payload`` (see the module doc) atomically to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    torch.save({"format": CHECKPOINT_FORMAT, "version": 1, **payload}, tmp)
    os.replace(tmp, path)


def network_payload(
    net: nn.Module, kind: str, options: dict[str, Any], step: int, meta: dict, model: str = LEGACY_MODEL
) -> dict:
    """The checkpoint fields of a network of ``model``'s trainable ``kind`` (no optimizer state)."""
    return {
        "model": model,
        "kind": kind,
        "options": dict(options),
        "state_dict": {k: v.detach().cpu() for k, v in net.state_dict().items()},
        "step": int(step),
        "meta": dict(meta),
    }


def read_checkpoint(
    path: str | os.PathLike, kind: str | None = None, model: str | None = None
) -> dict[str, Any]:
    """Load a checkpoint dict (``weights_only=True``), checking its format and, if given, model and kind.

    The returned dict always has ``model`` (:data:`LEGACY_MODEL` when the file has none).

    Raises:
        CheckpointError: missing file, unreadable or foreign content, or another model or kind of network.
    """
    path = Path(path)
    if not path.is_file():
        raise MissingWeightsError(f"checkpoint not found: {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises many types for corrupt or foreign files
        raise CheckpointError(f"cannot read checkpoint {path}: {type(err).__name__}: {err}") from err
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT or ckpt.get("version") != 1:
        raise CheckpointError(
            f"{path} is not a lagfluid network checkpoint (format {CHECKPOINT_FORMAT!r} v1)"
        )
    ckpt.setdefault("model", LEGACY_MODEL)
    if model is not None and ckpt["model"] != model:
        raise CheckpointError(f"{path} holds a network of model {ckpt['model']!r}, expected {model!r}")
    if kind is not None and ckpt.get("kind") != kind:
        raise CheckpointError(f"{path} holds a {ckpt.get('kind')!r} network, expected {kind!r}")
    _check_weights(path, ckpt.get("state_dict") or {})
    return ckpt


def _check_weights(path: Path, state: dict[str, Any]) -> None:
    """Refuse NaN or infinite weights and non-positive normalisation scales (``*std`` buffers).

    Either would only show up later as a rollout that "blew up", with the advice to lower dt.
    """
    for name, tensor in state.items():
        if not (isinstance(tensor, torch.Tensor) and tensor.is_floating_point()):
            continue
        if not torch.isfinite(tensor).all():
            count = int((~torch.isfinite(tensor)).sum())
            raise CheckpointError(f"{path}: {count} of {tensor.numel()} values of {name} are NaN or infinite")
        if name.endswith("std") and (tensor <= 0).any():
            raise CheckpointError(
                f"{path}: normalisation scale {name} has values <= 0 ({tensor.min().item():.3g}): the "
                "statistics are broken; retrain or re-export the network"
            )


def checkpoint_range(
    path: str | os.PathLike, quantities: Sequence[str] = tuple(UNITS)
) -> dict[str, list[float]] | None:
    """The training range recorded in (or rebuilt for) the checkpoint at ``path``.

    Only ``quantities`` (:data:`lagfluid.models.training_range.UNITS`' keys) are kept; None when the
    checkpoint records none and its training data is gone.

    Raises:
        CheckpointError: see :func:`read_checkpoint`.
    """
    return range_from_checkpoint_meta(read_checkpoint(path).get("meta") or {}, quantities)


def export_weights(
    run_dir: str | os.PathLike,
    dest_dir: str | os.PathLike,
    kinds: Sequence[str] | None = None,
    ranges: dict[str, dict[str, list[float]]] | None = None,
) -> list[Path]:
    """Copy a training run's network checkpoints without optimizer and RNG state (shipping size).

    ``python -m lagfluid.models.checkpoint RUN_DIR DEST_DIR`` does the same from the shell.

    Args:
        run_dir: a ``task=train`` out_dir.
        dest_dir: the folder to write ``<kind>.pt`` into (it must exist).
        kinds: the checkpoints to copy by name (``advection``, ``gns``...); None = every ``*.pt``.
        ranges: per kind, the training range to record (:mod:`lagfluid.models.training_range`); else the
            checkpoint's own, or one rebuilt from its training data when still there.

    Raises:
        CheckpointError: ``run_dir`` holds no checkpoint (or not one of ``kinds``), or one that is unreadable.
    """
    if kinds is None:
        paths = sorted(Path(run_dir).glob("*.pt"))
    else:
        paths = [Path(run_dir) / f"{kind}.pt" for kind in kinds]
        missing = [p.name for p in paths if not p.is_file()]
        if missing:
            raise CheckpointError(f"no {', '.join(missing)} in {run_dir}")
    if not paths:
        raise CheckpointError(f"no checkpoints (*.pt) in {run_dir}")
    written = []
    for path in paths:
        ckpt = read_checkpoint(path)
        meta = dict(ckpt.get("meta") or {})
        trained = (ranges or {}).get(str(ckpt.get("kind"))) or range_from_checkpoint_meta(meta)
        # shipped weights carry it: their training data stays behind
        if trained is not None:
            meta["range"] = trained
        save_checkpoint(Path(dest_dir) / path.name, {**{k: ckpt[k] for k in _EXPORTED}, "meta": meta})
        written.append(Path(dest_dir) / path.name)
    return written


if __name__ == "__main__":
    import sys

    if len(sys.argv) != 3:
        sys.exit("usage: python -m lagfluid.models.checkpoint RUN_DIR DEST_DIR")
    for path in export_weights(sys.argv[1], sys.argv[2]):
        sys.stdout.write(f"{path} ({path.stat().st_size / 1e3:.0f} kB)\n")
