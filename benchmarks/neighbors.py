"""Neighbour-search speed per backend, particle count and radius.

``python -m benchmarks.neighbors`` times :func:`lagfluid.neighbors.radius_graph` on a fluid-like
block (a simple-cubic lattice of spacing l0 = 0.05 m, jittered by up to 0.1 l0, so the degree is
that of a real fluid at rest) and writes ``benchmarks/results/neighbors.md`` and ``.csv`` with the
machine, versions, git commit and command. Every backend's edges are compared with the first
backend's for the same case (column ``identical``), so a fast but wrong backend shows up.
"""

from __future__ import annotations

import argparse
import csv
import logging
import math
import os
import statistics
import time
from pathlib import Path

import torch

from benchmarks.provenance import markdown, provenance
from lagfluid.neighbors import available_backends, radius_graph

L0 = 0.05
RESULTS = Path(__file__).resolve().parent / "results"
log = logging.getLogger("benchmarks.neighbors")


def fluid_block(
    n: int, jitter: float = 0.1, seed: int = 0, dtype: torch.dtype = torch.float32
) -> torch.Tensor:
    """First ``n`` points (row-major) of a cubic lattice of spacing L0, each moved by up to ``jitter`` L0.

    Returns:
        (n, 3) positions, metres.
    """
    m = math.ceil(n ** (1 / 3) - 1e-9)
    grid = torch.stack(torch.meshgrid(*[torch.arange(m)] * 3, indexing="ij"), dim=-1).reshape(-1, 3)[:n]
    gen = torch.Generator().manual_seed(seed)
    shake = (torch.rand(n, 3, generator=gen, dtype=torch.float64) * 2 - 1) * jitter
    return ((grid.double() + shake) * L0).to(dtype)


def time_once(pos: torch.Tensor, r: float, backend: str) -> tuple[float, torch.Tensor]:
    if pos.device.type == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    edges = radius_graph(pos, r, backend=backend)
    if pos.device.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - start, edges


def run_provenance(args: argparse.Namespace, load_before: tuple[float, ...]) -> dict[str, str]:
    return provenance(
        "benchmarks.neighbors",
        load_before[0],
        args.device,
        particles=f"jittered simple-cubic block, l0 = {L0} m, jitter 0.1 l0, {args.dtype}",
    )


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10000, 40000, 80000])
    parser.add_argument("--radii", type=float, nargs="+", default=[0.92, 1.86, 3.1], help="in units of l0")
    parser.add_argument("--repeats", type=int, default=5, help="timed calls per case (after one warm-up)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    parser.add_argument("--backends", nargs="+", default=None, help="default: every available backend")
    parser.add_argument("--brute-max", type=int, default=10000, help="largest N for the O(N^2) backend")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--out", type=Path, default=RESULTS / "neighbors", help="path stem for .md/.csv")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> list[dict[str, object]]:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    if args.threads:
        torch.set_num_threads(args.threads)
    load_before = os.getloadavg()
    device = torch.device(args.device)
    backends = args.backends or list(available_backends())
    rows: list[dict[str, object]] = []
    for n in args.sizes:
        pos = fluid_block(n, dtype=getattr(torch, args.dtype)).to(device)
        for factor in args.radii:
            reference = None
            for backend in backends:
                if backend == "brute" and n > args.brute_max:
                    continue
                _, edges = time_once(pos, factor * L0, backend)  # warm-up (imports, allocator, caches)
                times = [time_once(pos, factor * L0, backend)[0] for _ in range(args.repeats)]
                if reference is None:
                    reference = edges
                row = {
                    "backend": backend,
                    "N": n,
                    "radius_l0": factor,
                    "median_ms": round(1e3 * statistics.median(times), 1),
                    "min_ms": round(1e3 * min(times), 1),
                    "mean_degree": round(edges.shape[1] / n, 2),
                    "edges": int(edges.shape[1]),
                    "identical": bool(torch.equal(edges, reference)),
                }
                rows.append(row)
                log.info("%s", row)
    write(rows, run_provenance(args, load_before), args.out)
    return rows


def markdown_table(rows: list[dict[str, object]]) -> str:
    head = "| backend | N | radius (l0) | median (ms) | min (ms) | mean degree | edges | identical |"
    lines = [head, "|---|---:|---:|---:|---:|---:|---:|:---:|"]
    for r in rows:
        lines.append(
            f"| {r['backend']} | {r['N']} | {r['radius_l0']} | {r['median_ms']} | {r['min_ms']} | "
            f"{r['mean_degree']} | {r['edges']} | {'yes' if r['identical'] else 'NO'} |"
        )
    return "\n".join(lines)


def write(rows: list[dict[str, object]], prov: dict[str, str], stem: Path) -> None:
    stem.parent.mkdir(parents=True, exist_ok=True)
    table = markdown_table(rows)
    print(table)  # the command's output is the table
    notes = markdown(prov)
    load = max(float(x) for x in prov["load average (1 min) before / after"].split(" / "))
    if load > 0.5 * (os.cpu_count() or 1):
        notes += (
            "\n\n**The machine was shared with other jobs while this ran** (see the load average): "
            "timings are pessimistic and noisy; compare backends within this table only."
        )
    stem.with_suffix(".md").write_text(
        "# Neighbour search: radius_graph per backend\n\n"
        "Median over the timed repeats (one untimed warm-up call first); `identical` compares the edges "
        "with the first backend's for the same case.\n\n"
        f"{notes}\n\n{table}\n"
    )
    with stem.with_suffix(".csv").open("w", newline="") as f:
        for k, v in prov.items():
            f.write(f"# {k}: {v}\n")
        writer = csv.DictWriter(f, fieldnames=list(rows[0]) if rows else ["backend"])
        writer.writeheader()
        writer.writerows(rows)


if __name__ == "__main__":
    main()
