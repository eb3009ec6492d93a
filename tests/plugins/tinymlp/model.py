"""The plugin's model: per-particle acceleration from a kernel-weighted neighbourhood, semi-implicit Euler.

Inputs of fluid particle ``i`` (radius ``r = radius * l0``, MPS kernel ``w``): the weighted sums
``sum_j w_ij (x_j - x_i) / r`` (3), ``sum_j w_ij (v_j - v_i)`` (3) and ``sum_j w_ij`` (1) over every
particle ``j`` within ``r`` (boundary particles included, velocity 0). Relative positions and velocities
only: translation- and permutation-invariant by construction. Output: the acceleration ``a_i``; the step
is :func:`lagfluid.zoo.semi_implicit_euler` at the spacing of the training frames (the model's own
``dt``), and the training target is that update's inverse (:func:`acceleration_from_positions`).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf
from torch import Tensor, nn
from torch_geometric.data import Batch, Data

from lagfluid.zoo import (
    ParticleState,
    ParticleType,
    TrajectoryWindows,
    acceleration_from_positions,
    kernel,
    radius_graph,
    read_checkpoint,
    semi_implicit_euler,
)

NAME = "tiny_mlp"
SHIPPED = Path(__file__).resolve().parent / "weights"


def neighbourhood_features(
    pos: Tensor, vel: Tensor, fluid: Tensor, radius: float, batch: Tensor | None
) -> Tensor:
    """The (N_fluid, 7) inputs of the fluid (module doc) from ``pos``, ``vel`` (N, 3) and ``fluid`` (N,)."""
    src, dst = radius_graph(pos, radius, batch=batch, receivers=fluid)
    rel = pos.index_select(0, src) - pos.index_select(0, dst)
    w = kernel(rel.norm(dim=1), radius).unsqueeze(1)
    out = torch.zeros(pos.shape[0], 7, dtype=pos.dtype, device=pos.device)
    out.index_add_(0, dst, torch.cat([w * rel / radius, w * (vel[src] - vel[dst]), w], dim=1))
    return out[fluid]


class TinyMLPNet(nn.Module):
    """MLP 7 -> hidden -> hidden -> 3 on standardised inputs; statistics and frame spacing in buffers."""

    def __init__(self, radius: float = 2.1, hidden: int = 16) -> None:
        super().__init__()
        self.radius = float(radius)
        self.mlp = nn.Sequential(
            nn.Linear(7, hidden), nn.SiLU(), nn.Linear(hidden, hidden), nn.SiLU(), nn.Linear(hidden, 3)
        )
        self.register_buffer("feature_scale", torch.ones(7))
        self.register_buffer("target_mean", torch.zeros(3))
        self.register_buffer("target_std", torch.ones(3))
        self.register_buffer("frame_dt", torch.zeros(1))

    def forward(self, features: Tensor) -> Tensor:
        """Standardised acceleration (N, 3) of features (N, 7)."""
        return self.mlp(features / self.feature_scale)

    def acceleration(self, features: Tensor) -> Tensor:
        """Acceleration in m/s^2, (N, 3)."""
        return self.forward(features) * self.target_std + self.target_mean


def _inputs(net: TinyMLPNet, data: Data) -> tuple[Tensor, Tensor]:
    """Features (Nf, 7) and target acceleration (Nf, 3) of a TrajectoryWindows item or batch of them."""
    fluid = data.ptype == ParticleType.FLUID
    batch = data.batch if isinstance(data, Batch) else None
    l0, dt = float(data.l0.unique()[0]), float(data.frame_dt.unique()[0])
    previous = data.history[:, -1]
    vel = torch.zeros_like(data.pos)
    vel[fluid] = (data.pos[fluid] - previous) / dt
    features = neighbourhood_features(data.pos, vel, fluid, net.radius * l0, batch)
    return features, acceleration_from_positions(previous, data.pos[fluid], data.y, dt)


class TinyMLPTrainable:
    """The plugin's one trainable: :class:`TinyMLPNet` on one-step windows of the MPS trajectories."""

    name = NAME
    model = NAME
    loss = None  # train.loss.tiny_mlp

    def __init__(self, cfg: Any) -> None:
        self.options = OmegaConf.to_container(cfg.model[NAME], resolve=True)

    def datasets(self, data_dir: Path) -> tuple[Any, Any]:
        """Windows of one frame of history from the train and valid splits."""
        return TrajectoryWindows(data_dir, "train", history=1), TrajectoryWindows(
            data_dir, "valid", history=1
        )

    def build_network(self) -> nn.Module:
        """A fresh network."""
        return TinyMLPNet(**self.options)

    def fit_statistics(self, net: nn.Module, items: Any) -> dict[str, Any]:
        """Input scales, target mean and std, and the frame spacing (the model's own dt)."""
        pairs = [_inputs(net, item) for item in items]
        features = torch.cat([f for f, _ in pairs]).double()
        target = torch.cat([t for _, t in pairs]).double()
        net.feature_scale.copy_(features.std(dim=0).clamp_min(1e-6))
        net.target_mean.copy_(target.mean(dim=0))
        net.target_std.copy_(target.std(dim=0).clamp_min(1e-6))
        net.frame_dt.fill_(float(items[0].frame_dt[0]))
        return {"frame_dt": float(net.frame_dt), "target_std": net.target_std.tolist()}

    def predict(self, net: nn.Module, batch: Batch) -> tuple[Tensor, Tensor]:
        """Standardised prediction and target, (Nf, 3) each."""
        features, target = _inputs(net, batch)
        return net(features), (target - net.target_mean) / net.target_std

    def identity(self) -> dict[str, Any]:
        """Nothing besides options, data and schedule."""
        return {}


class TinyMLPSimulator:
    """The :class:`lagfluid.models.simulator.Simulator` of the plugin."""

    name = NAME
    history_length = 0  # velocities are in the state
    max_courant = None  # the run's solver.guard
    last_fields = None  # no intermediates to declare
    predicts_pressure = False  # its states carry zero pressure

    def __init__(self, net: TinyMLPNet) -> None:
        self.net = net.eval()
        self.dt = round(float(net.frame_dt), 9)  # a float32 buffer: the frames are whole ns apart
        self.last_info: dict[str, float] = {}
        self._timings: dict[str, float] = {}

    @property
    def parameters(self) -> int:
        """Trainable parameters of the network."""
        return sum(p.numel() for p in self.net.parameters() if p.requires_grad)

    @property
    def last_timings(self) -> dict[str, float]:
        """Seconds of the last step (one stage: the network)."""
        return dict(self._timings)

    def reset(self, state: ParticleState, history: Any = ()) -> None:
        """Nothing per scene: the network needs only the state."""

    @torch.no_grad()
    def step(self, state: ParticleState, *, record: bool = False) -> ParticleState:
        """One semi-implicit Euler step with the predicted accelerations of the fluid."""
        start = time.perf_counter()
        nf, dt = state.n_fluid, state.params.dt
        dtype = self.net.feature_scale.dtype
        features = neighbourhood_features(
            state.pos.to(dtype),
            state.vel.to(dtype),
            state.fluid_mask,
            self.net.radius * state.params.l0,
            None,
        )
        acc = self.net.acceleration(features).to(state.dtype)
        pos, vel = state.pos.clone(), state.vel.clone()
        pos[:nf], vel[:nf] = semi_implicit_euler(state.pos[:nf], state.vel[:nf], acc, dt)
        self._timings = {"network": time.perf_counter() - start}
        return ParticleState(
            pos=pos,
            vel=vel,
            ptype=state.ptype,
            params=state.params,
            pressure=torch.zeros_like(state.pressure),
            time=state.time + dt,
            step=state.step + 1,
            bounds=state.bounds,
            check=False,
        )

    def attributes(self) -> dict[str, Any]:
        """Where the weights came from is in the config; nothing else to store."""
        return {"frame_dt": self.dt}


def build_simulator(cfg: Any) -> TinyMLPSimulator:
    """``model=tiny_mlp``: the network of ``model.weights/tiny_mlp.pt`` (or the package's own weights)."""
    folder = Path(str(cfg.model.weights)) if cfg.model.get("weights") else SHIPPED
    ckpt = read_checkpoint(folder / f"{NAME}.pt", kind=NAME, model=NAME)
    net = TinyMLPNet(**ckpt["options"])
    net.load_state_dict(ckpt["state_dict"])
    return TinyMLPSimulator(
        net.to(device=torch.device(str(cfg.device)), dtype=getattr(torch, str(cfg.dtype)))
    )


def build_trainables(cfg: Any) -> dict[str, TinyMLPTrainable]:
    """The plugin's trainables by name."""
    return {NAME: TinyMLPTrainable(cfg)}
