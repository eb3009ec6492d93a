"""Where FGN's step goes, op by op, against what the machine can do: ``python -m benchmarks.fgn_speed``.

    python -m benchmarks.fgn_speed [--scenes dam_medium dam_large] [--warmup 5] [--steps 5] [--threads 2]

Per scene: ``--warmup`` steps (lazy set-up, the first neighbour list), then ``--steps`` steps under
``torch.profiler`` (CPU, shapes and FLOPs recorded), every stage of the step (the simulator's
:class:`~lagfluid.physics.timing.StageTimer` names: neighbours, advection, collision, pressure net,
correction) marked as a profiler range. Each torch op called in a stage (with what it calls) counts for
that stage and its kind: ``linear`` (dense matmuls), ``layer_norm``, ``sparse`` (CSR products),
``activation``, ``gather/scatter`` (index_select, scatter, index_add), ``elementwise`` and ``other``; a
stage's time outside torch ops (the Numba neighbour filter and gradient kernels, Python) is
``compiled/python``.

Bounds: the machine's dense float32 matmul rate (2048^2 ``torch.mm``, median of 5) and memory bandwidth
(a 256 MiB copy, median of 5) are measured in the same run; a kind's bound is ``max(FLOPs / rate, bytes /
bandwidth)`` with the dense layers' FLOPs (2 M K N per ``nn.Linear``) and bytes read = the inputs' sizes
(a lower bound of the traffic), so ``time / bound`` says how far each kind is from what the hardware
allows. Results: ``benchmarks/results/fgn_speed.{md,csv}`` with provenance; compare numbers of one run only.

``--rebuilds K``: also K forced rebuilds of the model's Verlet list at the warmed-up positions, under
``cProfile``: each function's cumulative ms per rebuild (``<name>_rebuild.{md,csv}``), since over a whole
flowing dam the rebuilds, not the per-step work, take most of the step (``fgn_step_speed.md``).
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import math
import os
import pstats
import time
from collections import defaultdict
from collections.abc import Iterator, Sequence
from pathlib import Path
from statistics import median
from typing import Any

import torch
from hydra import compose, initialize_config_dir
from torch.profiler import ProfilerActivity, profile, record_function

from benchmarks.provenance import provenance, write_results
from lagfluid.memory import keep_freed_memory
from lagfluid.models.simulator import Simulator
from lagfluid.physics.timing import StageTimer
from lagfluid.rollout import rollout
from lagfluid.run import CONF_DIR
from lagfluid.state import ParticleState
from lagfluid.tasks.config import at_simulator_time_step, build_initial_state, build_simulator

RESULTS = Path(__file__).resolve().parent / "results"
# The networks' dense layers are nn.Linear (aten::linear); a matmul called directly in a stage is one of the
# kernel-weighted adjacency products (a CSR matrix times the node features), hence sparse (CConv's layers
# also multiply their inputs by the kernel's cells with a dense matmul, counted there too). The profiler
# gives a CSR matrix by its dense shape, so a sparse row has no byte count and no bound.
KINDS = {
    "linear": ("aten::linear",),
    "layer_norm": ("aten::native_layer_norm", "aten::layer_norm"),
    "sparse": ("aten::addmm", "aten::mm", "aten::bmm", "aten::matmul", "sparse", "csr", "spmm"),
    "activation": ("aten::silu", "aten::relu", "aten::tanh", "aten::sigmoid", "aten::gelu"),
    "gather/scatter": ("index_select", "scatter", "index_add", "gather", "index", "take"),
    "elementwise": ("aten::add", "aten::mul", "aten::div", "aten::sub", "aten::pow", "aten::sqrt",
                    "aten::where", "aten::clamp", "aten::neg", "aten::rsub", "aten::copy_", "aten::fill_",
                    "aten::zero_", "aten::reciprocal", "aten::lt", "aten::gt", "aten::bitwise",
                    "aten::masked_fill"),
}  # fmt: skip
OUTSIDE = "compiled/python"


def kind_of(op: str) -> str:
    """The kind of a torch op name (``aten::addmm`` -> ``linear``); ``other`` when none matches."""
    for kind, needles in KINDS.items():
        if any(n in op for n in needles):
            return kind
    return "other"


def machine_rates(repeats: int = 5) -> dict[str, float]:
    """Dense float32 matmul GFLOP/s (2048^2) and copy bandwidth GB/s (256 MiB, read + write), medians."""
    a, b = torch.randn(2048, 2048), torch.randn(2048, 2048)
    times = []
    for _ in range(repeats + 1):
        start = time.perf_counter()
        torch.mm(a, b)
        times.append(time.perf_counter() - start)
    flops = 2 * 2048**3 / median(times[1:])
    src = torch.empty(64 * 1024 * 1024)  # 256 MiB of float32
    dst = torch.empty_like(src)
    src.fill_(1.0)
    copies = []
    for _ in range(repeats + 1):
        start = time.perf_counter()
        dst.copy_(src)
        copies.append(time.perf_counter() - start)
    return {"matmul_gflops": flops / 1e9, "copy_gbs": 2 * src.numel() * 4 / median(copies[1:]) / 1e9}


@contextlib.contextmanager
def stages_as_profiler_ranges() -> Iterator[None]:
    """Make every :class:`StageTimer` block a ``record_function`` range named ``stage:<name>``."""
    original = StageTimer.__call__

    @contextlib.contextmanager
    def marked(self: StageTimer, name: str, device: torch.device):
        with record_function(f"stage:{name}"), original(self, name, device):
            yield

    StageTimer.__call__ = marked  # type: ignore[method-assign]
    try:
        yield
    finally:
        StageTimer.__call__ = original  # type: ignore[method-assign]


def _bytes(shapes: Sequence[Sequence[int]] | None) -> float:
    """Bytes of an op's inputs (float32 assumed): a lower bound of its memory traffic."""
    return float(sum(4 * math.prod(s) for s in shapes or () if s))


def _linear_flops(event: Any) -> float:
    """2 M K N of an ``aten::linear`` (inputs (..., K) and (N, K)); 0 for any other op.

    The profiler's own FLOP count treats a sparse CSR operand as dense (2 n^2 k for an n x n adjacency),
    so it is not used.
    """
    shapes = event.input_shapes or []
    if event.name != "aten::linear" or len(shapes) < 2 or not shapes[0] or not shapes[1]:
        return 0.0
    return 2.0 * math.prod(shapes[0]) * shapes[1][0]


def attribute(events: Any, steps: int) -> dict[tuple[str, str], dict[str, float]]:
    """Per (stage, kind): ms per step, MFLOP and MB per step, from the profiler's event list.

    The unit is a torch op called directly in a stage (``aten::linear``, ``aten::index_select``, ...): its
    whole time, its subtree's FLOPs and its inputs' bytes go to its kind (an ``aten::linear``'s bias copy and
    GEMM stay ``linear``). A stage range's own self time (outside every torch op in it) is :data:`OUTSIDE`.
    """
    out: dict[tuple[str, str], dict[str, float]] = defaultdict(lambda: {"ms": 0.0, "mflop": 0.0, "mb": 0.0})
    for e in events:
        if e.name.startswith("stage:"):
            out[(e.name[6:], OUTSIDE)]["ms"] += e.self_cpu_time_total / 1e3 / steps
            continue
        parent = e.cpu_parent
        if parent is None or not parent.name.startswith("stage:"):
            continue  # not called directly in a stage: counted with the op that called it
        kind = kind_of(e.name)
        cell = out[(parent.name[6:], kind)]
        cell["ms"] += e.cpu_time_total / 1e3 / steps
        cell["mflop"] += _linear_flops(e) / 1e6 / steps
        if kind != "sparse":  # a CSR matrix's shape is its dense one: no byte count (KINDS)
            cell["mb"] += _bytes(e.input_shapes) / 1e6 / steps
    return out


def warmed_up(scene: str, warmup: int, model: str, threads: int) -> tuple[Simulator, ParticleState]:
    """``model``'s simulator on ``scene`` and its state after ``warmup`` steps (lazy set-up done)."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            config_name="config", overrides=[f"model={model}", f"scene={scene}", f"threads={threads}"]
        )
    sim = build_simulator(cfg)
    state = at_simulator_time_step(build_initial_state(cfg), sim, cfg)  # GNS steps by its frame spacing
    state, _ = rollout(sim, state, warmup)
    return sim, state


def measure(
    scene: str, warmup: int, steps: int, model: str, threads: int
) -> tuple[list[dict[str, Any]], dict]:
    """The profile rows of ``model`` on ``scene`` and its plain step times (median ms)."""
    sim, state = warmed_up(scene, warmup, model, threads)
    state, plain = rollout(sim, state, steps, reset=False)  # unprofiled: the honest step time
    with (
        stages_as_profiler_ranges(),
        profile(activities=[ProfilerActivity.CPU], record_shapes=True, with_flops=True) as prof,
    ):
        state, _ = rollout(sim, state, steps, reset=False)
    cells = attribute(prof.events(), steps)
    rows = [
        {
            "scene": scene,
            "fluid": state.n_fluid,
            "stage": stage,
            "kind": kind,
            **{k: round(v, 3) for k, v in c.items()},
        }
        for (stage, kind), c in sorted(cells.items(), key=lambda kv: -kv[1]["ms"])
    ]
    summary = {
        "scene": scene,
        "fluid": state.n_fluid,
        "step_ms": 1e3 * median(plain["step_seconds"]),
        "stages_ms": {k: 1e3 * median(v) for k, v in plain["stage_seconds"].items()},
    }
    return rows, summary


def rebuild_profile(scene: str, warmup: int, rebuilds: int, model: str, threads: int) -> list[dict[str, Any]]:
    """Cumulative ms per rebuild of each function in ``rebuilds`` forced rebuilds of the model's Verlet list.

    The list is the simulator's own (its cutoff, skin and wall hops), after ``warmup`` steps; each rebuild is
    ``reset()`` then ``update()`` at the same positions. Rows: the functions under ``update`` that take at
    least 1 % of it, largest first, with their share of the whole rebuild.
    """
    sim, state = warmed_up(scene, warmup, model, threads)
    neighbors = sim.neighbors
    neighbors.reset()
    neighbors.update(state.pos, state.ptype)  # compiled kernels warm
    profiler = cProfile.Profile()
    for _ in range(rebuilds):
        neighbors.reset()
        profiler.enable()
        neighbors.update(state.pos, state.ptype)
        profiler.disable()
    # (file, line, name) -> (calls, primitive calls, own time, cumulative time, callers)
    stats = pstats.Stats(profiler).stats
    total = max(cum for (_, _, _, cum, _) in stats.values())
    rows = []
    for (file, line, name), (calls, _, own, cum, _) in sorted(stats.items(), key=lambda kv: -kv[1][3]):
        if cum < 0.01 * total:
            break
        where = f"{Path(file).name}:{line}" if file != "~" else "built-in"
        rows.append(
            {
                "scene": scene,
                "fluid": state.n_fluid,
                "candidates": int(neighbors.candidates.shape[1]),
                "function": f"{name} ({where})",
                "calls_per_rebuild": round(calls / rebuilds, 1),
                "ms_per_rebuild": round(1e3 * cum / rebuilds, 2),
                "own_ms_per_rebuild": round(1e3 * own / rebuilds, 2),
                "share": round(cum / total, 3),
            }
        )
    return rows


def with_bounds(rows: list[dict[str, Any]], rates: dict[str, float]) -> list[dict[str, Any]]:
    """Each row with its bound (ms) and time / bound."""
    out = []
    for r in rows:
        bound_ms = 1e3 * max(
            r["mflop"] * 1e6 / (rates["matmul_gflops"] * 1e9), r["mb"] * 1e6 / (rates["copy_gbs"] * 1e9)
        )
        ratio = r["ms"] / bound_ms if bound_ms > 0 else math.nan
        out.append(
            {
                **r,
                "bound_ms": round(bound_ms, 3),
                "time_over_bound": round(ratio, 1) if math.isfinite(ratio) else "",
            }
        )
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m benchmarks.fgn_speed``."""
    keep_freed_memory()  # as the CLI does: the timings are a user's
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.fgn_speed", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--scenes", nargs="+", default=["dam_medium", "dam_large"])
    parser.add_argument("--model", default="fgn")
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--results", default=str(RESULTS))
    parser.add_argument("--name", default="fgn_speed")
    parser.add_argument("--rebuilds", type=int, default=0, help="also profile K forced Verlet-list rebuilds")
    args = parser.parse_args(argv)
    load = os.getloadavg()[0]
    torch.set_num_threads(args.threads)
    rates = machine_rates()
    rows, summaries = [], []
    for scene in args.scenes:
        scene_rows, summary = measure(scene, args.warmup, args.steps, args.model, args.threads)
        rows += with_bounds(scene_rows, rates)
        summaries.append(summary)
    steps = "; ".join(
        f"{s['scene']} ({s['fluid']:,} fluid): {s['step_ms']:.0f} ms/step unprofiled ("
        + ", ".join(f"{k} {v:.0f}" for k, v in s["stages_ms"].items())
        + ")"
        for s in summaries
    )
    intro = (
        f"# Where {args.model}'s step goes (`benchmarks/fgn_speed.py`)\n\n"
        f"Machine: dense float32 matmul {rates['matmul_gflops']:.0f} GFLOP/s, copy bandwidth "
        f"{rates['copy_gbs']:.1f} GB/s (measured in this run). Step time: {steps}. Rows: ms, MFLOP and MB "
        "read per step of each stage and op kind (profiled steps run slower than plain ones); "
        "bound = max(FLOPs / matmul rate, bytes / bandwidth); time_over_bound: how far from that bound."
    )
    prov = provenance("benchmarks.fgn_speed", load, threads=str(args.threads))
    write_results(Path(args.results), args.name, rows, intro, prov)
    print(f"wrote {Path(args.results) / args.name}.md")
    if args.rebuilds > 0:
        rebuild_rows = []
        for scene in args.scenes:
            rebuild_rows += rebuild_profile(scene, args.warmup, args.rebuilds, args.model, args.threads)
        intro = (
            f"# Where a rebuild of {args.model}'s Verlet list goes (`benchmarks/fgn_speed.py --rebuilds "
            f"{args.rebuilds}`)\n\nThe simulator's own list after {args.warmup} steps, rebuilt "
            f"{args.rebuilds} times at the same positions under cProfile (which adds a little to each "
            "Python call): each function's cumulative and own ms per rebuild and its share of the whole "
            "`update`."
        )
        write_results(Path(args.results), f"{args.name}_rebuild", rebuild_rows, intro, prov)
        print(f"wrote {Path(args.results) / args.name}_rebuild.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
