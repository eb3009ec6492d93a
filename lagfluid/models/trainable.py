"""The interface of everything ``task=train`` trains: one network of one model.

A model contributes one or more trainables (FGN: one per learned stage; an end-to-end model such as GNS:
one) through the registry (:func:`lagfluid.registry.get_trainables`). The generic loop in
:mod:`lagfluid.tasks.train` owns the schedule, resume, logging, checkpoints and validation; a trainable owns
everything that depends on the model: which data it learns from, how its inputs are built, what it
predicts and in which units.

A trainable is built by its model's factory from the composed config (``factory(cfg)`` returns
``{name: trainable}``), so it may read ``cfg.model.<name>`` (its network's options), ``cfg.solver``,
``cfg.seed`` or model-specific ``cfg.train`` keys at construction.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from torch import Tensor, nn
from torch_geometric.data import Batch, Data


@runtime_checkable
class Trainable(Protocol):
    """One trainable network of a model.

    Attributes:
        name: the trainable's name within its model (FGN: ``advection``, ``collision``, ``pressure``). It
            names the run's files (``<name>.pt``, ``<name>_loss.csv``), the checkpoint's ``kind`` and the
            per-trainable config keys ``train.iterations.<name>``, ``train.batch_size.<name>`` and
            ``train.loss.<name>``.
        model: the registry name of the model whose simulator loads the weights (``"fgn"``), recorded in
            every checkpoint as ``model``.
        options: the network's constructor options (plain JSON-able dict), recorded in the checkpoint so
            that it rebuilds its own architecture, and part of the resume fingerprint.
        loss: the trainable's own ``loss(prediction, target) -> Tensor`` (a scalar), or None: the loop
            then uses ``train.loss.<name>`` (``mse`` or ``huber``) on the two.
    """

    name: str
    model: str
    options: dict[str, Any]
    loss: Callable[[Tensor, Tensor], Tensor] | None

    def datasets(self, data_dir: Path) -> tuple[Any, Any]:
        """``(train, valid)`` map-style datasets of PyG :class:`~torch_geometric.data.Data` items.

        From the ``train`` and ``valid`` splits of the generated dataset in ``data_dir``; the loop batches
        them with :class:`torch_geometric.loader.DataLoader` (block-diagonal graphs, ``batch.batch`` (N,)
        the item of each node). ``valid`` may be empty.
        """
        ...

    def build_network(self) -> nn.Module:
        """A freshly initialised network from :attr:`options` (its statistics at the identity)."""
        ...

    def fit_statistics(self, net: nn.Module, items: Sequence[Data]) -> dict[str, Any]:
        """Set ``net``'s normalisation statistics from training ``items``; return them (JSON-able).

        The statistics live in the network's buffers, hence in its ``state_dict`` and every checkpoint;
        the returned summary is logged and stored in the checkpoint's ``meta``.
        """
        ...

    def predict(self, net: nn.Module, batch: Batch) -> tuple[Tensor, Tensor]:
        """``(prediction, target)`` of one batch, same shape, both in the loss's (standardised) units.

        Only the loss rows (e.g. FGN's advection: the fluid particles, (Nf, 3)).
        """
        ...

    def identity(self) -> dict[str, Any]:
        """Settings besides options, data and schedule that determine the trained weights (JSON-able).

        Part of the resume fingerprint: a checkpoint trained with others is refused, never continued.
        """
        ...
