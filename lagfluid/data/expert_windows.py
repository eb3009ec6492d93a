"""DAgger datasets of end-to-end models: the model's own trajectory, labelled by one MPS step from its states.

An end-to-end model (GNS) trained on MPS's trajectories meets, in its own rollouts, states MPS never visits
(fluid drifting into a wall) and extrapolates there. A DAgger dataset (Ross, Gordon and Bagnell 2011;
written by :mod:`lagfluid.tasks.generate.expert`) rolls the model out on the training scenes and, every
``every``-th frame the model made, lets the MPS solver advance one model step (``substeps`` solver steps)
from the model's positions ``x_t`` and the velocity its frames imply, ``v_t = (x_t - x_{t-1}) / frame_dt``.
Trained on ``(model's frames ..., x_t) -> x_{t+1}^MPS``, the integrator's inverse (GNS:
:func:`lagfluid.integrate.acceleration_from_positions`) turns MPS's answer into the acceleration that
brings the model back to where MPS would go, from the model's own history.

Layout (a trajectory dataset, ``metadata.json`` with ``samples: false``): each scene file holds the model's
frames as the trajectory group of :mod:`lagfluid.data.layout` (attrs ``dt`` the solver's step,
``sample_every`` the solver steps per model step, so ``frame_dt = dt * sample_every`` as in the training
data) and ::

    /expert                 one label per labelled frame (E of them)
        frame (E,) i8                trajectory frame t whose state MPS advanced
        position (E, Nf, 3)          MPS's fluid positions one model step later (the label)
        velocity (E, Nf, 3)          MPS's fluid velocities then
        later_position (E, H-1, Nf, 3)   with a label horizon H > 1 only: MPS's fluid positions 2..H model
                                     steps later, MPS going on from its own answer
        attrs: format_version, every, substeps, solver_dt, horizon (absent: 1), complete

and the metadata says whose is what: ``trajectory: model``, ``labels: mps``, ``policy`` (the model and a
hash of its weights), ``expert`` (``every``, ``substeps``). Only the training split's scenes are rolled out.

Models read it through :func:`trajectory_windows`, which gives a solver dataset's
:class:`~lagfluid.data.datasets.TrajectoryWindows` and a DAgger dataset's :class:`ExpertWindows`, whose items
have the same fields (so a trainable needs no other change, and ``train.extra_data`` mixes the two). Models
that step by the solver's ``dt`` from a state ``(x, v)`` (CConv) read it through :func:`step_windows`: a
solver dataset's :class:`~lagfluid.data.datasets.StepWindows`, a DAgger dataset's :class:`ExpertStepWindows`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Literal

import h5py
import numpy as np
import torch
from torch_geometric.data import Data

from lagfluid.data.datasets import StepWindows, TrajectoryWindows, _with_boundary
from lagfluid.data.layout import GROUP, SceneInfo, load_metadata
from lagfluid.data.store import TrajectoryFileError
from lagfluid.errors import LagfluidError
from lagfluid.integrate import velocity_from_positions

EXPERT = "expert"
"""The group of a DAgger scene file that holds the expert's labels."""
EXPERT_FORMAT_VERSION = 1
LATER = "later_position"
"""The ``/expert`` dataset of the label steps after the first (a horizon H > 1)."""
LABELS = "mps"
"""``metadata.json["labels"]`` of a DAgger dataset: who labelled the model's states."""


def is_expert_dataset(meta: dict[str, Any]) -> bool:
    """Whether a dataset's metadata is a DAgger dataset's (model's trajectory, expert labels)."""
    return meta.get("labels") == LABELS and EXPERT in meta


class ExpertWindows(TrajectoryWindows):
    """Windows of a DAgger dataset: the model's frames before a labelled frame, and MPS's next positions.

    Item ``(scene, e)`` for each label ``e`` at frame ``t >= first``: ``pos`` (N, 3) the model's frame t
    with the boundary, ``ptype`` (N,), ``history`` (Nf, H, 3) the model's frames t-H .. t-1, ``y`` (Nf, 3)
    MPS's fluid positions one model step after frame t; graph-level ``frame_dt``, ``step``,
    ``frames_before``, ``bounds`` and the scene fields, as :class:`~lagfluid.data.datasets.TrajectoryWindows`
    (frames before frame 0 likewise frame 0's copies).

    Raises:
        LagfluidError: the dataset is not a DAgger dataset.
        TrajectoryFileError: a scene file without a complete ``/expert`` group.
    """

    solver_trajectories_only = False  # the trajectory is the model's: that is the point

    def __init__(
        self,
        root: str | os.PathLike,
        split: str | None = "train",
        transform: Any = None,
        boundary_radius: float | Literal["default"] | None = "default",
        history: int = 5,
        first: int | None = None,
    ) -> None:
        if not is_expert_dataset(load_metadata(root)):
            raise LagfluidError(
                f"{root} is not a DAgger dataset (metadata without labels: {LABELS} and {EXPERT}); "
                "TrajectoryWindows reads the solver's trajectories"
            )
        self._labels: dict[Path, np.ndarray] = {}  # scene file -> frames of its usable labels
        super().__init__(root, split, transform, boundary_radius, history, first)

    def _count(self, info: SceneInfo) -> int:
        with h5py.File(info.path, "r") as f:
            group = f.get(EXPERT)
            if group is None or not bool(group.attrs.get("complete", False)):
                raise TrajectoryFileError(f"{info.path} has no complete '/{EXPERT}' group of labels")
            frames = group["frame"][()]
        # the labels from the first window frame on
        self._labels[info.path] = np.flatnonzero((frames >= self.first) & (frames < info.frames))
        return len(self._labels[info.path])

    def _item(self, file: int, local: int) -> Data:
        f = self._h5(file)
        g, labels = f[GROUP], f[EXPERT]
        row = int(self._labels[self.files[file]][local])
        t = int(labels["frame"][row])
        window, before = self._frames(g["position"], t, 0)  # the model's frames t-H .. t
        b_pos, b_type = self._near_boundary(file, window[-1])
        a = self.infos[file].attrs
        every = int(a["sample_every"])
        return Data(
            **_with_boundary(window[-1], None, b_pos, b_type),
            history=torch.from_numpy(np.ascontiguousarray(window[:-1].transpose(1, 0, 2))),
            y=torch.from_numpy(labels["position"][row]),
            frame_dt=torch.tensor([float(a["dt"]) * every], dtype=torch.float32),
            step=torch.tensor([t * every]),
            frames_before=torch.tensor([before]),
            **self._bounds(file),
            **self._scene_fields(file),
        )


def trajectory_windows(
    root: str | os.PathLike, split: str | None, history: int, first: int | None = None, stride: int = 1
) -> TrajectoryWindows:
    """The windows of ``root``: :class:`ExpertWindows` for a DAgger dataset, else ``TrajectoryWindows``.

    ``stride``: stored frames per model frame of a solver dataset; a DAgger dataset's frames are already the
    model's, so it takes none but 1.
    """
    if is_expert_dataset(load_metadata(root)):
        if stride != 1:
            raise LagfluidError(
                f"{root} is a DAgger dataset, whose frames are the model's own steps: a frame stride of "
                f"{stride} does not apply (train.frame_stride 1 for DAgger rounds)"
            )
        return ExpertWindows(root, split, history=history, first=first)
    return TrajectoryWindows(root, split, history=history, first=first, stride=stride)


class ExpertStepWindows(ExpertWindows):
    """A DAgger dataset's windows for a model that steps from a state ``(x, v)``: ``StepWindows``' fields.

    Item ``(scene, e)`` for each label ``e`` at frame ``t >= 1``: ``pos`` (N, 3) the model's frame t with
    the boundary, ``vel`` (N, 3) the velocity its frames imply, ``(x_t - x_{t-1}) / frame_dt`` (0 on the
    boundary; what the model's own step carries, and what MPS started from), ``ptype`` (N,), ``y``
    (Nf, K, 3) MPS's fluid positions 1..K model steps later; graph-level ``dt`` (the solver's), ``step``,
    ``bounds`` and the scene fields. The same fields as a solver dataset's ``StepWindows(steps=K)``, so
    ``train.extra_data`` mixes the two in one batch.

    Raises:
        LagfluidError: not a DAgger dataset, a model step that is not the solver's (``substeps`` != 1), or
            labels of fewer than ``steps`` model steps.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        split: str | None = "train",
        transform: Any = None,
        boundary_radius: float | Literal["default"] | None = "default",
        steps: int = 2,
    ) -> None:
        expert = load_metadata(root).get(EXPERT) or {}  # not a DAgger dataset: ExpertWindows says so
        if int(expert.get("substeps", 1)) != 1:
            raise LagfluidError(
                f"{root}: its model stepped {expert['substeps']} solver steps at a time; these windows are "
                "of a model that steps by the solver's dt"
            )
        if expert and int(expert.get("horizon", 1)) < steps:
            raise LagfluidError(
                f"{root} holds labels of {expert.get('horizon', 1)} model step(s), this model trains on "
                f"{steps}: make the DAgger data with train.dagger.horizon={steps}"
            )
        self.steps = steps
        super().__init__(root, split, transform, boundary_radius, history=1, first=1)

    def _item(self, file: int, local: int) -> Data:
        f = self._h5(file)
        g, labels = f[GROUP], f[EXPERT]
        row = int(self._labels[self.files[file]][local])
        t = int(labels["frame"][row])
        before, now = g["position"][t - 1], g["position"][t]
        a = self.infos[file].attrs
        every = int(a["sample_every"])
        # the frames' velocity, as MPS started from it (lagfluid.tasks.generate.expert.expert_step)
        vel = velocity_from_positions(torch.from_numpy(before), torch.from_numpy(now), float(a["dt"]) * every)
        y = labels["position"][row][:, None]
        if self.steps > 1:
            y = np.concatenate([y, labels[LATER][row, : self.steps - 1].transpose(1, 0, 2)], axis=1)
        b_pos, b_type = self._near_boundary(file, now)
        return Data(
            **_with_boundary(now, vel.numpy(), b_pos, b_type),
            y=torch.from_numpy(np.ascontiguousarray(y)),
            step=torch.tensor([t * every]),
            **self._bounds(file),
            **self._scene_fields(file),
        )


def step_windows(
    root: str | os.PathLike,
    split: str | None,
    steps: int,
    boundary_radius: float | Literal["default"] | None = "default",
) -> StepWindows | ExpertStepWindows:
    """The state-and-next-``steps`` windows of ``root``: a DAgger dataset's or a solver dataset's."""
    if is_expert_dataset(load_metadata(root)):
        return ExpertStepWindows(root, split, boundary_radius=boundary_radius, steps=steps)
    return StepWindows(root, split, steps=steps, boundary_radius=boundary_radius)
