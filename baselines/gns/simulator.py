"""``model=gns``: the GNS network as a :class:`~lagfluid.models.simulator.Simulator`.

The model steps at the spacing of its training frames (its own ``dt``, stored in the weights) by
semi-implicit Euler with the predicted acceleration of the fluid, ``v' = v + a dt``, ``x' = x + v' dt``
(:func:`lagfluid.integrate.semi_implicit_euler`), keeping an explicit velocity state (paper A.5); the
network sees the last ``H`` velocities, ``(x_t - x_{t-1}) / dt`` of its frames, as in training. Boundary
particles never move.

**Start.** :meth:`GNSSimulator.reset` takes the ``H`` earlier frames from ``history`` (a trajectory started
at frame t: ``scene=trajectory``), or, for a scene built from scratch, warm-starts as the paper (A.5): the
first ``H`` frames are MPS's (``solver_dt`` steps of the ground-truth solver per frame, ``cfg.solver``),
returned by the first ``H`` calls of :meth:`GNSSimulator.step` and timed as ``mps_warm_start``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import OmegaConf

from lagfluid.zoo import (
    ParticleState,
    RangeWarner,
    RolloutError,
    Simulator,
    StageTimer,
    build_mps,
    checkpoint_range,
    memory_needed,
    pair_bytes,
    read_checkpoint,
    rollout_bytes,
    scene_params,
    semi_implicit_euler,
)

from .graph import build_graph, fluid_acceleration
from .network import GNSNet
from .trainable import NAME

SHIPPED = Path(__file__).resolve().parent / "weights"
"""The shipped weights (``gns.pt``) and their model card."""
DAGGER = SHIPPED / "dagger"
"""``model=gns_dagger``'s shipped weights: GNS trained on its own rollouts' states (DAgger; card there)."""
UNROLL = SHIPPED / "unroll"
"""``model=gns_unroll``'s shipped weights: the DAgger weights fine-tuned on a loss over 4 unrolled steps."""
BYTES_PER_EDGE = 1300.0
"""Memory per graph edge of a step (latent edge features of every block), rounded up from the measurement."""


class GNSSimulator:
    """GNS rollouts (module doc).

    Args:
        net: a trained :class:`GNSNet` (statistics and ``frame_dt`` set), on the run's device and dtype.
        warm_start: the MPS simulator of the warm start (None: a rollout needs ``history``).
        weights: where the weights came from (stored with every rollout).
        name: the model's name (``model.name``): which shipped weights these are.
    """

    name = NAME
    last_fields = None  # no intermediates to declare
    predicts_pressure = False  # positions only: previews colour by speed (lagfluid.viz.colour_field)
    # One particle spacing per step, under half the connectivity radius: the graph still sees what the step
    # runs into. The training frames (data=cpu, 8 ms apart) reach 0.8; MPS's own limit, 0.5, is for its 2 ms.
    max_courant = 1.0

    def __init__(self, net: GNSNet, warm_start: Simulator | None, weights: str, name: str = NAME) -> None:
        self.name = name  # the model's name in tables and rollouts (gns, gns_dagger)
        self.net = net.eval()
        self.history_length = net.history
        self.dt = seconds_of(net.frame_dt)
        self.solver_dt = seconds_of(net.solver_dt)
        if not self.dt > 0:
            raise RolloutError("the GNS weights hold no frame spacing (frame_dt); were they trained?")
        self.warm_start = warm_start
        self.weights = weights
        # the frame spacing is the network's own (scenes are stepped by it): dt is not checked
        trained = (
            checkpoint_range(weights, ("l0", "gravity", "viscosity")) if Path(weights).is_file() else None
        )
        self._ranges = RangeWarner(name, {NAME: {"range": trained}})
        self.last_info: dict[str, float] = {}
        self._timer = StageTimer()  # the last step's
        self._velocities: torch.Tensor | None = None  # (Nf, H, 3) the last H velocities, oldest first
        self._warm_frames = 0
        self._next_step: int | None = None
        self._mps: ParticleState | None = None  # the warm start's own state
        self.last_step_learned = True  # False after an MPS warm-start frame (exact already)

    @property
    def parameters(self) -> int:
        """Trainable parameters of the network."""
        return sum(p.numel() for p in self.net.parameters() if p.requires_grad)

    @property
    def last_timings(self) -> dict[str, float]:
        """Seconds of the last step: ``neighbors`` and ``network`` (``mps_warm_start`` in the warm start)."""
        return self._timer.read()

    def reset(self, state: ParticleState, history: Sequence[ParticleState] = ()) -> None:
        """Take the velocity history from ``history`` (``H`` frames) or plan the MPS warm start (module doc).

        Raises:
            RolloutError: too short a history with no warm start, or a history of other particles.
        """
        self._ranges.check(state.params)
        nf, h = state.n_fluid, self.history_length
        self._next_step = state.step
        if len(history) >= h:
            frames = [s.pos[:nf] for s in history[-h:]] + [state.pos[:nf]]
            for s in history[-h:]:
                if s.n_fluid != nf:
                    raise RolloutError(f"GNS history frame has {s.n_fluid} fluid particles, the start {nf}")
            stacked = torch.stack(frames, dim=1)
            self._velocities = (stacked[:, 1:] - stacked[:, :-1]) / self.dt
            self._warm_frames = 0
            return
        if self.warm_start is None:
            raise RolloutError(f"GNS needs {h} earlier frames (a trajectory's history) or an MPS warm start")
        substeps = round(self.dt / self.solver_dt) if self.solver_dt > 0 else 0
        if substeps < 1 or abs(substeps * self.solver_dt - self.dt) > 1e-9:
            raise RolloutError(
                f"GNS's frame spacing {self.dt} s is not a whole number of MPS steps of {self.solver_dt} s"
            )
        self._substeps = substeps
        self._mps = self._mps_state(state)
        self.warm_start.reset(self._mps)
        self._velocities = torch.zeros(nf, h, 3, dtype=state.dtype, device=state.device)
        self._warm_frames = h

    def memory_needed(self, state: ParticleState) -> float:
        """Bytes a rollout from ``state`` needs: the MPS warm start's, plus the network's per graph edge.

        Measured (peak RSS of ``task=simulate``, 8 steps so that the network steps after the warm start, dams
        of 4,000 to 40,000 fluid particles, ``threads=1``): 940-1,210 B per pair within the connectivity
        radius above the peak of MPS alone on the same dam (``lagfluid/memory.py``). The warm start is
        counted whatever the history (a ``scene=trajectory`` start has none): an estimate on the safe side.
        """
        radius = self.net.radius * state.params.l0
        if self.warm_start is None:
            return rollout_bytes(state, radius, BYTES_PER_EDGE)
        return memory_needed(self.warm_start, state) + pair_bytes(state, radius, BYTES_PER_EDGE)

    def rollout_memory(self) -> dict[str, torch.Tensor]:
        """What the rollout carries beyond the state: the velocity history (Nf, H, 3), for a resume.

        A resumed run (:mod:`lagfluid.tasks.simulate_resume`) restores it bit for bit; velocities rebuilt from
        the stored positions differ from the integrated ones in the last bits.
        """
        if self._velocities is None or self._warm_frames:
            return {}
        return {"velocities": self._velocities}

    def restore_rollout_memory(self, state: ParticleState, memory: dict[str, torch.Tensor]) -> None:
        """Continue from ``state`` with :meth:`rollout_memory`'s ``memory`` (after :meth:`reset`)."""
        velocities = memory["velocities"].to(device=state.device, dtype=state.dtype)
        if velocities.shape != (state.n_fluid, self.history_length, 3):
            raise RolloutError(
                f"GNS velocity history of shape {tuple(velocities.shape)} does not fit {state.n_fluid} fluid "
                f"particles and a history of {self.history_length}"
            )
        self._velocities, self._warm_frames, self._next_step = velocities, 0, state.step

    def _mps_state(self, state: ParticleState) -> ParticleState:
        """``state`` at the MPS step of the warm start."""
        return ParticleState(
            pos=state.pos,
            vel=state.vel,
            ptype=state.ptype,
            params=state.params.with_overrides(dt=self.solver_dt),
            pressure=state.pressure,
            time=state.time,
            step=state.step,
            bounds=state.bounds,
            check=False,
            fluid_count=state.n_fluid,
        )

    @torch.no_grad()
    def step(self, state: ParticleState, *, record: bool = False) -> ParticleState:
        """The state one frame later (an MPS frame during the warm start)."""
        if self._velocities is None or state.step != self._next_step:
            raise RolloutError(
                f"GNS keeps the velocity history of its own rollout: step {state.step} does not follow the "
                "last state it returned; call reset(state, history) first"
            )
        nf, dt = state.n_fluid, state.params.dt
        if abs(dt - self.dt) > 1e-9:
            raise RolloutError(f"GNS steps by its training frame spacing {self.dt} s, the state has dt {dt}")
        self.last_step_learned = not self._warm_frames
        if self._warm_frames:
            new, velocity = self._warm_step(state)
        else:
            timer, device = StageTimer(), state.pos.device
            net = self.net
            dtype = net.velocity.mean.dtype
            pos = state.pos.to(dtype)
            radius = net.radius * state.params.l0
            with timer("neighbors", device):
                graph = build_graph(pos, state.fluid_mask, radius)
            with timer("network", device):
                bounds = None if state.bounds is None else state.bounds.to(dtype)
                acc = fluid_acceleration(net, pos, self._velocities.to(dtype), graph, bounds, radius)
                acc = net.acceleration.inverse(acc).to(state.dtype)
                fluid_pos, velocity = semi_implicit_euler(state.pos[:nf], self._velocities[:, -1], acc, dt)
                new = state.advanced_fluid(fluid_pos, velocity, dt)
            self._timer = timer
            self.last_info = {"graph_edges": float(graph.edge_index.shape[1])}
        self._velocities = torch.cat([self._velocities[:, 1:], velocity.unsqueeze(1)], dim=1)
        self._next_step = new.step
        return new

    def amend_last_step(self, before: ParticleState, after: ParticleState) -> None:
        """The rollout replaced the state :meth:`step` returned from ``before`` by ``after``.

        Exact stages ran after the step (:mod:`lagfluid.models.exact_after`): the newest velocity of the
        history becomes the corrected displacement over the frame spacing, ``(x_after - x_before) / dt``,
        as the next frame difference of a stored rollout would be.
        """
        nf = before.n_fluid
        displacement = (after.pos[:nf] - before.pos[:nf]) / self.dt
        self._velocities = torch.cat([self._velocities[:, :-1], displacement.unsqueeze(1)], dim=1)

    def _warm_step(self, state: ParticleState) -> tuple[ParticleState, torch.Tensor]:
        """One frame of the MPS warm start and its finite-difference velocity (Nf, 3), as in training.

        The MPS solver continues from its own state (its velocities are not the frames' differences).
        """
        timer, nf = StageTimer(), state.n_fluid
        with timer("mps_warm_start", state.pos.device):
            mps = self._mps
            for _ in range(self._substeps):
                mps = self.warm_start.step(mps)
            self._mps = mps
            self._warm_frames -= 1
            velocity = (mps.pos[:nf] - state.pos[:nf]) / state.params.dt
            new = state.advanced_fluid(mps.pos[:nf], mps.vel[:nf], state.params.dt, pressure=mps.pressure)
        self._timer = timer
        self.last_info = {}
        return new, velocity

    def attributes(self) -> dict[str, Any]:
        """Where the weights came from, the frame spacing and the warm start."""
        return {
            "weights": self.weights,
            "frame_dt": self.dt,
            "warm_start_frames": self.history_length,
            "warm_start_solver_dt": self.solver_dt,
        }


def seconds_of(buffer: torch.Tensor) -> float:
    """The time step in a network buffer, as the decimal it was stored from (0.016, not 0.016000001).

    The buffer is float32 (or float32 cast up): its nearest float64 differs from the decimal by up to 6e-8
    relative, and the frames' times ``k dt`` must land on the reference's grid (to 1e-6 of its 2 ms step,
    :func:`lagfluid.tasks.evaluate.compare.common_frames`). The shortest decimal that rounds to the same
    float32 is the one written.
    """
    return float(str(np.float32(float(buffer))))


def load_gns(path: str | Path, device: str = "cpu", dtype: torch.dtype = torch.float32) -> GNSNet:
    """The :class:`GNSNet` of a checkpoint ``path`` (``gns.pt``) on ``device`` in ``dtype``.

    Raises:
        CheckpointError: a missing or unreadable file, or the network of another model.
    """
    ckpt = read_checkpoint(path, kind=NAME, model=NAME)
    net = GNSNet(**ckpt["options"])
    net.load_state_dict(ckpt["state_dict"])
    return net.to(device=torch.device(device), dtype=dtype)


UNTRAINED = "untrained"
"""``model.weights=untrained``: a freshly initialised network of ``model.gns``'s options, stepping at the
scene's ``dt`` with no normalisation (to time a network size, e.g. the paper's; its rollouts mean nothing)."""


def untrained_network(options: dict[str, Any], dt: float) -> GNSNet:
    """A fresh :class:`GNSNet` of ``options`` stepping by ``dt`` (statistics at the identity)."""
    torch.manual_seed(0)
    net = GNSNet(**options)
    net.frame_dt.fill_(dt)
    net.solver_dt.fill_(dt)
    return net


def build_simulator(cfg: Any) -> GNSSimulator:
    """``model=gns``: the network of ``model.weights/gns.pt`` (null: the shipped ones), MPS warm start."""
    dtype = getattr(torch, str(cfg.dtype))
    if str(cfg.model.get("weights")) == UNTRAINED:
        options = OmegaConf.to_container(cfg.model[NAME], resolve=True)
        net = untrained_network(options, scene_params(cfg).dt).to(torch.device(str(cfg.device)), dtype)
        return GNSSimulator(net, build_mps(cfg), UNTRAINED)
    return _trained(cfg, NAME, SHIPPED)


def build_dagger(cfg: Any) -> GNSSimulator:
    """``model=gns_dagger``: GNS after DAgger rounds (:data:`DAGGER`; ``model.weights`` another folder)."""
    return _trained(cfg, "gns_dagger", DAGGER)


def build_unroll(cfg: Any) -> GNSSimulator:
    """``model=gns_unroll``: the DAgger weights fine-tuned with ``train.unroll_loss`` (:data:`UNROLL`)."""
    return _trained(cfg, "gns_unroll", UNROLL)


def _trained(cfg: Any, name: str, shipped: Path) -> GNSSimulator:
    """The simulator ``name`` of ``model.weights/gns.pt`` (null: ``shipped``'s), MPS warm start."""
    folder = Path(str(cfg.model.weights)) if cfg.model.get("weights") else shipped
    net = load_gns(folder / f"{NAME}.pt", str(cfg.device), getattr(torch, str(cfg.dtype)))
    return GNSSimulator(net, build_mps(cfg), str(folder / f"{NAME}.pt"), name)
