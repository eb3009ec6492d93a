"""Open3D's ``ContinuousConv`` configured as DeepLagrangianFluids uses it: the optional test oracle.

Only the tests and ``benchmarks.cconv_layer`` use it (``pip install -e ".[cconv-oracle]"``, which needs
Debian's ``libusb-1.0-0``); nothing at run time does.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from .conv import window_poly6

__all__ = ["open3d_layer"]


def open3d_layer(
    kernel: Tensor,
    bias: Tensor | None = None,
    mapping: str = "ball_to_cube_volume_preserving",
) -> nn.Module | None:
    """Open3D's layer holding ``kernel`` (k_z, k_y, k_x, C_in, C_out) and ``bias``, or None without Open3D.

    DeepLagrangianFluids' options: aligned corners, linear interpolation, poly6 window, no normalisation,
    coincident points ignored. Called as ``layer(features, inp_positions, out_positions, 2 * radius)``.
    """
    try:
        import open3d.ml.torch as ml3d
    except Exception:  # absent, or present without its native library: no oracle either way
        return None
    size: Sequence[int] = tuple(kernel.shape[:3])
    layer = ml3d.layers.ContinuousConv(
        in_channels=int(kernel.shape[3]),
        filters=int(kernel.shape[4]),
        kernel_size=list(size),
        activation=None,
        align_corners=True,
        interpolation="linear",
        coordinate_mapping=mapping,
        normalize=False,
        window_function=window_poly6,
        radius_search_ignore_query_points=True,
    )
    with torch.no_grad():
        layer.kernel.copy_(kernel)
        layer.bias.copy_(bias if bias is not None else torch.zeros(kernel.shape[4]))
    return layer
