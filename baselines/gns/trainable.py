"""GNS's one trainable: one-step acceleration of the fluid on windows of the MPS trajectories.

A training item (:class:`~lagfluid.data.datasets.TrajectoryWindows`) is a window of ``H + K + 1`` stored
frames (``H`` the velocity history, ``K`` the longest pushforward unroll) and the frame after it, for every
frame ``t >= H`` of a trajectory: the first ``H`` frames of a rollout from rest are MPS's warm start
(:mod:`baselines.gns.simulator`), so frame ``H`` is the first the network steps from. Windows of
``t < H + K`` hold fewer than ``H + K`` trajectory frames (the rest copies of frame 0: ``frames_before``).
Per batch:

1. **Pushforward** (LagrangeBench; Brandstetter et al. 2022), optional: with probability ``probs[k]`` the
   model first rolls ``k`` steps forward without gradient from the frames ``k`` earlier, so the step that
   learns starts from the model's own positions, as in a rollout; ``k`` at most ``frames_before - H`` of
   every window of the batch (a roll starts from ``H`` frames of the trajectory).
2. **Noise** (DeepMind): a random walk on the input positions of the fluid, ``noise_std`` (in ``l0``) at the
   last input frame; the target frame is shifted by the last frame's noise, so the target acceleration
   ``(x_{t+1} - 2 x_t + x_{t-1}) / dt^2`` (:func:`lagfluid.integrate.acceleration_from_positions`, the
   inverse of the rollout's semi-implicit Euler) restores the true next velocity.
3. **Loss**: MSE of the standardised acceleration of the fluid particles (boundary nodes carry none).
4. **Unrolled loss** (``train.unroll_loss`` U > 1, optional): the learning step starts ``U - 1`` frames
   earlier and the model rolls ``U`` steps *with* gradient through its own positions (semi-implicit Euler),
   each step's target the acceleration that takes the model's last two frames to the true next frame (shifted
   by the start window's last noise). Step k's acceleration error is its position error over
   ``dt^2``, so the loss is the mean standardised position error of the ``U`` steps, and a step is answerable
   for the steps after it (the pushforward's steps carry no gradient). U = 1 is the one-step loss above.
   The windows then hold ``H + max(K, U - 1)`` earlier frames; windows near a trajectory's start unroll
   fewer steps. The pushforward, when drawn, runs before the first of the ``U`` steps.

Optionally (``train.horizontal_symmetries``), each batch first goes through one of the 8 horizontal
symmetries of its tank (:class:`lagfluid.data.symmetry.HorizontalSymmetry`, drawn uniformly): GNS is not
equivariant to them, and the data press fluid on some walls far more than on others.

Statistics (:meth:`GNSTrainable.fit_statistics`): mean and std per axis of the finite-difference velocities
and accelerations of the training frames (of each window: its trajectory frames before t, frame t and the
next), std combined with the noise's, ``sqrt(std^2 + noise^2)`` (DeepMind), stored in the network's buffers
with the frame spacing (the model's time step).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf
from torch import Tensor, nn
from torch_geometric.data import Batch, Data

from lagfluid.zoo import (
    ConfigError,
    HorizontalSymmetry,
    LagfluidError,
    ParticleType,
    acceleration_from_positions,
    semi_implicit_euler,
    trajectory_windows,
)

from .graph import build_graph, fluid_acceleration
from .network import GNSNet

NAME = "gns"


def random_walk_noise(shape: tuple[int, int, int], std_last: float, generator: Any = None) -> Tensor:
    """Random-walk noise (Nf, T, 3) on ``T`` positions whose last frame has std ``std_last`` (DeepMind).

    Each of the ``T - 1`` velocities gets independent noise of std ``std_last / sqrt(T - 1)``; the positions
    take its running sum, starting from 0 on the first frame.
    """
    nf, frames, dim = shape
    if frames < 2 or std_last == 0:
        return torch.zeros(shape)
    steps = torch.randn(nf, frames - 1, dim, generator=generator) * (std_last / math.sqrt(frames - 1))
    return torch.cat([torch.zeros(nf, 1, dim), steps.cumsum(dim=1)], dim=1)


def _scalar(values: Tensor, name: str) -> float:
    """The one value of a per-sample field (a batch must not mix frame spacings or spacings l0)."""
    unique = values.unique()
    if unique.numel() != 1:
        raise LagfluidError(f"a GNS batch mixes {name} values {unique.tolist()}; train on one dataset")
    return float(unique[0])


def _bounds(data: Data) -> Tensor | None:
    """Per-particle (P, 2, 3) domain bounds of a batch, (2, 3) of one item, or None."""
    bounds = getattr(data, "bounds", None)
    if bounds is None:
        return None
    return bounds[data.batch] if isinstance(data, Batch) else bounds[0]


def _placed(pos: Tensor, fluid: Tensor, frame: Tensor) -> Tensor:
    """A copy of the (P, 3) positions with the fluid rows set to ``frame`` (Nf, 3); autograd-safe."""
    out = pos.clone()
    out[fluid] = frame
    return out


def _trajectory_history(item: Data) -> Tensor:
    """The history frames (Nf, h, 3) of one window that are its trajectory's (not frame 0's copies)."""
    before = getattr(item, "frames_before", None)
    return item.history if before is None else item.history[:, item.history.shape[1] - int(before) :]


def step_acceleration(
    net: GNSNet,
    pos: Tensor,
    fluid: Tensor,
    frames: Tensor,
    dt: float,
    l0: float,
    bounds: Tensor | None,
    batch: Tensor | None = None,
) -> Tensor:
    """Standardised acceleration (Nf, 3) of the fluid from its last ``H + 1`` frames.

    Args:
        net: the network.
        pos: (P, 3) positions of every particle (fluid rows hold the last frame).
        fluid: (P,) bool.
        frames: (Nf, H + 1, 3) the fluid's positions, oldest first (the last equals ``pos[fluid]``).
        dt: frame spacing (s).
        l0: particle spacing (m).
        bounds: as :func:`baselines.gns.graph.graph_inputs`.
        batch: optional (P,) sample id.
    """
    radius = net.radius * l0
    graph = build_graph(pos, fluid, radius, batch)
    velocities = (frames[:, 1:] - frames[:, :-1]) / dt
    return fluid_acceleration(net, pos, velocities, graph, bounds, radius)


def next_window(net: GNSNet, window: Tensor, standardised: Tensor, dt: float) -> Tensor:
    """The fluid's last ``H + 1`` frames (Nf, H + 1, 3) after one model step.

    ``standardised`` (Nf, 3) is the network's acceleration; semi-implicit Euler from the window's last frame
    and velocity, as a rollout steps.
    """
    acc = net.acceleration.inverse(standardised)
    nxt, _ = semi_implicit_euler(window[:, -1], (window[:, -1] - window[:, -2]) / dt, acc, dt)
    return torch.cat([window[:, 1:], nxt.unsqueeze(1)], dim=1)


def symmetric_batch(batch: Data, symmetry: HorizontalSymmetry) -> Data:
    """A copy of a window batch with positions, history, target and bounds mapped by ``symmetry``.

    Raises:
        LagfluidError: the batch has no domain bounds (a symmetry needs the box it maps onto itself).
    """
    bounds = _bounds(batch)
    if bounds is None:
        raise LagfluidError(
            "train.horizontal_symmetries needs scenes with a tank (the windows have no bounds)"
        )
    if symmetry.is_identity:
        return batch
    fluid = batch.ptype == ParticleType.FLUID
    fluid_bounds = bounds[fluid] if bounds.dim() == 3 else bounds
    out = batch.clone()
    out.pos = symmetry.points(batch.pos, bounds)
    out.history = symmetry.points(batch.history, fluid_bounds.unsqueeze(-3))
    out.y = symmetry.points(batch.y, fluid_bounds)
    out.bounds = symmetry.bounds(batch.bounds)
    return out


class GNSTrainable:
    """:class:`~lagfluid.models.trainable.Trainable` of ``model=gns`` (module doc).

    Reads ``cfg.model.gns`` (network options) and ``cfg.train``: ``noise_std`` (l0, random-walk noise at the
    last input frame), ``pushforward`` (``unrolls`` list, ``probs`` weights, ``start`` the batch after
    which unrolls are drawn), ``horizontal_symmetries`` (bool, default false: augment, module doc) and
    ``unroll_loss`` (U >= 1 model steps with gradient in a training batch's loss, default 1: module doc).
    """

    name = NAME
    model = NAME
    loss = None  # train.loss.gns (mse)

    def __init__(self, cfg: Any) -> None:
        self.options = OmegaConf.to_container(cfg.model[NAME], resolve=True)
        tcfg = cfg.train
        self.noise_std = float(tcfg.get("noise_std", 0.0))
        if not (math.isfinite(self.noise_std) and self.noise_std >= 0):
            raise ConfigError(f"train.noise_std must be >= 0 (in l0), got {tcfg.get('noise_std')!r}")
        push = tcfg.get("pushforward") or {}
        self.unrolls = [int(u) for u in push.get("unrolls", [0])]
        probs = [float(p) for p in push.get("probs", [1.0])]
        if len(probs) != len(self.unrolls) or min(probs) < 0 or sum(probs) <= 0 or min(self.unrolls) < 0:
            raise ConfigError(
                f"train.pushforward: unrolls {self.unrolls} and probs {probs} must be the same length, "
                "unrolls >= 0, probs >= 0 with a positive sum"
            )
        self.probs = torch.tensor(probs) / sum(probs)
        self.push_start = int(push.get("start", 0))
        self.history = int(self.options.get("history", 5))
        self.symmetries = bool(tcfg.get("horizontal_symmetries", False))
        stride = tcfg.get("frame_stride", 1)
        if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
            raise ConfigError(f"train.frame_stride must be a whole number of stored frames >= 1: {stride!r}")
        self.frame_stride = stride
        steps = tcfg.get("unroll_loss", 1)
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
            raise ConfigError(f"train.unroll_loss must be a whole number of model steps >= 1: {steps!r}")
        self.loss_steps = steps

    # ------------------------------------------------------------------------ Trainable
    def datasets(self, data_dir: Path) -> tuple[Any, Any]:
        """Windows of ``H + K`` earlier frames from the train and valid splits.

        A model frame every ``train.frame_stride`` stored frames (its time step: the data's spacing times it).

        A DAgger dataset (``train.dagger``) gives the model's own frames and MPS's next positions
        (:class:`~lagfluid.data.expert_windows.ExpertWindows`), items of the same fields.
        """
        earlier = max(max(self.unrolls), self.loss_steps - 1)
        frames, first, stride = self.history + earlier, self.history, self.frame_stride
        return (
            trajectory_windows(data_dir, "train", history=frames, first=first, stride=stride),
            trajectory_windows(data_dir, "valid", history=frames, first=first, stride=stride),
        )

    def build_network(self) -> nn.Module:
        """A fresh :class:`GNSNet` from the options."""
        return GNSNet(**self.options)

    def fit_statistics(self, net: nn.Module, items: Sequence[Data]) -> dict[str, Any]:
        """Velocity and acceleration statistics (module doc), the frame spacing and the solver's step."""
        dt = _scalar(torch.cat([item.frame_dt for item in items]), "frame_dt")
        l0 = _scalar(torch.cat([item.l0 for item in items]), "l0")
        vel, acc = [], []
        for item in items:
            fluid = item.ptype == ParticleType.FLUID
            frames = torch.cat(
                [_trajectory_history(item), item.pos[fluid].unsqueeze(1), item.y.unsqueeze(1)], dim=1
            ).double()
            v = (frames[:, 1:] - frames[:, :-1]) / dt
            vel.append(v.reshape(-1, 3))
            acc.append(((v[:, 1:] - v[:, :-1]) / dt).reshape(-1, 3))
        vel_all, acc_all = torch.cat(vel), torch.cat(acc)
        noise = self.noise_std * l0
        vel_std = (vel_all.var(dim=0) + (noise / dt) ** 2).sqrt()
        acc_std = (acc_all.var(dim=0) + (noise / dt**2) ** 2).sqrt()
        net.velocity.set(vel_all.mean(dim=0), vel_std)
        net.acceleration.set(acc_all.mean(dim=0), acc_std)
        net.frame_dt.fill_(dt)
        net.solver_dt.fill_(_scalar(torch.cat([item.dt for item in items]), "dt"))
        return {
            "frame_dt": dt,
            "solver_dt": float(net.solver_dt),
            "l0": l0,
            "noise_std_m": noise,
            "velocity_mean": vel_all.mean(dim=0).tolist(),
            "velocity_std": vel_std.tolist(),
            "acceleration_mean": acc_all.mean(dim=0).tolist(),
            "acceleration_std": acc_std.tolist(),
        }

    def predict(self, net: nn.Module, batch: Batch) -> tuple[Tensor, Tensor]:
        """Standardised predicted and target accelerations of the fluid, (U Nf, 3) each.

        The ``U`` unrolled steps' rows one after the other (module doc); U = 1 outside training.
        """
        if net.training and self.symmetries:
            batch = symmetric_batch(batch, HorizontalSymmetry.draw())
        fluid = batch.ptype == ParticleType.FLUID
        dt = _scalar(batch.frame_dt, "frame_dt")
        l0 = _scalar(batch.l0, "l0")
        sample = batch.batch if isinstance(batch, Batch) else None
        bounds = _bounds(batch)
        frames = torch.cat([batch.history, batch.pos[fluid].unsqueeze(1)], dim=1)  # (Nf, H + K + 1, 3)
        training = net.training
        most = self._most_unroll(batch)
        steps = min(self.loss_steps, most + 1) if training else 1
        later = steps - 1  # the learning steps start this many frames before the window's last
        # the true frames each learning step aims at: the stored ones after the start, then the target
        truth = torch.cat([frames[:, frames.shape[1] - later :], batch.y.unsqueeze(1)], dim=1)  # (Nf, U, 3)
        end = frames.shape[1] - later
        window = frames[:, end - self.history - 1 : end]
        pos = _placed(batch.pos, fluid, window[:, -1]) if later else batch.pos
        if training:
            net.trained_batches += 1
            unroll = min(self._draw_unroll(int(net.trained_batches)), most - later)
            if unroll:
                pos, window = self._pushforward(
                    net, batch, fluid, frames, unroll, later, dt, l0, bounds, sample
                )
        if training and self.noise_std > 0:
            noise = random_walk_noise(tuple(window.shape), self.noise_std * l0).to(window)
            window = window + noise
            truth = truth + noise[:, -1:]
            pos = _placed(pos, fluid, window[:, -1])
        predictions, targets = [], []
        for k in range(steps):
            if k:  # the model's own step, with gradient: later steps' errors reach this one's weights
                window = next_window(net, window, predictions[-1], dt)
                pos = _placed(pos, fluid, window[:, -1])
            targets.append(
                net.acceleration(acceleration_from_positions(window[:, -2], window[:, -1], truth[:, k], dt))
            )
            predictions.append(step_acceleration(net, pos, fluid, window, dt, l0, bounds, sample))
        return torch.cat(predictions), torch.cat(targets)

    def identity(self) -> dict[str, Any]:
        """Noise and pushforward settings (they change the trained weights)."""
        identity = {
            "noise_std": self.noise_std,
            "pushforward": {"unrolls": self.unrolls, "probs": self.probs.tolist(), "start": self.push_start},
        }
        if self.symmetries:  # only then, so checkpoints trained without it keep their identity
            identity["horizontal_symmetries"] = True
        if self.frame_stride != 1:  # likewise
            identity["frame_stride"] = self.frame_stride
        if self.loss_steps != 1:  # likewise
            identity["unroll_loss"] = self.loss_steps
        return identity

    # ------------------------------------------------------------------------ helpers
    def _most_unroll(self, batch: Data) -> int:
        """The longest unroll all windows of ``batch`` have trajectory frames for: ``frames_before - H``."""
        before = getattr(batch, "frames_before", None)
        if before is None:  # windows without the field hold trajectory frames only
            return batch.history.shape[1] - self.history
        return int(before.min()) - self.history

    def _draw_unroll(self, batches: int) -> int:
        """Unroll steps of training batch ``batches``: 0 until ``pushforward.start``, then drawn."""
        if batches <= self.push_start or self.unrolls == [0]:
            return 0
        return self.unrolls[int(torch.multinomial(self.probs, 1))]

    @torch.no_grad()
    def _pushforward(
        self,
        net: GNSNet,
        batch: Batch,
        fluid: Tensor,
        frames: Tensor,
        unroll: int,
        later: int,
        dt: float,
        l0: float,
        bounds: Tensor | None,
        sample: Tensor | None,
    ) -> tuple[Tensor, Tensor]:
        """Roll ``unroll`` steps from ``unroll + later`` frames before the last.

        Returns the positions and the last H + 1 frames (ending ``later`` frames before the window's last).
        """
        end = frames.shape[1] - unroll - later
        window = frames[:, end - self.history - 1 : end]
        pos = batch.pos.clone()
        for _ in range(unroll):
            pos[fluid] = window[:, -1]
            window = next_window(
                net, window, step_acceleration(net, pos, fluid, window, dt, l0, bounds, sample), dt
            )
        pos[fluid] = window[:, -1]
        return pos, window


def build_trainables(cfg: Any) -> dict[str, GNSTrainable]:
    """``model=gns``'s trainables by name: one, the whole network."""
    return {NAME: GNSTrainable(cfg)}
