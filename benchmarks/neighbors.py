"""Neighbour-search speed per backend, particle count and radius.

``python -m benchmarks.neighbors`` times :func:`lagfluid.neighbors.radius_graph` on a fluid-like
block (a simple-cubic lattice of spacing l0 = 0.05 m, jittered by up to 0.1 l0, so the degree is
that of a real fluid at rest) and writes ``benchmarks/results/neighbors.md`` and ``.csv`` with the
machine, versions, git commit and command. Every backend's edges are compared with the first
backend's for the same case (column ``identical``), so a fast but wrong backend shows up.

``python -m benchmarks.neighbors --verlet dam_medium dam_large`` instead times the search of a simulator's
Verlet list alone (``neighbors_verlet.{md,csv}``), on the dam at rest and in the flow (its state after
``--flow-seconds`` of a ``--flow-model`` rollout, made once and kept under ``runs/neighbors/``): the previous
search (one cell list over every particle) and the present one (the fluid searched against the boundary's
index, made once per scene) alternated in one process, each with its pairs checked equal; a first build (the
boundary indexed too); the filter every step pays; and two floors, the pairs written (16 bytes each) at the
copy bandwidth of a numpy copy measured in the same run, and the candidates scanned at the cost of one
distance measured in the same run. vesin and warp-lang (optional, never dependencies of the package) are
timed beside it on the same pairs when installed, and skipped with a message when not.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import functools
import logging
import math
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import numpy as np
import torch

from benchmarks.provenance import markdown, provenance, write_results
from lagfluid.neighbors import available_backends, pair_kernels, radius_graph
from lagfluid.neighbors.verlet import VerletNeighborList
from lagfluid.state import ParticleState, ParticleType, SceneParams

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
    parser.add_argument(
        "--verlet",
        nargs="+",
        default=None,
        metavar="SCENE",
        help="time the Verlet list's search on these scenes instead (neighbors_verlet.md)",
    )
    parser.add_argument("--lists", nargs="+", default=["fgn", "mps"], help="--verlet: whose list (model)")
    parser.add_argument("--flow-seconds", type=float, default=0.3, help="--verlet: the flowing state's time")
    parser.add_argument(
        "--flow-model", default="mps", help="--verlet: the model that makes the flowing state"
    )
    parser.add_argument("--states", type=Path, default=Path("runs/neighbors"), help="--verlet: kept states")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> list[dict[str, object]]:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    if args.threads:
        torch.set_num_threads(args.threads)
    load_before = os.getloadavg()
    if args.verlet:
        return verlet_main(args, load_before[0])
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


# ------------------------------------------------------------------------------------ --verlet (issue 37)
def flow_state(scene: str, seconds: float, model: str, folder: Path, threads: int) -> ParticleState:
    """The state of ``model`` on ``scene`` after ``seconds``, made by a rollout once and kept in ``folder``.

    At ``seconds`` 0 the scene at rest (nothing is kept). The kept file is a run's output (``runs/`` is not
    committed); delete it to make it again.
    """
    from benchmarks.fgn_speed import warmed_up

    if seconds <= 0:
        return warmed_up(scene, 0, model, threads)[1]
    path = folder / f"{scene}_{model}_{seconds:g}s.pt"
    if path.exists():  # tensors and plain values only: nothing is unpickled
        saved = torch.load(path, weights_only=True)
        return ParticleState(
            **saved["tensors"], params=SceneParams(**saved["params"]), time=saved["time"], step=saved["step"]
        )
    state = warmed_up(scene, 0, model, threads)[1]
    steps = round(seconds / state.params.dt)
    log.info("making %s: %d steps of %s on %s (kept for later runs)", path, steps, model, scene)
    state = warmed_up(scene, steps, model, threads)[1]
    folder.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tensors = {k: getattr(state, k) for k in ("pos", "vel", "ptype", "pressure", "bounds")}
    params = dataclasses.asdict(state.params)
    torch.save({"tensors": tensors, "params": params, "time": state.time, "step": state.step}, tmp)
    os.replace(tmp, path)
    return state


def list_of(model: str, threads: int) -> VerletNeighborList:
    """A fresh Verlet list with the cutoff, skin and wall hops of ``model``'s simulator on the dam."""
    from benchmarks.fgn_speed import warmed_up

    sim, _ = warmed_up("dam_small", 1, model, threads)
    nl = sim.neighbors
    return VerletNeighborList(nl.cutoff, nl.skin, wall_hops=nl.wall_hops)


def copy_bandwidth(megabytes: int = 256, repeats: int = 5) -> float:
    """Bytes per second of a numpy copy (read + write of ``megabytes``), the best of ``repeats``."""
    src = np.ones(megabytes << 17, dtype=np.float64)
    dst = np.empty_like(src)
    best = min(_seconds(lambda: np.copyto(dst, src)) for _ in range(repeats))
    return src.nbytes / best


def distance_seconds(pos: torch.Tensor, edges: torch.Tensor, radius: float, repeats: int = 5) -> float:
    """Seconds per candidate of the compiled distance test over the pairs ``edges`` (2, E), the best."""
    p = pos.numpy()
    src, dst = edges[0].numpy(), edges[1].numpy()
    bound2 = p.dtype.type(radius * radius)
    kern = pair_kernels._kernels()
    mask = np.ones(1, dtype=np.bool_)
    best = min(_seconds(lambda: kern.count_within(p, src, dst, bound2, mask, False)) for _ in range(repeats))
    return best / max(1, src.shape[0])


def _seconds(fn: Callable[[], object]) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def scanned(pos: torch.Tensor, nl: VerletNeighborList, fluid: torch.Tensor, n_fluid: int) -> tuple[int, int]:
    """Candidates scanned (particles in the cells visited) by the previous and the present search."""
    kern = pair_kernels._kernels()
    cells = pair_kernels.CellList.build(pos, nl.list_radius)
    recv = np.flatnonzero((nl.candidates[1].bincount(minlength=pos.shape[0]) > 0).numpy() | fluid.numpy())
    sizes = np.zeros(recv.shape[0] + 1, dtype=np.int64)
    _, cell, _, start, dims, reach = cells._args
    kern.cell_scan_sizes(cell, start, dims, reach, recv.astype(np.int64), sizes)
    static = nl._boundary
    fcells = pair_kernels.CellList.build(pos[:n_fluid], nl.list_radius)
    now = 0
    for grid, qcell in (
        (fcells, fcells._args[1]),
        (static.cells, static.cells.cells_of(pos[:n_fluid].double().numpy())),
    ):
        q = np.zeros(n_fluid + 1, dtype=np.int64)
        kern.query_scan_sizes(qcell, grid._args[3], grid._args[4], grid._args[5], q)
        now += int(q.sum())
    return int(sizes.sum()), now


def vesin_pairs(pos: torch.Tensor, radius: float, sort: bool = True) -> torch.Tensor | None:
    """Every ordered pair closer than ``radius`` by vesin (a C++ cell list), (2, E) [j; i] sorted; or None."""
    try:
        import vesin
    except ImportError:
        return None
    p = pos.double().numpy()
    i, j = vesin.NeighborList(cutoff=float(radius), full_list=True).compute(p, np.zeros((3, 3)), False, "ij")
    return _pairs(torch.from_numpy(j.astype(np.int64)), torch.from_numpy(i.astype(np.int64)), sort)


def warp_pairs(pos: torch.Tensor, radius: float, sort: bool = True) -> torch.Tensor | None:
    """Every ordered pair closer than ``radius`` by warp-lang's HashGrid (CPU), (2, E) sorted; or None."""
    try:
        import warp as wp
    except ImportError:
        return None
    wp.config.quiet = True
    wp.init()
    kernels = _warp_kernels(wp)
    n = pos.shape[0]
    pts = wp.array(pos.float().numpy(), dtype=wp.vec3, device="cpu")
    extent = (pos.max(0).values - pos.min(0).values).tolist()
    dims = [max(1, min(128, int(e / radius) + 1)) for e in extent]
    grid = wp.HashGrid(*dims, device="cpu")
    grid.build(pts, float(radius))
    counts = wp.zeros(n, dtype=wp.int32, device="cpu")
    wp.launch(kernels[0], dim=n, inputs=[grid.id, pts, float(radius), counts], device="cpu")
    c = counts.numpy().astype(np.int64)
    offsets = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(c, out=offsets[1:])
    src = wp.zeros(int(offsets[-1]), dtype=wp.int32, device="cpu")
    wp.launch(kernels[1], dim=n, inputs=[grid.id, pts, float(radius), wp.array(offsets, dtype=wp.int64), src])
    j = torch.from_numpy(src.numpy().astype(np.int64))
    i = torch.repeat_interleave(torch.arange(n), torch.from_numpy(c))
    return _pairs(j, i, sort)


@functools.cache
def _warp_kernels(wp: ModuleType) -> tuple[object, object]:
    """warp-lang's count and fill kernels over a HashGrid (defined once)."""

    @wp.kernel
    def count(grid: wp.uint64, pts: wp.array(dtype=wp.vec3), r: float, counts: wp.array(dtype=wp.int32)):
        i = wp.tid()
        p = pts[i]
        n = wp.int32(0)  # a dynamic variable (warp keeps a plain 0 constant)
        for j in wp.hash_grid_query(grid, p, r):
            if j != i and wp.length(pts[j] - p) < r:
                n += 1
        counts[i] = n

    @wp.kernel
    def fill(grid: wp.uint64, pts: wp.array(dtype=wp.vec3), r: float, offsets: wp.array(dtype=wp.int64),
             out: wp.array(dtype=wp.int32)):  # fmt: skip
        i = wp.tid()
        p = pts[i]
        k = offsets[i]
        for j in wp.hash_grid_query(grid, p, r):
            if j != i and wp.length(pts[j] - p) < r:
                out[k] = j
                k += wp.int64(1)

    return count, fill


def _pairs(j: torch.Tensor, i: torch.Tensor, sort: bool) -> torch.Tensor:
    """(2, E) [j; i], sorted by target then source with ``sort`` (to compare: not in a library's time)."""
    if not sort:
        return torch.stack([j, i])
    key = torch.from_numpy(np.sort(((i << 32) | j).numpy()))
    return torch.stack([key & 0xFFFFFFFF, key >> 32])


def _timed(fn: Callable[[], object]) -> tuple[float, object]:
    start = time.perf_counter()
    out = fn()
    return time.perf_counter() - start, out


def verlet_rows(
    scene: str,
    label: str,
    state: ParticleState,
    nl: VerletNeighborList,
    model: str,
    repeats: int,
    rates: dict,
) -> list[dict[str, object]]:
    """The rows of one state and one list: each way of searching, alternated ``repeats`` times."""
    pos, ptype, nf = state.pos, state.ptype, state.n_fluid
    fluid, walls = ptype == ParticleType.FLUID, ptype == ParticleType.WALL
    nl.reset()
    nl.update(pos, ptype)
    static = nl._boundary
    r = nl.list_radius

    def previous() -> torch.Tensor:
        return nl._search_with_cells(pair_kernels.CellList.build(pos, r), fluid, walls)

    def present() -> torch.Tensor:
        return pair_kernels.verlet_candidates(pos, static, nl.wall_hops)[0]

    def first_build() -> torch.Tensor:
        return pair_kernels.verlet_candidates(
            pos, pair_kernels.StaticBoundary.build(pos, walls, nf, r), nl.wall_hops
        )[0]

    def update() -> torch.Tensor:  # the whole rebuild as a step pays it (the wall rows' index included)
        nl.candidates = None
        nl.update(pos, ptype)
        return nl.candidates

    def step_filter() -> torch.Tensor:
        return nl.graph(pos, ptype, nl.cutoff).edge_index

    ways = {"previous search": previous, "present search": present, "present, first build": first_build,
            "present, whole update": update, "filter (every step)": step_filter}  # fmt: skip
    # like for like with the libraries: every ordered pair among the fluid at the list radius
    fluid_pos = pos[:nf].contiguous()
    ways["radius_graph, fluid pairs"] = lambda: radius_graph(fluid_pos, r)
    others = {"vesin, fluid pairs": vesin_pairs, "warp HashGrid, fluid pairs": warp_pairs}
    outs = {}
    for name, library in others.items():
        outs[name] = library(fluid_pos, r)  # sorted, to compare; the timed calls leave the pairs as found
        if outs[name] is None:
            log.info("%s skipped: not installed (pip install vesin warp-lang)", name)
        else:
            ways[name] = functools.partial(library, fluid_pos, r, sort=False)
    times = {name: [] for name in ways}
    for name, fn in ways.items():  # warm-up (compilation, allocator)
        out = fn()
        outs.setdefault(name, out)
    for _ in range(repeats):
        for name, fn in ways.items():
            seconds, _ = _timed(fn)
            times[name].append(seconds)
    want = previous()
    cand_before, cand_now = scanned(pos, nl, fluid, nf)
    per_distance = distance_seconds(pos, want, r)
    fluid_pairs = outs["radius_graph, fluid pairs"]
    rows = []
    for name, t in times.items():
        out = outs[name]
        if "fluid pairs" in name:
            same, scans = bool(torch.equal(out, fluid_pairs)), None
        elif name.startswith("filter"):
            same, scans = True, None
        else:
            same, scans = bool(torch.equal(out, want)), cand_before if name == "previous search" else cand_now
        pairs = int(out.shape[1])
        rows.append({
            "scene": scene, "fluid": nf, "particles": int(pos.shape[0]), "state": label, "list": model,
            "radius_l0": round(r / state.params.l0, 3), "way": name,
            "median_ms": round(1e3 * statistics.median(t), 2), "min_ms": round(1e3 * min(t), 2),
            "pairs": pairs, "scanned": scans if scans is not None else "",
            "floor_write_ms": round(1e3 * 16 * pairs / rates["copy_bytes_per_s"], 2),
            "floor_distance_ms": round(1e3 * scans * per_distance, 2) if scans is not None else "",
            "same_pairs": same,
        })  # fmt: skip
    return rows


def verlet_main(args: argparse.Namespace, load_before: float) -> list[dict[str, object]]:
    """``--verlet``: the Verlet list's search timed on each scene, at rest and in the flow, per list."""
    threads = args.threads or torch.get_num_threads()
    rates = {"copy_bytes_per_s": copy_bandwidth()}
    rows: list[dict[str, object]] = []
    for model in args.lists:
        nl = list_of(model, threads)
        for scene in args.verlet:
            for seconds in (0.0, args.flow_seconds):
                state = flow_state(scene, seconds, args.flow_model, args.states, threads)
                label = "rest" if seconds == 0 else f"flow {seconds:g} s ({args.flow_model})"
                rows += verlet_rows(scene, label, state, nl, model, args.repeats, rates)
                log.info("%s", rows[-1])
    prov = provenance(
        "benchmarks.neighbors", load_before, "cpu",
        copy_bandwidth=f"{rates['copy_bytes_per_s'] / 1e9:.2f} GB/s (numpy copy, read + write, best of 5)",
    )  # fmt: skip
    intro = (
        "# The Verlet list's search alone (`python -m benchmarks.neighbors --verlet`)\n\n"
        "Each way alternated with the others in one process, median and min of the timed repeats after one "
        "warm-up. `previous search`: one cell list over every particle, walls searched at every rebuild; "
        "`present search`: the fluid searched against its own cells and the boundary's index (made once per "
        "scene, `present, first build` includes making it); `present, whole update`: the rebuild a step pays "
        "(the wall rows' index included); `filter`: the pairs within the cutoff from the candidates, every "
        "step. `same_pairs`: the candidates equal the previous search's, pair for pair (`fluid pairs`: every "
        "ordered pair among the fluid at the list radius, against `radius_graph`'s). Floors: the pairs "
        "written (2 x int64) at the copy bandwidth; the candidates scanned (particles in the visited cells) "
        "at the cost of one compiled distance test, both measured in this run."
    )
    write_results(args.out.parent, "neighbors_verlet", rows, intro, prov)
    print((args.out.parent / "neighbors_verlet.md").read_text())
    return rows


if __name__ == "__main__":
    main()
