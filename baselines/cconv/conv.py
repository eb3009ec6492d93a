"""Continuous convolution (Ummenhofer et al. 2020) in pure PyTorch, with Open3D's semantics.

For every output point ``i`` and every input point ``j`` within the filter radius ``R = extent / 2``::

    out_i = bias + sum_j  window(|x_j - x_i|^2 / R^2) * sum_c  w_c(u_ij) * (f_j @ K[cell_c(u_ij)])

``u_ij = map((x_j - x_i) / R)`` sends the ball to the unit cube (``ball_to_cube_volume_preserving``:
sphere -> cylinder -> cube, Griepentrog et al.), the cube is the (k_z, k_y, k_x) grid of the kernel
``K`` (align_corners: the grid's corner cells sit on the cube's faces), ``w_c`` and ``cell_c`` are the 8
trilinear weights and cells. The window (DeepLagrangianFluids: poly6, ``clamp((1 - r^2/R^2)^3, 0, 1)``) and
the pairs are what Open3D's ``ContinuousConv`` computes with ``normalize=False``. Its
``radius_search_ignore_query_points`` drops every pair at distance 0 -- the query itself, and any input
point that coincides with it, in the same or in another set (checked against Open3D 0.20: not by index);
``ignore_coincident`` does the same here.

Fast form (the gather form): the pair geometry does not depend on the features, so
:func:`conv_geometry` turns it, once per step and without autograd, into sparse CSR matrices ``M_b`` of
shape ``(N_out, N_in * cells_b)``, one per block ``b`` of kernel cells, holding the window x interpolation
weight of pair ``(i, j)`` at row ``i``, column ``j * cells_b + cell``. A layer is then
``sum_b M_b @ (f @ K_b).reshape(N_in * cells_b, C_out)``: per block one dense product (the FLOPs of the
layer) and one sparse product over the ``8 E`` pair-corner weights. The pairs come sorted by output row, so
the CSR rows need no sort; the blocks bound the memory to ``N_in * cells_b * C_out`` floats (see
``benchmarks/results/cconv_layer.md`` for the time against the dense products' FLOP bound). A layer with
few input channels (``4 C_in <= C_out``, DeepLagrangianFluids' first) scatters instead: the ``8 E`` weighted
inputs into an ``(N_out, cells * C_in)`` array, then one dense product with the kernel.
Like Open3D's op, no gradient flows to the positions (only to the features, the kernel and the bias).
"""

from __future__ import annotations

import itertools
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor, nn

from lagfluid.zoo import (
    ConfigError,
    device_constant,
    edge_vectors,
    pair_kernels,
    radius_graph,
    radius_graph_between,
)

__all__ = [
    "MAPPINGS",
    "ContinuousConv",
    "ConvGeometry",
    "ball_to_cube_radial",
    "ball_to_cube_volume_preserving",
    "conv_geometry",
    "conv_pairs",
    "filter_coordinates",
    "window_poly6",
]


def window_poly6(r_sqr: Tensor) -> Tensor:
    """DeepLagrangianFluids' window of the squared distance over ``R^2``: ``clamp((1 - r^2)^3, 0, 1)``."""
    return torch.clamp((1 - r_sqr) ** 3, 0, 1)


def ball_to_cube_volume_preserving(xyz: Tensor) -> Tensor:
    """(E, 3) points of the unit ball -> the cube [-1, 1]^3, volume preserving (Open3D's mapping).

    Sphere to cylinder (axis z), then cylinder to cube; the origin stays put.
    """
    x, y, z = xyz.unbind(-1)
    sq = x * x + y * y + z * z
    norm = sq.sqrt()
    tiny = sq < 1e-12
    cap = 1.25 * z * z > x * x + y * y  # the polar caps map to the cylinder's top and bottom
    s_cap = torch.sqrt(3 * norm / (norm + z.abs()).clamp_min(1e-30))
    s_side = norm / torch.sqrt(x * x + y * y).clamp_min(1e-30)
    s = torch.where(cap, s_cap, s_side)
    x, y = x * s, y * s
    z = torch.where(cap, torch.copysign(norm, z), 1.5 * z)
    x, y, z = (torch.where(tiny, 0.0, c) for c in (x, y, z))

    sq_xy = x * x + y * y
    norm_xy = sq_xy.sqrt()
    x_major = y.abs() <= x.abs()
    # atan of the smaller over the larger component: the ratio is in [-1, 1], never 0/0 off the axis
    big = torch.where(x_major, x, y)
    small = torch.where(x_major, y, x)
    ratio = small / torch.where(big == 0, 1.0, big)
    major = torch.copysign(norm_xy, big)
    minor = major * (4 / math.pi) * torch.atan(ratio)
    x2 = torch.where(x_major, major, minor)
    y2 = torch.where(x_major, minor, major)
    flat = sq_xy < 1e-12
    x2 = torch.where(flat, 0.0, x2)
    y2 = torch.where(flat, 0.0, y2)
    return torch.stack([x2, y2, z], dim=-1)


def ball_to_cube_radial(xyz: Tensor) -> Tensor:
    """(E, 3) points of the unit ball -> the cube [-1, 1]^3 by radial stretching (Open3D's mapping)."""
    radius = xyz.norm(dim=-1, keepdim=True)
    abs_max = xyz.abs().amax(dim=-1, keepdim=True)
    return torch.where(abs_max < 1e-8, 0.0, xyz * radius / abs_max.clamp_min(1e-30))


MAPPINGS: dict[str, Callable[[Tensor], Tensor] | None] = {
    "ball_to_cube_volume_preserving": ball_to_cube_volume_preserving,
    "ball_to_cube_radial": ball_to_cube_radial,
    "identity": None,
}
"""Open3D's coordinate mappings of the filter ball (``identity``: the filter is the cube itself)."""


def filter_coordinates(rel: Tensor, radius: float, kernel_size: tuple[int, int, int], mapping: str) -> Tensor:
    """(E, 3) continuous kernel-grid coordinates (x, y, z), each in ``[0, k - 1]`` (align_corners).

    Args:
        rel: (E, 3) ``x_j - x_i``, neighbour minus query.
        radius: filter radius ``R`` (half Open3D's extent).
        kernel_size: grid points per axis in the kernel array's order, (k_z, k_y, k_x) as Open3D's.
        mapping: a key of :data:`MAPPINGS`.
    """
    unit = rel / radius  # in the unit ball
    fn = MAPPINGS[mapping]
    cube = fn(unit) if fn is not None else unit
    size = device_constant(kernel_size[::-1], rel.dtype, rel.device)
    return (0.5 * cube + 0.5) * (size - 1)


@dataclass(frozen=True)
class ConvGeometry:
    """The pairs of one convolution and their weights, shared by every layer over the same point sets.

    Attributes:
        chunks: CSR matrices, one per block of kernel cells, each ``(N_out, N_in * cells_b)``: row ``i``,
            column ``j * cells_b + (cell - first cell of the block)`` holds ``window_ij * w_cell(u_ij)``.
        cell_splits: (len(chunks) + 1,) first kernel cell of each block (last: ``cells``).
        n_in: number of input points.
        n_out: number of output points.
        cells: kernel cells, ``k_x k_y k_z``.
        num_neighbors: (N_out,) float pairs per output point (DeepLagrangianFluids' loss weight).
        pair_rows: (E, 8) ``i * cells + cell`` of each pair's 8 corners (the scatter form's rows).
        pair_inputs: (E,) input point ``j`` of each pair.
        pair_weights: (E, 8) ``window_ij * w_cell(u_ij)`` of each pair's corners.
    """

    chunks: tuple[Tensor, ...]
    cell_splits: tuple[int, ...]
    n_in: int
    n_out: int
    cells: int
    num_neighbors: Tensor
    pair_rows: Tensor
    pair_inputs: Tensor
    pair_weights: Tensor
    transposed: dict[int, Tensor] = field(default_factory=dict, compare=False, repr=False)

    def transpose(self, chunk: int) -> Tensor:
        """The CSR transpose of ``chunks[chunk]``, built once and shared by every layer's backward pass."""
        if chunk not in self.transposed:
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message=".*Sparse CSR tensor support is in beta.*")
                self.transposed[chunk] = self.chunks[chunk].t().to_sparse_csr()
        return self.transposed[chunk]


class _GeometryMatmul(torch.autograd.Function):
    """``chunks[k] @ dense`` whose backward uses the geometry's cached transpose.

    torch's own backward of a CSR product transposes the matrix anew each time (measured: 0.31 s of its
    0.42 s at 6,000 points, 1 thread; ``benchmarks/results/cconv_layer.md``); the layers of a step share it.
    """

    @staticmethod
    def forward(ctx: Any, dense: Tensor, geometry: ConvGeometry, chunk: int) -> Tensor:
        ctx.geometry, ctx.chunk = geometry, chunk
        return geometry.chunks[chunk] @ dense

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None, None]:
        return ctx.geometry.transpose(ctx.chunk) @ grad, None, None


@torch.no_grad()
def conv_pairs(
    inp_pos: Tensor,
    out_pos: Tensor | None,
    radius: float,
    *,
    inp_batch: Tensor | None = None,
    out_batch: Tensor | None = None,
) -> Tensor:
    """(2, E) pairs (row 0 input ``j``, row 1 output ``i``) with ``|x_j - x_i| < radius``.

    ``out_pos`` None: the output points are the input points (no pair of a point with itself). Otherwise
    the two sets are distinct. Coincident pairs are kept; :func:`conv_geometry` drops them. ``*_batch``:
    optional (N,) scene ids; no pair joins two scenes.
    """
    if out_pos is None:
        return radius_graph(inp_pos, radius, batch=inp_batch)
    if (inp_batch is None) != (out_batch is None):
        raise ValueError("conv_pairs: give both inp_batch and out_batch, or neither")
    # the inputs binned, the outputs querying them: no output-output pair is scanned (the fluid's, for the
    # boundary's pairs into the fluid)
    return radius_graph_between(inp_pos, out_pos, radius, source_batch=inp_batch, target_batch=out_batch)


def _block_entries_torch(
    i: Tensor, j: Tensor, cell: Tensor, w: Tensor, counts: Tensor, lo: int, hi: int, n_out: int
) -> tuple[Tensor, Tensor, Tensor]:
    """The CSR ``(crow (n_out + 1,), cols, vals)`` of the kernel cells ``[lo, hi)`` of every pair.

    Args:
        i: (E,) each pair's output point.
        j: (E,) each pair's input point.
        cell: (E, 8) the kernel cells of each pair's 8 corners.
        w: (E, 8) their weights.
        counts: (n_out,) pairs per output point.
        lo: the block's first kernel cell.
        hi: the block's past-last kernel cell.
        n_out: output points.
    """
    inside = (cell >= lo) & (cell < hi)  # (E, 8)
    crow = torch.zeros(n_out + 1, dtype=torch.long, device=i.device)
    crow[1:] = torch.cumsum(torch.zeros_like(counts).index_add_(0, i, inside.sum(1)), 0)
    return crow, (j[:, None] * (hi - lo) + (cell - lo))[inside], w[inside]


def _block_entries_compiled(
    i: Tensor, j: Tensor, cell: Tensor, w: Tensor, counts: Tensor, lo: int, hi: int, n_out: int
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`_block_entries_torch` in one compiled pass each to count and to fill (the same entries).

    Instead of an (E, 8) mask, its nonzero and two gathers: 40k's geometry 0.73-0.77 -> 0.29-0.30 s a step
    (``benchmarks/results/fgn_step_speed.md``).
    """
    pair_kernels.set_threads()
    arrays = (t.contiguous().numpy() for t in (i, j, cell, w))
    entries = pair_kernels.load(_NUMBA).block_entries(*arrays, lo, hi, n_out)
    crow, cols, vals = (torch.from_numpy(a) for a in entries)
    return crow, cols, vals


_NUMBA = "baselines.cconv._geometry_numba"
pair_kernels.register(
    "cconv_block_entries", compiled=_block_entries_compiled, torch=_block_entries_torch, module=_NUMBA
)


@torch.no_grad()
def conv_geometry(
    inp_pos: Tensor,
    out_pos: Tensor,
    pairs: Tensor,
    radius: float,
    kernel_size: tuple[int, int, int] = (4, 4, 4),
    mapping: str = "ball_to_cube_volume_preserving",
    window: Callable[[Tensor], Tensor] | None = window_poly6,
    ignore_coincident: bool = True,
    chunk_cells: int | None = None,
) -> ConvGeometry:
    """The sparse interpolation matrices of the pairs ``pairs`` (see :class:`ConvGeometry`).

    Args:
        inp_pos: (N_in, 3) input point positions.
        out_pos: (N_out, 3) output point positions (``inp_pos`` itself for a self-convolution).
        pairs: (2, E) from :func:`conv_pairs`, row 0 input ``j``, row 1 output ``i``.
        radius: filter radius ``R``.
        kernel_size: (k_z, k_y, k_x), the kernel array's (and Open3D's ``kernel_size``) order, each >= 2.
        mapping: a key of :data:`MAPPINGS`.
        window: of ``r^2 / R^2``; None: every pair weighs 1.
        ignore_coincident: drop the pairs at distance 0 (Open3D's ``radius_search_ignore_query_points``).
        chunk_cells: kernel cells per block (memory of a layer ~ ``N_in * chunk_cells * C_out`` floats);
            None: all of them up to 2^21 input-cells (a 64-cell kernel up to 32k points), then fewer.
    """
    if mapping not in MAPPINGS:
        raise ConfigError(f"unknown coordinate mapping {mapping!r}; known: {sorted(MAPPINGS)}")
    if min(kernel_size) < 2:
        raise ConfigError(f"kernel_size must be at least 2 per axis, got {tuple(kernel_size)}")
    kz, ky, kx = kernel_size
    cells = kx * ky * kz
    n_in, n_out = inp_pos.shape[0], out_pos.shape[0]
    j, i = pairs[0], pairs[1]
    # rel = x_j - x_i (edge_vectors works on one array: stack the outputs after the inputs)
    both = torch.cat([inp_pos, out_pos]) if out_pos is not inp_pos else inp_pos
    shift = n_in if out_pos is not inp_pos else 0
    rel, dist = edge_vectors(both, torch.stack([j, i + shift]))
    if ignore_coincident:
        keep = dist > 0
        if not bool(keep.all()):
            j, i, rel, dist = j[keep], i[keep], rel[keep], dist[keep]
    coord = filter_coordinates(rel, radius, kernel_size, mapping)
    # Trilinear weights with Open3D's clamping; the lower corner stops at k - 2 so the 8 cells of a pair are
    # distinct (the same weights: at x = k - 1 the upper corner takes all of it). Built from (E, 2) factors,
    # not (E, 8, 3) arrays: at 400k pairs those cost more in allocation than in arithmetic.
    size = device_constant(kernel_size[::-1], torch.long, coord.device)  # (k_x, k_y, k_z), as coord
    lower = torch.minimum(coord.floor().long().clamp_min(0), size - 2)
    frac = (coord - lower).clamp(0, 1)
    lx, ly, lz = lower.unbind(1)
    base = (lz * ky + ly) * kx + lx  # the lower corner's cell in the kernel array (k_z, k_y, k_x)
    offsets = device_constant(
        [(c * ky + b) * kx + a for c in (0, 1) for b in (0, 1) for a in (0, 1)], torch.long, coord.device
    )  # the 8 corners, x fastest (Open3D's order)
    cell = base[:, None] + offsets[None]  # (E, 8)
    fx, fy, fz = (torch.stack([1 - f, f], dim=1) for f in frac.unbind(1))  # (E, 2) each
    w = (fz[:, :, None, None] * fy[:, None, :, None] * fx[:, None, None, :]).reshape(-1, 8)
    if window is not None:
        w = w * window((dist * dist) / (radius * radius))[:, None]
    counts = torch.bincount(i, minlength=n_out)
    num_neighbors = counts.to(inp_pos.dtype)

    if chunk_cells is None:
        chunk_cells = max(1, min(cells, (1 << 21) // max(n_in, 1)))
    chunks, splits = [], [*list(range(0, cells, chunk_cells)), cells]
    block_entries = pair_kernels.backend_for("cconv_block_entries", cell, w) if len(splits) > 2 else None
    for lo, hi in itertools.pairwise(splits):
        # Row order (by output point) and column order (j, then cell: the corners come x fastest) are kept
        if hi - lo == cells:
            crow = torch.zeros(n_out + 1, dtype=torch.long, device=i.device)
            cols, vals = (j[:, None] * cells + cell).flatten(), w.flatten()
            crow[1:] = torch.cumsum(8 * counts, 0)
        else:
            crow, cols, vals = block_entries(i, j, cell, w, counts, lo, hi, n_out)
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*Sparse CSR tensor support is in beta.*")
            chunks.append(
                torch.sparse_csr_tensor(
                    crow, cols, vals, size=(n_out, n_in * (hi - lo)), check_invariants=False
                )
            )
    rows = i[:, None] * cells + cell
    return ConvGeometry(tuple(chunks), tuple(splits), n_in, n_out, cells, num_neighbors, rows, j, w)


class ContinuousConv(nn.Module):
    """Open3D's ``ContinuousConv`` layer as DeepLagrangianFluids configures it, in pure PyTorch.

    Parameters and buffers keep Open3D's names and shapes, so their state dicts load unchanged:
    ``kernel`` (k_z, k_y, k_x, C_in, C_out): Open3D's array, cell (x, y, z) at ``kernel[z, y, x]`` (its
    ``kernel_size`` lists the axes in that order; checked against Open3D with a 3 x 4 x 5 kernel), ``bias``
    (C_out,) and ``offset`` (3,), a buffer (unused with ``align_corners``, as in Open3D; not a trained
    parameter, so not counted).

    Args:
        in_channels: C_in.
        filters: C_out.
        kernel_size: (k_z, k_y, k_x), Open3D's order.
        mapping: filter coordinate mapping (:data:`MAPPINGS`).
        window: window of ``r^2 / R^2`` (None: none); it shapes the geometry, which the caller builds.
    """

    def __init__(
        self,
        in_channels: int,
        filters: int,
        kernel_size: tuple[int, int, int] = (4, 4, 4),
        mapping: str = "ball_to_cube_volume_preserving",
        window: Callable[[Tensor], Tensor] | None = window_poly6,
    ) -> None:
        super().__init__()
        if mapping not in MAPPINGS:
            raise ConfigError(f"unknown coordinate mapping {mapping!r}; known: {sorted(MAPPINGS)}")
        self.in_channels, self.filters = int(in_channels), int(filters)
        self.kernel_size = tuple(int(k) for k in kernel_size)
        self.mapping, self.window = mapping, window
        self.kernel = nn.Parameter(torch.empty(*self.kernel_size, self.in_channels, self.filters))
        self.bias = nn.Parameter(torch.zeros(self.filters))
        self.register_buffer("offset", torch.zeros(3))
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Xavier-uniform kernel (Open3D's default initializer), zero bias."""
        cells = math.prod(self.kernel_size)
        bound = math.sqrt(6.0 / (cells * self.in_channels + self.filters))
        with torch.no_grad():
            self.kernel.uniform_(-bound, bound)
            self.bias.zero_()

    def forward(self, features: Tensor, geometry: ConvGeometry) -> Tensor:
        """(N_out, C_out) outputs of (N_in, C_in) input ``features`` over the pairs of ``geometry``."""
        if features.shape != (geometry.n_in, self.in_channels):
            raise ValueError(
                f"ContinuousConv: features of shape {tuple(features.shape)}, expected "
                f"({geometry.n_in}, {self.in_channels})"
            )
        if geometry.cells != math.prod(self.kernel_size):
            raise ValueError(
                f"ContinuousConv: geometry of {geometry.cells} cells for a {self.kernel_size} kernel"
            )
        if 4 * self.in_channels <= self.filters:
            # Few input channels (DeepLagrangianFluids' first layer: 4 -> 32): scattering the E x 8 weighted
            # inputs to (N_out * cells, C_in) moves C_in numbers per corner, gathering moves C_out
            # (benchmarks/results/cconv_layer.md: 4 -> 32)
            src = (
                geometry.pair_weights[..., None] * features[geometry.pair_inputs][:, None, :]
            )  # (E, 8, C_in)
            spread = features.new_zeros(geometry.n_out * geometry.cells, self.in_channels)
            spread = spread.index_add(0, geometry.pair_rows.flatten(), src.reshape(-1, self.in_channels))
            out = spread.reshape(geometry.n_out, -1) @ self.kernel.reshape(-1, self.filters)
            return out + self.bias
        kernel = self.kernel.reshape(geometry.cells, self.in_channels, self.filters)
        out = None
        blocks = itertools.pairwise(geometry.cell_splits)
        for chunk, (lo, hi) in enumerate(blocks):
            # (C_in, cells_b * C_out): every input point's contribution to every cell of the block at once
            block = kernel[lo:hi].permute(1, 0, 2).reshape(self.in_channels, -1)
            spread = (features @ block).reshape(-1, self.filters)
            if torch.is_grad_enabled() and spread.requires_grad:
                part = _GeometryMatmul.apply(spread, geometry, chunk)
            else:
                part = geometry.chunks[chunk] @ spread
            out = part if out is None else out + part
        return out + self.bias
