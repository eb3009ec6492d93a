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
from ``DIR/<name>.pt``'s weights and keeps its statistics.
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
labelled by the exact solver (DAgger; :mod:`lagfluid.onpolicy_rounds`); the last round's folder holds the
run's final networks.

**DAgger rounds for end-to-end models.** ``train.dagger.rounds=R`` (GNS: ``train=gns_dagger``) then rolls
the model out on the training scenes, labels its own states by one MPS model step and fine-tunes it on the
original data and rounds 1..k's together, R times (:mod:`lagfluid.dagger_rounds`); with
``train.dagger.start_from=DIR`` the rounds start from those weights and nothing is trained in ``out_dir``
first.

**Export.** With ``export_to=DIR`` the trained networks are copied into ``DIR`` once every trainable of the
run has finished (with rounds: the last round's), without optimizer and RNG state
(:func:`lagfluid.models.checkpoint.export_weights`; the ``retrain_*`` experiments set it to the shipped
weights' folder).
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
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig
from torch import Tensor, nn
from torch.utils.data import ConcatDataset
from torch_geometric.loader import DataLoader

import lagfluid
from lagfluid import distributed
from lagfluid.config import apply_threads, run_device
from lagfluid.dagger_rounds import DAgger, run_dagger
from lagfluid.data.datasets import load_metadata
from lagfluid.errors import ConfigError, LagfluidError
from lagfluid.locks import hold_outputs
from lagfluid.models.checkpoint import export_weights, network_payload, read_checkpoint, save_checkpoint
from lagfluid.models.trainable import Trainable
from lagfluid.models.training_range import UNITS, range_from_checkpoint_meta, training_range
from lagfluid.onpolicy_rounds import OnPolicy, check_same_scenes, run_rounds
from lagfluid.progress import progress_bar
from lagfluid.registry import get_trainables

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


def _valid_loss(
    trainable: Trainable, net: nn.Module, loader: DataLoader | None, batches: int, loss: Any
) -> float:
    if loader is None:
        return float("nan")
    net.eval()
    losses = []
    with torch.no_grad():
        for k, batch in enumerate(loader):
            if k >= batches:
                break
            pred, target = trainable.predict(net, batch.to(next(net.parameters()).device))
            losses.append(float(loss(pred, target)))
    net.train()
    return sum(losses) / len(losses) if losses else float("nan")


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


def train_one(
    cfg: DictConfig, trainable: Trainable, out_dir: Path, deadline: float | None = None
) -> dict[str, Any]:
    """Train (or resume, or skip when finished) one trainable's network; returns its summary.

    With a ``deadline`` (a :func:`time.monotonic` value, from ``train.max_seconds``) the first iteration that
    ends after it is checkpointed and the training stops there: the summary's ``stopped`` is then True.
    """
    tcfg, kind = cfg.train, trainable.name
    options = dict(trainable.options)
    iterations = int(_per_trainable(tcfg, "iterations", kind))
    batch_size = int(_per_trainable(tcfg, "batch_size", kind))
    loss_name = str(_per_trainable(tcfg, "loss", kind, "mse"))
    delta = float(tcfg.get("huber_delta", 1.0))
    loss_fn = _loss_fn(trainable, loss_name, delta)
    data_dir = Path(str(cfg.data.out_dir))
    extra_dirs = [Path(str(d)) for d in tcfg.get("extra_data") or []]
    metadata = load_metadata(data_dir)
    identity = {
        "options": options,
        "data": {"dir": str(data_dir.resolve()), "scenes": metadata.get("splits", {}).get("train")},
        **trainable.identity(),
        "batch_size": batch_size,
        "lr": [float(tcfg.lr_start), float(tcfg.lr_end)],
        "iterations": iterations,
    }
    if extra_dirs:  # only then, as below
        identity["extra_data"] = [
            {"dir": str(d.resolve()), "scenes": load_metadata(d).get("splits", {}).get("train")}
            for d in extra_dirs
        ]
    if loss_name != "mse":  # only then: checkpoints trained before the option existed keep their fingerprint
        identity["loss"] = {"name": loss_name, "delta": delta}
    milestones = [int(m) for m in tcfg.get("lr_milestones") or []]
    adam_eps = float(tcfg.get("adam_eps") or 1e-8)
    if milestones or adam_eps != 1e-8:  # only then, likewise
        identity["schedule"] = {
            "milestones": milestones,
            "gamma": float(tcfg.get("lr_gamma", 0.5)),
            "eps": adam_eps,
        }
    init_from = tcfg.get("init_from")
    if init_from:  # only then, likewise
        identity["init_from"] = str(Path(str(init_from)).resolve())
    fingerprint = _fingerprint(identity)
    quantities = getattr(trainable, "range_quantities", tuple(UNITS))
    trained_range = training_range([data_dir, *extra_dirs], identity, quantities)  # derived: no fingerprint
    ckpt_path, csv_path = out_dir / f"{kind}.pt", out_dir / f"{kind}_loss.csv"

    torch.manual_seed(int(cfg.seed))
    device = distributed.init(run_device(cfg))
    rank, ranks = distributed.world()
    main = distributed.is_main()
    net = trainable.build_network()
    optimizer = torch.optim.Adam(net.parameters(), lr=float(tcfg.lr_start), eps=adam_eps)
    start_step, elapsed, stats, window = 0, 0.0, None, []
    if init_from and not ckpt_path.is_file():  # fine-tuning: start from trained weights and their statistics
        init = read_checkpoint(Path(str(init_from)) / f"{kind}.pt", kind, model=trainable.model)
        if dict(init["options"]) != options:
            raise ConfigError(
                f"train.init_from={init_from}: {kind}.pt has network options {init['options']}, not {options}"
            )
        net.load_state_dict(init["state_dict"])
        stats = init.get("meta", {}).get("stats")
        log.info("%s: starting from the weights and statistics of %s", kind, init_from)
    if ckpt_path.is_file():
        ckpt = read_checkpoint(ckpt_path, kind, model=trainable.model)
        meta = ckpt.get("meta", {})
        if meta.get("fingerprint") != fingerprint:
            raise ConfigError(
                f"{ckpt_path} was trained with other settings (network options, data, batch size, schedule); "
                "use another out_dir or delete it to start afresh"
            )
        net.load_state_dict(ckpt["state_dict"])
        start_step, elapsed, stats = (
            int(ckpt["step"]),
            float(meta.get("train_seconds", 0.0)),
            meta.get("stats"),
        )
        if start_step >= iterations:
            log.info("%s: already trained (%d iterations) in %s, skipped", kind, start_step, ckpt_path)
            return {"kind": kind, "step": start_step, "skipped": True, "stopped": False, **meta}
        optimizer.load_state_dict(ckpt["optimizer"])
        torch.set_rng_state(ckpt["rng"])
        window = [float(v) for v in ckpt.get("loss_window", [])]  # the next log row's losses before the stop
        log.info("%s: resuming at iteration %d from %s", kind, start_step, ckpt_path)

    train_items, valid_items = trainable.datasets(data_dir)
    if extra_dirs:  # the union: each dataset's train split trains, data.out_dir's valid split validates
        train_items = ConcatDataset([train_items, *(trainable.datasets(d)[0] for d in extra_dirs)])
    if len(train_items) == 0:
        raise LagfluidError(f"no {kind} training samples in {data_dir}")
    # the batch order is a function of (seed, iteration) alone: a resumed run continues it exactly
    # own generators: a DataLoader iterator draws its base seed from the global RNG otherwise, which the
    # trainables' noise and pushforward draws (restored from the checkpoint) must not share
    batches = EpochBatches(len(train_items), batch_size, int(cfg.seed), start=start_step)
    # under torchrun each rank takes its piece of the global batch (lagfluid.distributed)
    pieces = distributed.RankBatches(batches, rank, ranks) if ranks > 1 else None
    loader = DataLoader(
        KeyedItems(train_items),
        batch_sampler=pieces or batches,
        generator=torch.Generator().manual_seed(int(cfg.seed)),
    )
    valid_loader = (
        DataLoader(
            valid_items,
            batch_size=batch_size,
            shuffle=False,
            generator=torch.Generator().manual_seed(int(cfg.seed)),
        )
        if len(valid_items)
        else None
    )

    if stats is None:
        n_stat = min(len(train_items), int(tcfg.stat_samples))
        pick = torch.randperm(len(train_items), generator=torch.Generator().manual_seed(int(cfg.seed)))[
            :n_stat
        ]
        stats = trainable.fit_statistics(net, [train_items[int(i)] for i in pick])
        log.info("%s statistics from %d training samples: %s", kind, n_stat, stats)
    net.to(device)
    for state in optimizer.state.values():  # a resumed optimizer's moments follow the weights
        for key, value in state.items():
            if isinstance(value, Tensor) and key != "step":
                state[key] = value.to(device)

    net.train()
    if main:
        _start_csv(csv_path, start_step)
    csv_file = csv_path.open("a", newline="") if main else open(os.devnull, "w")  # rank 0 writes the log
    writer = csv.writer(csv_file)

    def save(step: int) -> None:
        meta = {
            "fingerprint": fingerprint,
            "identity": json.dumps(identity, default=str),
            "stats": stats,
            "train_seconds": elapsed,
            "profile": str(tcfg.name),
            "version": lagfluid.__version__,
            "data_dir": str(data_dir),
            "range": trained_range,
        }
        payload = network_payload(net, kind, options, step, meta, model=trainable.model)
        # training state, as the optimizer's: the losses since the last logged row, which a resume averages
        payload.update(optimizer=optimizer.state_dict(), rng=torch.get_rng_state(), loss_window=list(window))
        if main:
            save_checkpoint(ckpt_path, payload)
        distributed.barrier()  # no rank runs ahead of a checkpoint it may have to resume from

    step, t_last, stopped = start_step, time.perf_counter(), False
    bar = progress_bar(iterations, enabled=bool(cfg.progress), initial=start_step, desc=f"train {kind}")
    try:
        while step < iterations and not stopped:
            for batch in loader:
                if step >= iterations:
                    break
                batch = batch.to(device)
                lr = learning_rate(
                    step,
                    iterations,
                    float(tcfg.lr_start),
                    float(tcfg.lr_end),
                    milestones,
                    float(tcfg.get("lr_gamma", 0.5)),
                )
                for group in optimizer.param_groups:
                    group["lr"] = lr
                pred, target = trainable.predict(net, batch)
                # torchrun: the gradient and the logged loss of the global batch (lagfluid.distributed)
                rows = 0 if pieces is not None and pieces.padding else int(target.shape[0])
                loss, batch_loss = distributed.global_mean(loss_fn(pred, target), rows)
                if not torch.isfinite(batch_loss):
                    raise LagfluidError(
                        f"{kind}: loss is {float(batch_loss)} at iteration {step}; lower train.lr_start"
                    )
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                distributed.average_gradients(net)
                optimizer.step()
                step += 1
                window.append(float(batch_loss))
                bar.update(1)
                now = time.perf_counter()
                elapsed += now - t_last
                t_last = now
                last = step == iterations
                if step % int(tcfg.log_every) == 0 or last:
                    valid = (
                        _valid_loss(trainable, net, valid_loader, int(tcfg.valid_batches), loss_fn)
                        if main and (step % int(tcfg.valid_every) == 0 or last)
                        else float("nan")
                    )
                    writer.writerow(
                        [
                            step,
                            f"{lr:.6g}",
                            f"{sum(window) / len(window):.6g}",
                            f"{valid:.6g}",
                            f"{elapsed:.1f}",
                        ]
                    )
                    csv_file.flush()
                    bar.set_postfix(loss=f"{sum(window) / len(window):.4g}", valid=f"{valid:.4g}")
                    window = []
                    t_last = time.perf_counter()
                stopped = not last and deadline is not None and time.monotonic() >= deadline
                if step % int(tcfg.checkpoint_every) == 0 or last or stopped:
                    save(step)
                    t_last = time.perf_counter()
                if stopped:
                    break
    finally:
        bar.close()
        csv_file.close()
    if stopped:
        log.info(
            "%s: stopped by train.max_seconds at iteration %d of %d (checkpoint %s); the same command "
            "continues",
            kind,
            step,
            iterations,
            ckpt_path,
        )
    else:
        log.info("%s: %d iterations in %.0f s -> %s", kind, step, elapsed, ckpt_path)
    return {
        "kind": kind,
        "step": step,
        "train_seconds": elapsed,
        "checkpoint": str(ckpt_path),
        "stopped": stopped,
    }


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
    from_elsewhere = dagger.rounds > 0 and dagger.start_from is not None  # the rounds start from those
    for name in [] if from_elsewhere else names:
        summaries.append(train_one(cfg, trainables[name], out_dir, deadline))
        if summaries[-1].get("stopped"):  # the cap is the run's: the later trainables and the export wait
            return summaries
    sources = dict.fromkeys(names, out_dir)  # where each trained network ends up
    if with_rounds:
        if dagger.rounds:
            last_round = run_dagger(cfg, dagger, out_dir, train_one)
        else:
            last_round = run_rounds(cfg, onpolicy, out_dir, train_one)
        sources = {name: last_round for name in names}
    export_to = cfg.get("export_to")
    if export_to and distributed.is_main():
        check_export_to(export_to)  # again: the folder may have changed during the training
        dest = Path(str(export_to))
        dest.mkdir(exist_ok=True)
        for name, source in sources.items():  # only this run's trainables: out_dir may hold others
            meta = read_checkpoint(Path(source) / f"{name}.pt").get("meta") or {}
            quantities = getattr(trainables[name], "range_quantities", tuple(UNITS))
            trained = range_from_checkpoint_meta({**meta, "range": None}, quantities)
            written = export_weights(
                source, export_to, kinds=[name], ranges={name: trained} if trained else None
            )
            log.info("%s: exported to %s", name, written[0])
    distributed.finish()
    return summaries
