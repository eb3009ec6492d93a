"""DeepLagrangianFluids' ``MyParticleNetwork`` (Ummenhofer et al. 2020) on :class:`ContinuousConv`.

One step of ``dt`` for the fluid positions ``x`` and velocities ``v``, boundaries as static surface points
``b`` with their normals ``n`` (pointing into the fluid)::

    v* = v + dt g,  x* = x + dt (v + v*) / 2                     gravity and the trapezoid position update
    h0 = [conv0_obstacle(n at b -> x*), conv0_fluid([1, v*] at x* -> x*), dense0([1, v*])]   (96 channels)
    h1 = conv1(relu h0) + dense1(relu h0)                         64
    h2 = conv2(relu h1) + dense2(relu h1) + h1                    64, residual
    h3 = conv3(relu h2) + dense3(relu h2)                         3
    x' = x* + u h3 / 128,  v' = (x' - x) / dt                     the correction and the velocity it implies

``u`` is ``length_unit`` (1 m for their network). A correction is an acceleration times dt^2, so at another
time step than their 20 ms its size changes by (dt / 20 ms)^2: 100x smaller at our 2 ms. With u = 1 m there,
Adam's steps of ~lr in the weights move the correction by more than the whole signal (~20 um a step) and the
training stalls above the trivial predictor's loss (measured: ``baselines/cconv/weights/MODEL_CARD.md``);
u = (dt / 20 ms)^2 m gives the network and its loss (:func:`baselines.cconv.trainable.dlf_loss`) their scale.

Layer names, shapes and buffers are DeepLagrangianFluids' (``models/default_torch.py``), so their
``state_dict`` loads unchanged (692,902 trained parameters; the 5 ``offset`` and ``gravity`` are buffers).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from .conv import ContinuousConv, ConvGeometry, conv_geometry, conv_pairs, window_poly6

__all__ = ["CConvNet"]


class CConvNet(nn.Module):
    """DeepLagrangianFluids' default network (see the module doc); units are the caller's.

    Args:
        layer_channels: output channels of layers 0..3 (layer 0 is three branches of ``[0]`` each).
        kernel_size: (k_z, k_y, k_x) of every convolution (Open3D's order).
        radius_scale: filter radius = ``radius_scale * 3 * particle_radius`` (Open3D extent = 2 radii).
        particle_radius: half the particle spacing, m.
        timestep: dt of one step, s.
        gravity: (3,) gravitational acceleration, m/s^2.
        mapping: the convolutions' coordinate mapping.
        use_window: the poly6 window on every convolution.
        other_feats_channels: extra fluid input channels beside ``[1, v]``.
        length_unit: m per unit of the correction and of the training loss (module doc; 1 = theirs).
    """

    def __init__(
        self,
        layer_channels: Sequence[int] = (32, 64, 64, 3),
        kernel_size: Sequence[int] = (4, 4, 4),
        radius_scale: float = 1.5,
        particle_radius: float = 0.025,
        timestep: float = 1 / 50,
        gravity: Sequence[float] = (0.0, -9.81, 0.0),
        mapping: str = "ball_to_cube_volume_preserving",
        use_window: bool = True,
        other_feats_channels: int = 0,
        length_unit: float = 1.0,
    ) -> None:
        super().__init__()
        self.layer_channels = [int(c) for c in layer_channels]
        self.kernel_size = tuple(int(k) for k in kernel_size)
        self.radius_scale, self.particle_radius = float(radius_scale), float(particle_radius)
        self.timestep = float(timestep)
        self.mapping = mapping
        self.window = window_poly6 if use_window else None
        self.other_feats_channels = int(other_feats_channels)
        if not float(length_unit) > 0:
            raise ValueError(f"length_unit must be > 0 (m), got {length_unit!r}")
        self.length_unit = float(length_unit)
        self.register_buffer("gravity", torch.tensor([float(g) for g in gravity]))

        c0 = self.layer_channels[0]
        fluid_in = 4 + self.other_feats_channels
        self.conv0_fluid = self._conv(fluid_in, c0)
        self.conv0_obstacle = self._conv(3, c0)
        self.dense0_fluid = self._dense(fluid_in, c0)
        for k in range(1, len(self.layer_channels)):
            c_in = self.layer_channels[k - 1] * (3 if k == 1 else 1)
            setattr(self, f"dense{k}", self._dense(c_in, self.layer_channels[k]))
            setattr(self, f"conv{k}", self._conv(c_in, self.layer_channels[k]))

    def _conv(self, c_in: int, c_out: int) -> ContinuousConv:
        return ContinuousConv(c_in, c_out, self.kernel_size, self.mapping, self.window)

    @staticmethod
    def _dense(c_in: int, c_out: int) -> nn.Linear:
        layer = nn.Linear(c_in, c_out)
        nn.init.xavier_uniform_(layer.weight)
        nn.init.zeros_(layer.bias)
        return layer

    @property
    def filter_radius(self) -> float:
        """Radius of every convolution: half Open3D's extent ``radius_scale * 6 * particle_radius``."""
        return self.radius_scale * 3 * self.particle_radius

    def layers(self) -> list[tuple[ContinuousConv, nn.Linear]]:
        """The (conv, dense) pairs of layers 1..3."""
        return [
            (getattr(self, f"conv{k}"), getattr(self, f"dense{k}"))
            for k in range(1, len(self.layer_channels))
        ]

    def integrate_pos_vel(self, pos: Tensor, vel: Tensor) -> tuple[Tensor, Tensor]:
        """Gravity and the position update before the correction: (x*, v*), each (N, 3)."""
        vel2 = vel + self.timestep * self.gravity
        return pos + self.timestep * (vel2 + vel) / 2, vel2

    def geometries(
        self,
        pos: Tensor,
        box: Tensor,
        batch: Tensor | None = None,
        box_batch: Tensor | None = None,
    ) -> tuple[ConvGeometry, ConvGeometry]:
        """The fluid->fluid and the boundary->fluid pair geometries at the fluid positions ``pos`` (N, 3)."""
        # Neither the search nor conv_geometry is differentiated (no gradient to positions, as Open3D's op)
        r, options = self.filter_radius, (self.kernel_size, self.mapping, self.window)
        fluid = conv_geometry(pos, pos, conv_pairs(pos, None, r, inp_batch=batch), r, *options)
        pairs = conv_pairs(box, pos, r, inp_batch=box_batch, out_batch=batch)
        return fluid, conv_geometry(box, pos, pairs, r, *options)

    def compute_correction(
        self,
        pos: Tensor,
        vel: Tensor,
        other_feats: Tensor | None,
        box: Tensor,
        box_feats: Tensor,
        batch: Tensor | None = None,
        box_batch: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        """The position correction (N, 3) at (x*, v*) and the fluid neighbour counts (N,).

        Args:
            pos: (N, 3) fluid positions after :meth:`integrate_pos_vel`.
            vel: (N, 3) fluid velocities after :meth:`integrate_pos_vel`.
            other_feats: optional (N, other_feats_channels) extra fluid inputs.
            box: (M, 3) boundary surface points.
            box_feats: (M, 3) their normals.
            batch: optional (N,) scene id of each fluid particle (several scenes in one call).
            box_batch: optional (M,) scene id of each surface point.
        """
        fluid_geo, obstacle_geo = self.geometries(pos, box, batch, box_batch)
        return self.correction(fluid_geo, obstacle_geo, vel, other_feats, box_feats), fluid_geo.num_neighbors

    def correction(
        self,
        fluid_geo: ConvGeometry,
        obstacle_geo: ConvGeometry,
        vel: Tensor,
        other_feats: Tensor | None,
        box_feats: Tensor,
    ) -> Tensor:
        """(N, 3) position correction over precomputed :meth:`geometries` (arguments as there)."""
        feats = [torch.ones_like(vel[:, :1]), vel]
        if other_feats is not None:
            feats.append(other_feats)
        fluid_feats = torch.cat(feats, dim=-1)
        h = torch.cat(
            [
                self.conv0_obstacle(box_feats, obstacle_geo),
                self.conv0_fluid(fluid_feats, fluid_geo),
                self.dense0_fluid(fluid_feats),
            ],
            dim=-1,
        )
        for conv, dense in self.layers():
            x = F.relu(h)
            out = conv(x, fluid_geo) + dense(x)
            h = out + h if out.shape[-1] == h.shape[-1] else out
        return h * (self.length_unit / 128)  # DeepLagrangianFluids' output scale, in length units

    def forward(self, inputs: Sequence[Tensor | None]) -> tuple[Tensor, Tensor]:
        """One step, DeepLagrangianFluids' signature: ``(pos, vel, feats, box, box_feats) -> (pos, vel)``."""
        pos, vel, feats, box, box_feats = inputs
        pos2, vel2 = self.integrate_pos_vel(pos, vel)
        correction, _ = self.compute_correction(pos2, vel2, feats, box, box_feats)
        new_pos = pos2 + correction
        return new_pos, (new_pos - pos) / self.timestep

    def trained_parameter_count(self) -> int:
        """Parameters a training updates (the paper's Table 2 count; buffers excluded)."""
        return sum(p.numel() for p in self.parameters())
