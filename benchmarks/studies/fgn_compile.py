"""Does ``torch.compile`` fuse FGN's node networks faster on the CPU? Eager against compiled, one sitting.

FGN's node networks at a flowing 40k state spend ~10 ms a step in LayerNorm, activation and elementwise
passes at 2-7x their memory bound (``benchmarks/results/fgn_speed_flow.md``); fusing them is what
``torch.compile`` (inductor, C++ on the CPU) offers. The sparse product in each layer is a graph break, so
the pieces around it are compiled: the encoder and decoder MLPs, each layer's LayerNorm and update MLP,
with dynamic shapes (the node count changes every step).

The networks' inputs are captured from one FGN step at the kept flow state of ``benchmarks.neighbors``
(``runs/neighbors/dam_large_mps_0.3s.pt``, made by it if missing); each network is then timed eager and
compiled, alternated ``--rounds`` times (median of 15 calls each after 3 warm-up calls), with the first
compiled call's seconds and the largest difference of the outputs.

Usage::

    python -m benchmarks.studies.fgn_compile [--threads 2] [--rounds 3]

Writes ``benchmarks/results/fgn_compile.{md,csv}`` with provenance.
"""

from __future__ import annotations

import argparse
import copy
import os
import time
from collections.abc import Callable
from pathlib import Path
from statistics import median

import torch
from torch import nn

from benchmarks.fgn_speed import warmed_up
from benchmarks.neighbors import flow_state
from benchmarks.provenance import provenance, write_results
from lagfluid.memory import keep_freed_memory

RESULTS = Path(__file__).resolve().parents[1] / "results"


def call_ms(fn: Callable[..., torch.Tensor], args: tuple, calls: int = 15) -> float:
    """Median ms of ``calls`` calls of ``fn(*args)`` after 3 untimed ones, without autograd."""
    times = []
    with torch.no_grad():
        for _ in range(3):
            fn(*args)
        for _ in range(calls):
            start = time.perf_counter()
            fn(*args)
            times.append(time.perf_counter() - start)
    return 1e3 * median(times)


def compiled_pieces(net: nn.Module) -> nn.Module:
    """A copy of a :class:`~lagfluid.models.fgn.networks.NodeNet` with its dense pieces compiled."""
    out = copy.deepcopy(net)
    out.node_encoder = torch.compile(out.node_encoder, dynamic=True)
    out.node_decoder = torch.compile(out.node_decoder, dynamic=True)
    for pair in out.mp_layers:
        pair[0] = torch.compile(pair[0], dynamic=True)
        pair[1].mlp = torch.compile(pair[1].mlp, dynamic=True)
    return out


def main(argv: list[str] | None = None) -> None:
    keep_freed_memory()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--states", default="runs/neighbors", help="where benchmarks.neighbors keeps flow states")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    load = os.getloadavg()[0]
    sim, _ = warmed_up("dam_large", 0, "fgn", args.threads)
    state = flow_state("dam_large", 0.3, "mps", Path(args.states), args.threads)
    nets = {"advection": sim.advection.net.net, "pressure": sim.pressure.net.net}
    captured: dict[str, tuple] = {}

    def keep_inputs(name: str) -> Callable[..., None]:
        def hook(module: nn.Module, inputs: tuple, output: torch.Tensor) -> None:  # None: output kept
            captured.setdefault(name, inputs)

        return hook

    for name, net in nets.items():
        net.register_forward_hook(keep_inputs(name))
    sim.reset(state)
    with torch.no_grad():
        sim.step(state)
    rows = []
    for name, net in nets.items():
        inputs = captured[name]
        compiled = compiled_pieces(net)
        start = time.perf_counter()
        with torch.no_grad():
            difference = float((compiled(*inputs) - net(*inputs)).abs().max())
        first_call = time.perf_counter() - start
        eager, fused = [], []
        for _ in range(args.rounds):
            eager.append(call_ms(net, inputs))
            fused.append(call_ms(compiled, inputs))
        rows.append(
            {
                "network": name,
                "nodes": int(inputs[0].shape[0]),
                "eager_ms": round(median(eager), 1),
                "compiled_ms": round(median(fused), 1),
                "compiled_over_eager": round(median(fused) / median(eager), 2),
                "eager_ms_each": " ".join(f"{t:.1f}" for t in eager),
                "compiled_ms_each": " ".join(f"{t:.1f}" for t in fused),
                "first_compiled_call_s": round(first_call, 1),
                "largest_output_difference": f"{difference:.2e}",
            }
        )
    intro = (
        "# FGN's node networks: eager against `torch.compile` (CPU)\n\n"
        "The networks' inputs from one FGN step at the 40k dam's flow state (0.3 s), each timed eager "
        "and with its dense pieces compiled (`benchmarks/studies/fgn_compile.py`), alternated per round; "
        "medians over the rounds (each round: the median of 15 calls)."
    )
    prov = provenance("benchmarks.studies.fgn_compile", load, "cpu", rounds=str(args.rounds))
    print(write_results(RESULTS, "fgn_compile", rows, intro, prov))


if __name__ == "__main__":
    main()
