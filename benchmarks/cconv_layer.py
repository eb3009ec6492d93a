"""The continuous convolution layer (baselines/cconv): accuracy against Open3D, time against its FLOP bound.

Points: a jittered cubic lattice of ``--particles`` fluid particles at DeepLagrangianFluids' spacing
(0.05 m, filter radius 0.1125 m: ~40 neighbours each), the inside of a body of water.

* **Accuracy** (when ``open3d-cpu`` is installed, ``pip install -e ".[cconv-oracle]"``): ours against
  Open3D's ``ContinuousConv`` with the same random kernel and features, every mapping, DeepLagrangianFluids'
  options (align_corners, poly6 window, no normalisation, coincident points ignored): the largest absolute
  difference and that over the largest output.
* **Time** of one forward pass of the layers of DeepLagrangianFluids' network (C_in -> C_out), with the
  pair geometry built beforehand (once per step, shared by the layers; timed apart), against the *FLOP
  bound*: a dense ``(N, 64 C_in) @ (64 C_in, C_out)`` product, the multiply-adds a continuous convolution
  cannot avoid, timed on the same machine in the same run; and Open3D's op on the same input (its own
  neighbour search included: it has no other mode). Medians of ``--repeats``.

Usage::

    python -m benchmarks.cconv_layer --particles 10000 --threads 2

Writes ``benchmarks/results/cconv_layer.{md,csv}`` with provenance.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch

from baselines.cconv.conv import MAPPINGS, ContinuousConv, conv_geometry, conv_pairs
from baselines.cconv.oracle import open3d_layer
from benchmarks.provenance import markdown_table, provenance, write_results

RESULTS = Path(__file__).resolve().parent / "results"
SPACING = 0.05
RADIUS = 1.5 * 3 * 0.025  # DeepLagrangianFluids: radius_scale * 6 * particle_radius / 2
LAYERS = [(4, 32), (96, 64), (64, 64), (64, 3)]


def lattice(n: int, seed: int = 0) -> torch.Tensor:
    """(n, 3) points of a jittered cubic lattice of spacing 0.05 m."""
    side = round(n ** (1 / 3)) + 1
    g = torch.Generator().manual_seed(seed)
    a = torch.arange(side, dtype=torch.float32) * SPACING
    pts = torch.stack(torch.meshgrid(a, a, a, indexing="ij"), -1).reshape(-1, 3)[:n]
    return pts + 0.1 * SPACING * torch.randn(pts.shape, generator=g)


def median_time(fn: Callable[[], object], repeats: int) -> float:
    """Median wall time of ``fn`` over ``repeats`` calls after one warm-up."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--particles", type=int, default=10_000)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    load = os.getloadavg()[0]
    pos = lattice(args.particles)
    g = torch.Generator().manual_seed(1)

    rows: list[dict[str, float | int | str]] = []
    with torch.no_grad():
        pairs = conv_pairs(pos, None, RADIUS)
        geometry = conv_geometry(pos, pos, pairs, RADIUS)
        t_pairs = median_time(lambda: conv_pairs(pos, None, RADIUS), args.repeats)
        t_geometry = median_time(lambda: conv_geometry(pos, pos, pairs, RADIUS), args.repeats)
        for cin, cout in LAYERS:
            for mapping in (
                sorted(MAPPINGS) if (cin, cout) in ((4, 32), (96, 64)) else ["ball_to_cube_volume_preserving"]
            ):
                conv = ContinuousConv(cin, cout, mapping=mapping)
                with torch.no_grad():
                    conv.kernel.normal_(generator=g)
                feats = torch.randn(args.particles, cin, generator=g)
                geo = (
                    geometry
                    if mapping == "ball_to_cube_volume_preserving"
                    else conv_geometry(pos, pos, pairs, RADIUS, mapping=mapping)
                )
                ours = conv(feats, geo)
                row: dict[str, float | int | str] = {"c_in": cin, "c_out": cout, "mapping": mapping}
                reference = open3d_layer(conv.kernel.detach(), None, mapping)
                if reference is not None:
                    expected = reference(feats, pos, pos, 2 * RADIUS)
                    err = float((ours - expected).abs().max())
                    row.update(max_abs_error=err, relative_error=err / float(expected.abs().max()))
                if mapping != "ball_to_cube_volume_preserving":
                    rows.append(row)
                    continue
                dense_in = torch.randn(args.particles, 64 * cin, generator=g)
                dense_kernel = conv.kernel.detach().reshape(-1, cout)
                t_layer = median_time(lambda conv=conv, feats=feats: conv(feats, geometry), args.repeats)
                t_bound = median_time(lambda a=dense_in, b=dense_kernel: a @ b, args.repeats)
                row.update(
                    layer_ms=1e3 * t_layer, flop_bound_ms=1e3 * t_bound, layer_over_bound=t_layer / t_bound
                )
                if reference is not None:
                    t_o3d = median_time(
                        lambda r=reference, feats=feats: r(feats, pos, pos, 2 * RADIUS), args.repeats
                    )
                    row.update(open3d_ms=1e3 * t_o3d)
                rows.append(row)

    fields = list(dict.fromkeys(k for r in rows for k in r))
    rows = [{k: r.get(k, "") for k in fields} for r in rows]  # every column, blank where a row has none

    def cell(v: object) -> str:
        return f"{v:.3g}" if isinstance(v, float) else str(v)

    prov = provenance("benchmarks.cconv_layer", load)
    intro = (
        "# The continuous convolution layer: accuracy against Open3D, time against the FLOP bound\n\n"
        f"{args.particles} points of a jittered lattice (spacing 0.05 m, filter radius {RADIUS} m, "
        f"{pairs.shape[1] / args.particles:.1f} neighbours each), {args.threads} threads, medians of "
        f"{args.repeats}. Pair search {1e3 * t_pairs:.1f} ms and pair geometry {1e3 * t_geometry:.1f} ms "
        "(once per step, shared by every layer over the same points); layer_ms excludes them, open3d_ms "
        "includes Open3D's own search (it has no other mode). flop_bound_ms: a dense "
        "(N, 64 C_in) @ (64 C_in, C_out) product, the multiply-adds the layer cannot avoid. Errors: ours "
        "against Open3D's op (float32), empty where open3d-cpu is not installed."
    )
    body = markdown_table(rows, cell=cell, align="---:", left=("mapping",))
    print(write_results(RESULTS, "cconv_layer", rows, intro, prov, body))


if __name__ == "__main__":
    main()
