"""``model=mps``: the ground-truth MPS solver as a :class:`~lagfluid.physics.scheme.SplitStepSimulator`."""

from __future__ import annotations

from typing import Any

from lagfluid.physics.mps import CollisionRule, ExactAdvection, ExactPressure
from lagfluid.physics.scheme import SplitStepSimulator
from lagfluid.physics.settings import SolverSettings


def build_mps(cfg: Any) -> SplitStepSimulator:
    """Build the MPS simulator from a composed config (reads ``cfg.solver``)."""
    settings = SolverSettings.from_config(cfg.solver)
    return SplitStepSimulator("mps", settings, ExactAdvection(), CollisionRule(), ExactPressure())
