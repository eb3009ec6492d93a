"""``model=cconv`` / ``model=cconv_original``: a CConv network as a lagfluid ``Simulator``.

Each step is the network's own (DeepLagrangianFluids): gravity and a trapezoid position update, a learned
position correction, the velocity implied by the displacement (:class:`~baselines.cconv.network.CConvNet`).
The state is the fluid's positions and velocities (no history). The boundary enters once per scene, at
:meth:`CConvSimulator.reset`, as surface points and normals (:func:`baselines.cconv.boundary.surface_points`);
the convolutions see only those within their radius of the fluid. The network works in its own axes:
``model=cconv_original`` is DeepLagrangianFluids' published network (y up, dt 20 ms), so positions and
velocities are rotated into its frame and back (z up here); ``model=cconv`` is trained here, in ours.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from lagfluid.zoo import (
    CheckpointError,
    ConfigError,
    MissingWeightsError,
    ParticleState,
    RangeWarner,
    RolloutError,
    StageTimer,
    checkpoint_range,
    read_checkpoint,
    rollout_bytes,
)

from .boundary import surface_points
from .network import CConvNet

BYTES_PER_PAIR = 900.0
"""Memory per pair within the filter radius of a step (:meth:`CConvSimulator.memory_needed`)."""

__all__ = [
    "AXES",
    "DLF_SURFACE_WEIGHT",
    "MAX_COURANT",
    "Y_UP",
    "CConvSimulator",
    "build_original",
    "load_dlf_network",
    "surface_weight_of",
]

DLF_SURFACE_WEIGHT = 1.9 * 4 / math.pi
"""Surface points DeepLagrangianFluids samples per ``l0^2`` of wall (their ``obj_surface_to_particles``:
``1.9 area / (pi r^2)`` with ``r = l0 / 2``), 2.42; ours, the wall particles' faces, are 1 per ``l0^2``. The
obstacle convolution sums over points, unnormalised: scaling each normal by this weight gives their network
the wall signal it was trained with (each of our points stands for 2.42 of theirs). Measured on the dam:
with it the fluid rests 5.5 cm above the floor's wall particles, as in MPS (5 cm); without it, 3.3 cm."""

MAX_COURANT = 5.0
"""Spacings a step may move a particle: a wall's 4 particle layers plus the one spacing the fluid rests in
front of it; a longer step could carry a particle through a wall before its correction (made at the moved
positions) sees the wall. The correction scheme itself takes long steps: DeepLagrangianFluids' 20 ms at the
water fall's splashes (MPS reaches 11 m/s there) is 4.5 spacings."""

Y_UP = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""Rotation from lagfluid's axes (z up) to DeepLagrangianFluids' (y up): ``x_theirs = Y_UP @ x_ours``."""

AXES = {"z_up": torch.eye(3), "y_up": Y_UP}
"""``model.axes``: the rotation from lagfluid's axes to a network's (``y_up``: DeepLagrangianFluids')."""


def surface_weight_of(model: Any, default: float = 1.0) -> float:
    """``model.surface_weight``: a number, ``dlf`` (:data:`DLF_SURFACE_WEIGHT`) or null/absent (``default``).

    Raises:
        ConfigError: anything else, or a weight that is not > 0.
    """
    value = model.get("surface_weight")
    if value is None:
        return float(default)
    if str(value) == "dlf":
        return DLF_SURFACE_WEIGHT
    try:
        weight = float(value)
    except (TypeError, ValueError):
        weight = float("nan")
    if not weight > 0:
        raise ConfigError(f"model.surface_weight={value!r}: give a number > 0, 'dlf' or null")
    return weight


class CConvSimulator:
    """CConv rollouts (module doc).

    Args:
        net: the network, on the run's device and dtype.
        name: registry name (``cconv`` or ``cconv_original``).
        weights: where the weights came from (stored with every rollout).
        axes: (3, 3) rotation from lagfluid's axes to the network's (identity: the same).
        surface_offset: boundary surface points in front of the wall particles, l0 (see ``boundary``).
        surface_weight: each surface point's normal is scaled by it (its share of the wall's area, in the
            network's points: :data:`DLF_SURFACE_WEIGHT` for DeepLagrangianFluids' network, 1 for ours).
        trained_range: the scene parameters the network was trained on (a lagfluid checkpoint's; None for
            DeepLagrangianFluids' network): a scene outside them is warned about once.
    """

    history_length = 0
    last_fields = None
    predicts_pressure = False  # positions only: previews colour by speed (lagfluid.viz.colour_field)

    def __init__(
        self,
        net: CConvNet,
        name: str,
        weights: str,
        axes: Tensor,
        surface_offset: float = 0.5,
        surface_weight: float = 1.0,
        trained_range: dict[str, list[float]] | None = None,
    ) -> None:
        self.net = net.eval()
        self.name = name
        self.weights = weights
        self.dt = float(net.timestep)
        self.max_courant = MAX_COURANT
        dtype = net.gravity.dtype
        self.axes = axes.to(device=net.gravity.device, dtype=dtype)
        self.surface_offset = float(surface_offset)
        self.surface_weight = float(surface_weight)
        self.last_info: dict[str, float] = {}
        self._timer = StageTimer()  # the last step's
        self._box: Tensor | None = None  # (S, 3) surface points, network axes
        self._box_normals: Tensor | None = None
        self._ranges = RangeWarner(name, {name: {"range": trained_range}})

    @property
    def parameters(self) -> int:
        """Trained parameters (692,902 for DeepLagrangianFluids' network)."""
        return sum(p.numel() for p in self.net.parameters())

    @property
    def last_timings(self) -> dict[str, float]:
        """Seconds of the last step: ``neighbors`` (the pair geometry) and ``network``."""
        return self._timer.read()

    def memory_needed(self, state: ParticleState) -> float:
        """Bytes a rollout from ``state`` needs: :func:`lagfluid.memory.rollout_bytes` at the filter radius.

        Measured (peak RSS of ``task=simulate``, 3 steps, dams of 4,000 to 80,000 fluid particles,
        ``threads=1``): 530-910 B per pair of a fluid particle within the filter radius.
        """
        radius = self.net.filter_radius / (2 * self.net.particle_radius) * state.params.l0  # l0 = 2 radii
        return rollout_bytes(state, radius, BYTES_PER_PAIR)

    def reset(self, state: ParticleState, history: Sequence[ParticleState] = ()) -> None:
        """The scene's boundary surface, in the network's axes (``history`` is not needed).

        Raises:
            RolloutError: a scene at another particle spacing than the network's.
        """
        self._ranges.check(state.params)
        spacing = 2 * self.net.particle_radius
        if abs(state.params.l0 - spacing) > 1e-6 * spacing:
            raise RolloutError(
                f"{self.name}: the network was trained at particle spacing {spacing} m (2 particle radii), "
                f"the scene has l0 = {state.params.l0} m"
            )
        boundary = state.pos[state.n_fluid :].to(self.axes.dtype)
        points, normals, _ = surface_points(boundary, state.params.l0, self.surface_offset)
        self._box = points @ self.axes.T
        self._box_normals = self.surface_weight * normals @ self.axes.T
        self.last_info = {"surface_points": float(points.shape[0])}

    @torch.no_grad()
    def step(self, state: ParticleState, *, record: bool = False) -> ParticleState:
        """The state one network step (``dt``) later; the boundary never moves."""
        if self._box is None or self._box_normals is None:
            raise RolloutError(f"{self.name}: call reset(state) before step()")
        if abs(state.params.dt - self.dt) > 1e-9:
            raise RolloutError(f"{self.name} steps by {self.dt} s, the state has dt {state.params.dt}")
        timer, device = StageTimer(), state.pos.device
        nf, net, axes = state.n_fluid, self.net, self.axes
        with timer("neighbors", device):
            pos = state.pos[:nf].to(axes.dtype) @ axes.T
            vel = state.vel[:nf].to(axes.dtype) @ axes.T
            pos2, vel2 = net.integrate_pos_vel(pos, vel)
            fluid_geo, obstacle_geo = net.geometries(pos2, self._box)
        with timer("network", device):
            new_pos = pos2 + net.correction(fluid_geo, obstacle_geo, vel2, None, self._box_normals)
            new_vel = (new_pos - pos) / net.timestep
        self._timer = timer
        self.last_info = {
            "fluid_pairs": float(fluid_geo.num_neighbors.sum()),
            "surface_points": float(len(self._box)),
        }
        # axes is a rotation: its inverse is its transpose
        return state.advanced_fluid(new_pos @ axes, new_vel @ axes, self.dt)

    def attributes(self) -> dict[str, Any]:
        """Where the weights came from, the step and the boundary surface."""
        return {
            "weights": self.weights,
            "network_dt": self.dt,
            "particle_radius": self.net.particle_radius,
            "surface_offset_l0": self.surface_offset,
            "surface_weight": self.surface_weight,
        }


def load_dlf_network(path: str | Path, **options: Any) -> CConvNet:
    """DeepLagrangianFluids' ``MyParticleNetwork`` with the weights of their checkpoint ``path``.

    The module takes ``forward((pos, vel, feats, box, box_feats))`` and returns ``(pos, vel)`` in their
    units and axes (y up, dt 0.02 s, particle radius 0.025 m), so their scripts port unchanged. Their
    published ``pretrained_model_weights.pt`` is a plain tensor state dict (CDLA-Permissive-1.0).

    Args:
        path: a ``.pt`` state dict of ``MyParticleNetwork``.
        options: :class:`CConvNet` arguments where the checkpoint was made with non-default ones.

    Raises:
        CheckpointError: a missing or unreadable file, or a state dict of another network.
    """
    file = Path(path)
    if not file.is_file():
        raise MissingWeightsError(f"no DeepLagrangianFluids checkpoint at {file}")
    try:
        state = torch.load(file, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise CheckpointError(f"{file} is not a readable torch state dict: {exc}") from exc
    if isinstance(state, dict) and "model" in state and isinstance(state["model"], dict):
        state = state["model"]  # their training script saves {"model": state_dict, "optimizer": ...}
    net = CConvNet(**options)
    result = net.load_state_dict(state, strict=False)
    if result.missing_keys or result.unexpected_keys:
        raise CheckpointError(
            f"{file} is not a MyParticleNetwork state dict: missing {result.missing_keys[:5]}, "
            f"unexpected {result.unexpected_keys[:5]}"
        )
    return net


def build_original(cfg: Any) -> CConvSimulator:
    """``model=cconv_original``: DeepLagrangianFluids' network, their axes and dt.

    ``model.weights`` null: their published ``pretrained_model_weights.pt``, shipped in :data:`DLF_WEIGHTS`.
    """
    weights = cfg.model.get("weights") or DLF_WEIGHTS
    dtype = getattr(torch, str(cfg.dtype))
    net = load_dlf_network(str(weights)).to(device=torch.device(str(cfg.device)), dtype=dtype)
    weight = surface_weight_of(cfg.model, DLF_SURFACE_WEIGHT)
    return CConvSimulator(net, "cconv_original", str(weights), Y_UP, float(cfg.model.surface_offset), weight)


SHIPPED = Path(__file__).resolve().parent / "weights"
"""The shipped weights of ``model=cconv`` (``cconv.pt``) and their model card, once trained."""
DLF_WEIGHTS = SHIPPED / "dlf" / "pretrained_model_weights.pt"
"""DeepLagrangianFluids' published network (CDLA-Permissive-1.0, licence and card beside it)."""
FINETUNED = SHIPPED / "dlf_finetuned"
"""``model=cconv_finetuned``'s shipped weights: :data:`DLF_WEIGHTS` fine-tuned here (card beside them)."""


def load_cconv(
    path: str | Path, device: str = "cpu", dtype: torch.dtype = torch.float32
) -> tuple[CConvNet, dict[str, Any]]:
    """The :class:`CConvNet` of a lagfluid checkpoint ``path`` (``cconv.pt``) and how it sees a scene.

    Returns:
        The network and its training's ``surface_offset`` (l0), ``axes`` (a name of :data:`AXES`) and
        ``surface_weight``, each with its default where the checkpoint predates it.

    Raises:
        CheckpointError: a missing or unreadable file, or the network of another model.
    """
    ckpt = read_checkpoint(path, kind="cconv", model="cconv")
    net = CConvNet(**ckpt["options"])
    net.load_state_dict(ckpt["state_dict"])
    identity = json.loads(ckpt.get("meta", {}).get("identity", "{}"))
    view = {
        "surface_offset": float(identity.get("surface_offset", 0.5)),
        "axes": str(identity.get("axes", "z_up")),
        "surface_weight": float(identity.get("surface_weight", 1.0)),
    }
    if view["axes"] not in AXES:
        raise CheckpointError(f"{path}: axes {view['axes']!r} is none of {sorted(AXES)}")
    return net.to(device=torch.device(device), dtype=dtype), view


def build_simulator(cfg: Any) -> CConvSimulator:
    """``model=cconv``: the network of ``model.weights/cconv.pt`` (null: the shipped ones).

    Axes, wall weighting and surface offset are the checkpoint's own (:func:`load_cconv`).

    Raises:
        CheckpointError: no weights there.
    """
    training = "python -m lagfluid.run task=train model=cconv train=cconv_cpu data=cpu"
    return _trained(cfg, "cconv", SHIPPED, training)


def build_finetuned(cfg: Any) -> CConvSimulator:
    """``model=cconv_finetuned``: DeepLagrangianFluids' network fine-tuned here (:data:`FINETUNED`).

    ``model.weights`` null: the shipped ones; else the out_dir of ``experiment=finetune_cconv_dlf``.

    Raises:
        CheckpointError: no weights there.
    """
    return _trained(
        cfg, "cconv_finetuned", FINETUNED, "python -m lagfluid.run experiment=finetune_cconv_dlf threads=2"
    )


def _trained(cfg: Any, name: str, shipped: Path, train_command: str) -> CConvSimulator:
    """The simulator ``name`` of the checkpoint ``model.weights/cconv.pt`` (null: ``shipped``'s)."""
    folder = Path(str(cfg.model.weights)) if cfg.model.get("weights") else shipped
    path = folder / "cconv.pt"
    if not path.is_file():
        raise MissingWeightsError(
            f"no CConv weights at {path}: train them ({train_command}) and pass model.weights=<that out_dir>"
        )
    net, view = load_cconv(path, str(cfg.device), getattr(torch, str(cfg.dtype)))
    return CConvSimulator(
        net,
        name,
        str(path),
        AXES[view["axes"]],
        view["surface_offset"],
        view["surface_weight"],
        # not dt: the network steps by its own timestep (a scene's dt is set to it; another one is refused)
        trained_range=checkpoint_range(path, ("l0", "gravity", "viscosity")),
    )
