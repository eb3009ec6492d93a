"""The device path of a step reads the device only where it must (``benchmarks/host_syncs.py``).

On CUDA every read of a device value stalls the host until the device drains its queue. These tests run
the code a CUDA device takes on the CPU (Numba off, the torch cell list) and count those reads, so a new
``.item()`` in a stage fails here, without a GPU.
"""

from __future__ import annotations

import contextlib
import importlib.util
from pathlib import Path

import pytest
import torch

import lagfluid
from benchmarks.host_syncs import HostSyncCounter, count_steps, device_path, device_path_simulation
from lagfluid.rollout import Guard

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")

# Where a steady step of FGN (no rebuild of its neighbour list) may read the device, and why it must.
FGN_READS = {
    "needs_rebuild": "the Verlet list's rebuild test, once per set of positions it is asked at",
    "moved": "the displacement since an anchor graph, which sets the radius a derived graph is cut at",
    "_derive": "whether a wall newly within reach of the fluid needs the full filter",
    "_adjacency_torch": "a CSR matrix's range and order checks (kernel_adjacency), one read per matrix",
}


def _function(where: str) -> str:
    """The function name of a counter key ``"op file:line function"``."""
    return where.rsplit(" ", 1)[1]


@pytest.fixture(scope="module")
def fgn_steady_steps():
    with device_path():
        sim, state = device_path_simulation("fgn", "dam", warmup=3)
        _, counters, rebuilds = count_steps(sim, state, 3)
    steady = [c for c, r in zip(counters, rebuilds, strict=True) if r == 0]
    assert steady, "every counted step rebuilt the neighbour list: no steady step to check"
    return steady


def test_fgn_steady_step_reads_the_device_only_where_it_must(fgn_steady_steps):
    for counter in fgn_steady_steps:
        unexpected = {w: n for w, n in counter.reads.items() if _function(w) not in FGN_READS}
        assert not unexpected, f"reads of the device outside {sorted(FGN_READS)}: {unexpected}"
        # numpy()/cpu() would fail on a CUDA tensor: the device path must never take them
        assert not [w for w in counter.reads if w.startswith(("numpy ", "cpu "))]
        assert sum(counter.reads.values()) <= 7, dict(counter.reads)


def test_fgn_steady_step_sizes_only_its_graphs(fgn_steady_steps):
    # data-dependent sizes: the graphs at each radius and the stages' node sets (nonzero), never a mask
    # index on a hot path
    for counter in fgn_steady_steps:
        assert sum(counter.sizes.values()) <= 16, dict(counter.sizes)
        assert all(w.startswith("nonzero ") for w in counter.sizes), dict(counter.sizes)


def test_counter_sees_a_read_a_mask_and_an_upload():
    # the counter itself: it must see what it claims to count
    x = torch.arange(5.0)
    with HostSyncCounter() as counter:
        float(x.sum())
        x[x > 2]
        x.tolist()
        torch.tensor([1.0, 2.0], device=x.device)
        torch.tensor([1.0, 2.0])  # made where it is used: no copy to a device
    assert sum(counter.reads.values()) == 3 and sum(counter.sizes.values()) == 1
    assert torch.tensor is not None and torch.Tensor.tolist(x) == [0.0, 1.0, 2.0, 3.0, 4.0]


def test_reads_are_attributed_to_the_package_not_to_a_folder_that_shares_its_name(tmp_path):
    # a checkout cloned into a folder called lagfluid: its tests and benchmarks are not the package
    clone = tmp_path / "lagfluid" / "tests"
    clone.mkdir(parents=True)
    (clone / "reader.py").write_text("def read(x):\n    return float(x.sum())\n")
    spec = importlib.util.spec_from_file_location("reader_in_a_clone", clone / "reader.py")
    reader = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(reader)
    with device_path():
        _, state = device_path_simulation("fgn", "dam", warmup=1)
    with HostSyncCounter() as counter:
        reader.read(torch.arange(3.0))
        Guard().check(state)  # one read, in the package
    reads = dict(counter.reads)
    assert reads.pop("_local_scalar_dense elsewhere", 0) == 1, dict(counter.reads)
    package = Path(lagfluid.__file__).parent
    assert len(reads) == 1 and all(any(package.rglob(w.split()[1].split(":")[0])) for w in reads), reads


def test_guard_reads_a_passing_state_once():
    with device_path():
        _, state = device_path_simulation("fgn", "dam", warmup=1)
    with HostSyncCounter() as counter:
        Guard().check(state)
    assert counter.total() == 1, dict(counter.reads) | dict(counter.sizes)


@CUDA
@pytest.mark.parametrize("model", ["fgn", "gns", "cconv"])
def test_cuda_rollout_matches_the_cpu_device_path(model):
    from hydra import compose, initialize_config_dir

    from lagfluid.rollout import rollout
    from lagfluid.run import CONF_DIR
    from lagfluid.tasks.config import at_simulator_time_step, build_initial_state, build_simulator

    finals = {}
    for device in ("cpu", "cuda"):
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(config_name="config", overrides=[f"model={model}", "scene=dam", f"device={device}"])
        sim = build_simulator(cfg)
        state = at_simulator_time_step(build_initial_state(cfg), sim, cfg)
        finals[device], record = rollout(sim, state, 10)
        assert all(v and min(v) >= 0 for v in record["stage_seconds"].values())
    assert finals["cuda"].pos.device.type == "cuda"
    torch.testing.assert_close(finals["cuda"].pos.cpu(), finals["cpu"].pos, rtol=0, atol=1e-5)


@pytest.mark.parametrize("model", ["fgn", "mps"])
def test_device_path_rollout_is_the_compiled_paths(model):
    # what CUDA runs (torch ops throughout) and the CPU's compiled kernels: the same pairs, the same sums
    from hydra import compose, initialize_config_dir

    from lagfluid.rollout import rollout
    from lagfluid.run import CONF_DIR
    from lagfluid.tasks.config import build_initial_state, build_simulator

    def final(on_device_path: bool):
        with contextlib.ExitStack() as stack:
            if on_device_path:
                stack.enter_context(device_path())
            with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
                cfg = compose(config_name="config", overrides=[f"model={model}", "scene=dam"])
            state, record = rollout(build_simulator(cfg), build_initial_state(cfg), 40)
        return state, sum(record["info"]["list_rebuilds"])

    (compiled, builds), (device, device_builds) = final(False), final(True)
    assert builds >= 2 and device_builds == builds  # rebuilds of the list included
    for name in ("pos", "vel", "pressure"):
        assert torch.equal(getattr(device, name), getattr(compiled, name)), name


def test_cuda_counter_counts_what_torch_reports_as_synchronising(monkeypatch):
    # torch's sync debug mode needs CUDA; what the counter does with its warnings is checked here
    import warnings

    from benchmarks.host_syncs import CudaSyncCounter

    modes = []
    monkeypatch.setattr(torch.cuda, "set_sync_debug_mode", modes.append)
    with CudaSyncCounter() as counter:
        warnings.warn("called a synchronizing CUDA operation", UserWarning, stacklevel=1)
        warnings.warn("called a synchronizing CUDA operation", UserWarning, stacklevel=1)
        warnings.warn("something else", UserWarning, stacklevel=1)
    assert counter.total() == 2 and modes == ["warn", "default"]
    assert all(key.startswith("cuda_sync test_host_syncs.py:") for key in counter.reads)
