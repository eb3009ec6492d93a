"""CConv (baselines/cconv) by value, without Open3D: the layer against a direct sum over the neighbours
written here (the poly6 window, Open3D's ball-to-cube mapping and the trilinear interpolation of the kernel,
per pair, in plain Python), a three-point case worked by hand, and the network's first layer (seconds).

Nothing here calls the package to compute an expectation: a change of the window, the mapping, the kernel's
axis order or the pair's direction shows as a wrong number.
"""

import itertools
import math

import pytest
import torch

from baselines.cconv.conv import ContinuousConv, conv_geometry, conv_pairs
from baselines.cconv.network import CConvNet

F64 = torch.float64


def _poly6(r2_over_R2: float) -> float:
    """DeepLagrangianFluids' window: ``(1 - r^2 / R^2)^3`` inside the ball."""
    return (1.0 - r2_over_R2) ** 3


def _ball_to_cube(x: float, y: float, z: float) -> tuple[float, float, float]:
    """A point of the unit ball to the cube [-1, 1]^3 (Open3D's BALL_TO_CUBE_VOLUME_PRESERVING).

    Sphere to cylinder (axis z): the polar caps (5/4 z^2 > x^2 + y^2) go to the top and bottom faces, the
    rest to the side; then the cylinder's discs to squares, angle for angle (4 / pi atan).
    """
    norm = math.sqrt(x * x + y * y + z * z)
    if norm * norm < 1e-12:
        return 0.0, 0.0, 0.0
    if 1.25 * z * z > x * x + y * y:
        s = math.sqrt(3 * norm / (norm + abs(z)))
        x, y, z = x * s, y * s, math.copysign(norm, z)
    else:
        s = norm / math.sqrt(x * x + y * y)
        x, y, z = x * s, y * s, 1.5 * z
    rho = math.sqrt(x * x + y * y)
    if rho * rho < 1e-12:
        return 0.0, 0.0, z
    if abs(y) <= abs(x):
        side = math.copysign(rho, x)
        return side, side * 4 / math.pi * math.atan(y / x), z
    side = math.copysign(rho, y)
    return side * 4 / math.pi * math.atan(x / y), side, z


def _hat(t: float) -> float:
    """Linear interpolation's weight of a grid point at distance ``t`` (in cells)."""
    return max(0.0, 1.0 - abs(t))


def _direct_conv(kernel, bias, feats, inp, out, radius):
    """``out_i = bias + sum_{0 < |x_j - x_i| < R} window * f_j @ K(u_ij)``, one pair at a time.

    ``kernel`` (k_z, k_y, k_x, C_in, C_out) is indexed ``[z, y, x]``; the filter coordinate of a pair is its
    offset ``x_j - x_i`` over R, mapped to the cube, then to ``[0, k - 1]`` per axis (corners aligned), where
    the kernel is interpolated trilinearly.
    """
    kz, ky, kx = kernel.shape[:3]
    result = []
    for xi in out.tolist():
        total = bias.clone()
        for j, xj in enumerate(inp.tolist()):
            d = [a - b for a, b in zip(xj, xi, strict=True)]
            r2 = sum(c * c for c in d) / radius**2
            if r2 == 0.0 or r2 >= 1.0:
                continue
            u = _ball_to_cube(*(c / radius for c in d))
            gx, gy, gz = ((c + 1) / 2 * (k - 1) for c, k in zip(u, (kx, ky, kz), strict=True))
            k_ij = torch.zeros(kernel.shape[3:], dtype=F64)
            for a, b, c in itertools.product(range(kx), range(ky), range(kz)):
                w = _hat(gx - a) * _hat(gy - b) * _hat(gz - c)
                if w:
                    k_ij += w * kernel[c, b, a]
            total += _poly6(r2) * (feats[j] @ k_ij)
        result.append(total)
    return torch.stack(result)


# (1, 4): the layer's scatter form (4 C_in <= C_out); (3, 2): its gather form
@pytest.mark.parametrize("channels", [(1, 4), (3, 2)])
@pytest.mark.parametrize("same", [True, False])
def test_the_layer_is_the_direct_sum_over_the_neighbours(channels, same):
    g = torch.Generator().manual_seed(0)
    c_in, c_out = channels
    radius = 0.3
    inp = torch.rand(14, 3, generator=g, dtype=F64) * 0.5
    out = inp if same else torch.rand(9, 3, generator=g, dtype=F64) * 0.5
    feats = torch.randn(14, c_in, generator=g, dtype=F64)
    conv = ContinuousConv(c_in, c_out, (3, 4, 5)).to(F64)  # k_z, k_y, k_x all different: the axis order shows
    with torch.no_grad():
        conv.kernel.copy_(torch.randn(conv.kernel.shape, generator=g, dtype=F64))
        conv.bias.copy_(torch.randn(c_out, generator=g, dtype=F64))
    geo = conv_geometry(inp, out, conv_pairs(inp, None if same else out, radius), radius, (3, 4, 5))
    assert 20 < int(geo.num_neighbors.sum()) < 14 * 13  # some pairs, not all
    expected = _direct_conv(conv.kernel.detach(), conv.bias.detach(), feats, inp, out, radius)
    torch.testing.assert_close(conv(feats, geo), expected, rtol=0, atol=1e-10)


def test_three_points_worked_by_hand():
    """R = 0.1; p1 = p0 + (0.05, 0, 0) and p2 = p0 + (0, 0, -0.09) are p0's neighbours, not each other's
    (|p1 - p2| = 0.103). On the axes the mapping is the identity; grid coordinates (u + 1) / 2 (k - 1) with
    (k_z, k_y, k_x) = (3, 4, 5): x 4 cells, y 3, z 2.

    - p0 reads p1 at u = (0.5, 0, 0): grid (3, 1.5, 1); window (1 - 0.25)^3 = 0.421875; the kernel there is
      half of K[z=1, y=1, x=3] = 1 and half of K[1, 2, 3] = 3: 2.
    - p0 reads p2 at u = (0, 0, -0.9): grid (2, 1.5, 0.1); window (1 - 0.81)^3 = 0.006859; kernel
      0.9 (K[0, 1, 2] / 2 + K[0, 2, 2] / 2) + 0.1 (K[1, 1, 2] / 2 + K[1, 2, 2] / 2) = 0.9 * 6 = 5.4.
    - p1 reads p0 at u = (-0.5, 0, 0): grid (1, 1.5, 1), p2 reads p0 at grid (2, 1.5, 1.9): zero cells.
    """
    pos = torch.tensor([[0.2, 0.3, 0.4], [0.25, 0.3, 0.4], [0.2, 0.3, 0.31]], dtype=F64)
    feats = torch.tensor([[1.0], [2.0], [4.0]], dtype=F64)
    conv = ContinuousConv(1, 1, (3, 4, 5)).to(F64)
    with torch.no_grad():
        conv.kernel.zero_()
        conv.kernel[1, 1, 3] = 1.0
        conv.kernel[1, 2, 3] = 3.0
        conv.kernel[0, 1, 2] = 5.0
        conv.kernel[0, 2, 2] = 7.0
        conv.bias.fill_(0.5)
    geo = conv_geometry(pos, pos, conv_pairs(pos, None, 0.1), 0.1, (3, 4, 5))
    assert geo.num_neighbors.tolist() == [2.0, 1.0, 1.0]
    expected = torch.tensor([[0.5 + 0.421875 * 2 * 2 + 0.006859 * 4 * 5.4], [0.5], [0.5]], dtype=F64)
    torch.testing.assert_close(conv(feats, geo), expected, rtol=0, atol=1e-12)


def test_the_networks_first_layer_is_the_direct_sum_at_the_advected_positions():
    """conv0_fluid on ``[1, v*]`` at ``x* = x + dt (v + v*) / 2``, ``v* = v + dt g``, and conv0_obstacle on
    the normals, both of radius ``radius_scale * 3 * particle_radius`` (1.5 * 3 * 0.025 = 0.1125)."""
    g = torch.Generator().manual_seed(1)
    net = CConvNet(layer_channels=(4, 4, 4, 3), kernel_size=(3, 4, 5), timestep=0.02).to(F64)
    pos = torch.rand(10, 3, generator=g, dtype=F64) * 0.2
    vel = torch.randn(10, 3, generator=g, dtype=F64)
    box = torch.rand(8, 3, generator=g, dtype=F64) * 0.2
    normals = torch.randn(8, 3, generator=g, dtype=F64)
    seen = {}
    for name in ("conv0_fluid", "conv0_obstacle"):
        getattr(net, name).register_forward_hook(lambda m, args, out, name=name: seen.update({name: out}))
    net([pos, vel, None, box, normals])
    v_star = vel + 0.02 * torch.tensor([0.0, -9.81, 0.0], dtype=F64)
    x_star = pos + 0.02 * (vel + v_star) / 2
    fluid_feats = torch.cat([torch.ones(10, 1, dtype=F64), v_star], dim=1)
    for name, inp, feats in (("conv0_fluid", x_star, fluid_feats), ("conv0_obstacle", box, normals)):
        layer = getattr(net, name)
        expected = _direct_conv(layer.kernel.detach(), layer.bias.detach(), feats, inp, x_star, 0.1125)
        # 1e-8: the gravity buffer holds -9.81 in float32 (-9.8100004) before the network is cast
        torch.testing.assert_close(seen[name], expected, rtol=0, atol=1e-8, msg=name)
