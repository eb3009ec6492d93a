"""PyG datasets over a generated dataset directory (layout: :mod:`lagfluid.data.layout`).

Every item is a :class:`torch_geometric.data.Data` *without edges*: each model builds its own radius graph
(FGN's advection, collision and pressure nets use 1.86, 0.92 and 1.705 l0). Batches from
:class:`torch_geometric.loader.DataLoader` stack the samples' particles; ``batch.batch`` (B samples) says
which sample a particle belongs to, and ``lagfluid.neighbors.radius_graph(batch.pos, r,
batch=batch.batch)`` then gives a block-diagonal graph: no edge joins two samples, even though every
scene sits in the same tank. Rows are fluid first, then boundary, per sample; a label ``y`` with one
row per fluid particle lines up with ``batch.pos[batch.ptype == ParticleType.FLUID]``.

============================ ==============================================================================
dataset                      one item (N particles: Nf fluid, then boundary; graph-level fields are (1, ...))
============================ ==============================================================================
:class:`AdvectionSamples`    ``pos`` x^n (N, 3), ``vel`` v^n (N, 3; 0 on the boundary), ``ptype`` (N,),
                             ``y`` a = (v* - v^n)/dt (Nf, 3); ``gravity`` (1, 3), ``viscosity`` (1,)
:class:`PressureSamples`     the PPE unknowns only (M non-free-surface fluid and wall particles):
                             ``pos`` x** (M, 3), ``vel`` v** (M, 3), ``ptype`` (M,), ``density`` n (M,),
                             ``y`` pressure (M,), ``particle_id`` (M,) row in the scene; ``n0`` (1,)
:class:`CollisionSamples`    the collision-only systems: ``pos`` x* (N, 3), ``vel`` v* (N, 3), ``ptype``,
                             ``y`` v** - v* (Nf, 3); ``restitution`` (1,)
:class:`TrajectoryWindows`   GNS-style windows of the trajectory: ``pos`` frame t (N, 3), ``ptype``,
                             ``history`` frames t-H .. t-1 (Nf, H, 3), ``y`` frame t+1 (Nf, 3);
                             ``frame_dt`` (1,) = dt * sample_every; ``frames_before`` (1,); ``bounds``
                             (1, 2, 3) the domain box (m), when the scene has a tank
============================ ==============================================================================

All items also carry ``dt``, ``l0`` (1,) and ``scene`` (1,) (scene index); scene samples carry
``gravity``, ``viscosity`` and ``step`` (1,) (solver step). ``dataset.metadata["statistics"]`` describes the
train split; networks fit their normalisation from training items (their trainable's ``fit_statistics``).

Scenes hold ~85k static boundary particles of which only those near the fluid matter to a graph:
``boundary_radius`` (m) keeps the boundary particles within that distance of some fluid particle of the
sample (default: the dataset's ``default_connectivity_radius``, 3.1 l0, the largest radius any FGN or MPS
stage uses; ``None`` keeps all). A model with a radius up to it sees exactly the neighbours it would see
with the whole boundary.

Example::

    ds = AdvectionSamples("data/cpu", split="train")
    loader = DataLoader(ds, batch_size=16, shuffle=True)
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Literal

import h5py
import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor
from torch_geometric.data import Data, Dataset

from lagfluid.data.layout import (
    GROUP,
    SPLITS,
    SceneInfo,
    load_metadata,
    read_scene_info,
)
from lagfluid.data.store import TrajectoryFileError
from lagfluid.errors import LagfluidError
from lagfluid.state import ParticleState, ParticleType, SceneParams

__all__ = [
    "AdvectionSamples",
    "CollisionSamples",
    "PressureSamples",
    "TrajectoryWindows",
    "load_metadata",
]


class _SceneDataset(Dataset):
    """Samples spread over the scene files of one split; items are numbered scene by scene.

    Args:
        root: dataset directory (``data.out_dir`` of ``task=generate``).
        split: ``"train"``, ``"valid"``, ``"test"`` or None (every scene).
        transform: optional PyG transform applied to every item.
        boundary_radius: keep the boundary particles within this distance (m) of the fluid; ``"default"``:
            the dataset's ``default_connectivity_radius``; None: keep all.

    Raises:
        TrajectoryFileError: a missing directory, metadata or scene file, or a scene file that is corrupt,
            incomplete or not of this layout (the message names the file).
        LagfluidError: an unknown split, or an on-policy dataset for a dataset of trajectories.
    """

    # True for datasets whose targets are the trajectory itself: an on-policy dataset's trajectory is a
    # learned model's, not the solver's (lagfluid.tasks.generate.policy), so they refuse it
    solver_trajectories_only = False
    # False for datasets that read the trajectory alone: they also take a trajectory dataset (converted from
    # LagrangeBench or DeepMind, metadata "samples": false, lagfluid.data.convert)
    needs_samples = True

    def __init__(
        self,
        root: str | os.PathLike,
        split: str | None = "train",
        transform: Any = None,
        boundary_radius: float | Literal["default"] | None = "default",
    ) -> None:
        self.root_dir = Path(root)
        self.metadata = load_metadata(self.root_dir)
        policy = self.metadata.get("policy")
        if policy and self.solver_trajectories_only:
            raise LagfluidError(
                f"{self.root_dir} is an on-policy dataset (its scenes were moved by "
                f"model={policy.get('model')}, only its labels are the solver's): {type(self).__name__} "
                "learns from trajectories and needs a dataset generated by the solver (data.policy=null)"
            )
        has_samples = self.metadata.get("samples", True) is not False
        if self.needs_samples and not has_samples:
            raise LagfluidError(
                f"{self.root_dir} holds trajectories only ({self.metadata.get('name', 'converted')}): "
                f"{type(self).__name__} learns from the MPS stage samples of task=generate; a model that "
                "learns from trajectories (GNS) trains on it"
            )
        if split is None:
            names = [s["file"] for s in self.metadata["scenes"]]
        elif split in SPLITS:
            names = self.metadata["splits"][split]
        else:
            raise LagfluidError(f"unknown split '{split}'; available: {', '.join(SPLITS)} or None (all)")
        self.split = split
        self.files = [self.root_dir / name for name in names]
        self.infos: list[SceneInfo] = []
        for path in self.files:
            info = read_scene_info(path, samples=has_samples)
            if not info.complete:
                raise TrajectoryFileError(f"{path} is incomplete; rerun task=generate to regenerate it")
            self.infos.append(info)
        if boundary_radius == "default":
            boundary_radius = float(self.metadata["default_connectivity_radius"])
        self.boundary_radius = boundary_radius
        counts = [self._count(info) for info in self.infos]
        self._offsets = np.cumsum([0, *counts])
        self._handles: dict[int, h5py.File] = {}
        self._static: dict[int, dict[str, Any]] = {}
        self._pid = os.getpid()
        super().__init__(root=None, transform=transform, log=False)

    # -------------------------------------------------------------- to be provided by subclasses
    def _count(self, info: SceneInfo) -> int:
        raise NotImplementedError

    def _item(self, file: int, local: int) -> Data:
        raise NotImplementedError

    # -------------------------------------------------------------- PyG Dataset interface
    def len(self) -> int:
        """Number of items."""
        return int(self._offsets[-1])

    def get(self, idx: int) -> Data:
        """Item ``idx``."""
        return self._item(*self._locate(idx))

    def scene_attributes(self, idx: int) -> dict[str, Any]:
        """Attributes of item ``idx``'s scene file (``dt``, ``l0``, ``n0``, the generating ``config``...)."""
        return dict(self.infos[self._locate(idx)[0]].attrs)

    def _locate(self, idx: int) -> tuple[int, int]:
        """``(file, local index)`` of item ``idx``."""
        if not 0 <= idx < self.len():
            raise IndexError(f"index {idx} out of range for {self.len()} items")
        file = int(np.searchsorted(self._offsets, idx, side="right")) - 1
        return file, idx - int(self._offsets[file])

    def __getstate__(self) -> dict[str, Any]:
        # HDF5 handles do not survive pickling (DataLoader workers with spawn); they reopen lazily.
        state = dict(self.__dict__)
        state["_handles"], state["_static"] = {}, {}
        return state

    # -------------------------------------------------------------- helpers
    def _h5(self, file: int) -> h5py.File:
        """The open scene file (one handle per process: forked DataLoader workers open their own)."""
        if self._pid != os.getpid():
            self._handles, self._static, self._pid = {}, {}, os.getpid()
        handle = self._handles.get(file)
        if handle is None:
            try:
                handle = h5py.File(self.files[file], "r")
            except OSError as err:
                raise TrajectoryFileError(f"cannot read {self.files[file]}: {err}") from err
            self._handles[file] = handle
        return handle

    def _boundary(self, file: int) -> dict[str, Any]:
        """Static boundary of a scene: positions and types (cached per process)."""
        static = self._static.get(file)
        if static is None:
            g = self._h5(file)[GROUP]
            pos = g["boundary_position"][()].astype(np.float32)
            static = {"pos": pos, "ptype": g["boundary_type"][()].astype(np.int64)}
            self._static[file] = static
        return static

    def _near_boundary(self, file: int, fluid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Boundary positions and types within ``boundary_radius`` of the fluid at ``fluid`` (Nf, 3)."""
        b = self._boundary(file)
        if self.boundary_radius is None or len(b["pos"]) == 0:
            return b["pos"], b["ptype"]
        r = float(self.boundary_radius)
        dist, _ = cKDTree(fluid).query(b["pos"], k=1, distance_upper_bound=r)
        keep = dist < r  # strict, as radius_graph
        return b["pos"][keep], b["ptype"][keep]

    def _bounds(self, file: int) -> dict[str, torch.Tensor]:
        """``{"bounds": (1, 2, 3)}`` the scene's domain box, or nothing (a scene without a tank has none)."""
        bounds = self.infos[file].attrs.get("bounds")
        if isinstance(bounds, np.ndarray) and bounds.shape == (2, 3):
            return {"bounds": torch.from_numpy(bounds.astype(np.float32)).unsqueeze(0)}
        return {}

    def _scene_fields(self, file: int) -> dict[str, torch.Tensor]:
        """Graph-level fields every scene sample carries."""
        a = self.infos[file].attrs
        return {
            "gravity": torch.tensor([list(a["gravity"])], dtype=torch.float32),
            "viscosity": torch.tensor([float(a["viscosity"])], dtype=torch.float32),
            "dt": torch.tensor([float(a["dt"])], dtype=torch.float32),
            "l0": torch.tensor([float(a["l0"])], dtype=torch.float32),
            "scene": torch.tensor([int(a["scene_index"])], dtype=torch.long),
        }


def _with_boundary(
    fluid_pos: np.ndarray, fluid_vel: np.ndarray | None, b_pos: np.ndarray, b_type: np.ndarray
) -> dict[str, torch.Tensor]:
    """``pos``, ``vel`` (zero on the boundary) and ``ptype`` of fluid rows followed by boundary rows."""
    nf = len(fluid_pos)
    out = {
        "pos": torch.from_numpy(np.concatenate([fluid_pos, b_pos]).astype(np.float32)),
        "ptype": torch.from_numpy(np.concatenate([np.full(nf, int(ParticleType.FLUID), np.int64), b_type])),
    }
    if fluid_vel is not None:
        out["vel"] = torch.from_numpy(np.concatenate([fluid_vel, np.zeros_like(b_pos)]).astype(np.float32))
    return out


class AdvectionSamples(_SceneDataset):
    """Advection-net samples ``[x^n, v^n, g, nu] -> a`` (paper A.2), one per sampled solver step.

    Item: ``pos``, ``vel`` (N, 3), ``ptype`` (N,), ``y`` (Nf, 3) the advection acceleration; graph-level
    ``gravity`` (1, 3), ``viscosity``, ``dt``, ``l0``, ``scene``, ``step`` (1,). See the module doc.
    """

    def _count(self, info: SceneInfo) -> int:
        return info.samples

    def _item(self, file: int, local: int) -> Data:
        f = self._h5(file)
        g, s = f[GROUP], f["samples"]
        frame = int(s["frame"][local])
        pos, vel = g["position"][frame], g["velocity"][frame]
        b_pos, b_type = self._near_boundary(file, pos)
        return Data(
            **_with_boundary(pos, vel, b_pos, b_type),
            y=torch.from_numpy(s["advection/acceleration"][local]),
            step=torch.tensor([int(s["step"][local])]),
            **self._scene_fields(file),
        )


class PressureSamples(_SceneDataset):
    """Pressure-net samples ``[x**, v**, n] -> p`` on the PPE unknowns (non-free-surface particles).

    The nodes are the unknowns of the pressure Poisson equation at that step (fluid and wall particles with
    ``n >= beta n0``), as FGN's pressure graph; free-surface particles have ``p = 0`` by definition.
    Item: ``pos`` x** (M, 3), ``vel`` v** (M, 3; 0 for walls), ``ptype`` (M,), ``density`` n (M,), ``y``
    the PPE pressure (M,), ``particle_id`` (M,) row in the scene (fluid < Nf, then boundary); graph-level
    ``n0`` and the scene fields.
    """

    def _count(self, info: SceneInfo) -> int:
        return info.samples

    def _item(self, file: int, local: int) -> Data:
        f = self._h5(file)
        s = f["samples/pressure"]
        lo, hi = (int(v) for v in s["offsets"][local : local + 2])
        rows = s["index"][lo:hi].astype(np.int64)
        nf = self.infos[file].n_fluid
        fluid = rows < nf
        b = self._boundary(file)
        pos = np.empty((len(rows), 3), np.float32)
        vel = np.zeros((len(rows), 3), np.float32)
        ptype = np.full(len(rows), int(ParticleType.FLUID), np.int64)
        pos[fluid] = s["position"][local][rows[fluid]]
        vel[fluid] = s["velocity"][local][rows[fluid]]
        pos[~fluid] = b["pos"][rows[~fluid] - nf]
        ptype[~fluid] = b["ptype"][rows[~fluid] - nf]
        return Data(
            pos=torch.from_numpy(pos),
            vel=torch.from_numpy(vel),
            ptype=torch.from_numpy(ptype),
            density=torch.from_numpy(s["number_density"][lo:hi]),
            y=torch.from_numpy(s["pressure"][lo:hi]),
            particle_id=torch.from_numpy(rows),
            n0=torch.tensor([float(self.infos[file].attrs["n0"])], dtype=torch.float32),
            step=torch.tensor([int(f["samples/step"][local])]),
            **self._scene_fields(file),
        )

    def scene_state(
        self, idx: int, boundary_radius: float | None = None, dtype: torch.dtype = torch.float64
    ) -> tuple[ParticleState, Tensor]:
        """The particles of item ``idx``'s scene at the pressure stage's input.

        Args:
            idx: the item.
            boundary_radius: keep only the boundary particles within this distance (m) of the fluid; None:
                the whole boundary.
            dtype: of the state's positions and velocities (the generating run's, to rebuild its PPE).

        Returns:
            The state (fluid ``x**``, ``v**``, then the kept boundary, dummies included, at rest)
            and each row's ``particle_id`` (N,): with :meth:`scene_attributes`, what rebuilds the step's PPE
            (:class:`lagfluid.models.fgn.ppe_term.WithPPESystem`).
        """
        file, local = self._locate(idx)
        s = self._h5(file)["samples/pressure"]
        fluid = s["position"][local]
        b = self._boundary(file)
        keep = np.ones(len(b["pos"]), bool)
        if boundary_radius is not None and len(b["pos"]):
            dist, _ = cKDTree(fluid).query(b["pos"], k=1, distance_upper_bound=boundary_radius)
            keep = dist < boundary_radius
        arrays = _with_boundary(fluid, s["velocity"][local], b["pos"][keep], b["ptype"][keep])
        rows = np.concatenate([np.arange(len(fluid)), len(fluid) + np.flatnonzero(keep)])
        a = self.infos[file].attrs
        params = SceneParams(
            gravity=tuple(float(g) for g in a["gravity"]),
            viscosity=float(a["viscosity"]),
            density=float(a["density"]),
            dt=float(a["dt"]),
            l0=float(a["l0"]),
            dim=int(a["dim"]),
        )
        bounds = self._bounds(file).get("bounds")
        state = ParticleState(
            pos=arrays["pos"].to(dtype),
            vel=arrays["vel"].to(dtype),
            ptype=arrays["ptype"],
            params=params,
            bounds=None if bounds is None else bounds[0].to(dtype),
            check=False,
        )
        return state, torch.from_numpy(rows)


class CollisionSamples(_SceneDataset):
    """Collision-net samples: relative positions and velocities before -> velocity change (paper A.2).

    From the collision-only particle systems of every scene (see :mod:`lagfluid.data.layout`). Item:
    ``pos`` x* (N, 3), ``vel`` v* (N, 3; 0 on the floor), ``ptype`` (N,), ``y`` v** - v* (Nf, 3);
    graph-level ``restitution``, ``dt``, ``l0``, ``scene``, ``system`` (1,). The net's edge inputs are
    ``vel[j] - vel[i]`` and ``pos[j] - pos[i]`` over a radius graph at ``re_collision * l0``.
    The boundary (a small floor) is never pruned.
    """

    def _count(self, info: SceneInfo) -> int:
        return info.collision_samples

    def _boundary(self, file: int) -> dict[str, Any]:
        static = self._static.get(file)
        if static is None:
            c = self._h5(file)["samples/collision"]
            static = {
                "pos": c["boundary_position"][()].astype(np.float32),
                "ptype": c["boundary_type"][()].astype(np.int64),
                "restitution": float(c.attrs["restitution"]),
            }
            self._static[file] = static
        return static

    def _item(self, file: int, local: int) -> Data:
        c = self._h5(file)["samples/collision"]
        b = self._boundary(file)
        a = self.infos[file].attrs
        return Data(
            **_with_boundary(c["position"][local], c["velocity"][local], b["pos"], b["ptype"]),
            y=torch.from_numpy(c["delta_velocity"][local]),
            restitution=torch.tensor([b["restitution"]], dtype=torch.float32),
            dt=torch.tensor([float(a["dt"])], dtype=torch.float32),
            l0=torch.tensor([float(a["l0"])], dtype=torch.float32),
            scene=torch.tensor([int(a["scene_index"])], dtype=torch.long),
            system=torch.tensor([int(c["system"][local])]),
        )


class TrajectoryWindows(_SceneDataset):
    """GNS-style windows of the MPS trajectories (for end-to-end models).

    Uses the uniformly spaced frames (every ``sample_every`` steps), a model frame every ``stride`` of them
    (``s``). Item ``(scene, t)`` for stored frames ``first * s <= t < T - s``: ``pos`` (N, 3) frame t with the
    boundary, ``ptype`` (N,), ``history`` (Nf, H, 3) fluid positions of frames t-H*s, ..., t-s, ``y`` (Nf, 3)
    fluid positions of frame t+s; graph-level ``frame_dt`` = dt * sample_every * s, ``step`` (solver step of
    frame t), ``frames_before`` (1,) how many of the history frames are the trajectory's, ``min(t // s, H)``,
    and the scene fields. Every stored frame starts a window, so a stride of 2 keeps both phases of the data.

    ``first < H`` gives the earliest frames too: a frame before frame 0 is a copy of frame 0 (padding,
    never a state: ``frames_before`` says where the trajectory starts). GNS keeps ``H`` = its velocity
    history plus its pushforward unroll but learns from frame ``first`` = its history on, the first frame a
    warm-started rollout steps from.

    Args:
        root, split, transform, boundary_radius: as the other datasets.
        history: H, past frames per item (GNS: 5).
        first: the earliest frame t of an item, in model frames, 0 < first <= H (None: H, no padding).
        stride: stored frames per model frame (1: the model steps by the data's frame spacing).
    """

    solver_trajectories_only = True
    needs_samples = False

    def __init__(
        self,
        root: str | os.PathLike,
        split: str | None = "train",
        transform: Any = None,
        boundary_radius: float | Literal["default"] | None = "default",
        history: int = 5,
        first: int | None = None,
        stride: int = 1,
    ) -> None:
        if history < 1:
            raise LagfluidError(f"history must be >= 1, got {history}")
        first = history if first is None else first
        if not 1 <= first <= history:
            raise LagfluidError(f"the first window frame must be in 1..history={history}, got {first}")
        if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
            raise LagfluidError(f"the frame stride must be a whole number of stored frames >= 1: {stride!r}")
        self.history, self.first, self.stride = history, first, stride
        super().__init__(root, split, transform, boundary_radius)

    @staticmethod
    def _uniform_frames(info: SceneInfo) -> int:
        return min(info.frames, int(info.attrs["steps"]) // int(info.attrs["sample_every"]) + 1)

    def _count(self, info: SceneInfo) -> int:
        return max(0, self._uniform_frames(info) - self.stride * (1 + self.first))

    def _frames(self, positions: h5py.Dataset, t: int, after: int) -> tuple[np.ndarray, int]:
        """Stored frames t-H*s, ..., t+after*s of ``positions`` (H + 1 + after, Nf, 3), ``s`` the stride.

        Frame 0 stands for those before frame 0.

        Returns:
            The frames and how many of the H before t are the trajectory's, ``min(t // s, H)``.
        """
        s = self.stride
        start = max(0, t - self.history * s)
        block = positions[start : t + after * s + 1]
        index = np.maximum(np.arange(t - self.history * s, t + after * s + 1, s), 0) - start
        return block[index], min(t // s, self.history)

    def _item(self, file: int, local: int) -> Data:
        g = self._h5(file)[GROUP]
        t = local + self.first * self.stride
        window, before = self._frames(g["position"], t, 1)  # frames t-H*s .. t+s
        b_pos, b_type = self._near_boundary(file, window[-2])
        a = self.infos[file].attrs
        every = int(a["sample_every"])
        return Data(
            **_with_boundary(window[-2], None, b_pos, b_type),
            history=torch.from_numpy(np.ascontiguousarray(window[:-2].transpose(1, 0, 2))),
            y=torch.from_numpy(window[-1]),
            frame_dt=torch.tensor([float(a["dt"]) * every * self.stride], dtype=torch.float32),
            step=torch.tensor([t * every]),
            frames_before=torch.tensor([before]),
            **self._bounds(file),
            **self._scene_fields(file),
        )


class StepWindows(_SceneDataset):
    """Windows of consecutive solver steps: a sample's state and its next ``K`` steps (``samples/next``).

    For models that step by the solver's own ``dt`` and train on short unrolls (CConv: K = 2, as
    DeepLagrangianFluids). Needs a dataset generated with ``data.next_steps >= K``. Item ``(scene, s)``:
    ``pos``, ``vel`` (N, 3) the state of sample s's step with the boundary within reach, ``ptype`` (N,),
    ``y`` (Nf, K, 3) the fluid positions of the next K steps; graph-level ``dt``, ``step``, ``bounds``
    (1, 2, 3) when the scene has a tank, and the scene fields.

    With ``frames`` F > 0 an item also holds ``y_frames`` (Nf, F, 3), the fluid positions of the F stored
    frames after the sample's (``frame_steps`` (1,) solver steps apart): a longer horizon over which MPS's
    step-to-step noise averages out (``benchmarks/results/acceleration_noise.md``). Samples too close to the
    end of their trajectory for F frames are left out.

    Args:
        root, split, transform, boundary_radius: as the other datasets.
        steps: K, the solver steps after the state each item holds (0 with ``frames`` > 0: none).
        frames: F, the stored frames after the state each item holds.

    Raises:
        TrajectoryFileError: a scene file without ``samples/next`` or with fewer than ``steps`` of them.
    """

    solver_trajectories_only = True

    def __init__(
        self,
        root: str | os.PathLike,
        split: str | None = "train",
        transform: Any = None,
        boundary_radius: float | Literal["default"] | None = "default",
        steps: int = 2,
        frames: int = 0,
    ) -> None:
        if steps < 0 or frames < 0 or steps + frames < 1:
            raise LagfluidError(f"steps and frames must be >= 0 with at least one > 0, got {steps}, {frames}")
        self.steps, self.frames = steps, frames
        super().__init__(root, split, transform, boundary_radius)

    def _count(self, info: SceneInfo) -> int:
        with h5py.File(info.path, "r") as f:
            samples = int(f["samples/frame"].shape[0])  # the last ones may lack their next steps or frames
            if self.steps:
                nxt = f["samples"].get("next/position")
                if nxt is None or nxt.shape[1] < self.steps:
                    have = 0 if nxt is None else nxt.shape[1]
                    raise TrajectoryFileError(
                        f"{info.path} stores {have} solver steps after each sample, this model needs "
                        f"{self.steps}: generate the dataset with data.next_steps={self.steps}"
                    )
                samples = min(samples, int(nxt.shape[0]))
            if not self.frames:
                return samples
            sample_frames = f["samples/frame"][()]
        if np.any(np.diff(sample_frames) <= 0):
            raise TrajectoryFileError(f"{info.path}: samples/frame is not increasing")
        # the uniformly spaced frames only (TrajectoryWindows): frame k is at solver step k * sample_every
        last = TrajectoryWindows._uniform_frames(info) - 1
        return min(samples, int(np.count_nonzero(sample_frames + self.frames <= last)))

    def _item(self, file: int, local: int) -> Data:
        f = self._h5(file)
        g, s = f[GROUP], f["samples"]
        frame = int(s["frame"][local])
        pos, vel = g["position"][frame], g["velocity"][frame]
        b_pos, b_type = self._near_boundary(file, pos)
        extra = {}
        if self.steps:
            nxt = s["next/position"][local, : self.steps]
            extra["y"] = torch.from_numpy(nxt).transpose(0, 1).contiguous()
        if self.frames:
            after = g["position"][frame + 1 : frame + 1 + self.frames]
            every = int(self.infos[file].attrs["sample_every"])
            extra["y_frames"] = torch.from_numpy(np.ascontiguousarray(after.transpose(1, 0, 2)))
            extra["frame_steps"] = torch.tensor([every])
        return Data(
            **_with_boundary(pos, vel, b_pos, b_type),
            **extra,
            step=torch.tensor([int(s["step"][local])]),
            **self._bounds(file),
            **self._scene_fields(file),
        )
