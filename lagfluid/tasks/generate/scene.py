"""One scene of a dataset: the MPS rollout with its one-step samples and collision samples, one file."""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path
from statistics import median
from typing import Any

from omegaconf import DictConfig

from lagfluid.data.layout import (
    GROUP,
    SampleWriter,
    read_scene_info,
    scene_path,
)
from lagfluid.data.store import TrajectoryFileError, TrajectoryWriter
from lagfluid.errors import LagfluidError, RolloutError, SceneError
from lagfluid.models.mps_simulator import build_mps
from lagfluid.physics.settings import SolverSettings
from lagfluid.rollout import Guard, rollout
from lagfluid.scenes import build_scene
from lagfluid.state import ParticleState
from lagfluid.tasks.config import check_run_memory, run_attributes
from lagfluid.tasks.generate.collision import write_collision_samples
from lagfluid.tasks.generate.policy import build_policy
from lagfluid.tasks.generate.spec import DataSpec

log = logging.getLogger(__name__)


def scene_done(path: Path, fingerprint: str, samples: bool = True) -> bool:
    """True for a finished scene file made with ``fingerprint``; False when it must be (re)generated.

    ``samples=False``: a scene without the stage samples (a DAgger scene,
    :mod:`lagfluid.tasks.generate.expert`).

    Raises:
        LagfluidError: a finished file made with another configuration.
    """
    if not path.exists():
        return False
    try:
        info = read_scene_info(path, samples=samples)
    except TrajectoryFileError as err:
        log.warning("%s; regenerating it", err)
        return False
    if not info.complete:
        log.warning("%s is incomplete; regenerating it", path)
        return False
    found = str(info.attrs.get("fingerprint", ""))
    if found != fingerprint:
        raise LagfluidError(
            f"{path} was generated with another configuration (fingerprint {found}, this run {fingerprint}: "
            "scene options, materials, steps, sample_every, solver or collision settings differ); "
            "use another data.out_dir or delete the file"
        )
    return True


def generate_scene(cfg: DictConfig, spec: DataSpec, index: int) -> Path:
    """Simulate scene ``index`` with MPS and write its file (trajectory + samples); returns the path.

    With ``spec.policy`` the scene is moved by ``cfg.model`` instead, each sample labelled by the exact
    stages at the model's own states (:mod:`lagfluid.tasks.generate.policy`).

    Raises:
        LagfluidError: the rollout guard stopped the scene (the file is kept as ``*.failed.h5``), or the scene
            is invalid.
    """
    path = scene_path(spec.out_dir, index)
    failed = path.with_name(path.stem + ".failed.h5")
    options, params, seed = spec.scene_setup(index)
    try:
        state = build_scene(spec.builder, params, dtype=spec.dtype, **options).to(device=spec.device)
    except SceneError as err:
        raise SceneError(f"scene {index} (seed {seed}): {err}") from err
    settings = SolverSettings.from_config(cfg.solver)
    sim = build_policy(cfg) if spec.policy is not None else build_mps(cfg)
    check_run_memory(cfg, state, sim)  # before the first neighbour search
    sim.reset(state)
    nf = state.n_fluid
    attrs = {
        **run_attributes(state, cfg, sim.name, spec.builder, spec.sample_every),
        "scene_options": options,
        "scene_index": index,
        "seed": seed,
        "sample_every": spec.sample_every,
        "steps": spec.steps,
        "fingerprint": spec.fingerprint(index),
        "dataset": spec.name,
        **sim.attributes(),
        **({"policy": json.dumps(spec.policy)} if spec.policy is not None else {}),
    }
    writer = TrajectoryWriter(
        path, nf, state.pos[nf:].cpu().numpy(), state.ptype[nf:].cpu().numpy(), attrs, group=GROUP
    )
    start = time.perf_counter()
    try:
        samples = SampleWriter(writer.file.create_group("samples"), nf, params.dt, spec.next_steps)
        guard = Guard(float(cfg.solver.guard.max_courant), int(cfg.solver.guard.check_every))
        every = spec.sample_every

        def keep_sample(before: ParticleState, after: ParticleState, fields: Any) -> None:
            if fields is not None:
                samples.append(before.step, fields)
            samples.after_step(after.step, after.pos[:nf])

        stopped: dict[str, Any] = {}
        try:
            _, record = rollout(
                sim,
                state,
                spec.steps,
                guard=guard,
                write_every=every,
                on_frame=writer.append_state,
                on_step=keep_sample,
                record_when=lambda s: s.step % every == 0,  # recording costs copies: only the sampled steps
                progress=bool(cfg.progress),
                reset=False,  # reset above: its constants are in the file's attributes
            )
        except RolloutError as err:
            # The ground truth must not stop, except (data.on_fluid_leaving=keep) for a splash over the
            # tank's rim: the authors' runs delete such particles and go on; a fixed-count file ends there.
            splash = spec.on_fluid_leaving == "keep" and err.kind == "left_domain"
            if spec.policy is None and not splash:
                raise
            # A model that leaves the domain is what on-policy rounds correct: the states it visited up to
            # there (each labelled by the exact stages) are kept as a shorter scene.
            record = getattr(err, "record", {"step_seconds": [0.0], "info": {}})
            last = getattr(err, "state", state)
            stopped = {"stopped_at_step": int(last.step), "stop_reason": str(err)}
            log.warning(
                "scene %d: the %s stopped at step %d (%s); its %d steps are kept",
                index,
                "policy" if spec.policy is not None else "MPS solver",
                last.step,
                str(err).split(";")[0],
                last.step,
            )
        sim_seconds = time.perf_counter() - start
        collisions = write_collision_samples(
            samples.group.create_group("collision"), spec, settings, params, seed
        )
        samples.group.attrs["complete"] = True
        writer.group.attrs.update(
            wall_time_s=time.perf_counter() - start,
            simulation_time_s=sim_seconds,
            step_time_median_s=median(record["step_seconds"] or [0.0]),
            ppe_iterations_median=median(record["info"].get("ppe_iterations", [0.0])),
            collision_samples=collisions,
            **stopped,
        )
        writer.close(complete=True, stop_reason=stopped.get("stop_reason"))
        failed.unlink(missing_ok=True)  # a failure of an earlier run with other settings
    except RolloutError as err:
        writer.file.close()
        os.replace(writer.tmp_path, failed)
        raise LagfluidError(
            f"scene {index} ({path.name}, seed {seed}) stopped: {err}; kept as {failed}"
        ) from err
    except BaseException:
        # Interrupted or failed otherwise: leave the .part file; the next run overwrites it.
        if writer.file.id.valid:
            writer.file.close()
        raise
    log.info(
        "scene %d: %d steps in %.0f s (%.0f ms/step median), %d + %d collision samples -> %s",
        index,
        stopped.get("stopped_at_step", spec.steps),
        time.perf_counter() - start,
        1e3 * median(record["step_seconds"] or [0.0]),
        samples.count,  # spec.num_samples unless the scene stopped early
        collisions,
        path,
    )
    return path
