"""Progress of a long loop: a tqdm bar on a terminal, a log line every 10 % anywhere else.

Without a terminal (a log file, SLURM, ``nohup``, a Hydra multirun) tqdm's carriage-return updates pile up
into one unreadable line; there, :class:`LogProgress` writes one line per tenth of the work instead.

Both have :meth:`~LogProgress.restart_clock`: a rollout's first step also compiles the CPU kernels on a fresh
install (~18 s) and builds the first neighbour list, so its rate and time left are counted from the end of
that step, not from the start.
"""

from __future__ import annotations

import logging
import sys
import time
from typing import Any

from tqdm import tqdm

log = logging.getLogger(__name__)


class LogProgress:
    """tqdm's ``update`` / ``set_postfix`` / ``close`` as a log line at every ``every`` fraction of ``total``.

    Args:
        total: units of work.
        initial: units already done (a resumed run).
        desc: what is counted, first on every line.
        unit: the unit's name.
        every: the fraction of ``total`` between two lines.
    """

    def __init__(
        self, total: int, initial: int = 0, desc: str = "", unit: str = "it", every: float = 0.1
    ) -> None:
        self.total, self.n, self.desc, self.unit = int(total), int(initial), desc, unit
        self.step = max(1, round(every * self.total))
        self.next = (self.n // self.step + 1) * self.step
        self.began = time.perf_counter()  # for the elapsed time shown
        self.start_n, self.start = self.n, self.began  # for the rate and the time left
        self.postfix = ""

    def update(self, n: int = 1) -> None:
        """Count ``n`` more units; log a line when a tenth of the work (or all of it) is done."""
        self.n += n
        if self.n >= self.next or self.n == self.total:
            self.next = (self.n // self.step + 1) * self.step
            now = time.perf_counter()
            timed = now - self.start
            rate = (self.n - self.start_n) / timed if timed > 0 else float("inf")
            left = (self.total - self.n) / rate if rate > 0 else float("nan")
            log.info(
                "%s: %d/%d %s (%.0f %%), %.3g %s/s, %.0f s elapsed, ~%.0f s left%s",
                self.desc,
                self.n,
                self.total,
                self.unit,
                100 * self.n / max(self.total, 1),
                rate,
                self.unit,
                now - self.began,
                left,
                self.postfix,
            )

    def restart_clock(self) -> None:
        """Count the rate (and the time left) from now on: the work so far was a warm-up."""
        self.start_n, self.start = self.n, time.perf_counter()

    def set_postfix(self, **values: Any) -> None:
        """Shown at the end of the next line."""
        self.postfix = ", " + ", ".join(f"{k}={v}" for k, v in values.items())

    def close(self) -> None:
        """Nothing to release (tqdm's interface)."""


class ProgressBar(tqdm):
    """tqdm with :meth:`restart_clock`."""

    def restart_clock(self) -> None:
        """Count the rate and the time left from now on (tqdm's smoothed rate would remember a slow start)."""
        if self.disable:
            return
        done = self.n
        self.reset(self.total)  # a fresh clock and fresh rate averages, at a count of 0
        self.n = self.last_print_n = self.initial = done  # tqdm's plain average counts from `initial`
        self.refresh()


def progress_bar(
    total: int, *, enabled: bool, initial: int = 0, desc: str = "", unit: str = "it"
) -> ProgressBar | LogProgress:
    """A tqdm bar when stderr is a terminal, else a :class:`LogProgress`; disabled: a silent tqdm."""
    if enabled and not sys.stderr.isatty():
        return LogProgress(total, initial, desc, unit)
    return ProgressBar(
        total=total, initial=initial, desc=desc, unit=unit, disable=not enabled, dynamic_ncols=True
    )
