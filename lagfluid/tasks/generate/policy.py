"""On-policy datasets: scenes moved by a learned model, every sample labelled by the exact solver.

A network trained on the solver's own trajectories only ever sees the states the solver visits; in a
rollout it meets the states it makes itself (a learned pressure that under-corrects leaves the fluid more
compressed than MPS ever is) and extrapolates there. ``data.policy=model`` generates a dataset whose scenes
are rolled out by ``model=`` (a split-step model: ``fgn``, its ablations, ``hybrid``) while each sample's
labels are what the exact MPS stage answers at the very state the learned stages reached: the advection
acceleration at ``(x^n, v^n)`` and the PPE's pressure at the learned ``(x**, v**)``. Training on it (e.g.
fine-tuning with ``train.init_from``) is dataset aggregation with the solver as the expert (DAgger, Ross,
Gordon and Bagnell 2011), the exact-label form of multi-step (pushforward) training.

The trajectory in such a file is the model's, not the solver's: models that learn from trajectories (GNS,
CConv: :class:`~lagfluid.data.datasets.TrajectoryWindows`, :class:`~lagfluid.data.datasets.StepWindows`)
refuse it. The collision samples are the solver's own small systems, as in every dataset.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf
from torch import Tensor

from lagfluid.errors import ConfigError
from lagfluid.physics.mps import ExactAdvection, ExactPressure
from lagfluid.physics.scheme import SplitStepSimulator
from lagfluid.physics.settings import SolverSettings
from lagfluid.physics.step_context import StepContext
from lagfluid.state import SceneParams

POLICIES = (None, "model")  # data.policy: null = the MPS solver moves the particles; model = cfg.model


class ExpertLabelled:
    """A stage that moves the particles by ``act`` and records ``expert``'s answer as the step's label.

    Args:
        act: the stage whose output the step integrates (a learned stage).
        expert: the exact stage of the same kind, run only on steps that record their fields.
        label: the :class:`~lagfluid.physics.step_context.SplitStepFields` name of the label
            (``advection_acceleration`` or ``pressure_unclamped``).
    """

    def __init__(self, act: Any, expert: Any, label: str) -> None:
        self.act, self.expert, self.label = act, expert, label

    def radii(self, settings: SolverSettings, params: SceneParams) -> tuple[float, ...]:
        """Radii (l0) both stages search."""
        return tuple(sorted({*self.act.radii(settings, params), *self.expert.radii(settings, params)}))

    def __call__(self, ctx: StepContext, pos: Tensor, vel: Tensor) -> Tensor:
        """``act``'s output; on recording steps ``expert``'s answer at the same input becomes the label."""
        out = self.act(ctx, pos, vel)
        if ctx.fields is not None:
            ctx.record_label(**{self.label: self.expert(ctx, pos, vel)})
        return out


# per stage: the exact stage and its label's SplitStepFields name (collision samples are separate systems)
_EXPERTS = {
    "advection": (ExactAdvection, "advection_acceleration"),
    "pressure": (ExactPressure, "pressure_unclamped"),
}


def build_policy(cfg: Any) -> SplitStepSimulator:
    """``cfg.model`` as the simulator of an on-policy dataset: its learned stages labelled by the exact ones.

    Raises:
        ConfigError: ``cfg.model`` is not a split-step model, or skips a stage (``none``): a sample needs
            the advection and pressure labels.
    """
    from lagfluid.tasks.config import build_simulator

    sim = build_simulator(cfg)
    if not isinstance(sim, SplitStepSimulator):
        raise ConfigError(
            "data.policy=model needs a split-step model (fgn, its ablations, hybrid), "
            f"not model={cfg.model.name}"
        )
    for kind, (exact, label) in _EXPERTS.items():
        stage = getattr(sim, kind)
        if stage is None:
            raise ConfigError(
                f"data.policy=model: model.stages.{kind} is none; its samples need a {kind} stage"
            )
        if not isinstance(stage, exact):
            setattr(sim, kind, ExpertLabelled(stage, exact(), label))
    return sim


def policy_identity(cfg: Any) -> dict[str, Any] | None:
    """What of ``data.policy`` decides a file's content (None: the solver moves the particles).

    Else the model, its stages and a hash of each network file it loads.

    Raises:
        ConfigError: an unknown ``data.policy``.
    """
    policy = cfg.data.get("policy")
    if policy not in POLICIES:
        raise ConfigError(f"data.policy must be null (the MPS solver) or 'model' (model=...), got {policy!r}")
    if policy is None:
        return None
    sim = build_policy(cfg)
    networks = getattr(sim, "networks", {})
    digests = {
        kind: hashlib.sha256(Path(source["source"]).read_bytes()).hexdigest()[:16]
        if Path(source["source"]).is_file()
        else str(source["source"])  # a directory of the authors' arrays: named, not hashed
        for kind, source in sorted(networks.items())
    }
    stages = OmegaConf.to_container(cfg.model.stages, resolve=True) if "stages" in cfg.model else None
    return {"model": str(cfg.model.name), "stages": stages, "networks": digests}
