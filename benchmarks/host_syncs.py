"""How often a model's step reads the device: the host synchronisations of its CUDA path, counted on the CPU.

On CUDA the host queues kernels ahead of the device; a read of a device value (``.item()``, ``bool(t)``,
``.tolist()``, ``.cpu()``, ``torch.tensor(..., device=)``'s copy of host data) or an op whose output size
depends on the data (``nonzero``, a boolean mask
index, ``bincount``, ``unique``, ...) makes the host wait for the device to drain its queue. This benchmark
runs a model's *device path* on the CPU (the compiled Numba kernels off, the neighbour search on the torch
cell list: what a CUDA run takes, see :mod:`lagfluid.neighbors`) and counts, per step, every such call,
where it comes from, and whether it is a *read* (a value brought to the host: avoidable by design) or a
*size* (an output whose length depends on the data: inherent in a dynamic graph built with eager PyTorch).

``python -m benchmarks.host_syncs`` writes ``benchmarks/results/host_syncs.{md,csv}``; the test
``tests/test_host_syncs.py`` holds FGN's step to the reads listed there. On a GPU, ``--device cuda`` counts
instead what torch itself reports as synchronising (``torch.cuda.set_sync_debug_mode``, by calling line, all
in the reads column) into ``host_syncs_cuda.{md,csv}``: the check of the CPU count.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import os
import traceback
import warnings
from collections import Counter
from collections.abc import Iterator, Sequence
from pathlib import Path
from statistics import median
from typing import Any

import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from torch.utils._python_dispatch import TorchDispatchMode

import baselines
import lagfluid
from benchmarks.provenance import provenance, write_results
from lagfluid.errors import ConfigError
from lagfluid.neighbors import pair_kernels, search
from lagfluid.rollout import rollout
from lagfluid.run import CONF_DIR
from lagfluid.tasks.config import at_simulator_time_step, build_initial_state, build_simulator, run_device

RESULTS = Path(__file__).resolve().parent / "results"

# aten ops that bring a value to the host (reads) or size their output from the data (sizes); on CUDA each
# waits for the device. (torch.cuda.set_sync_debug_mode reports these too, but only on a CUDA device.)
READ_OPS = frozenset({"_local_scalar_dense", "equal", "is_nonzero", "allclose"})
SIZE_OPS = frozenset(
    {"nonzero", "masked_select", "_unique2", "unique_dim", "unique_consecutive", "bincount", "argwhere"}
)
# Tensor methods that read the whole tensor on the host (not aten ops on the CPU, so patched here).
READ_METHODS = ("tolist", "numpy", "cpu")
# Factories that copy host data (not a tensor) to their ``device=``: on CUDA a blocking copy (the host waits
# for the queue). Counted as reads ("upload") when given a device; copies by ``Tensor.to`` are not counted.
UPLOAD_FACTORIES = ("tensor", "as_tensor")
# The package's and the baselines' folders, as absolute paths: a name match ("/lagfluid/") would also take
# every file of a checkout cloned into a folder called lagfluid (this file and the tests included).
_OURS = tuple(str(Path(m.__file__).resolve().parent) + os.sep for m in (lagfluid, baselines))


@functools.cache
def _is_ours(filename: str) -> bool:
    """Whether the source file ``filename`` (as a frame names it) lies in the package or the baselines."""
    return str(Path(filename).resolve()).startswith(_OURS)


def _caller() -> str:
    """``file:line function`` of the innermost frame of the package (or the baselines) on the stack."""
    for frame in reversed(traceback.extract_stack()):
        if _is_ours(frame.filename):
            return f"{Path(frame.filename).name}:{frame.lineno} {frame.name}"
    return "elsewhere"


class HostSyncCounter(TorchDispatchMode):
    """Counts the calls that synchronise a CUDA host with its device, by kind and by calling line.

    Use as a context manager around CPU code. ``reads`` and ``sizes`` map ``"op file:line function"`` to a
    count; :meth:`total` sums them.
    """

    def __init__(self) -> None:
        super().__init__()
        self.reads: Counter[str] = Counter()
        self.sizes: Counter[str] = Counter()
        self._patched: dict[str, Any] = {}

    def __torch_dispatch__(self, func: Any, types: Any, args: Sequence[Any] = (), kwargs: Any = None) -> Any:
        name = func.__name__.split(".")[0]
        if name in READ_OPS:
            self.reads[f"{name} {_caller()}"] += 1
        elif name in SIZE_OPS or (name == "repeat_interleave" and not (kwargs or {}).get("output_size")):
            self.sizes[f"{name} {_caller()}"] += 1
        elif name in ("index", "index_put", "index_put_", "_index_put_impl_") and any(
            t is not None and t.dtype == torch.bool for t in args[1]
        ):
            self.sizes[f"{name}[mask] {_caller()}"] += 1
        return func(*args, **(kwargs or {}))

    def __enter__(self) -> HostSyncCounter:
        for factory in UPLOAD_FACTORIES:
            make = getattr(torch, factory)
            self._patched[f"torch.{factory}"] = make

            def uploaded(*a: Any, _make: Any = make, **k: Any) -> Any:
                if k.get("device") is not None and not (a and isinstance(a[0], torch.Tensor)):
                    self.reads[f"upload {_caller()}"] += 1
                return _make(*a, **k)

            setattr(torch, factory, uploaded)
        for method in READ_METHODS:
            original = getattr(torch.Tensor, method)
            self._patched[method] = original

            def counted(
                tensor: torch.Tensor, *a: Any, _name: str = method, _f: Any = original, **k: Any
            ) -> Any:
                self.reads[f"{_name} {_caller()}"] += 1
                return _f(tensor, *a, **k)

            setattr(torch.Tensor, method, counted)
        return super().__enter__()

    def __exit__(self, *exc: Any) -> None:
        for name, original in self._patched.items():
            if name.startswith("torch."):
                setattr(torch, name.removeprefix("torch."), original)
            else:
                setattr(torch.Tensor, name, original)
        self._patched = {}
        return super().__exit__(*exc)

    def total(self) -> int:
        """Every counted call."""
        return sum(self.reads.values()) + sum(self.sizes.values())


class CudaSyncCounter:
    """On CUDA: every synchronisation torch reports (``torch.cuda.set_sync_debug_mode("warn")``), by line.

    Same ``reads`` / ``sizes`` / :meth:`total` as :class:`HostSyncCounter`; torch does not say which kind a
    synchronisation is, so all go to ``reads``.
    """

    def __init__(self) -> None:
        self.reads: Counter[str] = Counter()
        self.sizes: Counter[str] = Counter()
        self._catcher: Any = None
        self._caught: list[warnings.WarningMessage] = []

    def __enter__(self) -> CudaSyncCounter:
        self._catcher = warnings.catch_warnings(record=True)
        self._caught = self._catcher.__enter__()
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        return self

    def __exit__(self, *exc: Any) -> None:
        torch.cuda.set_sync_debug_mode("default")
        self._catcher.__exit__(*exc)
        for w in self._caught:
            if "synchroniz" in str(w.message):
                self.reads[f"cuda_sync {Path(w.filename).name}:{w.lineno}"] += 1

    def total(self) -> int:
        """Every counted synchronisation."""
        return sum(self.reads.values())


@contextlib.contextmanager
def device_path() -> Iterator[None]:
    """Run the CPU through the code a CUDA device takes.

    Every compiled Numba path off, and the neighbour search ``"auto"`` on the torch cell list (CUDA's choice
    without the optional torch_cluster).

    The exact MPS pressure solve still takes its CPU helpers (SciPy components, assembly): on CUDA it runs
    its torch forms, so MPS's counts here are a partial picture of its CUDA path.
    """
    applies, resolve = pair_kernels.applies, search._resolve_backend

    def on_device(backend: str, device: torch.device) -> str:
        return "cell_list" if backend == "auto" else resolve(backend, device)

    pair_kernels.applies = lambda *tensors: False  # type: ignore[assignment]
    search._resolve_backend = on_device  # type: ignore[assignment]
    try:
        yield
    finally:
        pair_kernels.applies = applies  # type: ignore[assignment]
        search._resolve_backend = resolve  # type: ignore[assignment]


def device_path_simulation(model: str, scene: str, warmup: int, device: str = "cpu") -> tuple[Any, Any]:
    """``model``'s simulator on ``scene`` after ``warmup`` steps (on the CPU: inside :func:`device_path`)."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            config_name="config",
            # the PPE solver a CUDA run takes ("auto" picks it there)
            overrides=[
                f"model={model}",
                f"scene={scene}",
                f"device={device}",
                "solver.ppe.method=torch_cg",
            ],
        )
    sim = build_simulator(cfg)
    state = at_simulator_time_step(build_initial_state(cfg), sim, cfg)
    state, _ = rollout(sim, state, warmup)
    return sim, state


def count_steps(
    sim: Any, state: Any, steps: int, counter_type: type = HostSyncCounter
) -> tuple[Any, list[Any], list[float]]:
    """Each of ``steps`` steps' counter (the step alone, not the rollout's guard) and its list rebuilds."""
    counters, rebuilds = [], []
    for _ in range(steps):
        counter = counter_type()
        with counter:
            state = sim.step(state)
        counters.append(counter)
        rebuilds.append(float(sim.last_info.get("list_rebuilds", 0.0)))
    return state, counters, rebuilds


def measure(
    model: str, scene: str, warmup: int, steps: int, device: str = "cpu"
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """A summary row of ``model`` on ``scene`` and one row per calling line (per-step means).

    ``device="cpu"``: the CUDA code path run on the CPU, counted by :class:`HostSyncCounter`; a CUDA device:
    the run itself, counted by :class:`CudaSyncCounter`.
    """
    if torch.device(device).type == "cuda":
        sim, state = device_path_simulation(model, scene, warmup, device)
        state, counters, rebuilds = count_steps(sim, state, steps, CudaSyncCounter)
    else:
        with device_path():
            sim, state = device_path_simulation(model, scene, warmup)
            state, counters, rebuilds = count_steps(sim, state, steps)
    steady = [c for c, r in zip(counters, rebuilds, strict=True) if r == 0] or counters
    summary = {
        "model": model,
        "scene": scene,
        "fluid": state.n_fluid,
        "steps": steps,
        "steps_with_rebuild": sum(1 for r in rebuilds if r > 0),
        "reads_per_step_median": median(sum(c.reads.values()) for c in steady),
        "sizes_per_step_median": median(sum(c.sizes.values()) for c in steady),
        "syncs_per_step_mean": sum(c.total() for c in counters) / len(counters),
    }
    per_line: Counter[tuple[str, str]] = Counter()
    for c in steady:
        for kind, table in (("read", c.reads), ("size", c.sizes)):
            for where, n in table.items():
                per_line[kind, where] += n
    rows = [
        {"model": model, "kind": kind, "where": where, "per_steady_step": round(n / len(steady), 2)}
        for (kind, where), n in sorted(per_line.items(), key=lambda kv: (kv[0][0], -kv[1]))
    ]
    return summary, rows


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m benchmarks.host_syncs``."""
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.host_syncs", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--models", nargs="+", default=["fgn", "mps", "gns", "cconv"])
    parser.add_argument("--scene", default="dam")
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument(
        "--device", default="cpu", help="cpu (the CUDA path, counted here) or cuda (torch's own count)"
    )
    parser.add_argument("--results", default=str(RESULTS))
    parser.add_argument("--name", default=None, help="default: host_syncs, host_syncs_cuda on CUDA")
    args = parser.parse_args(argv)
    try:
        on_cuda = run_device(OmegaConf.create({"device": args.device})).type == "cuda"
    except ConfigError as err:
        parser.error(f"--device {args.device}: {err}")
    args.name = args.name or ("host_syncs_cuda" if on_cuda else "host_syncs")
    load = os.getloadavg()[0]
    summaries, rows = [], []
    for model in args.models:
        summary, model_rows = measure(model, args.scene, args.warmup, args.steps, args.device)
        summaries.append(summary)
        rows += model_rows
    lines = [
        f"| {s['model']} | {s['fluid']:,} | {s['reads_per_step_median']:g} | "
        f"{s['sizes_per_step_median']:g} | {s['steps_with_rebuild']} of {s['steps']} | "
        f"{s['syncs_per_step_mean']:.1f} |"
        for s in summaries
    ]
    intro = "\n".join(
        [
            "# Host synchronisations per step on the device path "
            f"(`benchmarks/host_syncs.py`, scene {args.scene})",
            "",
            "Each model's CUDA code path, run on the CPU (Numba off, torch cell list), counted per step "
            f"after {args.warmup} warm-up steps, over {args.steps} steps. A *read* brings a device value "
            "to the host (`.item()`, `bool()`, `.tolist()`); a *size* is an op whose output length depends "
            "on the data (`nonzero`, a mask index): on CUDA each makes the host wait for the device. Steady "
            "steps: those without a rebuild of the neighbour list. The rollout's guard adds one read per "
            "checked step."
            + (
                " This run: on CUDA, every synchronisation torch reports (set_sync_debug_mode), all under "
                "reads."
                if on_cuda
                else ""
            ),
            "",
            "| model | fluid | reads / steady step | sizes / steady step | steps with a rebuild "
            "| syncs / step (mean, all) |",
            "|---|---|---|---|---|---|",
            *lines,
            "",
            "Rows below: per calling line, its mean count per steady step.",
        ]
    )
    prov = provenance("benchmarks.host_syncs", load, args.device, scene=args.scene)
    write_results(Path(args.results), args.name, rows, intro, prov)
    print(intro)
    print(f"wrote {Path(args.results) / args.name}.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
