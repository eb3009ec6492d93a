"""Process-wide allocator settings for long simulations: :func:`keep_freed_memory`."""

from __future__ import annotations

import ctypes
import logging
import os
import sys

log = logging.getLogger(__name__)

# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
_SETTINGS = {
    _M_MMAP_THRESHOLD: 32 << 20,  # glibc's largest: blocks up to 32 MiB come from the heap, not fresh mmap
    _M_TRIM_THRESHOLD: 1 << 30,  # keep up to 1 GiB of free heap instead of returning it after every step
    _M_TOP_PAD: 256 << 20,  # grow the heap in 256 MiB steps
}


def keep_freed_memory() -> bool:
    """Let glibc's malloc keep freed blocks for reuse instead of handing them back to the OS.

    A simulation step allocates and frees the same few hundred MB of tensors every step. By default glibc
    serves large blocks with fresh ``mmap`` pages and trims the heap after frees, so every step pays a page
    fault per 4 KiB it touches again (~40k per step at 40,000 particles); kept, FGN's step at 40,000 fluid
    particles went from 132 to 112 ms on 2 cores (``benchmarks/results/fgn_step_speed.md``). The price: the
    process keeps its peak memory until it ends. Called by the command-line entry points, not on import.

    Returns:
        True when applied; False off glibc or when the user set ``MALLOC_*`` variables (theirs win).
    """
    if not sys.platform.startswith("linux") or any(k.startswith("MALLOC_") for k in os.environ):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl or another libc: nothing to tune
        return False
    applied = all(mallopt(param, value) == 1 for param, value in _SETTINGS.items())
    log.debug("malloc keeps freed memory: %s", applied)
    return applied
