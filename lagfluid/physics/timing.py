"""Seconds per named stage of a step, without a host synchronisation inside the step on CUDA."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import torch


class StageTimer:
    """Seconds per named stage of the last step.

    On the CPU wall-clock time; on CUDA the time between two events the stream records around the block:
    no host synchronisation inside the step (a synchronisation per stage would stall the device at every
    stage boundary). :meth:`read` waits for the last event, after the step.
    """

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._events: list[tuple[str, Any, Any]] = []  # (name, start, end) CUDA events not yet read

    def reset(self) -> None:
        """Forget the last step's times."""
        self.seconds = {}
        self._events = []

    @contextmanager
    def __call__(self, name: str, device: torch.device) -> Iterator[None]:
        """Time the ``with`` block and add it to ``seconds[name]``."""
        if device.type == "cuda":
            stream = torch.cuda.current_stream(device)  # that device's, whichever device is current
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record(stream)
            try:
                yield
            finally:
                end.record(stream)
                self._events.append((name, start, end))
            return
        start_s = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - start_s

    def read(self) -> dict[str, float]:
        """Seconds per stage so far (reading CUDA's events: waits for the device to reach the last one)."""
        for name, start, end in self._events:
            end.synchronize()
            self.seconds[name] = self.seconds.get(name, 0.0) + start.elapsed_time(end) / 1e3
        self._events = []
        return dict(self.seconds)
