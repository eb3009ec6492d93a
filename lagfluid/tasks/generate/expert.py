"""DAgger datasets for end-to-end models: the model rolls the scenes out, MPS labels one model step.

For each training scene of a dataset (same scene settings, seeds, materials and steps: a
:class:`~lagfluid.tasks.generate.spec.DataSpec` of the dataset's own generation config), an end-to-end model
(``model=gns`` or ``cconv`` with ``model.weights``; any simulator that is not split-step, with
``model.exact_after``'s stages after each step if on) is rolled out from the scene's start as
``task=simulate`` would (GNS: its MPS warm start, then its own steps of ``frame_dt``). At every ``every``-th
frame the model made (counted from its first own step), :func:`expert_step` lets MPS advance one model step
(``substeps = frame_dt / dt`` solver steps) from the model's positions ``x_t`` and velocity ``v_t = (x_t -
x_{t-1}) / frame_dt``; MPS starts its own state there (pressure 0, its PPE's warm start only), with the
constants of the scene's start; with a label ``horizon`` H > 1, MPS goes on H - 1 model steps from its own
answer (the targets of a model trained on H-step unrolls). The rollout stops where the model's guard stops it
(that is where its mistakes are); the frames and labels before are kept, and the file says where and why it
stopped. MPS's answer from a model state is checked by the solver's own guard: where it fails, the scene stops
there.

Files (layout: :mod:`lagfluid.data.expert_windows`) are written as ``task=generate`` writes scenes: into a
``.part`` file renamed when complete, locked per scene, with a fingerprint of the dataset scene's and of the
expert settings (model, hash of its weights, ``every``, ``horizon``); a finished scene of the same fingerprint
is skipped, one of another is an error. ``metadata.json`` follows once every training scene is there.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig

import lagfluid
from lagfluid.data.expert_windows import EXPERT, EXPERT_FORMAT_VERSION, LABELS, LATER
from lagfluid.data.layout import (
    DATASET_FORMAT,
    GROUP,
    METADATA_FILE,
    SPLITS,
    append_rows,
    appendable,
    read_scene_info,
    scene_path,
    split_of,
)
from lagfluid.data.store import TrajectoryWriter, stored_dtype
from lagfluid.errors import ConfigError, RolloutError, SceneError
from lagfluid.integrate import velocity_from_positions
from lagfluid.models.exact_after import ExactAfter
from lagfluid.models.mps_simulator import build_mps
from lagfluid.models.simulator import Simulator
from lagfluid.physics.scheme import SplitStepSimulator
from lagfluid.physics.settings import SolverSettings
from lagfluid.rollout import Guard, rollout
from lagfluid.scenes import build_scene
from lagfluid.state import ParticleState
from lagfluid.tasks.config import (
    apply_threads,
    at_simulator_time_step,
    build_simulator,
    check_run_memory,
    git_commit,
    run_attributes,
    run_guard,
)
from lagfluid.tasks.generate.metadata import write_json_atomic
from lagfluid.tasks.generate.scene import scene_done
from lagfluid.tasks.generate.spec import DataSpec
from lagfluid.tasks.locks import hold_outputs

log = logging.getLogger(__name__)


def substeps_of(model_dt: float, solver_dt: float, name: str) -> int:
    """Solver steps of ``solver_dt`` in one step of the model, ``model_dt / solver_dt``.

    Raises:
        ConfigError: not a whole number of them.
    """
    substeps = round(model_dt / solver_dt)
    if substeps < 1 or abs(substeps * solver_dt - model_dt) > 1e-9 * max(model_dt, 1.0):
        raise ConfigError(
            f"model {name} steps by {model_dt} s, not a whole number of the dataset's solver steps of "
            f"{solver_dt} s: MPS cannot label one model step"
        )
    return substeps


@torch.no_grad()
def expert_step(
    expert: SplitStepSimulator, before: ParticleState, after: ParticleState, solver_dt: float, substeps: int
) -> ParticleState:
    """MPS's state one model step after the model's frame ``after``, started from the model's own state.

    Args:
        expert: the MPS simulator (reset at the scene's start: its constants).
        before: the model's frame ``t - 1`` (its positions only are read).
        after: the model's frame ``t``, at the model's step ``frame_dt``.
        solver_dt: MPS's time step (s).
        substeps: MPS steps in one model step (``frame_dt = substeps * solver_dt``).

    Returns:
        MPS's state after ``substeps`` steps from positions ``x_t`` and fluid velocities
        ``v_t = (x_t - x_{t-1}) / frame_dt`` (the boundary at rest, pressure 0), at the solver's ``dt``.
    """
    nf = after.n_fluid
    vel = after.vel.clone()
    vel[:nf] = velocity_from_positions(before.pos[:nf], after.pos[:nf], after.params.dt)
    state = ParticleState(
        pos=after.pos,
        vel=vel,
        ptype=after.ptype,
        params=after.params.with_overrides(dt=solver_dt),
        pressure=torch.zeros_like(after.pressure),  # the PPE's warm start only: its answer is the same
        time=after.time,
        step=after.step,
        bounds=after.bounds,
        check=False,
        fluid_count=nf,
    )
    for _ in range(substeps):
        state = expert.step(state)
    return state


class ExpertLabels:
    """Appends the labels of a DAgger scene to its file's ``/expert`` group (layout: the module doc).

    Args:
        group: the open file's new ``/expert`` group.
        n_fluid: Nf.
        dtype: stored dtype of the positions and velocities (the run's).
        attrs: ``every``, ``substeps``, ``solver_dt``.
    """

    def __init__(self, group: Any, n_fluid: int, dtype: np.dtype, attrs: dict[str, Any]) -> None:
        self.group = group
        group.attrs.update(format_version=EXPERT_FORMAT_VERSION, complete=False, **attrs)
        self.frame = appendable(group, "frame", (), "i8", 1024)
        self.position = appendable(group, "position", (n_fluid, 3), dtype.str)
        self.velocity = appendable(group, "velocity", (n_fluid, 3), dtype.str)
        horizon = int(attrs.get("horizon", 1))
        self.later = appendable(group, LATER, (horizon - 1, n_fluid, 3), dtype.str) if horizon > 1 else None
        self.count = 0

    def append(self, frame: int, states: Sequence[ParticleState]) -> None:
        """Store the labels of trajectory frame ``frame``: the fluid rows of MPS's ``states``, one per step.

        ``states[0]`` (one model step after the frame) fills ``position`` and ``velocity``; the further
        steps (``horizon`` > 1) ``later_position``.
        """
        nf = self.position.shape[1]
        dtype = self.position.dtype

        def rows(t: torch.Tensor) -> np.ndarray:
            return t[:nf].detach().cpu().numpy().astype(dtype)

        append_rows(self.frame, np.array([frame], np.int64))
        append_rows(self.position, rows(states[0].pos)[None])
        append_rows(self.velocity, rows(states[0].vel)[None])
        if self.later is not None:
            append_rows(self.later, np.stack([rows(s.pos) for s in states[1:]])[None])
        self.count += 1

    def close(self) -> None:
        """Mark the labels complete (the file is renamed complete after it)."""
        self.group.attrs.update(complete=True, count=self.count)


def expert_identity(sim: Simulator, every: int, horizon: int = 1) -> dict[str, Any]:
    """What decides a DAgger scene's content besides the dataset scene.

    The model (its name says which exact stages follow it), a hash of its weights, ``every`` and, when more
    than one, the label ``horizon`` (absent at 1: the fingerprints of datasets made before it existed hold).
    """
    weights = str(sim.attributes().get("weights", ""))
    digest = (
        hashlib.sha256(Path(weights).read_bytes()).hexdigest()[:16] if Path(weights).is_file() else weights
    )
    identity = {"model": sim.name, "weights": digest, "every": every, "labels": LABELS}
    if horizon != 1:
        identity["horizon"] = horizon
    return identity


def expert_fingerprint(spec: DataSpec, index: int, identity: dict[str, Any]) -> str:
    """The fingerprint of DAgger scene ``index``: the dataset scene's and the expert settings'."""
    content = {"scene": spec.fingerprint(index), "expert": identity, "format": EXPERT_FORMAT_VERSION}
    return hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()[:16]


def end_to_end_simulator(cfg: DictConfig) -> Simulator:
    """``cfg.model`` as the policy of a DAgger dataset, with ``model.exact_after``'s stages if on.

    Raises:
        ConfigError: a split-step model (its DAgger is ``train.onpolicy``).
    """
    sim = build_simulator(cfg)
    model = sim.model if isinstance(sim, ExactAfter) else sim
    if isinstance(model, SplitStepSimulator):
        raise ConfigError(
            f"train.dagger is for end-to-end models (gns, cconv): model {cfg.model.name} is split-step; its "
            "rounds are train.onpolicy.rounds"
        )
    return sim


def expert_scene(
    cfg: DictConfig, spec: DataSpec, index: int, sim: Simulator, every: int, horizon: int = 1
) -> Path:
    """Roll ``sim`` out on scene ``index``, label it with MPS, and write its file; returns the path.

    Each label is ``horizon`` model steps of MPS from the model's frame (the first from the model's
    state, the others continuing MPS's own: the windows of a model trained on short unrolls, CConv's two).

    Raises:
        ConfigError: the model's step is not a whole number of solver steps, or (a model with a history of
            frames) not the dataset's frame spacing.
        SceneError: the scene is invalid.
    """
    path = scene_path(spec.out_dir, index)
    options, params, seed = spec.scene_setup(index)
    try:
        start = build_scene(spec.builder, params, dtype=spec.dtype, **options).to(device=spec.device)
    except SceneError as err:
        raise SceneError(f"scene {index} (seed {seed}): {err}") from err
    substeps = substeps_of(float(sim.dt or params.dt), params.dt, sim.name)
    if sim.history_length and substeps != spec.sample_every:
        raise ConfigError(
            f"model {sim.name} steps by {sim.dt} s, the dataset's frames are {spec.sample_every * params.dt} "
            "s apart (data.sample_every x dt): it learns from those frames, so DAgger labels must match them"
        )
    state = at_simulator_time_step(start, sim, cfg)
    expert, expert_guard = build_mps(cfg), Guard(float(cfg.solver.guard.max_courant))
    check_run_memory(cfg, state, sim)  # before the first neighbour search
    expert.reset(start)  # the scene's constants, as the dataset's MPS run had them
    sim.reset(state)
    nf, steps = state.n_fluid, spec.steps // substeps
    identity = expert_identity(sim, every, horizon)
    attrs = {
        **run_attributes(state, cfg, sim.name, spec.builder, 1),
        **sim.attributes(),
        **expert.attributes(),  # the expert's n0, n0_lap, lambda
        "dt": params.dt,  # the solver's: a frame is sample_every of them, as in every dataset
        "sample_every": substeps,
        "steps": steps * substeps,
        "scene_options": options,
        "scene_index": index,
        "seed": seed,
        "fingerprint": expert_fingerprint(spec, index, identity),
        "dataset": f"{spec.name}_dagger",
        "trajectory": "model",
        "labels": LABELS,
        "policy": json.dumps(identity),
    }
    writer = TrajectoryWriter(
        path,
        nf,
        state.pos[nf:].cpu().numpy(),
        state.ptype[nf:].cpu().numpy(),
        attrs,
        GROUP,
        stored_dtype(state),
    )
    labels = ExpertLabels(
        writer.file.create_group(EXPERT),
        nf,
        stored_dtype(state),
        {"every": every, "substeps": substeps, "solver_dt": params.dt, "horizon": horizon},
    )
    learned, clock = 0, time.perf_counter()

    def label(before: ParticleState, after: ParticleState, fields: Any) -> None:
        nonlocal learned
        if not getattr(sim, "last_step_learned", True):  # GNS's MPS warm-start frames are not the model's
            return
        learned += 1
        if (learned - 1) % every:
            return
        answers = [expert_step(expert, before, after, params.dt, substeps)]
        for _ in range(horizon - 1):  # MPS goes on from its own answer
            answer = answers[-1]
            for _ in range(substeps):
                answer = expert.step(answer)
            answers.append(answer)
        for answer in answers:
            try:
                expert_guard.check(answer)
            except RolloutError as err:
                raise RolloutError(
                    f"MPS advanced from the model's frame {after.step} fails its guard: {err}"
                ) from err
        labels.append(after.step, answers)

    stopped: dict[str, Any] = {}
    try:
        try:
            rollout(
                sim,
                state,
                steps,
                guard=run_guard(cfg, sim),
                on_frame=writer.append_state,
                on_step=label,
                progress=bool(cfg.progress),
                reset=False,
            )
        except RolloutError as err:  # the model's mistakes end here: what came before is the data
            last = getattr(err, "state", state)
            stopped = {"stopped_after_frame": int(last.step), "stop_reason": str(err)}
            log.warning(
                "scene %d: the model stopped after frame %d (%s)", index, last.step, str(err).split(";")[0]
            )
        labels.close()
        writer.group.attrs.update(wall_time_s=time.perf_counter() - clock, labels=labels.count, **stopped)
        writer.close(complete=True, stop_reason=stopped.get("stop_reason"))
    except BaseException:  # interrupted or failed otherwise: the .part file stays; the next run overwrites it
        if writer.file.id.valid:
            writer.file.close()
        raise
    log.info(
        "scene %d: %d frames of %s, %d MPS labels, in %.0f s -> %s",
        index,
        writer.frames,
        sim.name,
        labels.count,
        time.perf_counter() - clock,
        path,
    )
    return path


def train_scenes(spec: DataSpec) -> list[int]:
    """The dataset's training scenes (the only ones a DAgger dataset rolls out)."""
    return [k for k, split in enumerate(split_of(spec.num_scenes, spec.splits)) if split == "train"]


def write_expert_metadata(spec: DataSpec, scenes: list[int], identity: dict[str, Any]) -> dict[str, Any]:
    """``metadata.json`` of a DAgger dataset of ``scenes`` (all finished; the train split); returns it."""
    infos = [read_scene_info(scene_path(spec.out_dir, k), samples=False) for k in scenes]
    first = infos[0].attrs
    rel = [str(i.path.relative_to(spec.out_dir)) for i in infos]
    labels = [int(i.attrs.get("labels", 0)) for i in infos]
    settings = SolverSettings.from_config(spec.solver)
    meta = {
        "format": DATASET_FORMAT,
        "format_version": 1,
        "samples": False,
        "name": f"{spec.name}_dagger",
        "trajectory": "model",
        "labels": LABELS,
        "policy": identity,
        EXPERT: {
            "every": identity["every"],
            "substeps": int(first["sample_every"]),
            "horizon": identity.get("horizon", 1),
            "solver": "mps",
        },
        "num_scenes": len(scenes),
        "steps": int(first["steps"]),
        "sample_every": int(first["sample_every"]),
        "write_every": int(first["sample_every"]),
        "dt": float(first["dt"]),
        "dim": int(first["dim"]),
        "l0": float(first["l0"]),
        "default_connectivity_radius": settings.re_laplacian * float(first["l0"]),
        "splits": {split: rel if split == "train" else [] for split in SPLITS},
        "counts": {
            "train": {"scenes": len(scenes), "frames": sum(i.frames for i in infos), "labels": sum(labels)}
        },
        "scenes": [
            {
                "index": k,
                "file": rel[j],
                "split": "train",
                "seed": int(i.attrs["seed"]),
                "gravity": [float(g) for g in i.attrs["gravity"]],
                "viscosity": float(i.attrs["viscosity"]),
                "n_fluid": i.n_fluid,
                "frames": i.frames,
                "labels": labels[j],
                "stopped_after_frame": int(i.attrs.get("stopped_after_frame", -1)),  # -1: ran to the end
                "wall_time_s": float(i.attrs.get("wall_time_s", 0.0)),
            }
            for j, (k, i) in enumerate(zip(scenes, infos, strict=True))
        ],
        "scene": {"builder": spec.builder, "options": spec.scene_options},
        "solver": spec.solver,
        "model": identity["model"],
        "version": lagfluid.__version__,
        "git_commit": git_commit(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    write_json_atomic(spec.out_dir / METADATA_FILE, meta)
    return meta


def generate_expert(cfg: DictConfig) -> dict[str, Any] | None:
    """The DAgger dataset of ``cfg`` (a ``task=generate`` config of the dataset, ``model=`` the policy).

    ``cfg.data.expert_every``: label every k-th frame the model made; ``cfg.data.expert_horizon`` (absent:
    1): model steps of MPS in each label; ``cfg.data.scene_index``: only that training scene (a job of
    several), else every training scene, then ``metadata.json``.

    Returns:
        the metadata once every training scene is there, else None.

    Raises:
        ConfigError: a bad ``data.expert_every``, a scene index that is not a training scene, or a model
            that cannot be labelled (:func:`end_to_end_simulator`, :func:`expert_scene`).
        LagfluidError: a finished scene file made with other settings.
    """
    apply_threads(cfg)
    spec = DataSpec.from_config(cfg)
    every = cfg.data.get("expert_every")
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise ConfigError(f"train.dagger.every must be a whole number >= 1, got {every!r}")
    horizon = cfg.data.get("expert_horizon", 1)
    if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 1:
        raise ConfigError(f"train.dagger.horizon must be a whole number >= 1, got {horizon!r}")
    scenes = train_scenes(spec)
    if spec.scene_index is not None and spec.scene_index not in scenes:
        raise ConfigError(f"data.scene_index={spec.scene_index} is not a training scene ({scenes})")
    todo = scenes if spec.scene_index is None else [spec.scene_index]
    sim = end_to_end_simulator(cfg)
    identity = expert_identity(sim, every, horizon)
    folder = scene_path(spec.out_dir, 0).parent
    with hold_outputs(folder, "generate", [scene_path(spec.out_dir, k).stem for k in todo], "data.out_dir"):
        for k in todo:
            if scene_done(scene_path(spec.out_dir, k), expert_fingerprint(spec, k, identity), samples=False):
                log.info("DAgger scene %d is done, skipped", k)
                continue
            expert_scene(cfg, spec, k, sim, every, horizon)
        done = all(
            scene_done(scene_path(spec.out_dir, k), expert_fingerprint(spec, k, identity), samples=False)
            for k in scenes
        )
        if not done:
            return None
        return write_expert_metadata(spec, scenes, identity)
