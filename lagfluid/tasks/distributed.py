"""Data-parallel training under ``torchrun``: the same loss curve as one process with the same global batch.

``torchrun --nproc_per_node N -m lagfluid.run task=train ...`` starts N processes (``RANK``, ``WORLD_SIZE``,
``LOCAL_RANK`` in their environment); :func:`init` joins them in a process group (gloo on the CPU, NCCL on
CUDA, each rank on ``cuda:LOCAL_RANK``). Then, per iteration:

* :class:`RankBatches` gives rank ``r`` the ``r``-th of N contiguous pieces of the global batch
  (:class:`~lagfluid.tasks.train.EpochBatches`: ``train.batch_size`` is the *global* batch);
* each rank scales its mean loss by ``n_r N / n`` (``n_r`` its rows, ``n`` the batch's) and
  :func:`average_gradients` averages the gradients over the ranks, which sums to the gradient of the global
  batch's mean (for a loss that is a mean over rows, as every built-in one is); every rank's Adam then takes
  the same step;
* rank 0 alone writes the loss CSV and the checkpoints (the others wait at a barrier); every rank reads the
  checkpoint on resume.

Why a gradient all-reduce and not ``DistributedDataParallel``: trainables call their networks' submodules
from ``predict`` (FGN's stages, GNS's encoder-processor-decoder), outside ``forward``, where DDP's hooks do
not see them; the networks are small (18k-700k parameters), so one all-reduce per tensor costs little.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator

import torch
import torch.distributed as dist
from torch import Tensor, nn


def world() -> tuple[int, int]:
    """``(rank, world size)`` from torchrun's environment; ``(0, 1)`` for a plain run."""
    return int(os.environ.get("RANK", 0)), int(os.environ.get("WORLD_SIZE", 1))


def init(device: torch.device) -> torch.device:
    """Join torchrun's process group (once) and return this rank's device (``cuda:LOCAL_RANK`` on CUDA)."""
    _, size = world()
    if size == 1:
        return device
    if device.type == "cuda":
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0)))
        torch.cuda.set_device(device)
    if not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        if not is_main():  # one voice: rank 0 logs progress, the others only warnings and errors
            logging.getLogger("lagfluid").setLevel(logging.WARNING)
    return device


def is_main() -> bool:
    """Whether this process writes files and logs (rank 0, or a plain run)."""
    return world()[0] == 0


def barrier() -> None:
    """Wait for every rank (nothing to wait for in a plain run)."""
    if dist.is_available() and dist.is_initialized():
        dist.barrier()


class RankBatches(torch.utils.data.Sampler[list]):
    """Rank ``rank``'s piece of every global batch: the ``rank``-th of ``size`` contiguous pieces.

    Args:
        batches: a batch sampler of global batches (lists of keys).
        rank: this process's rank.
        size: the number of ranks.


    A global batch smaller than the number of ranks (an epoch's last) leaves some ranks without items: such
    a rank gets the batch's first item as padding and :attr:`padding` is True while it is the current piece,
    so that the training loop weighs it 0 (every rank must take part in each all-reduce).
    """

    def __init__(self, batches: torch.utils.data.Sampler[list], rank: int, size: int) -> None:
        self.batches, self.rank, self.size = batches, rank, size
        self.padding = False

    def __iter__(self) -> Iterator[list]:
        for batch in self.batches:
            n = len(batch)
            lo, hi = n * self.rank // self.size, n * (self.rank + 1) // self.size
            self.padding = hi <= lo
            yield batch[:1] if self.padding else batch[lo:hi]


def global_mean(loss: Tensor, rows: int) -> tuple[Tensor, Tensor]:
    """``(loss to backpropagate, the global batch's mean loss)`` for this rank's mean ``loss`` over ``rows``.

    In a plain run both are ``loss``. Under torchrun the first is ``loss * rows * N / total_rows`` (so that
    the averaged gradients are the global mean's); the second is the row-weighted mean over the ranks.
    """
    _, size = world()
    if size == 1:
        return loss, loss.detach()
    counts = torch.tensor([float(rows), float(loss.detach()) * rows], dtype=torch.float64, device=loss.device)
    dist.all_reduce(counts)
    total = float(counts[0])
    return loss * (rows * size / total), (counts[1] / counts[0]).to(loss.dtype)


def finish() -> None:
    """Leave torchrun's process group (after the last collective of the run)."""
    if dist.is_available() and dist.is_initialized():
        dist.barrier()
        dist.destroy_process_group()


def average_gradients(net: nn.Module) -> None:
    """Average every parameter's gradient over the ranks (a parameter without one counts as zero)."""
    _, size = world()
    if size == 1:
        return
    for p in net.parameters():
        if not p.requires_grad:
            continue
        if p.grad is None:
            p.grad = torch.zeros_like(p)
        dist.all_reduce(p.grad)
        p.grad /= size
