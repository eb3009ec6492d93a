"""The horizontal symmetries of a tank scene, for data augmentation.

Gravity is vertical, so reflecting a scene in a vertical plane through its domain's centre, or swapping its
x and y axes, maps a solution of the flow equations (and of the MPS solver on a lattice symmetric about that
plane, which every tank of :mod:`lagfluid.scenes` is) to another solution: the 8 elements of the square's
symmetry group about the vertical axis. A model that is not equivariant to them (GNS, CConv) sees each wall
only as often as the data presses fluid on it; drawing one element per batch lets every wall teach every
other one.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["HorizontalSymmetry"]


@dataclass(frozen=True)
class HorizontalSymmetry:
    """One of the 8 symmetries: optional reflection of x and of y about the domain centre, then an x/y swap.

    Attributes:
        flip_x: reflect ``x -> (lower_x + upper_x) - x``.
        flip_y: reflect ``y -> (lower_y + upper_y) - y``.
        swap: exchange the x and y axes (after the reflections).
    """

    flip_x: bool = False
    flip_y: bool = False
    swap: bool = False

    @classmethod
    def draw(cls, generator: torch.Generator | None = None) -> HorizontalSymmetry:
        """A uniformly drawn element (the identity among them)."""
        bits = torch.randint(0, 2, (3,), generator=generator).tolist()
        return cls(bool(bits[0]), bool(bits[1]), bool(bits[2]))

    @property
    def is_identity(self) -> bool:
        """True for the element that changes nothing."""
        return not (self.flip_x or self.flip_y or self.swap)

    def points(self, x: Tensor, bounds: Tensor) -> Tensor:
        """Points ``x`` (..., 3) mapped; ``bounds`` (2, 3), or one box per point (..., 2, 3) broadcasting.

        The reflections are about each point's own domain centre, so a batch of scenes in different boxes
        maps each scene into its own (swapped) box.
        """
        # a reflected coordinate c - x is the vector rule's -(x - c), with c = lower + upper on that axis
        flipped = torch.tensor([self.flip_x, self.flip_y, False], dtype=x.dtype, device=x.device)
        return self.vectors(x - flipped * (bounds[..., 0, :] + bounds[..., 1, :]))

    def vectors(self, v: Tensor) -> Tensor:
        """Vectors ``v`` (..., 3) (velocities, displacements, normals) mapped: signs and the swap only."""
        out = v.clone()
        for axis, flip in ((0, self.flip_x), (1, self.flip_y)):
            if flip:
                out[..., axis] = -v[..., axis]
        return out[..., [1, 0, 2]] if self.swap else out

    def bounds(self, bounds: Tensor) -> Tensor:
        """Domain boxes (..., 2, 3) mapped: a reflection keeps the box, the swap exchanges its x and y."""
        return bounds[..., [1, 0, 2]] if self.swap else bounds.clone()
