"""The ``evaluate:`` block of the config, read and checked once."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from lagfluid.errors import ConfigError

SLICE_AXES = {"x": 0, "y": 1}


@dataclass(frozen=True)
class EvaluateOptions:
    """The ``evaluate:`` block of the config (see ``conf/config.yaml``).

    Attributes:
        reference_dir: root of the cached MPS reference rollouts.
        reuse_reference: reuse a cached reference whose key matches (False: always recompute).
        horizons: steps at which the position MSE is reported (those the run stores).
        one_step: compute the one-step errors (advection nMAE, PPE residual) at every stored frame.
        figures: write ``error_vs_time.png`` and ``pressure_slice.png`` (False: metrics only).
        slice_time: time (s) of the pressure slice; None = the middle stored frame.
        slice_axis: normal of the vertical slice plane, ``"x"`` or ``"y"``.
        slice_position: coordinate (m) of the plane along ``slice_axis``; None = the fluid layer nearest
            the initial fluid's centre.
        slice_width: thickness of the slab shown, in l0.
        reference: settings merged over the run's config for the MPS reference only (plain nested dict;
            empty = the run's own settings).
    """

    reference_dir: Path
    reuse_reference: bool = True
    horizons: tuple[int, ...] = (1, 10, 50, 100)
    one_step: bool = True
    figures: bool = True
    slice_time: float | None = None
    slice_axis: str = "y"
    slice_position: float | None = None
    slice_width: float = 1.0
    reference: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_config(cls, node: Any) -> EvaluateOptions:
        """Build and check the options of ``cfg.evaluate``; a bad value is a :class:`ConfigError`."""
        sl = node.get("slice") or {}
        horizons = tuple(int(h) for h in (node.get("horizons") or ()))
        if any(h < 1 for h in horizons):
            raise ConfigError(f"evaluate.horizons must be steps >= 1, got {list(horizons)}")
        axis = str(sl.get("axis", "y"))
        if axis not in SLICE_AXES:
            raise ConfigError(f"evaluate.slice.axis must be x or y (the slice is vertical), got '{axis}'")
        slice_time = sl.get("time")
        if slice_time is not None and not (math.isfinite(float(slice_time)) and float(slice_time) >= 0):
            raise ConfigError(f"evaluate.slice.time must be a time >= 0 in s or null, got {slice_time!r}")
        width = float(sl.get("width", 1.0))
        if not (math.isfinite(width) and width > 0):
            raise ConfigError(f"evaluate.slice.width must be > 0 (l0), got {width!r}")
        position = sl.get("position")
        reference = node.get("reference") or {}
        if OmegaConf.is_config(reference):
            reference = OmegaConf.to_container(reference, resolve=True)
        if not isinstance(reference, dict):
            raise ConfigError(f"evaluate.reference must be a mapping of settings, got {reference!r}")
        return cls(
            reference_dir=Path(str(node.get("reference_dir") or "runs/reference")),
            reuse_reference=bool(node.get("reuse_reference", True)),
            horizons=horizons,
            one_step=bool(node.get("one_step", True)),
            figures=bool(node.get("figures", True)),
            slice_time=None if slice_time is None else float(slice_time),
            slice_axis=axis,
            slice_position=None if position is None else float(position),
            slice_width=width,
            reference=dict(reference),
        )
