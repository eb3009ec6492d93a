"""Small constant tensors (a scene's gravity, a kernel's shape) made once per device, dtype and value.

``torch.tensor(values, device=cuda)`` copies from host memory with ``non_blocking=False``, which makes the
host wait for the device's queue to drain: once per step, that is a host synchronisation in the step
(``benchmarks/results/host_syncs.md``). Cached, the copy happens once.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import torch
from torch import Tensor


@functools.lru_cache(maxsize=256)
def _cached(values: tuple[float, ...] | float, dtype: torch.dtype, device: torch.device) -> Tensor:
    return torch.tensor(values, dtype=dtype, device=device)


def device_constant(
    values: Sequence[float] | float, dtype: torch.dtype, device: torch.device | str
) -> Tensor:
    """``torch.tensor(values, dtype=dtype, device=device)``, made once and shared: never modify it in place.

    Args:
        values: a number or a flat sequence of numbers (a shape (K,) tensor).
        dtype: its dtype.
        device: its device.
    """
    key = float(values) if isinstance(values, (int, float)) else tuple(float(v) for v in values)
    return _cached(key, dtype, torch.device(device))
