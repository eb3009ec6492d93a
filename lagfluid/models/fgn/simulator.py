"""``model=fgn``, ``model=hybrid`` and ``model=fgn_original``: the split-step scheme with learned stages.

The update scheme is MPS's (:class:`~lagfluid.physics.scheme.SplitStepSimulator`); ``model.stages`` picks,
per stage, ``learned`` (the network), ``exact`` (the MPS stage) or ``none`` (skip it), so a user can trade
speed for accuracy stage by stage (e.g. exact advection + learned pressure).

Weights: ``model.weights`` is a directory holding ``advection.pt``, ``collision.pt`` and ``pressure.pt``
(:mod:`lagfluid.models.checkpoint`, as ``task=train`` writes them) or, with ``model.format=original``, the
authors' arrays (:mod:`lagfluid.models.fgn.original`). ``null`` means the weights shipped in the package:
per stage, ``lagfluid/weights/<model.shipped.<stage>>`` (``fgn``, see its MODEL_CARD.md; Table 5's
reference ``fgn_trained_here`` ships its pressure net and the ablations ``fgn_gcn``, ``fgn_sage``, ``fgn_mlp``
their node-focused nets, sharing FGN's other nets, which they do not change); for ``format=original``,
the authors' published networks shipped in ``lagfluid/weights/fgn_original`` (MIT, with their licence and
card).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf

from lagfluid.errors import ConfigError
from lagfluid.models.checkpoint import CheckpointError, MissingWeightsError
from lagfluid.models.fgn.learned_stages import LearnedAdvection, LearnedCollision, LearnedPressure
from lagfluid.models.fgn.networks import KINDS, load_network, owned_stages
from lagfluid.models.fgn.original import load_original_network
from lagfluid.models.layers import parameter_count
from lagfluid.models.training_range import RangeWarner, range_from_checkpoint_meta
from lagfluid.physics.mps import CollisionRule, ExactAdvection, ExactPressure
from lagfluid.physics.scheme import SplitStepSimulator
from lagfluid.physics.settings import SolverSettings
from lagfluid.state import ParticleState, parse_dtype

log = logging.getLogger(__name__)

WEIGHTS_ROOT = Path(__file__).resolve().parents[2] / "weights"
SHIPPED_WEIGHTS = WEIGHTS_ROOT / "fgn"
AUTHORS_WEIGHTS = WEIGHTS_ROOT / "fgn_original"
"""The FGN authors' published networks (``model=fgn_original``'s default; see its MODEL_CARD.md)."""
_IDENTITY_OPTIONS = ("aggregation",)  # what makes a variant another model: never taken from a checkpoint
CHOICES = ("learned", "exact", "none")
_EXACT = {"advection": ExactAdvection, "collision": CollisionRule, "pressure": ExactPressure}
_LEARNED = {"advection": LearnedAdvection, "collision": LearnedCollision, "pressure": LearnedPressure}


class LearnedSplitStep(SplitStepSimulator):
    """A :class:`SplitStepSimulator` that also reports where its networks came from."""

    def __init__(self, *args: Any, networks: dict[str, Any], **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.networks = networks
        self._ranges = RangeWarner(self.name, networks)

    def reset(self, state: ParticleState, history: Sequence[ParticleState] = ()) -> None:
        """As the split-step scheme's; first one warning per parameter outside a network's training range."""
        self._ranges.check(state.params)
        super().reset(state, history)

    @property
    def parameters(self) -> int:
        """Trainable parameters of the learned stages (0 when every stage is exact)."""
        return sum(int(n["parameters"]) for n in self.networks.values())

    def attributes(self) -> dict[str, Any]:
        """MPS constants plus ``networks``: per learned stage its file, format, step, range and parameters.

        A dict (``metrics.json`` holds it as an object; the rollout file's attribute is its JSON text).
        """
        return {**super().attributes(), "networks": self.networks}


def _plain(node: Any) -> dict[str, Any]:
    return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else dict(node or {})


def load_stage_network(kind: str, model_cfg: Any) -> tuple[torch.nn.Module, dict[str, Any]]:
    """The network of stage ``kind`` for a model config (``cfg.model``) and a description of its source."""
    fmt = model_cfg.get("format", "lagfluid")
    weights = model_cfg.get("weights")
    if fmt == "original":
        weights = AUTHORS_WEIGHTS if weights in (None, "") else weights
        net = load_original_network(kind, _plain(model_cfg[kind]), weights)
        return net, {"source": str(weights), "format": "original"}
    if fmt != "lagfluid":
        raise ConfigError(f"model.format must be 'lagfluid' or 'original', got {fmt!r}")
    shipped = _plain(model_cfg.get("shipped")) or {}
    if kind not in owned_stages(model_cfg):  # another model's network (an ablation's collision net)
        weights = None
    directory = Path(weights) if weights else WEIGHTS_ROOT / str(shipped.get(kind, "fgn"))
    path = directory / f"{kind}.pt"
    if not path.is_file():
        hint = (
            "no weights are shipped for it yet; train them with python -m lagfluid.run task=train "
            f"model={model_cfg.get('name', 'fgn')} (stage={kind} for this one alone) and pass "
            "model.weights=<run dir>"
            if weights is None
            else "pass the out_dir of a task=train run, or model.weights=null for the shipped ones"
        )
        raise MissingWeightsError(f"{kind} network not found: {path}; {hint}")
    net, ckpt = load_network(path, kind)
    configured = _plain(model_cfg.get(kind))
    differs = {k: (v, ckpt["options"].get(k)) for k, v in configured.items() if ckpt["options"].get(k) != v}
    wrong = {k: differs[k] for k in _IDENTITY_OPTIONS if k in differs}
    if wrong:
        raise CheckpointError(
            f"{kind} network {path} is not model={model_cfg.get('name')}'s: "
            + ", ".join(f"{k} {v[1]!r} in the checkpoint, {v[0]!r} in the config" for k, v in wrong.items())
        )
    if differs:  # the checkpoint's own options win: they are what the weights were trained with
        log.info("%s network from %s uses its own options where the config differs: %s", kind, path, differs)
    source = {"source": str(path), "format": "lagfluid", "step": ckpt["step"]}
    trained = range_from_checkpoint_meta(ckpt.get("meta") or {})
    return net, {**source, "range": trained} if trained else source


def build_split_step(cfg: Any) -> LearnedSplitStep:
    """Build ``cfg.model`` (fgn, hybrid, fgn_original) as a :class:`SplitStepSimulator`."""
    model = cfg.model
    stages = _plain(model.stages)
    unknown = {k: v for k, v in stages.items() if k not in KINDS or v not in CHOICES}
    if unknown or set(stages) != set(KINDS):
        raise ConfigError(
            f"model.stages must give each of {', '.join(KINDS)} one of {', '.join(CHOICES)}; got {stages}"
        )
    dtype = parse_dtype(cfg.get("dtype", "float32"))
    device = torch.device(str(cfg.get("device", "cpu")))
    impl: dict[str, Any] = {}
    sources: dict[str, Any] = {}
    for kind in KINDS:
        if stages[kind] == "exact":
            impl[kind] = _EXACT[kind]()
        elif stages[kind] == "learned":
            net, source = load_stage_network(kind, model)
            net = net.to(device=device, dtype=dtype)
            impl[kind] = _LEARNED[kind](net)
            sources[kind] = {**source, "parameters": parameter_count(net)}
        else:
            impl[kind] = None
    settings = SolverSettings.from_config(cfg.solver)
    sim = LearnedSplitStep(
        str(model.name), settings, impl["advection"], impl["collision"], impl["pressure"], networks=sources
    )
    log.info("model %s: stages %s; networks %s", model.name, stages, sources)
    return sim
