"""The paper's tables and figures, and the speed/accuracy trade-off, regenerated from real runs.

Usage::

    python -m benchmarks.tables                  # full profile (prints its estimated runtime first)
    python -m benchmarks.tables --quick          # reduced profile, < 5 min; writes tables_quick_* files
    python -m benchmarks.tables --quick --readme --weights runs/train/fgn-cpu --threads 1
    python -m benchmarks.tables --only table2 tradeoff

Every row is a Hydra experiment file (``conf/experiment/<name>.yaml``: ``python -m lagfluid.run
experiment=table3_dam_fgn`` runs that row alone at the full profile); this script composes them in-process
(Hydra's compose API) and runs them one after another in one process, so every timing is taken under the
same conditions. A profile adds overrides (scene, steps, frames, dt) to each row; every row's complete
override list is written beside its numbers. Accuracy rows run ``task=evaluate`` (:mod:`lagfluid.evaluate`:
the model and the MPS reference from the same initial state, metrics per stored frame), so every number
comes from :mod:`lagfluid.metrics`.

Parts (``--only``):

* ``table3`` (paper Tables 1 and 3): density error, divergence (mean/max over the frames) and Chamfer
  distance to MPS (mean/max, mm) on the dam collapse and the water fall, for every registered simulator; MPS
  is the "Ground truth" row (its own density error and divergence).
* ``table2``: trainable parameters, median time per step, neighbour search and the rest ("inference") at
  ~40k fluid particles (``scene=dam_large``), warm-up steps excluded, every simulator in this process.
* ``table4``: the advection net's normalised MAE (eq. 32) on held-out gravity and viscosity (paper: ten
  sequences, g in [1, 100] m/s^2, nu in [1e-4, 0.1] m^2/s) and the pressure net's PPE relative residual
  (eq. 31), mean +- standard deviation.
* ``fig5``: FGN's Chamfer distance to MPS against time for dt from 0.5 ms up, until the rollout guard stops
  a run (the largest dt that completes is reported).
* ``tradeoff``: wall seconds per simulated second against accuracy (Chamfer distance to the reference MPS,
  density error) for every simulator, hybrids, FGN at other dt, and MPS at looser PPE tolerances, larger
  dt and a coarser resolution; the Pareto front is marked (:mod:`benchmarks.pareto`).

Outputs (``benchmarks/results/``, prefix ``tables`` or ``tables_quick``): ``<prefix>_report.md`` (every
table, the provenance and each row's overrides), ``<prefix>_parts.json`` (the rendered parts, so that an
``--only`` rerun replaces its parts and keeps the others, each saying when it ran),
``<prefix>_{table3,table2,table4,fig5,tradeoff}.csv``,
``<prefix>_{fig5,tradeoff}.png``, ``<prefix>_fig4_dam_fgn.png`` and ``<prefix>_fig6_dam_fgn.png`` (paper
Figs. 4 and 6 for FGN on the dam). The full profile also rewrites the README's results tables (between
``<!-- tables:start -->`` and ``<!-- tables:end -->``); ``--readme`` makes any profile do so. Rollouts
go to ``runs/tables/<profile>/`` and MPS references to ``runs/tables/reference/`` (not committed).
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import math
import os
import platform
import re
import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from statistics import median
from typing import Any

import numpy as np
import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from benchmarks.pareto import pareto_front
from benchmarks.provenance import git_commit, markdown, provenance
from lagfluid.errors import ConfigError
from lagfluid.evaluate import evaluate
from lagfluid.models.fgn_simulator import SHIPPED_WEIGHTS
from lagfluid.registry import available_simulators
from lagfluid.config import build_initial_state, build_simulator
from lagfluid.rollout import Guard, rollout
from lagfluid.run import CONF_DIR

log = logging.getLogger("benchmarks.tables")

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
README = REPO / "README.md"
AUTHORS_WEIGHTS = REPO.parent / "shared" / "reference" / "fgn_original" / "checkpoints"
MARK_START, MARK_END = "<!-- tables:start -->", "<!-- tables:end -->"
PARTS = ("table2", "table3", "table4", "fig5", "tradeoff")


# ------------------------------------------------------------------------------------------- simulators
@dataclass(frozen=True)
class Simulator:
    """One simulator of the tables: its key (experiment files ``table3_<case>_<key>``, ``table2_<key>``)."""

    key: str
    label: str
    model: str  # the registered simulator name (model=...)
    learned: bool  # needs FGN weights (model.weights)


SIMULATORS: tuple[Simulator, ...] = (
    Simulator("mps", "MPS", "mps", False),
    Simulator("fgn", "FGN", "fgn", True),
    Simulator("hybrid_pressure", "hybrid: learned pressure", "hybrid", True),
    Simulator("hybrid_advection", "hybrid: learned advection", "hybrid", True),
    Simulator("fgn_original", "FGN, authors' weights", "fgn_original", True),
)


def all_simulators(keys: Sequence[str] | None = None) -> list[Simulator]:
    """The simulators above plus any registered plugin without a row file (run as ``model=<name>``)."""
    sims = list(SIMULATORS)
    known = {s.model for s in sims}
    sims += [Simulator(n, n, n, False) for n in available_simulators() if n not in known]
    return [s for s in sims if keys is None or s.key in keys]


# Held-out materials for Table 4: g = 1..100 m/s^2 and nu = 1e-4..0.1 m^2/s, both log-spaced over ten
# values and paired by a fixed permutation, so that each range is covered evenly and the pairs are not
# ordered together (a random draw of ten clustered at small g).
MATERIALS: tuple[tuple[float, float], ...] = (
    (1.0, 1.0e-3),
    (1.7, 2.2e-2),
    (2.8, 1.0e-4),
    (4.6, 1.0e-1),
    (7.7, 4.6e-3),
    (13.0, 2.2e-4),
    (22.0, 4.6e-2),
    (36.0, 2.2e-3),
    (60.0, 4.6e-4),
    (100.0, 1.0e-2),
)

# The paper's numbers (/work/shared/paper: Tables 1, 2, 4).
PAPER_TABLE1 = {
    ("dam", "FGN"): (0.0461, 0.0900, 0.0195, 0.0280, 24.2, 30.1),
    ("dam", "Ground truth"): (0.0380, 0.0710, 0.0190, 0.0268, None, None),
    ("waterfall", "FGN"): (0.0541, 0.1350, 0.0207, 0.0431, 24.8, 29.6),
    ("waterfall", "Ground truth"): (0.0429, 0.0966, 0.0196, 0.0398, None, None),
}
PAPER_TABLE2 = {"FGN": (41996, 5.7, 46.4), "MPS": (None, 313.2, 42.3)}  # parameters, inference ms, NNS ms
PAPER_TABLE4 = {"advection": (12.4, 5.6), "pressure": (8.3, 1.1)}  # percent, mean and std


# ------------------------------------------------------------------------------------------- profiles
@dataclass(frozen=True)
class Profile:
    """How big each part is. The row files hold the full profile; other profiles override them.

    Attributes:
        name: ``full`` or ``quick`` (the run folder under ``runs/tables``).
        prefix: file prefix in ``benchmarks/results``.
        dam_scene: scene of the dam collapse rows (Tables 1/3, Fig. 5, trade-off).
        dam_duration: simulated seconds of those rows.
        frame_interval: seconds between compared frames (a multiple of every dt used).
        waterfall: overrides of the water-fall scene (its reduced size), None = no water-fall rows.
        waterfall_duration: simulated seconds of the water-fall rows.
        timing_scene: scene of Table 2.
        timing_warmup: steps run before the timed ones (lazy set-up, first neighbour list, PPE warm start).
        timing_steps: timed steps.
        table4_scene: scene of the advection sequences.
        table4_duration: simulated seconds per sequence.
        table4_materials: ``(g, nu)`` of the sequences.
        fig5_dts: time steps of Fig. 5, increasing; the sweep stops at the first run the guard stops.
        mps_dts: larger MPS time steps of the trade-off.
        ppe_tols: relative PPE tolerances of the trade-off's looser MPS rows.
        coarse: ``(factor, dt or None)`` of the trade-off's coarser MPS rows (l0 times factor).
        simulators: keys of the simulators in Tables 2/3 (None = all).
        figures: write evaluate's figures for the FGN dam row (paper Figs. 4 and 6).
        description: one line on what this profile reduces, printed in the report.
    """

    name: str
    prefix: str
    dam_scene: str
    dam_duration: float
    frame_interval: float
    waterfall: tuple[str, ...] | None
    waterfall_duration: float
    timing_scene: str
    timing_warmup: int
    timing_steps: int
    table4_scene: str
    table4_duration: float
    table4_materials: tuple[tuple[float, float], ...]
    fig5_dts: tuple[float, ...]
    mps_dts: tuple[float, ...]
    ppe_tols: tuple[float, ...]
    coarse: tuple[tuple[int, float | None], ...]
    simulators: tuple[str, ...] | None = None
    figures: bool = True
    description: str = ""


FULL = Profile(
    name="full",
    prefix="tables",
    dam_scene="dam",
    dam_duration=1.0,
    frame_interval=0.04,
    waterfall=("scene.scale=0.5",),
    waterfall_duration=0.6,
    timing_scene="dam_large",
    timing_warmup=5,
    timing_steps=10,
    table4_scene="dam_small",
    table4_duration=0.2,
    table4_materials=MATERIALS,
    fig5_dts=(0.0005, 0.001, 0.002, 0.0025, 0.004, 0.005, 0.008, 0.01, 0.02, 0.04),
    mps_dts=(0.004, 0.008),
    ppe_tols=(1e-3, 1e-2, 1e-1),
    coarse=((2, None), (2, 0.004)),
    description=(
        "dam collapse: the authors' 4,000-particle dam, 1 s (500 steps of 2 ms), frames every 40 ms; water "
        "fall at half size (scene.scale=0.5: 10,000 fluid particles at the same l0, every length halved; "
        "the paper's 80,000 cost ~5 s per MPS step here), 0.6 s; Table 2 on dam_large (40,000)"
    ),
)

QUICK = Profile(
    name="quick",
    prefix="tables_quick",
    dam_scene="dam_small",
    dam_duration=0.1,
    frame_interval=0.02,
    waterfall=("scene.scale=0.25",),
    waterfall_duration=0.04,
    timing_scene="dam_small",
    timing_warmup=2,
    timing_steps=5,
    table4_scene="dam_small",
    table4_duration=0.04,
    table4_materials=MATERIALS[::3],
    fig5_dts=(0.0005, 0.001, 0.002, 0.004, 0.01, 0.02),
    mps_dts=(0.004,),
    ppe_tols=(1e-2, 1e-1),
    coarse=((2, None),),
    description=(
        "QUICK profile (CI smoke run, not the paper's setting): dam_small (640 fluid particles) for 0.1 s, "
        "water fall at quarter size (1,200) for 0.04 s, Table 2 on dam_small (not ~40k), "
        "4 advection sequences of 0.04 s"
    ),
)

# Wall time per fluid particle per step of a row (rollout, evaluation and, for MPS, its reference),
# measured on the project's 2-core CPU machine (Intel Xeon, 2 torch threads, quiet) in the full run of
# 2026-12-01 (27.9 min): MPS 47 us on dam and 35 on the half-size water fall, FGN 19 and 17, the hybrids
# 20-35; row overhead ~1 s (the quick profile took 0.6 min). With these the full profile is estimated at
# 28 min; the estimate before the Verlet-skin fix (55 / 30 / 4 s) said 42.
_US_PER_PARTICLE_STEP = {"mps": 42.0, "learned": 18.0}
_ROW_OVERHEAD_S = 1.0
_FRAME_OVERHEAD_S_PER_1K = 0.03  # per stored frame and 1,000 fluid particles (metrics of model and MPS)


# ------------------------------------------------------------------------------------------- runs
@dataclass
class Run:
    """One row: what ran (experiment file and overrides) and what came out (evaluate's metrics.json)."""

    key: str
    label: str
    sim: Simulator
    experiment: str | None
    overrides: list[str]
    metrics: dict[str, Any] | None = None
    error: str = ""
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def command(self) -> str:
        """The ``python -m lagfluid.run`` line that reruns this row (the script's own paths included)."""
        head = [f"experiment={self.experiment}"] if self.experiment else []
        return " ".join(["python -m lagfluid.run", *head, *self.overrides])

    @property
    def ok(self) -> bool:
        """The run produced metrics (it may still have been stopped by the guard)."""
        return self.metrics is not None

    @property
    def complete(self) -> bool:
        """The run produced metrics and the rollout reached its last step."""
        return self.ok and bool(self.metrics.get("complete"))

    def summary(self, *keys: str) -> float:
        """A number of ``metrics["summary"]`` (NaN when absent), e.g. ``summary("chamfer_mm", "mean")``."""
        node: Any = (self.metrics or {}).get("summary", {})
        for k in keys:
            node = node.get(k) if isinstance(node, dict) else None
        return float(node) if isinstance(node, (int, float)) else math.nan


def row_file(name: str) -> str | None:
    """``name`` when ``conf/experiment/<name>.yaml`` exists (the row is defined there), else None."""
    return name if (CONF_DIR / "experiment" / f"{name}.yaml").is_file() else None


def compose_config(overrides: Sequence[str]) -> DictConfig:
    """The lagfluid config for ``overrides`` (as ``python -m lagfluid.run`` composes it)."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def steps_in(duration: float, dt: float, what: str) -> int:
    """``duration / dt`` as a whole number of steps.

    Raises:
        ConfigError: ``duration`` is not a multiple of ``dt`` (frames would not fall on common times).
    """
    n = round(duration / dt)
    if n < 1 or abs(n * dt - duration) > 1e-9 * max(1.0, duration):
        raise ConfigError(f"{what}: {duration} s is not a whole number of steps of dt = {dt} s")
    return n


def hydra_value(value: Any) -> str:
    """A Python value as a Hydra override value (nested dicts and lists, null)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, dict):
        return "{" + ",".join(f"{k}:{hydra_value(v)}" for k, v in value.items()) + "}"
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(hydra_value(v) for v in value) + "]"
    return repr(value) if isinstance(value, float) else str(value)


def coarsened_scene(scene: DictConfig, factor: int) -> dict[str, Any]:
    """The same physical dam at ``factor`` times the particle spacing: ``{l0, fluid_size, tank_size}``.

    The built scenes put the inner wall layers on x, y, z = 0 and ``tank_size * l0``, and a particle stands
    for a cube of side l0, so the fluid fills ``fluid_size * l0`` and the tank's inner surfaces are
    ``(tank_size - 1) * l0`` apart. Keeping both (and the wall height, ``2 * fluid_size[2]`` by default)
    gives the same physical scene, shifted by ``(factor - 1) * l0 / 2``, which :mod:`lagfluid.evaluate`
    undoes when it compares runs at different spacings.

    Raises:
        ConfigError: the scene has no ``fluid_size``/``tank_size`` (not a dam), or they do not divide.
    """
    if "fluid_size" not in scene or "tank_size" not in scene:
        raise ConfigError(f"scene {scene.name} has no fluid_size/tank_size: its resolution cannot be changed")
    fluid, tank = list(scene.fluid_size), list(scene.tank_size)
    if (
        scene.get("wall_height") is not None
        or any(f % factor for f in fluid)
        or any((t - 1) % factor for t in tank)
    ):
        raise ConfigError(
            f"scene {scene.name} (fluid_size {fluid}, tank_size {tank}, "
            f"wall_height {scene.get('wall_height')})"
            f" cannot be coarsened by {factor}: fluid_size and tank_size - 1 must be multiples of it"
        )
    return {
        "l0": float(scene.params.l0) * factor,
        "fluid_size": [f // factor for f in fluid],
        "tank_size": [(t - 1) // factor + 1 for t in tank],
    }


class Bench:
    """Runs rows once each (memoised by key) and keeps what every part needs."""

    def __init__(self, profile: Profile, args: argparse.Namespace) -> None:
        self.profile = profile
        self.threads = int(args.threads)
        self.weights = args.weights
        self.runs_dir = Path(args.runs_dir) / profile.name
        self.reference_dir = Path(args.runs_dir) / "reference"
        self.done: dict[str, Run] = {}
        self.scene_cache: dict[str, DictConfig] = {}

    # -------------------------------------------------------------- helpers
    def scene(self, name: str, extra: Sequence[str] = ()) -> DictConfig:
        """The composed scene config of ``scene=name`` (and ``extra`` scene overrides)."""
        key = " ".join([name, *extra])
        if key not in self.scene_cache:
            self.scene_cache[key] = compose_config([f"scene={name}", *extra]).scene
        return self.scene_cache[key]

    def model_overrides(self, sim: Simulator) -> list[str]:
        """Weights of a learned simulator: ``--weights`` (else the shipped ones) or the authors'."""
        if sim.model == "fgn_original":  # relative when possible: the commands in the report stay portable
            return [f"model.weights={os.path.relpath(AUTHORS_WEIGHTS)}"]
        if sim.learned and self.weights:
            return [f"model.weights={self.weights}"]
        return []

    def dam_overrides(
        self,
        scene: str,
        duration: float,
        dt: float | None = None,
        coarse: int = 1,
        extra: Sequence[str] = (),
    ) -> list[str]:
        """Scene, steps and frames of a dam-group row; ``evaluate.reference`` when dt or l0 differ.

        Every row of a group is compared with one MPS reference: the scene at its own dt and l0 for
        ``duration``, frames every ``profile.frame_interval``.
        """
        base = self.scene(scene, extra)
        base_dt = float(base.params.dt)
        run_dt = dt or base_dt
        frame = self.profile.frame_interval
        out = [f"scene={scene}", *extra]
        out += [f"steps={steps_in(duration, run_dt, 'duration')}"]
        out += [f"write_every={steps_in(frame, run_dt, 'frame interval')}"]
        reference: dict[str, Any] = {}
        if dt is not None and not math.isclose(dt, base_dt):
            out.append(f"dt={dt}")
            reference.update(
                dt=None,
                steps=steps_in(duration, base_dt, "duration"),
                write_every=steps_in(frame, base_dt, "frame interval"),
            )
        if coarse > 1:
            c = coarsened_scene(base, coarse)
            out += [
                f"scene.params.l0={c['l0']}",
                f"scene.fluid_size={hydra_value(c['fluid_size'])}",
                f"scene.tank_size={hydra_value(c['tank_size'])}",
            ]
            reference["scene"] = {
                "params": {"l0": float(base.params.l0)},
                "fluid_size": list(base.fluid_size),
                "tank_size": list(base.tank_size),
            }
        if reference:
            out.append(f"evaluate.reference={hydra_value(reference)}")
        return out

    # -------------------------------------------------------------- running rows
    def evaluate(self, run: Run, figures: bool = False, one_step: bool = True) -> Run:
        """Run ``task=evaluate`` for ``run`` once (memoised); a failure is recorded, not raised."""
        if run.key in self.done:
            return self.done[run.key]
        run.overrides = [
            *(["task=evaluate"] if not run.experiment else []),
            *([f"model={run.sim.model}"] if not run.experiment else []),
            *self.model_overrides(run.sim),
            *run.overrides,
            f"threads={self.threads}",
            "progress=false",
            f"evaluate.figures={hydra_value(figures)}",
            f"evaluate.one_step={hydra_value(one_step)}",
            f"evaluate.reference_dir={self.reference_dir}",
            f"out_dir={self.runs_dir / run.key.replace('/', '_')}",
        ]
        start = time.perf_counter()
        print(f"[tables] {run.key}: {run.command}", flush=True)
        try:
            cfg = compose_config(([f"experiment={run.experiment}"] if run.experiment else []) + run.overrides)
            if cfg.task != "evaluate":
                raise ConfigError(f"experiment {run.experiment} is task={cfg.task}, not evaluate")
            run.metrics = evaluate(cfg)
        except Exception as err:  # recorded: one failed row must not lose the hour of rows around it
            run.error = f"{type(err).__name__}: {err}".splitlines()[0]
            log.warning("row %s failed: %s", run.key, run.error)
        run.info["wall_s"] = time.perf_counter() - start
        state = "ok" if run.complete else ("stopped" if run.ok else "FAILED")
        print(f"[tables] {run.key}: {state} in {run.info['wall_s']:.1f} s {run.error}", flush=True)
        self.done[run.key] = run
        return run

    def time_steps(self, run: Run) -> Run:
        """Table 2: warm-up, then timed steps of ``run`` (no writer, no metrics), in this process."""
        if run.key in self.done:
            return self.done[run.key]
        p = self.profile
        run.overrides = [
            *self.model_overrides(run.sim),
            *run.overrides,
            f"scene={p.timing_scene}",
            f"steps={p.timing_steps}",
            f"threads={self.threads}",
            "progress=false",
        ]
        print(f"[tables] {run.key}: {run.command} (+{p.timing_warmup} warm-up steps)", flush=True)
        start = time.perf_counter()
        try:
            head = [f"experiment={run.experiment}"] if run.experiment else [f"model={run.sim.model}"]
            cfg = compose_config(head + run.overrides)
            torch.set_num_threads(self.threads)
            torch.manual_seed(int(cfg.seed))
            state = build_initial_state(cfg)
            sim = build_simulator(cfg)
            guard = Guard(float(cfg.solver.guard.max_courant), int(cfg.solver.guard.check_every))
            state, _ = rollout(sim, state, p.timing_warmup, guard=guard)
            state, record = rollout(sim, state, int(cfg.steps), guard=guard, reset=False)
            steps = record["step_seconds"]
            nns = record["stage_seconds"].get("neighbors", [0.0] * len(steps))
            networks = json.loads(sim.attributes().get("networks", "{}") or "{}")
            run.metrics = {
                "complete": True,
                "fluid": state.n_fluid,
                "particles": state.num_particles,
                "parameters": sum(int(n.get("parameters", 0)) for n in networks.values()) or None,
                "step_ms": 1e3 * median(steps),
                "neighbors_ms": 1e3 * median(nns),
                "inference_ms": 1e3 * median(s - n for s, n in zip(steps, nns, strict=True)),
                "stages_ms": {k: 1e3 * median(v) for k, v in record["stage_seconds"].items()},
                "timed_steps": len(steps),
            }
        except Exception as err:  # recorded: one failed row must not lose the hour of rows around it
            run.error = f"{type(err).__name__}: {err}".splitlines()[0]
            log.warning("row %s failed: %s", run.key, run.error)
        run.info["wall_s"] = time.perf_counter() - start
        print(f"[tables] {run.key}: {'ok' if run.ok else 'FAILED'} {run.error}", flush=True)
        self.done[run.key] = run
        return run

    # -------------------------------------------------------------- the rows of each part
    def table3_runs(self, case: str) -> list[Run]:
        """Tables 1/3 rows of ``case`` (``dam`` or ``waterfall``): every simulator against MPS."""
        p = self.profile
        if case == "dam":
            ov = self.dam_overrides(p.dam_scene, p.dam_duration)
        else:
            assert p.waterfall is not None
            ov = self.dam_overrides("waterfall", p.waterfall_duration, extra=p.waterfall)
        runs = []
        for sim in all_simulators(p.simulators):
            figures = p.figures and case == "dam" and sim.key == "fgn"
            run = Run(
                f"table3/{case}/{sim.key}", sim.label, sim, row_file(f"table3_{case}_{sim.key}"), list(ov)
            )
            runs.append(self.evaluate(run, figures=figures))
        return runs

    def table2_runs(self) -> list[Run]:
        """Table 2 rows: every simulator timed on the timing scene."""
        runs = []
        for sim in all_simulators(self.profile.simulators):
            runs.append(
                self.time_steps(Run(f"table2/{sim.key}", sim.label, sim, row_file(f"table2_{sim.key}"), []))
            )
        return runs

    def table4_runs(self) -> list[Run]:
        """Table 4's advection sequences: learned advection, exact collision and pressure, per (g, nu)."""
        p = self.profile
        sim = next(s for s in SIMULATORS if s.key == "hybrid_advection")
        base = self.scene(p.table4_scene)
        dt = float(base.params.dt)
        steps = steps_in(p.table4_duration, dt, "table4 duration")
        every = max(1, steps // 10)
        runs = []
        for g, nu in p.table4_materials:
            ov = [
                f"scene={p.table4_scene}",
                f"steps={steps}",
                f"write_every={every}",
                f"scene.params.gravity=[0.0,0.0,{-g}]",
                f"scene.params.viscosity={nu}",
            ]
            run = Run(
                f"table4/g{g:g}_nu{nu:g}", f"g = {g:g}, nu = {nu:g}", sim, row_file("table4_advection"), ov
            )
            run.info["material"] = (g, nu)
            runs.append(self.evaluate(run))
        return runs

    def fig5_runs(self) -> tuple[list[Run], float | None, float | None]:
        """FGN at increasing dt until the guard stops one.

        Returns:
            The runs, the largest dt that completed, and the first dt that did not (None: all completed).
        """
        p = self.profile
        sim = next(s for s in SIMULATORS if s.key == "fgn")
        base_dt = float(self.scene(p.dam_scene).params.dt)
        runs: list[Run] = []
        stable, stopped = None, None
        for dt in p.fig5_dts:
            if math.isclose(dt, base_dt):  # the Table 3 row itself
                run = self.table3_fgn_dam()
            else:
                ov = self.dam_overrides(p.dam_scene, p.dam_duration, dt=dt)
                label = f"FGN dt = {1e3 * dt:g} ms"
                run = self.evaluate(Run(f"fig5/fgn_dt{dt:g}", label, sim, row_file("fig5_fgn"), ov))
            run.info["dt"] = dt
            runs.append(run)
            if not run.ok:
                continue
            if not run.complete:
                stopped = dt
                break  # larger steps only move particles farther per step
            stable = dt
        return runs, stable, stopped

    def table3_fgn_dam(self) -> Run:
        """The FGN dam row of Table 3 (also Fig. 5's point at the scene's dt and a trade-off point)."""
        key = "table3/dam/fgn"
        if key not in self.done:
            self.table3_runs("dam")
        return self.done[key]

    def tradeoff_runs(self) -> list[Run]:
        """MPS at looser PPE tolerances, larger dt and a coarser spacing.

        The trade-off's other points are the dam rows of Table 3 and Fig. 5.
        """
        p = self.profile
        mps = SIMULATORS[0]
        runs = []
        for tol in p.ppe_tols:
            ov = self.dam_overrides(p.dam_scene, p.dam_duration)
            ov += ["solver.ppe.tol_mode=rel", f"solver.ppe.tol={tol}"]
            ov += ["evaluate.reference={solver:{ppe:{tol_mode:abs,tol:1.0e-06}}}"]
            exp = row_file(f"tradeoff_dam_mps_ppe_rel_{tol:.0e}".replace("e-0", "e-"))
            runs.append(
                self.evaluate(
                    Run(f"tradeoff/mps_ppe_rel_{tol:g}", f"MPS PPE tol {tol:g} (rel)", mps, exp, ov)
                )
            )
        for dt in p.mps_dts:
            ov = self.dam_overrides(p.dam_scene, p.dam_duration, dt=dt)
            exp = row_file(f"tradeoff_dam_mps_dt_{1e3 * dt:g}ms")
            runs.append(
                self.evaluate(Run(f"tradeoff/mps_dt{dt:g}", f"MPS dt = {1e3 * dt:g} ms", mps, exp, ov))
            )
        for factor, dt in p.coarse:
            try:
                ov = self.dam_overrides(p.dam_scene, p.dam_duration, dt=dt, coarse=factor)
            except ConfigError as err:
                run = Run(f"tradeoff/mps_coarse{factor}", f"MPS l0 x {factor}", mps, None, [], error=str(err))
                self.done[run.key] = run
                runs.append(run)
                continue
            l0 = float(self.scene(p.dam_scene).params.l0) * factor
            label = f"MPS l0 = {1e2 * l0:g} cm" + (f", dt = {1e3 * dt:g} ms" if dt else "")
            exp = row_file(f"tradeoff_dam_mps_l0_{1e2 * l0:g}cm" + (f"_dt_{1e3 * dt:g}ms" if dt else ""))
            run = Run(f"tradeoff/mps_l0_{l0:g}" + (f"_dt{dt:g}" if dt else ""), label, mps, exp, ov)
            run.info["coarse"] = factor
            runs.append(self.evaluate(run))
        return runs


# ------------------------------------------------------------------------------------------- table rows
def fmt(value: Any, digits: int = 3) -> str:
    """A table cell: ``digits`` significant digits for floats, '-' for missing values."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}g}" if abs(value) < 10**digits else f"{value:,.0f}"
    return str(value)


def md_table(header: Sequence[str], rows: Sequence[Sequence[Any]], align: str | None = None) -> str:
    """A markdown table; ``align`` gives l, r or c per column (default: first left, others right)."""
    align = align or "l" + "r" * (len(header) - 1)
    sep = [{"l": "---", "r": "---:", "c": ":---:"}[a] for a in align]
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join(sep) + " |"]
    lines += ["| " + " | ".join(c if isinstance(c, str) else fmt(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def status(run: Run) -> str:
    """How a row ended, for the tables: complete, stopped (by the guard, where) or failed (why)."""
    if not run.ok:
        return f"failed: {run.error}"
    if not run.complete:
        # the guard's message without its coordinates and advice: "step 12: fluid particle 3 left the domain"
        reason = re.split(r" at \[| \[|; | \(", str(run.metrics.get("stop_reason", "")))[0]
        return f"stopped: {reason}"
    return "complete"


def seconds_per_simulated_second(run: Run) -> float:
    """Wall seconds of the steps over the simulated seconds they covered (NaN without steps)."""
    m = run.metrics or {}
    steps, dt = int(m.get("steps") or 0), float(m.get("dt") or 0.0)
    total = float((m.get("timing") or {}).get("steps_total_s", math.nan))
    return total / (steps * dt) if steps and dt else math.nan


def chamfer_at_start(run: Run) -> float:
    """The Chamfer distance at t = 0 (mm): 0 at the reference's spacing, the lattice offset otherwise."""
    values = ((run.metrics or {}).get("frames") or {}).get("chamfer_mm") or []
    return float(values[0]) if values and values[0] is not None else math.nan


def provenance_columns(run: Run) -> dict[str, Any]:
    """Where a row's numbers come from: its experiment file, overrides, commit and time of the run."""
    return {
        "experiment": run.experiment or "",
        "overrides": " ".join(run.overrides),
        "git_commit": (run.metrics or {}).get("git_commit", ""),
        "created": (run.metrics or {}).get("created", ""),
    }


def table3_rows(case: str, runs: list[Run]) -> list[dict[str, Any]]:
    """CSV rows of Tables 1/3: every simulator; MPS's row is the ground truth's own field metrics."""
    rows = []
    for run in runs:
        is_gt = run.sim.key == "mps"
        who = "reference" if is_gt else "model"
        rows.append(
            {
                "case": case,
                "simulator": "Ground truth (MPS)" if is_gt else run.label,
                "density_error_mean": run.summary("density_error", who, "mean"),
                "density_error_max": run.summary("density_error", who, "max"),
                "divergence_mean_per_s": run.summary("velocity_divergence_per_s", who, "mean"),
                "divergence_max_per_s": run.summary("velocity_divergence_per_s", who, "max"),
                "chamfer_mean_mm": math.nan if is_gt else run.summary("chamfer_mm", "mean"),
                "chamfer_max_mm": math.nan if is_gt else run.summary("chamfer_mm", "max"),
                "fluid_particles": ((run.metrics or {}).get("particles") or {}).get("fluid"),
                "steps": (run.metrics or {}).get("steps"),
                "status": status(run),
                **provenance_columns(run),
            }
        )
    return rows


def table2_rows(runs: list[Run]) -> list[dict[str, Any]]:
    """CSV rows of Table 2, with each simulator's speed-up over MPS (time per step ratio)."""
    mps_ms = next((r.metrics["step_ms"] for r in runs if r.sim.key == "mps" and r.ok), math.nan)
    rows = []
    for run in runs:
        m = run.metrics or {}
        rows.append(
            {
                "simulator": run.label,
                "parameters": m.get("parameters"),
                "fluid_particles": m.get("fluid"),
                "step_ms": m.get("step_ms", math.nan),
                "inference_ms": m.get("inference_ms", math.nan),
                "neighbor_search_ms": m.get("neighbors_ms", math.nan),
                "speedup_vs_mps": ratio(mps_ms, m.get("step_ms", math.nan)),
                "stages_ms": " ".join(f"{k}={v:.1f}" for k, v in (m.get("stages_ms") or {}).items()),
                "status": "complete" if run.ok else f"failed: {run.error}",
                **provenance_columns(run),
            }
        )
    return rows


def mean_std(values: Sequence[float | None]) -> tuple[float, float, int]:
    """Mean and (population) standard deviation of the finite values, and how many there were."""
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], dtype=float)
    if not v.size:
        return math.nan, math.nan, 0
    return float(v.mean()), float(v.std()), int(v.size)


def table4_rows(adv_runs: list[Run], pressure_runs: list[Run]) -> list[dict[str, Any]]:
    """CSV rows of Table 4: advection nMAE per sequence and over the sequences; PPE residual over frames."""
    rows: list[dict[str, Any]] = []
    for run in adv_runs:
        g, nu = run.info["material"]
        frames = ((run.metrics or {}).get("frames") or {}).get("advection_nmae", [])
        mean, std, n = mean_std(frames)
        rows.append(
            {
                "network": "advection",
                "case": f"g={g:g} nu={nu:g}",
                "metric": "normalised MAE (eq. 32): mean +- std over the stored steps",
                "mean": mean,
                "std": std,
                "n": n,
                "status": status(run),
                **provenance_columns(run),
            }
        )
    mean, std, n = mean_std([r["mean"] for r in rows])
    rows.append(
        {
            "network": "advection",
            "case": "all sequences",
            "metric": "normalised MAE (eq. 32): mean +- std of the sequences' means",
            "mean": mean,
            "std": std,
            "n": n,
            "status": "",
            **provenance_columns(Run("", "", SIMULATORS[0], "table4_advection", [])),
        }
    )
    for run in pressure_runs:
        frames = ((run.metrics or {}).get("frames") or {}).get("ppe_relative_residual", [])
        mean, std, n = mean_std(frames)
        rows.append(
            {
                "network": "pressure",
                "case": f"{run.label}, dam",
                "metric": "PPE relative residual (eq. 31): mean +- std over the stored steps",
                "mean": mean,
                "std": std,
                "n": n,
                "status": status(run),
                **provenance_columns(run),
            }
        )
    return rows


def tradeoff_rows(runs: list[Run]) -> list[dict[str, Any]]:
    """CSV rows of the trade-off with their Pareto flags (only complete runs can be on a front)."""
    rows = []
    for run in runs:
        m = run.metrics or {}
        timing = m.get("timing") or {}
        rows.append(
            {
                "simulator": run.label,
                "s_per_simulated_s": seconds_per_simulated_second(run),
                "ms_per_step_median": 1e3 * float(timing.get("time_per_step_median_s", math.nan)),
                "chamfer_mean_mm": run.summary("chamfer_mm", "mean"),
                "chamfer_max_mm": run.summary("chamfer_mm", "max"),
                "chamfer_t0_mm": chamfer_at_start(run),
                "density_error_mean": run.summary("density_error", "model", "mean"),
                "divergence_mean_per_s": run.summary("velocity_divergence_per_s", "model", "mean"),
                "dt_s": m.get("dt"),
                "fluid_particles": (m.get("particles") or {}).get("fluid"),
                "steps": m.get("steps"),
                "reference": (m.get("reference") or {}).get("key_hash", ""),
                "status": status(run),
                **provenance_columns(run),
            }
        )
    for metric in TRADEOFF_METRICS:
        points = [
            (r["s_per_simulated_s"], r[metric]) if r["status"] == "complete" else (math.nan,) * 2
            for r in rows
        ]
        front = set(pareto_front(points))
        for i, r in enumerate(rows):
            r[f"pareto_{metric}"] = i in front
    return rows


TRADEOFF_METRICS = ("chamfer_mean_mm", "density_error_mean")


# ------------------------------------------------------------------------------------------- figures
def plot_fig5(path: Path, runs: list[Run], verdict: str, title: str) -> None:
    """Paper Fig. 5: FGN's Chamfer distance to MPS against time, one line per dt (dotted: stopped)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    fig.subplots_adjust(left=0.1, right=0.97, bottom=0.12, top=0.88)
    shown = [r for r in runs if r.ok]
    cmap = plt.get_cmap("viridis")
    for i, run in enumerate(shown):
        frames = run.metrics["frames"]
        t = np.asarray(frames["time_s"], dtype=float)
        y = np.asarray([np.nan if v is None else v for v in frames["chamfer_mm"]], dtype=float)
        label = f"dt = {1e3 * run.info['dt']:g} ms" + ("" if run.complete else " (stopped)")
        colour = cmap(i / max(1, len(shown) - 1))
        ax.plot(
            t, y, "-" if run.complete else ":", color=colour, label=label, marker="." if len(t) < 30 else None
        )
    ax.set_xlabel("time (s)")
    ax.set_ylabel("Chamfer distance to MPS (mm)")
    ax.set_title(f"{title}\n{verdict}", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _colour(name: str) -> str:
    if "authors" in name:
        return "C1"
    if "hybrid" in name:
        return "C2"
    return "k" if name.startswith("MPS") else "C0"


def plot_tradeoff(path: Path, rows: list[dict[str, Any]], title: str) -> None:
    """Wall seconds per simulated second (log x) against the Chamfer distance and the density error.

    Points are numbered (the key beside the panels names them), the Pareto front is a staircase: at any
    cost on the x axis, the front's height is the smallest error a run at most that expensive achieved.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    done = [r for r in rows if r["status"] == "complete" and math.isfinite(r["s_per_simulated_s"])]
    done.sort(key=lambda r: r["s_per_simulated_s"])
    fig, axes = plt.subplots(1, 2, figsize=(15, 6.2))
    fig.subplots_adjust(left=0.05, right=0.8, bottom=0.1, top=0.86, wspace=0.2)
    panels = (
        ("chamfer_mean_mm", "Chamfer distance to the reference MPS, mean over frames (mm)", "symlog"),
        ("density_error_mean", "density error, mean over frames", "log"),
    )
    x_max = max((r["s_per_simulated_s"] for r in done), default=1.0)
    for ax, (metric, ylabel, yscale) in zip(axes, panels, strict=True):
        for number, r in enumerate(done, start=1):
            colour = _colour(r["simulator"])
            hollow = math.isfinite(r["chamfer_t0_mm"]) and r["chamfer_t0_mm"] > 0
            x, y = r["s_per_simulated_s"], r[metric]
            ax.scatter(x, y, s=36, facecolors="none" if hollow else colour, edgecolors=colour, zorder=3)
            ax.annotate(str(number), (x, y), fontsize=8, xytext=(4, 3), textcoords="offset points")
        front = [r for r in done if r[f"pareto_{metric}"]]
        if front:
            # a staircase carried on to the right: no budget beyond the last point buys more accuracy
            xs = [r["s_per_simulated_s"] for r in front] + [1.3 * x_max]
            ys = [r[metric] for r in front] + [front[-1][metric]]
            ax.step(xs, ys, where="post", color="C3", lw=1.5, label="Pareto front", zorder=2)
            ax.legend(loc="upper right", fontsize=8)
        ax.set_xscale("log")
        values = [r[metric] for r in done if math.isfinite(r[metric])]
        positive = [v for v in values if v > 0]
        if yscale == "symlog":  # MPS against itself is exactly 0: linear below the smallest positive error
            ax.set_yscale("symlog", linthresh=min(positive, default=1e-3))
            ax.set_ylim(0.0, 2.0 * max(values, default=1.0))
        elif positive:
            ax.set_yscale("log")
            ax.set_ylim(0.7 * min(positive), 1.5 * max(positive))
        ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("wall seconds per simulated second (log)")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3, which="both")
    key = "\n".join(f"{i:2d}  {r['simulator']}" for i, r in enumerate(done, start=1))
    fig.text(0.815, 0.86, key, fontsize=8, va="top", family="monospace")
    sub = "black: MPS, blue: FGN, green: hybrids, orange: authors' FGN; hollow: coarser spacing (its Chamfer "
    sub += "includes the lattice offset at t = 0)"
    stopped = [r["simulator"] for r in rows if r not in done]
    if stopped:
        sub += "\nnot shown (stopped or failed): " + ", ".join(stopped)
    fig.suptitle(f"{title}\n{sub}", fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ------------------------------------------------------------------------------------------- outputs
def ratio(a: float | None, b: float | None) -> float:
    """``a / b``; NaN when either is missing or ``b`` is 0."""
    if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)) or b == 0:
        return math.nan
    return a / b


def write_csv(path: Path, rows: list[dict[str, Any]], meta: dict[str, str]) -> None:
    """Rows as CSV, each with the run-wide provenance columns (machine, date, the script's commit)."""
    if not rows:
        return
    rows = [{**r, **meta} for r in rows]
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})


def cpu_model() -> str:
    """The CPU's model name (Linux /proc/cpuinfo; the platform's processor string elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def estimate_seconds(profile: Profile, parts: Sequence[str] = PARTS) -> float:
    """Expected runtime of ``parts`` of ``profile`` from the per-particle-step costs measured on this machine.

    Follows :func:`run_all`: the dam rows run for every part but Table 2, Fig. 5's rows for Fig. 5 and the
    trade-off.
    """
    parts = set(parts)
    sims = len(all_simulators(profile.simulators))
    mps, learned = (_US_PER_PARTICLE_STEP[k] * 1e-6 for k in ("mps", "learned"))
    dt = 0.002

    def fluid(scene: str, extra: Sequence[str] = ()) -> int:
        if scene == "waterfall":
            scale = next((float(e.split("=")[1]) for e in extra if e.startswith("scene.scale=")), 1.0)
            return round(80000 * scale**3)
        return {"dam": 4000, "dam_small": 640, "dam_medium": 10000, "dam_large": 40000}.get(scene, 4000)

    def row(n: int, steps: int, frames: int, cost: float) -> float:
        return steps * n * cost + _ROW_OVERHEAD_S + frames * n / 1000 * _FRAME_OVERHEAD_S_PER_1K

    def group(n: int, duration: float) -> float:
        steps, frames = round(duration / dt), round(duration / profile.frame_interval) + 1
        return steps * n * mps + row(n, steps, frames, mps) + (sims - 1) * row(n, steps, frames, learned)

    p = profile
    n = fluid(p.dam_scene)
    frames = round(p.dam_duration / p.frame_interval) + 1
    total = 0.0
    if parts - {"table2"}:
        total += group(n, p.dam_duration)
    if "tradeoff" in parts:
        total += len(p.ppe_tols) * row(n, round(p.dam_duration / dt), frames, mps)
        total += sum(row(n, round(p.dam_duration / d), frames, mps) for d in p.mps_dts)
        total += sum(row(n // f**3, round(p.dam_duration / (d or dt)), frames, mps) for f, d in p.coarse)
    if parts & {"fig5", "tradeoff"}:
        total += sum(row(n, round(p.dam_duration / d), frames, learned) for d in p.fig5_dts if d != dt)
    if "table3" in parts and p.waterfall:
        total += group(fluid("waterfall", p.waterfall), p.waterfall_duration)
    if "table2" in parts:
        nt = fluid(p.timing_scene)
        total += (p.timing_warmup + p.timing_steps) * nt * (mps + (sims - 1) * learned) + 2 * sims
    if "table4" in parts:
        n4, s4 = fluid(p.table4_scene), round(p.table4_duration / dt)
        total += len(p.table4_materials) * (s4 * n4 * mps + row(n4, s4, 11, mps))
    return total


def write_readme(section: str, readme: Path = README) -> bool:
    """Replace the text between the README's table markers with ``section``; False when it has none."""
    text = readme.read_text()
    if MARK_START not in text or MARK_END not in text:
        log.warning("%s has no %s ... %s markers: README not updated", readme, MARK_START, MARK_END)
        return False
    head, rest = text.split(MARK_START, 1)
    _, tail = rest.split(MARK_END, 1)
    readme.write_text(f"{head}{MARK_START}\n{section.strip()}\n{MARK_END}{tail}")
    return True


def merge_parts(
    report: Report, partial: bool, commands: dict[str, str], invocation: str = ""
) -> dict[str, dict[str, str]]:
    """This run's report sections and README pieces, over those an earlier run saved (``--only`` reruns).

    Every run saves what it rendered to ``<prefix>_parts.json`` with the date and commit of the run that
    made each piece, so that ``--only table2`` (say, on a quieter machine) replaces Table 2 and keeps the
    other parts, each still saying when it was run. A full run starts afresh. ``history`` keeps each run's
    command and runtime, so the report still says what made the parts an ``--only`` run kept.

    Args:
        report: this run's rendered parts.
        partial: an ``--only`` run (merge with the saved parts) rather than a full one.
        commands: this run's rows, ``{row key: command}``.
        invocation: this run's command and runtime, for the history.

    Returns:
        ``{"sections": {part: markdown}, "readme": {piece: markdown}, "runs": {key: "date at commit"},
        "commands": {row key: command}, "history": {"date at commit": invocation}}``.
    """
    path = Path(f"{report.prefix}_parts.json")
    merged: dict[str, dict[str, str]] = {
        "sections": {},
        "readme": {},
        "runs": {},
        "commands": {},
        "history": {},
    }
    if partial and not path.is_file():
        raise ConfigError(
            f"--only reruns parts of an earlier run, but {path} is missing: run the whole profile first "
            "(without --only), or the other parts would vanish from the report and the README"
        )
    if partial:
        try:
            saved = json.loads(path.read_text())
            merged = {k: dict(saved.get(k, {})) for k in merged}
        except (OSError, ValueError) as err:
            log.warning("%s unreadable (%s): only this run's parts are written", path, err)
    run = f"{report.meta['date']} at commit {report.meta['script_commit']}"
    for kind in ("sections", "readme"):
        for key, text in getattr(report, kind).items():
            merged[kind][key] = text
            merged["runs"][f"{kind}:{key}"] = run
    merged["commands"].update(commands)
    merged["history"][run] = invocation
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(json.dumps(merged, indent=1))
    os.replace(tmp, path)
    report.files.append(path)
    return merged


def earlier_parts(merged: dict[str, dict[str, str]], kind: str, run: str) -> str:
    """A line naming the pieces of ``kind`` that come from earlier runs than ``run`` ('' when none)."""
    older = {k.split(":", 1)[1]: v for k, v in merged["runs"].items() if k.startswith(kind) and v != run}
    if not older:
        return ""
    return (
        "Parts from earlier runs (`--only` reran the others): "
        + "; ".join(f"{k}: {v}" for k, v in sorted(older.items()))
        + ".\n\n"
    )


@dataclass
class Report:
    """What a run of the script writes: CSV files, report sections, README pieces."""

    prefix: Path
    meta: dict[str, str]
    sections: dict[str, str] = field(default_factory=dict)
    readme: dict[str, str] = field(default_factory=dict)
    files: list[Path] = field(default_factory=list)
    rows: dict[str, list[dict[str, Any]]] = field(default_factory=dict)

    def path(self, suffix: str) -> Path:
        """``<prefix>_<suffix>`` (e.g. ``tables_quick_tradeoff.png``), remembered as written."""
        path = Path(f"{self.prefix}_{suffix}")
        self.files.append(path)
        return path

    def csv(self, name: str, rows: list[dict[str, Any]]) -> None:
        """Write ``<prefix>_<name>.csv`` with the run-wide provenance columns."""
        write_csv(self.path(f"{name}.csv"), rows, self.meta)
        self.rows[name] = rows


# ------------------------------------------------------------------------------------------- the parts
def part_table2(bench: Bench, report: Report) -> None:
    """Table 2: parameters and time per step, every simulator, one after another in this process."""
    p = bench.profile
    rows = table2_rows(bench.table2_runs())
    report.csv("table2", rows)
    cells = [
        [
            r["simulator"],
            r["parameters"],
            r["fluid_particles"],
            r["step_ms"],
            r["inference_ms"],
            r["neighbor_search_ms"],
            r["speedup_vs_mps"],
            r["status"],
        ]
        for r in rows
    ]
    header = [
        "simulator",
        "parameters",
        "fluid",
        "ms/step",
        "inference ms",
        "NNS ms",
        "MPS time / time",
        "status",
    ]
    paper = [[k, v[0], v[1], v[2]] for k, v in PAPER_TABLE2.items()]
    report.sections["table2"] = (
        f"## Table 2: time per step on `{p.timing_scene}`\n\n"
        f"Median over {p.timing_steps} steps after {p.timing_warmup} warm-up steps, every simulator in this "
        "process one after another. NNS: the neighbour search (Verlet list update and filtering); inference: "
        "the rest of the step (networks or exact stages, pressure gradient, update). Parameters: trainable "
        f"parameters of the learned stages. Machine: {report.meta['machine']}.\n\n"
        f"{md_table(header, cells, 'lrrrrrrl')}\n\nThe paper's Table 2 (a GPU, ~40k particles):\n\n"
        f"{md_table(['paper', 'parameters', 'inference ms', 'NNS ms'], paper)}\n"
    )
    fgn = next((r for r in rows if r["simulator"] == "FGN"), None)
    mps = next((r for r in rows if r["simulator"] == "MPS"), None)
    if fgn and mps:
        paper_ratio = (313.2 + 42.3) / (5.7 + 46.4)
        cells = [
            ["FGN, ours", fgn["parameters"], fgn["inference_ms"], fgn["neighbor_search_ms"], fgn["step_ms"]],
            ["MPS, ours", "-", mps["inference_ms"], mps["neighbor_search_ms"], mps["step_ms"]],
            ["FGN, paper (GPU)", 41996, 5.7, 46.4, 5.7 + 46.4],
            ["MPS, paper (GPU)", "-", 313.2, 42.3, 313.2 + 42.3],
        ]
        report.readme["table2"] = (
            f"**Table 2** (`{p.timing_scene}`, {fmt(mps['fluid_particles'])} fluid particles; "
            f"{report.meta['machine']}):\n\n"
            + md_table(["", "parameters", "inference ms", "NNS ms", "step ms"], cells)
            + f"\n\n- MPS / FGN time per step: ours {fmt(fgn['speedup_vs_mps'])}, paper {fmt(paper_ratio)} "
            f"(inference alone: ours {fmt(ratio(mps['inference_ms'], fgn['inference_ms']))}, paper "
            f"{fmt(313.2 / 5.7)}).\n"
        )


def part_table3(bench: Bench, report: Report, dam_runs: list[Run]) -> None:
    """Tables 1 and 3: accuracy of every simulator against MPS on the dam and the water fall."""
    p = bench.profile
    rows = table3_rows("dam", dam_runs)
    if p.waterfall:
        rows += table3_rows("waterfall", bench.table3_runs("waterfall"))
    report.csv("table3", rows)
    cases = {
        "dam": f"`{p.dam_scene}`, {p.dam_duration:g} s",
        "waterfall": f"`waterfall` {' '.join(p.waterfall or ())}, {p.waterfall_duration:g} s",
    }
    keys = ("density_error_mean", "density_error_max", "divergence_mean_per_s", "divergence_max_per_s")
    keys += ("chamfer_mean_mm", "chamfer_max_mm")
    header = ["density error mean", "max", "divergence mean (1/s)", "max", "Chamfer mean (mm)", "max"]
    cells = [[cases[r["case"]], r["simulator"], *(r[k] for k in keys), r["status"]] for r in rows]
    report.sections["table3"] = (
        "## Tables 1 and 3: accuracy against MPS\n\n"
        "`task=evaluate` for every simulator: the same initial state, MPS as the reference. Density error "
        "and divergence over the stored frames (mean and max); Chamfer distance (eq. 29) to MPS at the same "
        "time, mean and max over the frames. The MPS row is the ground truth's own density error and "
        "divergence.\n\n"
        + md_table(["case", "simulator", *header, "status"], cells, "ll" + "r" * 6 + "l")
        + "\n"
    )
    ours, lines = [], []
    for case in ("dam", "waterfall"):
        fgn = next((r for r in rows if r["case"] == case and r["simulator"] == "FGN"), None)
        gt = next((r for r in rows if r["case"] == case and r["simulator"].startswith("Ground")), None)
        p_fgn, p_gt = PAPER_TABLE1[(case, "FGN")], PAPER_TABLE1[(case, "Ground truth")]
        ours += [[case, "FGN, paper", *p_fgn], [case, "Ground truth, paper", *p_gt]]
        for who, r in (("FGN, ours", fgn), ("Ground truth (MPS), ours", gt)):
            if r:
                ours.append([case, who, *(r[k] for k in keys)])
        if fgn and gt:
            lines.append(
                f"- {case}: FGN / MPS density error {fmt(ratio(fgn[keys[0]], gt[keys[0]]))} (paper "
                f"{fmt(p_fgn[0] / p_gt[0])}), divergence {fmt(ratio(fgn[keys[2]], gt[keys[2]]))} (paper "
                f"{fmt(p_fgn[2] / p_gt[2])}); FGN's Chamfer distance to MPS {fmt(fgn[keys[4]])} mm (paper "
                f"{p_fgn[4]} mm); FGN {fgn['status']}."
            )
    ours.sort(key=lambda r: (r[0], "paper" in r[1], r[1]))
    report.readme["table1"] = (
        f"**Table 1** (dam: {cases['dam']}; "
        f"water fall: {cases['waterfall'] if p.waterfall else 'not run'}):\n\n"
        + md_table(["case", "", *header], ours, "ll" + "r" * 6)
        + "\n\n"
        + "\n".join(lines)
        + "\n"
    )


def part_fig5(bench: Bench, report: Report, fig5: tuple[list[Run], float | None, float | None]) -> None:
    """Fig. 5: FGN's Chamfer distance against time for increasing dt; the largest dt that completes."""
    p = bench.profile
    runs, stable, stopped = fig5
    frames = [((r.metrics or {}).get("frames") or {}).get("chamfer_mm") or [None] for r in runs]
    rows = [
        {
            "dt_s": r.info["dt"],
            "steps": (r.metrics or {}).get("steps"),
            "chamfer_mean_mm": r.summary("chamfer_mm", "mean"),
            "chamfer_max_mm": r.summary("chamfer_mm", "max"),
            "chamfer_last_mm": math.nan if f[-1] is None else float(f[-1]),
            "density_error_mean": r.summary("density_error", "model", "mean"),
            "status": status(r),
            **provenance_columns(r),
        }
        for r, f in zip(runs, frames, strict=True)
    ]
    report.csv("fig5", rows)
    verdict = fig5_verdict(p.dam_duration, runs, stable, stopped)
    png = report.path("fig5.png")
    plot_fig5(png, runs, verdict, f"FGN vs MPS on {p.dam_scene} at several dt ({p.name} profile)")

    def tail(r: dict[str, Any]) -> list[Any]:
        return [r["chamfer_last_mm"], r["density_error_mean"], r["status"]]

    cells = [
        [fmt(1e3 * r["dt_s"]), *(r[k] for k in ("steps", "chamfer_mean_mm", "chamfer_max_mm")), *tail(r)]
        for r in rows
    ]
    header = ["dt (ms)", "steps", "Chamfer mean (mm)", "max", "at the end", "density error mean", "status"]
    report.sections["fig5"] = (
        "## Fig. 5: FGN at other time steps\n\n"
        f"FGN rolled out at each dt for {p.dam_duration:g} s against the MPS reference at the scene's dt, "
        f"frames matched by time every {1e3 * p.frame_interval:g} ms. The sweep stops at the first dt the "
        "rollout guard stops (NaN, a particle leaving the domain, or a Courant number max|v| dt / l0 above "
        f"`solver.guard.max_courant`, 0.5); {verdict}.\n\n"
        f"{md_table(header, cells, 'rrrrrrl')}\n\n![Fig. 5]({png.name})\n"
    )
    report.readme["fig5"] = f"**Fig. 5**: {verdict} (paper: FGN converges for every dt < 5 ms).\n"


def fig5_verdict(duration: float, runs: list[Run], stable: float | None, stopped: float | None) -> str:
    """One line on Fig. 5's sweep: the largest dt that completed and what stopped the next one."""
    if stable is None and stopped is None:
        return "no dt produced a rollout (every row failed, see the table)"
    text = f"largest dt whose {duration:g} s rollout completes: {fmt(1e3 * stable) if stable else 'none'} ms"
    if stopped is not None:
        why = next((status(r).removeprefix("stopped: ") for r in runs if r.info.get("dt") == stopped), "")
        return text + f"; the rollout guard stopped dt = {1e3 * stopped:g} ms ({why})"
    failed = [r.info["dt"] for r in runs if not r.ok]
    if failed:
        return text + f"; dt = {', '.join(f'{1e3 * d:g}' for d in failed)} ms failed (see the table)"
    return text + " (every dt tried completed; the largest tried is a lower bound)"


def part_table4(bench: Bench, report: Report, dam_runs: list[Run]) -> None:
    """Table 4: the advection net on held-out materials, the pressure net as a PPE solver."""
    p = bench.profile
    adv = bench.table4_runs()
    # fgn_original: the authors' pressure net in the same metric, a yardstick for the paper's 8.3 %
    pressure = [r for r in dam_runs if r.sim.key in ("hybrid_pressure", "fgn", "fgn_original")]
    rows = table4_rows(adv, pressure)
    report.csv("table4", rows)
    cells = [[r["network"], r["case"], r["mean"], r["std"], r["n"], r["status"]] for r in rows]
    report.sections["table4"] = (
        "## Table 4: the networks as stand-alone solvers\n\n"
        f"Advection: {len(adv)} sequences on `{p.table4_scene}` ({p.table4_duration:g} s each) with held-out "
        "gravity g (m/s^2) and viscosity nu (m^2/s), rolled out with learned advection and exact collision "
        "and pressure (`table4_advection`); at every stored step the network's acceleration is compared with "
        "`g + nu lap(v)` at the same input (normalised MAE, eq. 32). Pressure: the network's pressure in the "
        "exact PPE at its own input (relative residual, eq. 31) over the stored steps of the dam rows "
        "(hybrid: exact advection and collision, so its input is MPS's; FGN: its own rollout).\n\n"
        + md_table(["network", "case", "mean", "std", "n", "status"], cells, "llrrrl")
        + f"\n\nPaper: advection {PAPER_TABLE4['advection'][0]} % +- {PAPER_TABLE4['advection'][1]} %, "
        f"pressure {PAPER_TABLE4['pressure'][0]} % +- {PAPER_TABLE4['pressure'][1]} %.\n"
    )

    def pct(r: dict[str, Any]) -> str:
        return f"{fmt(100 * r['mean'])} % +- {fmt(100 * r['std'])} %"

    adv_all = next(r for r in rows if r["case"] == "all sequences")
    cells = [
        ["advection", f"normalised MAE, {adv_all['n']} held-out (g, nu)", pct(adv_all), "12.4 % +- 5.6 %"]
    ]
    cells += [
        ["pressure", f"PPE relative residual, {r['case']}", pct(r), "8.3 % +- 1.1 %"]
        for r in rows
        if r["network"] == "pressure"
    ]
    report.readme["table4"] = (
        "**Table 4** (mean +- std):\n\n"
        + md_table(["network", "metric", "ours", "paper"], cells, "llrr")
        + "\n"
    )


def part_tradeoff(bench: Bench, report: Report, dam_runs: list[Run], fig5_runs: list[Run]) -> None:
    """The speed/accuracy trade-off on the dam: every simulator, hybrids, FGN and MPS variants."""
    p = bench.profile
    runs = dam_runs + bench.tradeoff_runs() + [r for r in fig5_runs if r.key.startswith("fig5/")]
    hashes = {r.metrics["reference"]["key_hash"] for r in runs if r.ok}
    if len(hashes) > 1:  # a row file whose reference settings drifted from the others'
        raise ConfigError(f"trade-off rows were compared with different MPS references: {sorted(hashes)}")
    rows = tradeoff_rows(runs)
    report.csv("tradeoff", rows)
    png = report.path("tradeoff.png")
    plot_tradeoff(png, rows, f"Speed/accuracy on {p.dam_scene}, {p.dam_duration:g} s ({p.name} profile)")
    order = sorted(rows, key=lambda r: (not math.isfinite(r["s_per_simulated_s"]), r["s_per_simulated_s"]))
    cells = [
        [
            r["simulator"],
            r["s_per_simulated_s"],
            r["ms_per_step_median"],
            r["chamfer_mean_mm"],
            r["chamfer_max_mm"],
        ]
        + [r["chamfer_t0_mm"], r["density_error_mean"]]
        + ["yes" if r[f"pareto_{m}"] else "" for m in TRADEOFF_METRICS]
        + [r["status"]]
        for r in order
    ]
    header = ["simulator", "s per simulated s", "ms/step", "Chamfer mean (mm)", "max", "at t = 0"]
    header += ["density error", "front: Chamfer", "front: density", "status"]
    report.sections["tradeoff"] = (
        "## Speed/accuracy trade-off\n\n"
        f"Every simulator on `{p.dam_scene}` for {p.dam_duration:g} s against one reference: MPS at the "
        "default settings (PPE to the absolute tolerance 1e-6, the scene's dt and l0; every row has the same "
        "reference hash). Cost: wall seconds of the steps per simulated second (writing and metrics "
        "excluded), the rows run one after another in one process. Accuracy: the Chamfer distance to the "
        "reference (mean over the frames) and the simulator's own density error. A run at a coarser spacing "
        "is compared in physical units in the frame of the boundary surface; its Chamfer distance includes "
        "the lattice offset already there at t = 0 (a coarse particle sits between reference particles; "
        "column 'at t = 0'). On the front: no other complete row is both cheaper and at least as accurate."
        "\n\n"
        f"{md_table(header, cells, 'lrrrrrrccl')}\n\n![trade-off]({png.name})\n"
    )
    front = [r["simulator"] for r in order if r["pareto_chamfer_mean_mm"]]
    report.readme["tradeoff"] = (
        f"**Trade-off** ([plot](benchmarks/results/{png.name})): on the time/Chamfer front, cheapest first: "
        f"{'; '.join(front) or '-'}.\n\n![trade-off](benchmarks/results/{png.name})\n"
    )


# ------------------------------------------------------------------------------------------- main
def run_all(profile: Profile, args: argparse.Namespace) -> dict[str, Any]:
    """Run the selected parts of ``profile`` and write every output.

    Returns:
        ``files`` written, CSV ``rows`` per part, ``failed`` row keys, ``elapsed_s`` and ``readme``
        (whether the README was rewritten).
    """
    start = time.perf_counter()
    load = os.getloadavg()[0]
    torch.set_num_threads(int(args.threads))
    parts = set(args.only or PARTS)
    bench = Bench(profile, args)
    out_dir = Path(args.results)
    out_dir.mkdir(parents=True, exist_ok=True)
    machine = (
        f"{cpu_model()}, {os.cpu_count()} cores, torch {torch.__version__}, {args.threads} torch threads"
    )
    meta = {"machine": machine, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    meta["script_commit"] = git_commit()
    report = Report(out_dir / profile.prefix, meta)

    if "table2" in parts:  # first: the timing rows run before anything else has warmed or loaded the machine
        part_table2(bench, report)
    dam_runs = bench.table3_runs("dam") if parts - {"table2"} else []
    if "table3" in parts:
        part_table3(bench, report, dam_runs)
    fig5 = bench.fig5_runs() if parts & {"fig5", "tradeoff"} else ([], None, None)
    if "fig5" in parts:
        part_fig5(bench, report, fig5)
    if "table4" in parts:
        part_table4(bench, report, dam_runs)
    if "tradeoff" in parts:
        part_tradeoff(bench, report, dam_runs, fig5[0])

    fgn_dam = bench.done.get("table3/dam/fgn")
    figures = ""
    if fgn_dam is not None and fgn_dam.ok and profile.figures:
        src = bench.runs_dir / fgn_dam.key.replace("/", "_")  # evaluate's out_dir of that row
        for name, fig in (("error_vs_time.png", "fig4_dam_fgn"), ("pressure_slice.png", "fig6_dam_fgn")):
            if (src / name).is_file():
                dest = report.path(f"{fig}.png")
                shutil.copy(src / name, dest)
                figures += f"![{fig}]({dest.name})\n\n"

    if figures:
        report.sections["figures"] = f"## Figs. 4 and 6: FGN on the dam\n\n{figures}"
    elapsed = time.perf_counter() - start
    extra = {"CPU": cpu_model(), "profile": f"{profile.name}: {profile.description}"}
    extra["runtime"] = f"{elapsed / 60:.1f} min"
    extra["FGN weights"] = str(args.weights or f"shipped ({SHIPPED_WEIGHTS.relative_to(REPO)})")
    prov = provenance("benchmarks.tables", load, "cpu", **extra)
    invocation = f"`{prov['command']}`, {extra['runtime']}"
    merged = merge_parts(report, bool(args.only), {r.key: r.command for r in bench.done.values()}, invocation)
    history = "\n".join(f"- {when}: {what}" for when, what in merged["history"].items())
    runs_md = "\n".join(f"- `{key}`: `{command}`" for key, command in merged["commands"].items())
    run = f"{meta['date']} at commit {meta['script_commit']}"
    sections = merged["sections"]
    body = earlier_parts(merged, "sections", run) + "\n".join(
        sections[k] for k in ("table3", "table2", "table4", "fig5", "tradeoff") if k in sections
    )
    md = report.path("report.md")
    md.write_text(
        f"# Tables and figures ({profile.name} profile)\n\n{profile.description}.\n\n{body}\n"
        + sections.get("figures", "")
        + f"## Provenance\n\n{markdown(prov)}\n\n"
        + f"### Runs of the script that made this report\n\n{history}\n\n"
        + f"### Rows (each row's command)\n\n{runs_md}\n"
    )
    written: dict[str, Any] = {"files": report.files, "rows": report.rows, "readme": False}
    if args.readme and merged["readme"]:
        label = (
            f"*{profile.name} profile*: {profile.description}. Run {meta['date']} at commit "
            f"{meta['script_commit']} on {machine}; FGN weights: {extra['FGN weights']}. Every table, each "
            f"row's command and the figures: [`benchmarks/results/{md.name}`]"
            f"(benchmarks/results/{md.name}).\n\n"
        )
        order = ("table1", "table2", "table4", "fig5", "tradeoff")
        pieces = merged["readme"]
        section = label + earlier_parts(merged, "readme", run)
        section += "\n".join(pieces[k] for k in order if k in pieces)
        written["readme"] = write_readme(section, Path(args.readme_path))
    written["failed"] = [r.key for r in bench.done.values() if not r.ok]
    written["elapsed_s"] = elapsed
    print(
        f"[tables] done in {elapsed / 60:.1f} min; wrote {len(report.files)} files to {out_dir}", flush=True
    )
    if written["failed"]:
        print(f"[tables] rows that failed: {', '.join(written['failed'])}", flush=True)
    return written


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line (see the module docstring)."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument(
        "--quick", action="store_true", help="the reduced profile (< 5 min), tables_quick_* files"
    )
    ap.add_argument("--only", nargs="+", choices=PARTS, help="run only these parts")
    ap.add_argument("--weights", default=None, help="FGN checkpoint directory (default: the shipped weights)")
    ap.add_argument(
        "--threads", type=int, default=os.cpu_count() or 1, help="torch threads (default: all cores)"
    )
    ap.add_argument("--results", default=str(RESULTS), help="where the md/csv/png files go")
    ap.add_argument("--runs-dir", default="runs/tables", help="rollouts and MPS references")
    ap.add_argument(
        "--readme",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="rewrite the README's results tables (default: yes for the full profile, no for --quick)",
    )
    ap.add_argument("--readme-path", default=str(README), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.readme is None:
        args.readme = not args.quick
    return args


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m benchmarks.tables``; returns the exit status (1 when a row failed)."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    args = parse_args(argv)
    profile = QUICK if args.quick else FULL
    if args.weights is None and not (SHIPPED_WEIGHTS / "advection.pt").is_file():
        sys.stderr.write(
            f"benchmarks.tables: no shipped FGN weights in {SHIPPED_WEIGHTS}; pass --weights DIR (a "
            "task=train out_dir holding advection.pt, collision.pt, pressure.pt)\n"
        )
        return 2
    print(f"[tables] {profile.name} profile: {profile.description}", flush=True)
    est = estimate_seconds(profile, args.only or PARTS)
    what = f"of {' '.join(args.only)} " if args.only else ""
    print(
        f"[tables] expected runtime {what}~{est / 60:.0f} min on the project's 2-core CPU machine", flush=True
    )
    written = run_all(profile, args)
    return 1 if written["failed"] else 0


if __name__ == "__main__":
    sys.exit(main())
