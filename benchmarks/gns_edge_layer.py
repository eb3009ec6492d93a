"""GNS training iterations per hour: the first edge-MLP layer applied by parts against the concatenated form.

Each interaction block's edge MLP starts with one linear layer on ``[e, v_receiver, v_sender]`` (3L inputs per
edge). :class:`baselines.gns.network.InteractionNetwork` applies it by parts,
``W_e e + (W_r v)[receiver] + (W_s v)[sender] + b``: the node projections on N rows, then gathered, instead
of a (E, 3L) concatenation and a (E, 3L) x (3L, hidden) product (E ~ 30 N). Same parameters, same function
(``tests/test_gns.py``). This benchmark times one training iteration (graph, forward, backward, Adam) of
both forms on one scene-sized graph, at the CPU size (``train=gns_cpu``) and the paper's (A.5), alternated
A B A B at one thread; the concatenated form is :func:`concatenated_edge_update`, patched in by
:func:`concatenated_first_layer` (everything else is the same code). The network has applied the layer by
parts since GNS was added (commit 3819f4e): "before" is the textbook concatenated form, not an older shipped
version, and no shipped weights or results change.

The graph: a 79 x 27 x 3 l0 sheet of fluid (6,399 particles) on the floor of the paper's 80 x 80 x 40 l0
random-scene tank, jittered by 0.15 l0 (Gaussian, seeded): 5,223 boundary nodes within reach and 196,695
edges, the size of a ``data=cpu`` frame (6,250 fluid, ~6,500 boundary nodes, ~194k edges).

Usage::

    python -m benchmarks.gns_edge_layer --pairs 5 --paper-pairs 2

Writes ``benchmarks/results/gns_edge_layer.{md,csv}`` with provenance.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from unittest import mock

import torch
from torch import Tensor

from baselines.gns.graph import build_graph
from baselines.gns.network import GNSNet, InteractionNetwork
from baselines.gns.trainable import step_acceleration
from benchmarks.provenance import provenance, write_results
from lagfluid.scenes.geometry import Container, FluidBlock, Scene
from lagfluid.state import ParticleType

RESULTS = Path(__file__).resolve().parent / "results"
RADIUS = 2.1
"""Connectivity radius in l0 (``model/gns.yaml``, both sizes)."""
SIZES = {
    "cpu (train=gns_cpu)": {"latent": 48, "hidden": 48, "mlp_layers": 2, "blocks": 5, "radius": RADIUS},
    "paper (A.5)": {"latent": 128, "hidden": 128, "mlp_layers": 2, "blocks": 10, "radius": RADIUS},
}
"""The two network sizes timed: ``train=gns_cpu``'s model options and ``model/gns.yaml``'s defaults."""
FRAME_DT = 0.008
"""s, the ``data=cpu`` frame spacing (the velocities' finite differences)."""


def concatenated_edge_update(self: InteractionNetwork, e: Tensor, edge_index: Tensor, x: Tensor) -> Tensor:
    """The edge MLP on the per-edge concatenation ``[e, x_receiver, x_sender]``, (E, L): the reference form.

    The textbook form (DeepMind's ``learning_to_simulate``): a (E, 3L) array and its (E, 3L) x (3L, hidden)
    product; a drop-in for :meth:`InteractionNetwork.edge_update` (same arguments, same parameters).
    """
    receiver, sender = x.index_select(0, edge_index[1]), x.index_select(0, edge_index[0])
    return self.edge_mlp(torch.cat([e, receiver, sender], dim=1))


@contextmanager
def concatenated_first_layer() -> Iterator[None]:
    """Every :class:`InteractionNetwork` uses :func:`concatenated_edge_update` inside the block."""
    with mock.patch.object(InteractionNetwork, "edge_update", concatenated_edge_update):
        yield


def sheet_state(seed: int = 0) -> tuple[Tensor, Tensor, Tensor, Tensor, float]:
    """The module doc's scene-sized state: positions (P, 3), fluid (P,), frames (Nf, 6, 3), bounds, l0."""
    state = Scene("sheet", (FluidBlock((1, 1, 1), (79, 27, 3)),), Container((80, 80), 40)).build(
        None, torch.float32
    )
    g = torch.Generator().manual_seed(seed)
    fluid = state.ptype == ParticleType.FLUID
    l0 = float(state.params.l0)
    pos = state.pos.clone()
    pos[fluid] += 0.15 * l0 * torch.randn(int(fluid.sum()), 3, generator=g)
    # five earlier frames a random walk behind: velocities of ~1 m/s (data=cpu's std), oldest first
    steps = 1.0 * FRAME_DT * torch.randn(int(fluid.sum()), 5, 3, generator=g)
    last = pos[fluid].unsqueeze(1)
    frames = torch.cat([last - steps.flip(1).cumsum(1).flip(1), last], dim=1)
    return pos, fluid, frames, state.bounds, l0


def training_iteration(net: GNSNet, optimizer: torch.optim.Optimizer, state: tuple, target: Tensor) -> float:
    """Seconds of one training iteration on ``state``: graph, forward, MSE on the fluid, backward, Adam."""
    pos, fluid, frames, bounds, l0 = state
    start = time.perf_counter()
    optimizer.zero_grad(set_to_none=True)
    prediction = step_acceleration(net, pos, fluid, frames, FRAME_DT, l0, bounds)
    torch.nn.functional.mse_loss(prediction, target).backward()
    optimizer.step()
    return time.perf_counter() - start


def time_pairs(size: str, pairs: int, state: tuple) -> list[dict]:
    """Seconds per iteration of ``pairs`` pairs (by parts, then concatenated) after one untimed warm-up pair.

    One network and optimizer for both forms (the same parameters either way): a pair's two iterations
    differ only in the first edge layer's form (and in the weights that one Adam step moved).
    """
    torch.manual_seed(0)
    net = GNSNet(**SIZES[size]).train()
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-4)
    target = torch.randn(int(state[1].sum()), 3)
    rows = []
    for k in range(pairs + 1):
        by_parts = training_iteration(net, optimizer, state, target)
        with concatenated_first_layer():
            concatenated = training_iteration(net, optimizer, state, target)
        print(f"{size} pair {k}: by parts {by_parts:.2f} s, concatenated {concatenated:.2f} s", flush=True)
        if k:  # pair 0 warms up (allocator, first calls)
            rows.append(
                {
                    "size": size,
                    "pair": k,
                    "by_parts_s": round(by_parts, 3),
                    "concatenated_s": round(concatenated, 3),
                    "ratio": round(concatenated / by_parts, 3),
                }
            )
    return rows


def summary(rows: list[dict]) -> str:
    """Markdown table per size: median seconds, iterations per hour and median ratio of the pairs."""
    lines = [
        "| size | pairs | by parts s/it (median) | concatenated s/it (median) | by parts it/h | "
        "concatenated it/h | ratio concatenated / by parts (median of pairs; min-max) |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for size in dict.fromkeys(r["size"] for r in rows):
        mine = [r for r in rows if r["size"] == size]
        a = statistics.median(r["by_parts_s"] for r in mine)
        b = statistics.median(r["concatenated_s"] for r in mine)
        ratios = [r["ratio"] for r in mine]
        lines.append(
            f"| {size} | {len(mine)} | {a:.2f} | {b:.2f} | {3600 / a:.0f} | {3600 / b:.0f} | "
            f"{statistics.median(ratios):.2f}; {min(ratios):.2f}-{max(ratios):.2f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, default=5, help="timed pairs at the CPU size")
    parser.add_argument("--paper-pairs", type=int, default=2, help="timed pairs at the paper size")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--note", default="", help="a line on the machine's load (other jobs running)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    load = os.getloadavg()[0]
    state = sheet_state()
    graph = build_graph(state[0], state[1], RADIUS * state[4])
    # again: the first Numba kernel of the radius search starts its OpenMP team with every core, which
    # resets torch's thread count too (torch.get_num_threads() 1 -> 2 on this machine)
    torch.set_num_threads(args.threads)
    cpu, paper = SIZES
    rows = time_pairs(cpu, args.pairs, state) + time_pairs(paper, args.paper_pairs, state)
    intro = (
        "# GNS training iterations per hour: first edge layer by parts vs concatenated "
        "(`benchmarks/gns_edge_layer.py`)\n\n"
        f"One training iteration (graph, forward, MSE, backward, Adam) on one scene-sized graph: "
        f"{int(state[1].sum()):,} fluid and {graph.nodes.numel() - graph.n_fluid:,} boundary nodes, "
        f"{graph.edge_index.shape[1]:,} edges (the module doc's jittered sheet; a `data=cpu` frame has 6,250 "
        "fluid, ~6,500 boundary nodes, ~194k edges). Alternated A B A B, A = the first edge-MLP layer by "
        "parts (`W_e e + (W_r v)[i] + (W_s v)[j]`, the network's form), B = the concatenated `[e, v_i, v_j]` "
        "(the reference form, patched in); one untimed warm-up pair per size. Ratio = B / A pair by pair.\n\n"
        f"{summary(rows)}\n\n"
        "The machine is shared: other jobs (data generation, trainings, tests) ran beside this measurement "
        "(load average below), so absolute times are upper bounds and vary from pair to pair; the pairs' "
        "ratios are the comparison." + (f" {args.note}" if args.note else "") + "\n\nPer pair:"
    )
    if torch.get_num_threads() != args.threads:
        raise RuntimeError(f"torch ran {torch.get_num_threads()} threads, not --threads {args.threads}")
    prov = provenance("benchmarks.gns_edge_layer", load, threads=str(args.threads))
    print(write_results(RESULTS, "gns_edge_layer", rows, intro, prov))


if __name__ == "__main__":
    main()
