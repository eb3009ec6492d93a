"""CConv's one trainable: DeepLagrangianFluids' two-step unroll on windows of consecutive solver steps.

A training item (:class:`~lagfluid.data.datasets.StepWindows`, a dataset generated with
``data.next_steps=2``) is a sampled MPS state ``(x, v)`` with the boundary and the fluid positions of the
next two solver steps. Per batch, as DeepLagrangianFluids' ``train_network_torch.py``:

1. the boundary particles become surface points with normals (:func:`baselines.cconv.boundary.surface_points`,
   per scene of the batch), as in rollouts;
2. two steps of the network, the second from the first's predicted positions and velocities (the gradient
   flows through both; none through the pair geometry, as Open3D's op gives none);
3. loss ``128 * sum_k 0.5 * mean_i exp(-n_i / 40) |x_pred - x_true|^0.5`` with ``n_i`` the fluid neighbours
   of particle i at step k (fewer neighbours, the free surface, weigh more), the distance in the network's
   ``length_unit`` (DeepLagrangianFluids' metre at their 20 ms; ``(dt / 20 ms)^2`` m at ours, see
   :mod:`baselines.cconv.network`).

With ``train.unroll_frames`` F > 0 the windows are the sample's state and the next F stored frames
(:class:`~lagfluid.data.datasets.StepWindows` ``frames=F``, e.g. 4 solver steps apart): the network unrolls
to each of them (``4 F`` steps, the gradient through all) and the loss is the same, at the frames, each
weighted 1 / F. MPS's per-step accelerations are mostly particle-level noise after the first impact
(residual 3.6x the smooth field at 2 ms, 2.0x at 8 ms: ``benchmarks/results/acceleration_noise.md``); a
longer horizon averages it out of the target.

**Fine-tuning DeepLagrangianFluids' network** (``experiment=finetune_cconv_dlf``): ``model.start_from=dlf``
starts from their published weights, ``model.axes=y_up`` trains in their axes (y up: positions, velocities,
walls and targets are rotated in, as in their rollouts), ``model.surface_weight`` scales the surface normals
as the simulator does, and the network steps by its own 20 ms: each stored frame of ``data=dlf_frames``
(every 10 solver steps) is one network step. ``train.rotate_about_gravity`` turns each batch by a random
angle about the vertical (their network is not rotation-equivariant; the data's walls are axis-aligned).

There are no normalisation statistics (their network has none); :meth:`CConvTrainable.fit_statistics`
checks that the network's time step, particle radius and gravity are the data's (gravity in its axes).
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
    LagfluidError,
    ParticleType,
    StepWindows,
    radius_graph,
    step_windows,
)

from .boundary import SURFACE_RADIUS, surface_points
from .network import CConvNet
from .simulator import AXES, DLF_WEIGHTS, load_dlf_network, surface_weight_of

NAME = "cconv"
UNROLL = 2
"""Steps per training window (DeepLagrangianFluids: 2, each loss weighted 0.5)."""
NEIGHBOR_SCALE = 40.0
"""The loss weight ``exp(-n / 40)`` of a particle with ``n`` fluid neighbours (DeepLagrangianFluids)."""
LOSS_SCALE = 128.0
"""DeepLagrangianFluids scales the loss by 128 (the inverse of the network's output scale)."""
REACH = 3.1
"""l0: the walls a window keeps, those within this of its fluid (the datasets' default crop, > the 2.25 l0
filter radius plus a step's motion)."""


def dlf_loss(prediction: Tensor, target: Tensor) -> Tensor:
    """DeepLagrangianFluids' loss of ``(Nf, K, 4)`` positions + neighbour weight (see :meth:`predict`).

    ``LOSS_SCALE * sum_k (1 / K) mean_i w_ik (|x_pred - x_true|^2 + 1e-9)^0.25``, ``w = exp(-n / 40)``,
    positions in the network's length unit (:meth:`CConvTrainable.predict` divides them by it).
    """
    distance = (((prediction[..., :3] - target[..., :3]) ** 2).sum(-1) + 1e-9) ** 0.25
    per_step = (target[..., 3] * distance).mean(dim=0)  # (K,)
    return LOSS_SCALE * per_step.mean()


def _scalar(values: Tensor, name: str) -> float:
    unique = values.unique()
    if unique.numel() != 1:
        raise LagfluidError(f"a CConv batch mixes {name} values {unique.tolist()}; train on one dataset")
    return float(unique[0])


class CConvTrainable:
    """:class:`~lagfluid.models.trainable.Trainable` of ``model=cconv`` (module doc).

    Reads ``cfg.model.cconv`` (the :class:`CConvNet` options, with its ``timestep``, ``particle_radius`` and
    ``gravity``: the data's) and ``cfg.model.surface_offset``.
    """

    name = NAME
    model = NAME
    loss = staticmethod(dlf_loss)

    def __init__(self, cfg: Any) -> None:
        self.options = OmegaConf.to_container(cfg.model[NAME], resolve=True)
        self.surface_offset = float(cfg.model.surface_offset)
        self.axes_name = str(cfg.model.get("axes") or "z_up")
        if self.axes_name not in AXES:
            raise ConfigError(f"model.axes={self.axes_name!r}: choose one of {sorted(AXES)}")
        self.axes = AXES[self.axes_name]
        self.surface_weight = surface_weight_of(cfg.model)
        self.start_from = cfg.model.get("start_from")
        if (
            self.start_from is not None
            and str(self.start_from) != "dlf"
            and not Path(str(self.start_from)).is_file()
        ):
            raise ConfigError(
                f"model.start_from={self.start_from!r}: give 'dlf' (DeepLagrangianFluids' published "
                "weights) or a MyParticleNetwork .pt state dict"
            )
        train = cfg.get("train") or {}
        self.unroll_frames = int(train.get("unroll_frames", 0) or 0)
        if self.unroll_frames < 0:
            raise ConfigError(f"train.unroll_frames must be >= 0, got {self.unroll_frames}")
        self.rotate_about_gravity = bool(train.get("rotate_about_gravity", False))
        dagger = train.get("dagger") or {}
        horizon = dagger.get("horizon", 1)
        short = isinstance(horizon, int) and 1 <= horizon < UNROLL  # a bad value: DAgger.from_config says so
        if dagger.get("rounds") and not self.unroll_frames and short:
            # refused before any round's rollouts: their labels could not train this model
            raise ConfigError(
                f"train.dagger.horizon={horizon}: CConv trains on {UNROLL}-step unrolls, so its DAgger "
                f"labels must be {UNROLL} MPS steps: set train.dagger.horizon={UNROLL} "
                "(train=cconv_dagger does)"
            )

    # ------------------------------------------------------------------------ Trainable
    def datasets(self, data_dir: Path) -> tuple[Any, Any]:
        """Windows of a state and its next two solver steps (or frames), train and valid splits.

        A DAgger dataset (``train.dagger``, made with ``horizon`` 2) gives the model's own states and MPS's
        next two steps from each (:class:`~lagfluid.zoo.ExpertStepWindows`).
        """
        return self.windows(data_dir, "train"), self.windows(data_dir, "valid")

    def windows(self, data_dir: Path, split: str) -> StepWindows:
        """The training windows of one split of ``data_dir`` (``train``, ``valid``, ``test``)."""
        # Cropped wider than REACH by the surface test's neighbourhood: a wall particle at the crop's edge
        # looks one-sided, a false surface point inside the wall that rollouts (the whole tank) never see.
        # Measured on data=cpu at a 3.1 l0 crop: 2,096 of a window's 3,989 surface points were such.
        crop = (REACH + SURFACE_RADIUS) * 2 * float(self.options["particle_radius"])
        if self.unroll_frames:
            return StepWindows(data_dir, split, steps=0, frames=self.unroll_frames, boundary_radius=crop)
        # a DAgger dataset's windows (the model's own states, MPS's next steps) have the same fields
        return step_windows(data_dir, split, UNROLL, boundary_radius=crop)

    def build_network(self) -> nn.Module:
        """A :class:`CConvNet` of the options: fresh, or ``model.start_from``'s weights (module doc).

        The gravity buffer is an option of the network (the data's, checked by :meth:`fit_statistics`), not a
        trained weight: DeepLagrangianFluids' file holds their 9.81 m/s^2, the data's may differ.
        """
        if self.start_from is None:
            return CConvNet(**self.options)
        path = DLF_WEIGHTS if str(self.start_from) == "dlf" else Path(str(self.start_from))
        net = load_dlf_network(path, **self.options)
        net.gravity.copy_(torch.tensor([float(g) for g in self.options["gravity"]]))
        return net

    def fit_statistics(self, net: nn.Module, items: Sequence[Data]) -> dict[str, Any]:
        """No statistics to fit: checks the network's dt, particle radius and gravity against the data.

        Raises:
            ConfigError: the data were made at another dt, spacing or gravity than ``model.cconv`` says.
        """
        dt = _scalar(torch.cat([item.dt for item in items]), "dt")
        l0 = _scalar(torch.cat([item.l0 for item in items]), "l0")
        step = dt  # the time a network step must take: the solver's, or one stored frame's
        if self.unroll_frames:
            step = dt * _scalar(torch.cat([item.frame_steps for item in items]).double(), "frame_steps")
        self.steps_per_frame(
            net.timestep, step
        )  # raises for a network step that fits no whole number of times
        if not self.unroll_frames and abs(net.timestep - dt) > 1e-6 * dt:
            raise ConfigError(
                f"model.cconv.timestep={net.timestep}, the data's is {dt}; set it to the data's"
            )
        if abs(net.particle_radius - l0 / 2) > 1e-6 * l0:
            raise ConfigError(
                f"model.cconv.particle_radius={net.particle_radius}, the data's is {l0 / 2}; "
                "set it to the data's"
            )
        gravity = torch.cat([item.gravity for item in items]).unique(dim=0)
        in_axes = gravity.double() @ self.axes.double().T  # the data's gravity in the network's axes
        if gravity.shape[0] != 1 or not torch.allclose(in_axes[0], net.gravity.cpu().double(), atol=1e-5):
            raise ConfigError(
                f"model.cconv.gravity={net.gravity.tolist()}, the data's is {in_axes.tolist()} in the "
                f"network's axes (model.axes={self.axes_name}); set it to the data's (CConv takes gravity as "
                "a constant of the network)"
            )
        return {"timestep": net.timestep, "particle_radius": l0 / 2, "gravity": in_axes[0].tolist()}

    @staticmethod
    def steps_per_frame(timestep: float, frame_dt: float) -> int:
        """Network steps of ``timestep`` s in one target interval of ``frame_dt`` s (a whole number >= 1).

        Raises:
            ConfigError: ``frame_dt`` is no whole multiple of the network's step.
        """
        ratio = frame_dt / timestep
        if round(ratio) < 1 or abs(ratio - round(ratio)) > 1e-6:
            raise ConfigError(
                f"model.cconv.timestep={timestep} s does not divide the data's interval {frame_dt} s between "
                "targets (dt, or dt x sample_every with train.unroll_frames): choose a divisor"
            )
        return round(ratio)

    def frame(self, device: torch.device, dtype: torch.dtype, turn: bool = True) -> Tensor:
        """(3, 3) rotation from the data's axes to the network's for one batch.

        ``model.axes``, after a random turn about the vertical (z, the data's gravity axis) when
        ``train.rotate_about_gravity`` and ``turn`` (training batches; not validation's): the walls,
        the fluid and the targets turn together.
        """
        rotation = self.axes.to(dtype=torch.float64)
        if self.rotate_about_gravity and turn:
            angle = float(torch.rand(()) * 2 * math.pi)  # torch's RNG: seeded, and restored on resume
            c, s = math.cos(angle), math.sin(angle)
            turn = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
            rotation = rotation @ turn
        return rotation.to(device=device, dtype=dtype)

    def predict(self, net: nn.Module, batch: Batch) -> tuple[Tensor, Tensor]:
        """Predicted and true fluid motion with the loss weight, (Nf, K, 4) each.

        K: the next 2 solver steps, or the next ``unroll_frames`` stored frames.

        Channels 0-2: displacements from the window's start in the network's ``length_unit``; channel 3:
        ``exp(-n / 40)`` of the particle's fluid neighbours at that step (the same in both tensors, so that
        :func:`dlf_loss` sees it).
        """
        fluid = batch.ptype == ParticleType.FLUID
        sample = batch.batch if isinstance(batch, Batch) else torch.zeros_like(batch.ptype)
        l0 = _scalar(batch.l0, "l0")
        points, normals, box_batch = self.surface(batch.pos, fluid, sample, l0)
        fluid_batch = sample[fluid]
        # data axes -> the network's; a network in eval mode (validation) sees the data unturned
        rotation = self.frame(batch.pos.device, batch.pos.dtype, turn=net.training)
        points, normals = points @ rotation.T, self.surface_weight * normals @ rotation.T
        pos, vel = batch.pos[fluid] @ rotation.T, batch.vel[fluid] @ rotation.T
        if self.unroll_frames:
            frame_dt = _scalar(batch.dt, "dt") * _scalar(batch.frame_steps.double(), "frame_steps")
            every = self.steps_per_frame(net.timestep, frame_dt)
            steps, truth = every * self.unroll_frames, batch.y_frames @ rotation.T
        else:
            every, steps, truth = 1, UNROLL, batch.y[:, :UNROLL] @ rotation.T
        predicted, weights = [], []
        for k in range(1, steps + 1):
            pos2, vel2 = net.integrate_pos_vel(pos, vel)
            correction, neighbors = net.compute_correction(
                pos2, vel2, None, points, normals, fluid_batch, box_batch
            )
            new_pos = pos2 + correction
            vel = (new_pos - pos) / net.timestep
            pos = new_pos
            if k % every == 0:  # a step with a target
                predicted.append(pos)
                weights.append(torch.exp(-neighbors / NEIGHBOR_SCALE))
        weight = torch.stack(weights, dim=1).unsqueeze(-1).detach()  # (Nf, K, 1)
        # displacements from the window's start: the same loss, without float32's rounding of whole positions
        start, unit = (batch.pos[fluid] @ rotation.T).unsqueeze(1), net.length_unit
        prediction = torch.cat([(torch.stack(predicted, dim=1) - start) / unit, weight], dim=-1)
        target = torch.cat([(truth - start) / unit, weight], dim=-1)
        return prediction, target

    def surface(self, pos: Tensor, fluid: Tensor, sample: Tensor, l0: float) -> tuple[Tensor, Tensor, Tensor]:
        """The walls' surface points and normals within ``REACH`` of the fluid, and their scene ids.

        ``pos`` (N, 3) holds the fluid (``fluid`` (N,) mask) and the boundary cropped at ``REACH + 1.5`` l0
        (:meth:`datasets`), so every kept point's surface test sees its whole neighbourhood: the points are
        those of the whole tank's surface (as in rollouts) near this fluid.
        """
        boundary = ~fluid
        points, normals, rows = surface_points(pos[boundary], l0, self.surface_offset, sample[boundary])
        box_batch, nf = sample[boundary][rows], int(fluid.sum())
        both = torch.cat([pos[fluid], pos[boundary][rows]])
        receivers = torch.arange(both.shape[0], device=both.device) >= nf  # the surface's wall particles
        edges = radius_graph(
            both, REACH * l0, batch=torch.cat([sample[fluid], box_batch]), receivers=receivers
        )
        keep = torch.zeros(both.shape[0], dtype=torch.bool, device=both.device)
        keep[edges[1][edges[0] < nf]] = True  # a fluid particle within REACH
        keep = keep[nf:]
        return points[keep], normals[keep], box_batch[keep]

    def identity(self) -> dict[str, Any]:
        """What the network sees of the walls (surface offset, weight), its axes, start and unroll.

        The simulator of ``model=cconv`` reads ``surface_offset``, ``axes`` and ``surface_weight`` back from
        the checkpoint, so a rollout sees the walls and axes the training did.
        """
        identity: dict[str, Any] = {"surface_offset": self.surface_offset}
        # each only when set, so checkpoints trained before the option existed keep their identity
        if self.unroll_frames:
            identity["unroll_frames"] = self.unroll_frames
        if self.axes_name != "z_up":
            identity["axes"] = self.axes_name
        if self.surface_weight != 1.0:
            identity["surface_weight"] = self.surface_weight
        if self.start_from is not None:
            identity["start_from"] = str(self.start_from)
        if self.rotate_about_gravity:
            identity["rotate_about_gravity"] = True
        return identity


def build_trainables(cfg: Any) -> dict[str, CConvTrainable]:
    """``model=cconv``'s trainables by name: one, the whole network."""
    return {NAME: CConvTrainable(cfg)}
