"""``task=train``: one generic loop for every trainable network (``python -m lagfluid.run task=train ...``).

The model's trainables come from the registry (:func:`lagfluid.registry.get_trainables`; FGN's three
networks in :mod:`lagfluid.models.fgn.trainables`). ``stage=<name>`` trains one of them, ``stage=all``
(the default) each in the model's order; the name is the only thing this module knows about them.

Per trainable ``<name>``: mini-batches of its dataset items as block-diagonal graphs (PyG ``Batch``), a
loss on its ``(prediction, target)`` (its own ``loss`` if it has one, else ``train.loss.<name>``: ``mse``,
or ``huber`` at ``train.huber_delta``), Adam, the learning rate decayed exponentially from
``train.lr_start`` to ``train.lr_end`` over ``train.iterations.<name>`` iterations in batches of
``train.batch_size.<name>``. Normalisation statistics are fitted by the trainable from
``train.stat_samples`` training items before the first iteration and live in the network's buffers.
``train.extra_data=[DIR, ...]`` (optional) adds those datasets' train splits to ``data.out_dir``'s
(validation stays on ``data.out_dir``'s). ``train.init_from=DIR`` (optional) fine-tunes: the network starts
from ``DIR/<name>.pt``'s weights and keeps its statistics; ``train.init_from={<name>: DIR}`` does so for the
trainables named, the others start afresh. ``train.iterations.<name>=0`` with it keeps those weights as they
are (a published network in the run's folder, for the on-policy rounds below); without rounds, the export
below copies the kept network's own file, with the record of the training that made it.
Measurements behind the profiles: ``docs/training.md``.

**Outputs** in ``out_dir`` (default ``runs/train/<model>-<data>``): ``<name>.pt`` (model, kind, network,
statistics, options, optimizer, RNG, step; :mod:`lagfluid.models.checkpoint`) and ``<name>_loss.csv``
(iteration, lr, train loss, valid loss, seconds).

**Resume.** A checkpoint is written every ``train.checkpoint_every`` iterations and at the end (atomic
rename). A rerun with the same command continues from it (weights, optimizer, RNG state and CSV rows after
the checkpoint dropped) exactly as the uninterrupted run would have (the batch order and each item's random
draws are functions of the seed and the iteration: :class:`EpochBatches`, :class:`KeyedItems`), and its
``<name>_loss.csv`` is the uninterrupted run's row for row, every column but ``seconds`` (wall time): the
checkpoint carries the losses since the last logged row, and a run stopped before its first checkpoint
starts its log afresh (:func:`_start_csv`). A finished trainable is skipped; a checkpoint of other network
options, data or settings is an error, never silently mixed. A non-finite loss stops the run naming the
iteration. ``train.max_seconds=S`` caps the run's wall time (a lease of a GPU, a job's time limit): once S
seconds have passed since the run began, the iteration in progress finishes, a checkpoint is written and the
run stops (exit status 0; later trainables, on-policy rounds and the export wait); the same command continues
it, exactly as above.

**On-policy rounds.** ``train.onpolicy.rounds=R`` (with ``stage=all``, or a stage in
``train.onpolicy.trainables``) then fine-tunes those networks on R rounds of the model's own rollouts
labelled by the exact solver (DAgger; :mod:`lagfluid.tasks.onpolicy_rounds`); the last round's folder holds
the run's final networks. With ``train.onpolicy.start_from=DIR`` the rounds start from those weights (the
shipped ones, another run's) and nothing is trained in ``out_dir`` first.

**DAgger rounds for end-to-end models.** ``train.dagger.rounds=R`` (GNS: ``train=gns_dagger``) then rolls
the model out on the training scenes, labels its own states by one MPS model step and fine-tunes it on the
original data and rounds 1..k's together, R times (:mod:`lagfluid.tasks.dagger_rounds`); with
``train.dagger.start_from=DIR`` the rounds start from those weights and nothing is trained in ``out_dir``
first.

**Export.** With ``export_to=DIR`` the trained networks are copied into ``DIR`` once every trainable of the
run has finished (with rounds: the last round's; a network kept as it is: its own file), without optimizer
and RNG state (:func:`lagfluid.models.checkpoint.export_weights`; the ``retrain_*`` experiments set it to
the shipped weights' folder).
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import json
import logging
import math
import os
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig
from torch import Tensor
from torch.utils.data import ConcatDataset
from torch_geometric.loader import DataLoader

import lagfluid
from lagfluid.data.datasets import load_metadata
from lagfluid.errors import ConfigError, LagfluidError
from lagfluid.models.checkpoint import export_weights, network_payload, read_checkpoint, save_checkpoint
from lagfluid.models.trainable import Trainable
from lagfluid.models.training_range import UNITS, range_from_checkpoint_meta, training_range
from lagfluid.progress import progress_bar
from lagfluid.registry import get_trainables
from lagfluid.tasks import distributed
from lagfluid.tasks.config import apply_threads, run_device
from lagfluid.tasks.dagger_rounds import DAgger, run_dagger
from lagfluid.tasks.locks import hold_outputs
from lagfluid.tasks.onpolicy_rounds import OnPolicy, check_same_scenes, run_rounds

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------- trainer
def learning_rate(
    iteration: int,
    iterations: int,
    lr_start: float,
    lr_end: float,
    milestones: Sequence[int] | None = None,
    gamma: float = 0.5,
) -> float:
    """Exponential decay from ``lr_start`` (iteration 0) to ``lr_end`` (the last iteration).

    With ``milestones``: steps instead, ``lr_start * gamma^k`` after the k-th milestone iteration
    (DeepLagrangianFluids: halved at 25k, 30k, 35k, 40k and 45k of 50k); ``lr_end`` is then unused.
    """
    if milestones:
        return lr_start * gamma ** sum(iteration >= int(m) for m in milestones)
    frac = iteration / max(iterations - 1, 1)
    return lr_start * math.exp(frac * math.log(lr_end / lr_start))


class EpochBatches(torch.utils.data.Sampler[list[tuple[int, int]]]):
    """Endless mini-batches of ``(index, epoch)`` keys, from iteration ``start`` on.

    Epoch ``e`` is a permutation of the ``n`` items drawn from ``(seed, e)`` alone, cut into batches of
    ``batch_size`` (the last one smaller); iteration ``k`` is batch ``k mod B`` of epoch ``k div B``. So the
    order is a function of the iteration, and a run resumed from a checkpoint at iteration ``k`` sees the
    batches the uninterrupted run saw (the shuffle used to be reseeded with ``seed + k``, a different order).
    """

    def __init__(self, n: int, batch_size: int, seed: int, start: int = 0) -> None:
        self.n, self.batch_size, self.seed, self.start = n, batch_size, seed, start
        self.per_epoch = -(-n // batch_size)

    def __iter__(self) -> Iterator[list[tuple[int, int]]]:
        step, epoch, order = self.start, -1, torch.empty(0, dtype=torch.long)
        while True:
            e, b = divmod(step, self.per_epoch)
            if e != epoch:
                epoch = e
                order = torch.randperm(
                    self.n, generator=torch.Generator().manual_seed(self.seed * 1_000_003 + e)
                )
            yield [(int(i), epoch) for i in order[b * self.batch_size : (b + 1) * self.batch_size]]
            step += 1


class KeyedItems(torch.utils.data.Dataset):
    """``items[index]`` for an ``(index, epoch)`` key of :class:`EpochBatches`.

    An item set that draws random numbers per read (FGN's advection samples: fresh g and nu) exposes
    ``reseed(key)``; it is called with ``epoch * len + index`` first, so each draw is a function of the
    key and a resumed run draws what the uninterrupted one did.
    """

    def __init__(self, items: Any) -> None:
        self.items = items
        self.reseed = getattr(items, "reseed", None)

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, key: tuple[int, int]) -> Any:
        index, epoch = key
        if self.reseed is not None:
            self.reseed(epoch * len(self.items) + index)
        return self.items[index]


def _fingerprint(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


CSV_HEADER = ("iteration", "lr", "train_loss", "valid_loss", "seconds")


def _start_csv(path: Path, step: int) -> None:
    """The loss log as a run at ``step`` (0: a fresh one) needs it: the header and the rows up to ``step``.

    Rows after the checkpoint a run resumes from are recomputed, so they go, and so do all rows of a run
    stopped before its first checkpoint (it starts again at 0), and a row a kill cut mid-line. The header is
    on disk before the first iteration (a kill -9 used to lose it with the first row still buffered).
    """
    rows: list[list[str]] = []
    if path.is_file():
        with path.open(newline="") as f:
            rows = [r for r in list(csv.reader(f))[1:] if len(r) == len(CSV_HEADER) and r[0].isdigit()]
    tmp = path.with_name(path.name + ".part")
    with tmp.open("w", newline="") as f:
        csv.writer(f).writerows([CSV_HEADER, *(r for r in rows if int(r[0]) <= step)])
    os.replace(tmp, path)


LOSSES = ("mse", "huber")


def stage_loss(pred: Tensor, target: Tensor, loss: str, delta: float = 1.0) -> Tensor:
    """Mean loss of standardised ``pred`` vs ``target`` (same shape): ``mse``, or ``huber`` at ``delta``."""
    if loss == "mse":
        return torch.mean((pred - target) ** 2)
    if loss == "huber":
        return torch.nn.functional.huber_loss(pred, target, delta=delta)
    raise ConfigError(f"unknown train.loss {loss!r}; choose from {', '.join(LOSSES)}")


def _loss_fn(trainable: Trainable, name: str, delta: float) -> Any:
    """``loss(prediction, target)``: the trainable's own, else ``train.loss.<name>`` (checked now)."""
    if trainable.loss is not None:
        return trainable.loss
    stage_loss(torch.zeros(1), torch.zeros(1), name, delta)  # an unknown loss fails before any work
    return lambda pred, target: stage_loss(pred, target, name, delta)


def _per_trainable(tcfg: DictConfig, key: str, name: str, default: Any = None) -> Any:
    """``train.<key>.<name>``: a per-trainable setting of the training profile."""
    section = tcfg.get(key) or {}
    if name not in section:
        if default is not None:
            return default
        raise ConfigError(
            f"train.{key} has no entry for '{name}' (train={tcfg.get('name')}); add train.{key}.{name}"
        )
    return section[name]


def _init_from(setting: Any, name: str) -> str | None:
    """``train.init_from`` for trainable ``name``: one folder for all, or ``{name: folder}`` for some.

    Raises:
        ConfigError: neither a folder (a string) nor a mapping of trainables to folders.
    """
    if setting is None or isinstance(setting, str):
        return setting
    if isinstance(setting, Mapping | DictConfig):
        value = setting.get(name)
        return None if value is None else str(value)
    raise ConfigError(
        f"train.init_from must be a folder of checkpoints or {{trainable: folder}}, got {setting!r}"
    )


class Trainer:
    """One trainable's training run in ``out_dir``: :func:`train_one` makes one and calls :meth:`run`.

    Its parts, in the order :meth:`run` takes them:

    * the run's identity and fingerprint (made at construction, :meth:`run_identity`), refused on resume by
      :meth:`check_resume` when a checkpoint's differs;
    * :meth:`build`: the network and its Adam optimizer, fine-tuning from ``train.init_from``
      (:meth:`fine_tune_from`); :meth:`resume` from ``<name>.pt``; :meth:`fit_statistics`; :meth:`to_device`;
    * :meth:`make_loaders`: the training batches, a function of (seed, iteration), and the validation batches;
    * :meth:`loop` of :meth:`iteration` (one optimizer step), :meth:`validate`, :meth:`log_row` (the CSV row),
      :meth:`save` (the atomic checkpoint) and the stop rules (:meth:`finished`, :meth:`out_of_time`);
    * :meth:`open_log` and :meth:`log_end`: the loss log's start and the run's last log line.

    Model-free: the trainable is reached through :class:`~lagfluid.models.trainable.Trainable` alone.
    Attributes ``step`` (iterations done), ``elapsed`` (training seconds), ``stats`` (the network's
    statistics, None until fitted) and ``window`` (the losses since the last logged row) are what a
    checkpoint stores of the run besides the weights, optimizer and RNG.
    """

    def __init__(
        self, cfg: DictConfig, trainable: Trainable, out_dir: Path, deadline: float | None = None
    ) -> None:
        """Read the run's settings and make its identity; nothing is built or read from ``out_dir`` yet.

        Args:
            cfg: the composed ``task=train`` config.
            trainable: the network to train.
            out_dir: the folder of ``<name>.pt`` and ``<name>_loss.csv``.
            deadline: a :func:`time.monotonic` value (from ``train.max_seconds``), or None: no cap.

        Raises:
            ConfigError: a per-trainable setting missing, an unknown ``train.loss.<name>``.
        """
        self.cfg, self.tcfg, self.trainable, self.deadline = cfg, cfg.train, trainable, deadline
        tcfg, kind = cfg.train, trainable.name
        self.kind, self.options = kind, dict(trainable.options)
        self.iterations = int(_per_trainable(tcfg, "iterations", kind))
        self.batch_size = int(_per_trainable(tcfg, "batch_size", kind))
        self.loss_name = str(_per_trainable(tcfg, "loss", kind, "mse"))
        self.delta = float(tcfg.get("huber_delta", 1.0))
        self.loss_fn = _loss_fn(trainable, self.loss_name, self.delta)
        self.data_dir = Path(str(cfg.data.out_dir))
        self.extra_dirs = [Path(str(d)) for d in tcfg.get("extra_data") or []]
        self.milestones = [int(m) for m in tcfg.get("lr_milestones") or []]
        self.gamma = float(tcfg.get("lr_gamma", 0.5))
        self.adam_eps = float(tcfg.get("adam_eps") or 1e-8)
        self.init_from = _init_from(tcfg.get("init_from"), kind)
        self.identity = self.run_identity()
        self.fingerprint = _fingerprint(self.identity)
        quantities = getattr(trainable, "range_quantities", tuple(UNITS))
        # derived from the identity and the data: not part of the fingerprint
        self.trained_range = training_range([self.data_dir, *self.extra_dirs], self.identity, quantities)
        self.ckpt_path, self.csv_path = out_dir / f"{kind}.pt", out_dir / f"{kind}_loss.csv"
        self.step, self.elapsed, self.stats, self.window = 0, 0.0, None, []

    # ------------------------------------------------------------------------------- identity and resume
    def run_identity(self) -> dict[str, Any]:
        """What determines the trained weights (JSON-able): options, data, the trainable's identity, schedule.

        The keys after ``iterations`` appear only when set off their defaults, so a checkpoint trained before
        such an option existed keeps its fingerprint.
        """
        tcfg, data_dir = self.tcfg, self.data_dir
        identity = {
            "options": self.options,
            "data": {"dir": str(data_dir.resolve()), "scenes": _train_scenes(data_dir)},
            **self.trainable.identity(),
            "batch_size": self.batch_size,
            "lr": [float(tcfg.lr_start), float(tcfg.lr_end)],
            "iterations": self.iterations,
        }
        if self.extra_dirs:
            identity["extra_data"] = [
                {"dir": str(d.resolve()), "scenes": _train_scenes(d)} for d in self.extra_dirs
            ]
        if self.loss_name != "mse":
            identity["loss"] = {"name": self.loss_name, "delta": self.delta}
        if self.milestones or self.adam_eps != 1e-8:
            identity["schedule"] = {"milestones": self.milestones, "gamma": self.gamma, "eps": self.adam_eps}
        if self.init_from:
            identity["init_from"] = str(Path(str(self.init_from)).resolve())
        return identity

    def check_resume(self, meta: dict[str, Any]) -> None:
        """Refuse to continue a checkpoint (its ``meta``) of another run: never silently mixed.

        Raises:
            ConfigError: its fingerprint is not this run's.
        """
        if meta.get("fingerprint") != self.fingerprint:
            raise ConfigError(
                f"{self.ckpt_path} was trained with other settings (network options, data, batch size, "
                "schedule); use another out_dir or delete it to start afresh"
            )

    # -------------------------------------------------------------------------- network and optimizer
    def build(self) -> None:
        """The network (seeded by ``cfg.seed``) and its Adam optimizer, on the run's device set-up.

        Sets ``device``, ``rank``/``ranks`` (torchrun, :mod:`lagfluid.tasks.distributed`), ``main`` (rank 0
        writes the files), ``net`` and ``optimizer``. A run without a checkpoint and with ``train.init_from``
        starts from those weights (:meth:`fine_tune_from`).
        """
        torch.manual_seed(int(self.cfg.seed))
        self.device = distributed.init(run_device(self.cfg))
        self.rank, self.ranks = distributed.world()
        self.main = distributed.is_main()
        self.net = self.trainable.build_network()
        self.optimizer = torch.optim.Adam(
            self.net.parameters(), lr=float(self.tcfg.lr_start), eps=self.adam_eps
        )
        if self.init_from and not self.ckpt_path.is_file():
            self.fine_tune_from(self.init_from)

    def fine_tune_from(self, init_from: str) -> None:
        """Start from ``init_from/<name>.pt``'s weights and keep its statistics (they are not refitted).

        Raises:
            ConfigError: that network was built with other options.
        """
        kind, options = self.kind, self.options
        init = read_checkpoint(Path(str(init_from)) / f"{kind}.pt", kind, model=self.trainable.model)
        if dict(init["options"]) != options:
            raise ConfigError(
                f"train.init_from={init_from}: {kind}.pt has network options {init['options']}, not {options}"
            )
        self.net.load_state_dict(init["state_dict"])
        self.stats = init.get("meta", {}).get("stats")
        log.info("%s: starting from the weights and statistics of %s", kind, init_from)

    def resume(self) -> dict[str, Any] | None:
        """Continue from ``<name>.pt`` if there is one: weights, step, seconds, statistics, optimizer, RNG.

        Returns:
            The summary of a run that had already finished (skipped; nothing more is read), else None.

        Raises:
            ConfigError: the checkpoint is another run's (:meth:`check_resume`).
        """
        if not self.ckpt_path.is_file():
            return None
        ckpt = read_checkpoint(self.ckpt_path, self.kind, model=self.trainable.model)
        meta = ckpt.get("meta", {})
        self.check_resume(meta)
        self.net.load_state_dict(ckpt["state_dict"])
        self.step, self.elapsed = int(ckpt["step"]), float(meta.get("train_seconds", 0.0))
        self.stats = meta.get("stats")
        if self.finished():
            log.info(
                "%s: already trained (%d iterations) in %s, skipped", self.kind, self.step, self.ckpt_path
            )
            return {"kind": self.kind, "step": self.step, "skipped": True, "stopped": False, **meta}
        self.optimizer.load_state_dict(ckpt["optimizer"])
        torch.set_rng_state(ckpt["rng"])
        # the next log row's losses before the stop
        self.window = [float(v) for v in ckpt.get("loss_window", [])]
        log.info("%s: resuming at iteration %d from %s", self.kind, self.step, self.ckpt_path)
        return None

    def fit_statistics(self) -> None:
        """Fit the network's statistics from ``train.stat_samples`` training items, unless it has them."""
        if self.stats is not None:
            return
        items, seed = self.train_items, int(self.cfg.seed)
        n_stat = min(len(items), int(self.tcfg.stat_samples))
        pick = torch.randperm(len(items), generator=torch.Generator().manual_seed(seed))[:n_stat]
        self.stats = self.trainable.fit_statistics(self.net, [items[int(i)] for i in pick])
        log.info("%s statistics from %d training samples: %s", self.kind, n_stat, self.stats)

    def to_device(self) -> None:
        """The network and a resumed optimizer's moments onto the run's device."""
        self.net.to(self.device)
        for state in self.optimizer.state.values():
            for key, value in state.items():
                if isinstance(value, Tensor) and key != "step":
                    state[key] = value.to(self.device)

    # -------------------------------------------------------------------------------------- loaders
    def make_loaders(self) -> None:
        """``train_items``, ``loader`` (endless training batches from ``step`` on) and ``valid_loader``.

        The batch order is a function of (seed, iteration) alone (:class:`EpochBatches`), so a resumed run
        continues it exactly; the loaders have their own generators, as a DataLoader iterator otherwise
        draws its base seed from the global RNG, which the trainables' draws (restored from the checkpoint)
        must not share. Under torchrun each rank takes its piece of the global batch (``pieces``).

        Raises:
            LagfluidError: no training items.
        """
        seed = int(self.cfg.seed)
        train_items, valid_items = self.trainable.datasets(self.data_dir)
        if self.extra_dirs:  # the union: each dataset's train split trains, data.out_dir's valid validates
            train_items = ConcatDataset(
                [train_items, *(self.trainable.datasets(d)[0] for d in self.extra_dirs)]
            )
        if len(train_items) == 0:
            raise LagfluidError(f"no {self.kind} training samples in {self.data_dir}")
        batches = EpochBatches(len(train_items), self.batch_size, seed, start=self.step)
        self.pieces = distributed.RankBatches(batches, self.rank, self.ranks) if self.ranks > 1 else None
        self.train_items = train_items
        self.loader = DataLoader(
            KeyedItems(train_items),
            batch_sampler=self.pieces or batches,
            generator=torch.Generator().manual_seed(seed),
        )
        self.valid_loader = (
            DataLoader(
                valid_items,
                batch_size=self.batch_size,
                shuffle=False,
                generator=torch.Generator().manual_seed(seed),
            )
            if len(valid_items)
            else None
        )

    # ------------------------------------------------------------------------------------ the loop
    def iteration(self, batch: Any) -> float:
        """One optimizer step on ``batch`` at iteration ``step``'s learning rate, which it returns.

        The gradient and the logged loss are the global batch's under torchrun; the loss joins ``window``.

        Raises:
            LagfluidError: the loss is not finite (naming the iteration).
        """
        tcfg, step = self.tcfg, self.step
        batch = batch.to(self.device)
        lr = learning_rate(
            step, self.iterations, float(tcfg.lr_start), float(tcfg.lr_end), self.milestones, self.gamma
        )
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        pred, target = self.trainable.predict(self.net, batch)
        rows = 0 if self.pieces is not None and self.pieces.padding else int(target.shape[0])
        loss, batch_loss = distributed.global_mean(self.loss_fn(pred, target), rows)
        if not torch.isfinite(batch_loss):
            raise LagfluidError(
                f"{self.kind}: loss is {float(batch_loss)} at iteration {step}; lower train.lr_start"
            )
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        distributed.average_gradients(self.net)
        self.optimizer.step()
        self.step += 1
        self.window.append(float(batch_loss))
        return lr

    def validate(self) -> float:
        """Mean loss over the first ``train.valid_batches`` validation batches (NaN without a valid split)."""
        net, loader = self.net, self.valid_loader
        if loader is None:
            return float("nan")
        net.eval()
        losses = []
        with torch.no_grad():
            for k, batch in enumerate(loader):
                if k >= int(self.tcfg.valid_batches):
                    break
                pred, target = self.trainable.predict(net, batch.to(next(net.parameters()).device))
                losses.append(float(self.loss_fn(pred, target)))
        net.train()
        return sum(losses) / len(losses) if losses else float("nan")

    def finished(self) -> bool:
        """Stop rule: all ``train.iterations.<name>`` iterations are done."""
        return self.step >= self.iterations

    def out_of_time(self, last: bool) -> bool:
        """Stop rule ``train.max_seconds``: the deadline has passed, after any iteration but the ``last``."""
        return not last and self.deadline is not None and time.monotonic() >= self.deadline

    def loop(self) -> bool:
        """Iterations from ``step`` on, each logged, validated and checkpointed when due; True: out of time.

        ``elapsed`` counts the iterations' wall time, not the logging, validation or checkpointing.
        """
        tcfg, stopped = self.tcfg, False
        t_last = time.perf_counter()
        bar = progress_bar(
            self.iterations, enabled=bool(self.cfg.progress), initial=self.step, desc=f"train {self.kind}"
        )
        try:
            while not self.finished() and not stopped:
                for batch in self.loader:
                    if self.finished():
                        break
                    lr = self.iteration(batch)
                    bar.update(1)
                    now = time.perf_counter()
                    self.elapsed += now - t_last
                    t_last = now
                    step, last = self.step, self.step == self.iterations
                    if step % int(tcfg.log_every) == 0 or last:
                        due = self.main and (step % int(tcfg.valid_every) == 0 or last)
                        self.log_row(lr, self.validate() if due else float("nan"), bar)
                        t_last = time.perf_counter()
                    stopped = self.out_of_time(last)
                    if step % int(tcfg.checkpoint_every) == 0 or last or stopped:
                        self.save()
                        t_last = time.perf_counter()
                    if stopped:
                        break
        finally:
            bar.close()
            self.csv_file.close()
        return stopped

    # ------------------------------------------------------------------------------- checkpointing
    def save(self) -> None:
        """``<name>.pt`` at ``step`` (atomic rename; rank 0 writes it, every rank waits for it).

        The network, options and ``meta`` (fingerprint, identity, statistics, training seconds, profile,
        version, data folder, trained range), with the training state: optimizer, RNG and ``window``, the
        losses since the last logged row, which a resume averages into its next row.
        """
        meta = {
            "fingerprint": self.fingerprint,
            "identity": json.dumps(self.identity, default=str),
            "stats": self.stats,
            "train_seconds": self.elapsed,
            "profile": str(self.tcfg.name),
            "version": lagfluid.__version__,
            "data_dir": str(self.data_dir),
            "range": self.trained_range,
        }
        payload = network_payload(
            self.net, self.kind, self.options, self.step, meta, model=self.trainable.model
        )
        payload.update(
            optimizer=self.optimizer.state_dict(), rng=torch.get_rng_state(), loss_window=list(self.window)
        )
        if self.main:
            save_checkpoint(self.ckpt_path, payload)
        distributed.barrier()  # no rank runs ahead of a checkpoint it may have to resume from

    # ------------------------------------------------------------------------------------ logging
    def open_log(self) -> None:
        """``<name>_loss.csv`` as a run at ``step`` needs it (:func:`_start_csv`), open to append rows.

        Rank 0 writes the log; the other ranks write to the null device.
        """
        if self.main:
            _start_csv(self.csv_path, self.step)
        self.csv_file = self.csv_path.open("a", newline="") if self.main else open(os.devnull, "w")
        self.csv_writer = csv.writer(self.csv_file)

    def log_row(self, lr: float, valid: float, bar: Any) -> None:
        """The loss log's row at ``step`` (the mean of ``window``, then emptied) and the bar's."""
        train_loss = sum(self.window) / len(self.window)
        self.csv_writer.writerow(
            [self.step, f"{lr:.6g}", f"{train_loss:.6g}", f"{valid:.6g}", f"{self.elapsed:.1f}"]
        )
        self.csv_file.flush()
        bar.set_postfix(loss=f"{train_loss:.4g}", valid=f"{valid:.4g}")
        self.window = []

    def log_end(self, stopped: bool) -> None:
        """The run's last log line: stopped by ``train.max_seconds`` (the same command continues), or done."""
        if stopped:
            log.info(
                "%s: stopped by train.max_seconds at iteration %d of %d (checkpoint %s); the same command "
                "continues",
                self.kind,
                self.step,
                self.iterations,
                self.ckpt_path,
            )
        else:
            log.info("%s: %d iterations in %.0f s -> %s", self.kind, self.step, self.elapsed, self.ckpt_path)

    # ------------------------------------------------------------------------------------ the run
    def run(self) -> dict[str, Any]:
        """Build, resume (or skip a finished run), load, fit the statistics, loop; the run's summary."""
        self.build()
        skipped = self.resume()
        if skipped is not None:
            return skipped
        self.make_loaders()
        self.fit_statistics()
        self.to_device()
        self.net.train()
        self.open_log()
        stopped = self.loop()
        if self.iterations == 0 and not self.ckpt_path.is_file():  # the initial weights, as they are
            self.save()
        self.log_end(stopped)
        return {
            "kind": self.kind,
            "step": self.step,
            "train_seconds": self.elapsed,
            "checkpoint": str(self.ckpt_path),
            "stopped": stopped,
        }


def _kept_networks(cfg: DictConfig, names: Sequence[str]) -> dict[str, Path]:
    """``{name: folder}`` of the trainables kept as they are: 0 iterations from ``train.init_from``."""
    tcfg = cfg.train
    kept = {}
    for name in names:
        source = _init_from(tcfg.get("init_from"), name)
        if source is not None and int(_per_trainable(tcfg, "iterations", name)) == 0:
            kept[name] = Path(source)
    return kept


def _train_scenes(data_dir: Path) -> Any:
    """The train split's scenes of the dataset in ``data_dir`` (part of a run's identity)."""
    return load_metadata(data_dir).get("splits", {}).get("train")


def train_one(
    cfg: DictConfig, trainable: Trainable, out_dir: Path, deadline: float | None = None
) -> dict[str, Any]:
    """Train (or resume, or skip when finished) one trainable's network; returns its summary.

    With a ``deadline`` (a :func:`time.monotonic` value, from ``train.max_seconds``) the first iteration that
    ends after it is checkpointed and the training stops there: the summary's ``stopped`` is then True.
    """
    return Trainer(cfg, trainable, out_dir, deadline).run()


def check_export_to(export_to: str | os.PathLike) -> None:
    """Refuse an ``export_to`` that cannot become the folder the trained networks are copied into.

    Raises:
        ConfigError: it is a file, its parent folder does not exist (a relative path run from elsewhere:
            not a stray ``lagfluid/weights`` here), or it cannot be written.
    """
    dest = Path(str(export_to))
    if dest.exists() and not dest.is_dir():
        raise ConfigError(f"export_to={export_to} is a file, not a folder for the trained networks")
    if not dest.parent.is_dir():
        raise ConfigError(
            f"export_to={export_to}: its parent folder {dest.parent.resolve()} does not exist; run from "
            "the repository root or give an absolute path"
        )
    folder = dest if dest.is_dir() else dest.parent
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ConfigError(f"export_to={export_to} cannot be written: {folder.resolve()} is not writable")


def max_seconds(cfg: DictConfig) -> float | None:
    """``train.max_seconds``: the run's wall-time cap in s, or None (no cap; also a profile without the key).

    Raises:
        ConfigError: not a finite number > 0.
    """
    value = cfg.train.get("max_seconds")
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
        raise ConfigError(
            f"train.max_seconds must be a number of seconds > 0 (or null: no cap), got {value!r}"
        )
    return float(value)


def train(cfg: DictConfig) -> list[dict[str, Any]]:
    """``task=train``: train ``cfg.stage`` (one trainable of ``cfg.model``, or ``all`` of them in turn).

    Raises:
        UnknownNameError: the model has no trainables.
        ConfigError: an unknown ``stage``; a ``train.max_seconds`` that is not a number > 0, or one with
            on-policy rounds or under torchrun.
    """
    start = time.monotonic()
    model = str(cfg.model.name)
    trainables = get_trainables(model, cfg)
    stage = str(cfg.stage)
    if stage != "all" and stage not in trainables:
        raise ConfigError(
            f"unknown stage '{stage}' of model {model}; available: {', '.join(trainables)}, all"
        )
    names = list(trainables) if stage == "all" else [stage]
    onpolicy = OnPolicy.from_config(cfg, list(trainables))
    with_rounds = onpolicy.rounds > 0 and (stage == "all" or stage in onpolicy.trainables)
    dagger = DAgger.from_config(cfg)
    if dagger.rounds and onpolicy.rounds:
        raise ConfigError(
            "train.dagger.rounds and train.onpolicy.rounds are both set: DAgger rounds are for end-to-end "
            "models, on-policy rounds for split-step ones; set one of them to 0"
        )
    with_rounds = with_rounds or dagger.rounds > 0
    if with_rounds and distributed.world()[1] > 1:
        key = "train.dagger.rounds" if dagger.rounds else "train.onpolicy.rounds"
        raise ConfigError(
            f"{key} under torchrun: the rounds generate data in one process; run them without "
            f"torchrun ({key}=0 for the data-parallel part)"
        )
    cap = max_seconds(cfg)
    if cap is not None and with_rounds:  # the rounds' own trainings would run past the cap
        raise ConfigError(
            f"train.max_seconds={cap:g} caps the one-step training, not the rounds (train.onpolicy.rounds="
            f"{onpolicy.rounds}, train.dagger.rounds={dagger.rounds}); set train.max_seconds=null or the "
            "rounds to 0"
        )
    if cap is not None and distributed.world()[1] > 1:  # each rank's clock would stop it at its own iteration
        raise ConfigError(f"train.max_seconds={cap:g} under torchrun: not supported; run without it")
    if with_rounds:  # a command that cannot remake the dataset's scenes fails now, not after the training
        check_same_scenes(cfg, "train.dagger.rounds" if dagger.rounds else "train.onpolicy.rounds")
    if cfg.get("export_to") and distributed.is_main():  # before the training, not after it
        check_export_to(cfg.export_to)
    apply_threads(cfg)
    out_dir = Path(str(cfg.out_dir))
    # each trainable's files are locked, not the folder: a sweep over stage trains them side by side in it;
    # under torchrun rank 0 writes them (and holds the locks)
    locks = hold_outputs(out_dir, "train", names) if distributed.is_main() else contextlib.nullcontext()
    deadline = None if cap is None else start + cap
    with locks:
        return _train_in(cfg, trainables, names, onpolicy, dagger, with_rounds, out_dir, deadline)


def _train_in(
    cfg: DictConfig,
    trainables: dict[str, Trainable],
    names: list[str],
    onpolicy: OnPolicy,
    dagger: DAgger,
    with_rounds: bool,
    out_dir: Path,
    deadline: float | None = None,
) -> list[dict[str, Any]]:
    """The training of :func:`train` once its trainables' files in ``out_dir`` are locked."""
    out_dir.mkdir(parents=True, exist_ok=True)
    summaries = []
    # the rounds start from those weights: nothing to train here first
    from_elsewhere = (dagger.rounds > 0 and dagger.start_from is not None) or (
        onpolicy.rounds > 0 and onpolicy.start_from is not None and with_rounds
    )
    for name in [] if from_elsewhere else names:
        summaries.append(train_one(cfg, trainables[name], out_dir, deadline))
        if summaries[-1].get("stopped"):  # the cap is the run's: the later trainables and the export wait
            return summaries
    # where each network to export is: the last round's folder, else this run's; without rounds a network
    # kept as it is (0 iterations from train.init_from) ships as its source's file, with the record of the
    # training that made it, not this run's record of 0 iterations
    kept = {} if with_rounds else _kept_networks(cfg, names)
    if with_rounds:
        if dagger.rounds:
            last_round = run_dagger(cfg, dagger, out_dir, train_one)
        else:
            last_round = run_rounds(cfg, onpolicy, out_dir, train_one)
        sources = dict.fromkeys(names, last_round)
    else:
        sources = {**dict.fromkeys(names, out_dir), **kept}
    export_to = cfg.get("export_to")
    if export_to and distributed.is_main():
        check_export_to(export_to)  # again: the folder may have changed during the training
        dest = Path(str(export_to))
        dest.mkdir(exist_ok=True)
        for name, source in sources.items():  # only this run's trainables: out_dir may hold others
            meta = read_checkpoint(Path(source) / f"{name}.pt").get("meta") or {}
            quantities = getattr(trainables[name], "range_quantities", tuple(UNITS))
            # a kept network's range is its own record (its training data need not be here)
            trained = (
                None if name in kept else range_from_checkpoint_meta({**meta, "range": None}, quantities)
            )
            written = export_weights(
                source, export_to, kinds=[name], ranges={name: trained} if trained else None
            )
            log.info("%s: exported to %s", name, written[0])
    distributed.finish()
    return summaries
