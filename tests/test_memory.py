"""``lagfluid.memory.keep_freed_memory``: freed tensors are reused without fresh page faults (glibc)."""

import os
import subprocess
import sys

import pytest

PROBE = """
import ctypes, resource, sys
ctypes.CDLL("libc.so.6").prctl(41, 1, 0, 0, 0)  # PR_SET_THP_DISABLE: count 4 KiB faults, not 2 MiB ones
import torch
from lagfluid.memory import keep_freed_memory
applied = keep_freed_memory() if sys.argv[1] == "keep" else False
def step():
    held = [torch.ones(5_000_000) for _ in range(8)]  # 160 MB of a step's temporaries alive at once
    held.append(torch.ones(60_000_000))  # one of 240 MB (GNS's edge latents at 40k): above any mmap threshold
    return sum(float(t[-1]) for t in held)
for _ in range(3):
    step()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    step()
print(applied, (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 10)
"""


def _faults(mode: str, env: dict | None = None) -> tuple[str, float]:
    out = subprocess.run(
        [sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True, env=env
    ).stdout.split()
    return out[0], float(out[1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_kept_memory_is_reused_without_page_faults():
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    applied, kept = _faults("keep", env)
    if applied != "True":
        pytest.skip("not glibc")
    # Without it glibc trims the 160 MB freed at the heap's top (~39,000 pages of 4 KiB touched afresh every
    # step) and maps the 240 MB block afresh every time (~58,600 pages, even with the mmap threshold at its
    # 32 MiB maximum, the previous setting): with it, none.
    assert kept < 2_000
    assert _faults("keep", env)[1] < 2_000  # every run, not by luck of the heap's layout
    # a user's own MALLOC_ settings win: nothing is changed
    assert _faults("keep", {**env, "MALLOC_ARENA_MAX": "2"})[0] == "False"
