"""Running the tables' rows: each row composed from its row file plus a profile's overrides, run once.

Accuracy rows run ``task=evaluate`` (:mod:`lagfluid.tasks.evaluate`: the model and the MPS reference from the
same initial state, metrics per stored frame), so every number comes from :mod:`lagfluid.metrics`; Table 2's
rows are timed steps in this process. A failed row is recorded, not raised; a row whose model's weights
file is missing (:class:`~lagfluid.models.checkpoint.MissingWeightsError`) is recorded as *skipped* with
the loader's reason and does not count as failed.

Table 2's warm-up (:func:`timing_warmup`) is the profile's ``timing_warmup`` steps, and at least the
simulator's ``history_length`` steps plus one: a simulator that wants ``H`` earlier states starts a scene
built from scratch with ``H`` steps of its own start-up (e.g. a warm start by the MPS solver), which are
not its time per step, and its first step of its own carries its lazy set-up. So the timed steps are all
steps of the simulator itself. The number of timed steps is the profile's ``timing_steps``, or fewer where
the key's ``table2`` row file caps it (``table.timing_steps``).
"""

from __future__ import annotations

import argparse
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from statistics import median
from typing import Any

import torch
from omegaconf import DictConfig

from benchmarks.tables.config import coarsened_scene, compose_config, hydra_value, row_file, steps_in
from benchmarks.tables.profiles import Profile
from benchmarks.tables.simulators import (
    FGN,
    GROUND_TRUTH,
    LEARNED_ADVECTION,
    Simulator,
    all_simulators,
    simulator,
)
from lagfluid.errors import ConfigError
from lagfluid.models.checkpoint import MissingWeightsError
from lagfluid.rollout import rollout
from lagfluid.tasks.config import at_simulator_time_step, build_initial_state, build_simulator, run_guard
from lagfluid.tasks.evaluate import evaluate

log = logging.getLogger("benchmarks.tables")


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
    skipped: bool = False
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def command(self) -> str:
        """The ``python -m lagfluid.run`` line that reruns this row (the script's own paths included)."""
        head = [f"experiment={self.experiment}"] if self.experiment else [f"model={self.sim.model}"]
        overrides = [o for o in self.overrides if o not in head]
        return " ".join(["python -m lagfluid.run", *head, *overrides])

    @property
    def ok(self) -> bool:
        """The run produced metrics (it may still have been stopped by the guard)."""
        return self.metrics is not None

    @property
    def failed(self) -> bool:
        """The run produced no metrics and was not skipped for missing weights."""
        return not self.ok and not self.skipped

    def record_error(self, err: Exception) -> None:
        """Keep ``err``'s first line; a missing weights file marks the row skipped instead of failed."""
        self.error = f"{type(err).__name__}: {err}".splitlines()[0]
        self.skipped = isinstance(err, MissingWeightsError)
        log.warning("row %s %s: %s", self.key, "skipped" if self.skipped else "failed", self.error)

    @property
    def state(self) -> str:
        """``ok``, ``stopped`` (by the guard), ``skipped`` (weights missing) or ``FAILED``, for the log."""
        if self.ok:
            return "ok" if self.complete else "stopped"
        return "skipped" if self.skipped else "FAILED"

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


def timing_warmup(profile: Profile, history_length: int) -> int:
    """Table 2's untimed steps before the timed ones: the profile's, and at least ``history_length + 1``.

    A simulator that wants ``history_length`` earlier states spends that many steps of a scene built from
    scratch on its start-up (another solver's warm start, not its own time per step); the one more step
    is its first own step, which carries its lazy set-up as the first step of any simulator does.
    """
    return max(profile.timing_warmup, history_length + 1 if history_length else 0)


class Bench:
    """Runs rows once each (memoised by key) and keeps what every part needs."""

    def __init__(self, profile: Profile, args: argparse.Namespace) -> None:
        self.profile = profile
        self.threads = int(args.threads)
        self.device = str(getattr(args, "device", "cpu"))
        self.weights = args.weights
        self.runs_dir = Path(args.runs_dir) / profile.name
        self.reference_dir = Path(args.runs_dir) / "reference"
        self.done: dict[str, Run] = {}
        self._own_dt: dict[str, float | None] = {}
        self.scene_cache: dict[str, DictConfig] = {}

    # -------------------------------------------------------------- helpers
    def scene(self, name: str, extra: Sequence[str] = ()) -> DictConfig:
        """The composed scene config of ``scene=name`` (and ``extra`` scene overrides)."""
        key = " ".join([name, *extra])
        if key not in self.scene_cache:
            self.scene_cache[key] = compose_config([f"scene={name}", *extra]).scene
        return self.scene_cache[key]

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
            *run.sim.model_overrides(self.weights),
            *run.overrides,
            f"threads={self.threads}",
            f"device={self.device}",
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
            run.info["stages"] = dict(cfg.model.get("stages") or {})  # Table 4 picks the learned pressures
            run.metrics = evaluate(cfg)
        except Exception as err:  # recorded: one failed row must not lose the hour of rows around it
            run.record_error(err)
        run.info["wall_s"] = time.perf_counter() - start
        print(f"[tables] {run.key}: {run.state} in {run.info['wall_s']:.1f} s {run.error}", flush=True)
        self.done[run.key] = run
        return run

    def time_steps(self, run: Run) -> Run:
        """Table 2: warm-up, then timed steps of ``run`` (no writer, no metrics), in this process.

        Warm-up: :func:`timing_warmup` steps; timed: the profile's ``timing_steps``, capped by the row's
        ``table.timing_steps`` (module doc).
        """
        if run.key in self.done:
            return self.done[run.key]
        p = self.profile
        timed = min(p.timing_steps, run.sim.timing_steps or p.timing_steps)
        run.overrides = [
            *run.sim.model_overrides(self.weights),
            *run.overrides,
            f"scene={p.timing_scene}",
            f"steps={timed}",
            f"threads={self.threads}",
            f"device={self.device}",
            "progress=false",
        ]
        print(f"[tables] {run.key}: {run.command} (after the warm-up steps)", flush=True)
        start = time.perf_counter()
        try:
            head = [f"experiment={run.experiment}"] if run.experiment else [f"model={run.sim.model}"]
            cfg = compose_config(head + run.overrides)
            torch.set_num_threads(self.threads)
            torch.manual_seed(int(cfg.seed))
            sim = build_simulator(cfg)
            warmup = timing_warmup(p, sim.history_length)
            state = at_simulator_time_step(build_initial_state(cfg), sim, cfg)
            guard = run_guard(cfg, sim)
            state, _ = rollout(sim, state, warmup, guard=guard)
            state, record = rollout(sim, state, int(cfg.steps), guard=guard, reset=False)
            steps = record["step_seconds"]
            nns = record["stage_seconds"].get("neighbors", [0.0] * len(steps))
            run.metrics = {
                "complete": True,
                "fluid": state.n_fluid,
                "particles": state.num_particles,
                "parameters": int(sim.parameters) or None,
                "step_ms": 1e3 * median(steps),
                "neighbors_ms": 1e3 * median(nns),
                "inference_ms": 1e3 * median(s - n for s, n in zip(steps, nns, strict=True)),
                "stages_ms": {k: 1e3 * median(v) for k, v in record["stage_seconds"].items()},
                "warmup_steps": warmup,
                "timed_steps": len(steps),
            }
        except Exception as err:  # recorded: one failed row must not lose the hour of rows around it
            run.record_error(err)
        run.info["wall_s"] = time.perf_counter() - start
        m = run.metrics or {}
        done = f"ok ({m['warmup_steps']} warm-up + {m['timed_steps']} timed steps)" if run.ok else run.state
        print(f"[tables] {run.key}: {done} in {run.info['wall_s']:.1f} s {run.error}", flush=True)
        self.done[run.key] = run
        return run

    # -------------------------------------------------------------- the rows of each part
    def accuracy_runs(self, case: str, table: str = "table3", keys: Sequence[str] | None = None) -> list[Run]:
        """Accuracy rows of ``case`` (``dam`` or ``waterfall``): every simulator against MPS (Tables 1/3).

        A key without a ``<table>_<case>`` row file but with other row files (a Table 2 timing row) is left
        out (:meth:`~benchmarks.tables.simulators.Simulator.appears_in`). ``table="table5"``: the rows of
        the Table 5 ablations (``table5_<case>_<key>``), run the same way. ``keys``: only these simulators.
        """
        p = self.profile
        if case == "dam":
            ov = self.dam_overrides(p.dam_scene, p.dam_duration)
        else:
            assert p.waterfall is not None
            ov = self.dam_overrides("waterfall", p.waterfall_duration, extra=p.waterfall)
        runs = []
        for sim in all_simulators(p.simulators):
            if keys is not None and sim.key not in keys:
                continue
            if not sim.appears_in(f"{table}_{case}_{sim.key}") or (table != "table3" and not sim.rows):
                continue
            figures = p.figures and case == "dam" and sim.key == FGN and table == "table3"
            own = self.own_dt(sim)
            if own is not None:  # the same duration and frames in its own steps, against the same MPS
                scene, duration, extra = (
                    (p.dam_scene, p.dam_duration, ())
                    if case == "dam"
                    else ("waterfall", p.waterfall_duration, p.waterfall)
                )
                sim_ov = self.dam_overrides(scene, duration, dt=own, extra=extra)
            else:
                sim_ov = list(ov)
            run = Run(
                f"{table}/{case}/{sim.key}", sim.label, sim, row_file(f"{table}_{case}_{sim.key}"), sim_ov
            )
            runs.append(self.evaluate(run, figures=figures))
        return runs

    def own_dt(self, sim: Simulator) -> float | None:
        """The simulator's own time step (``Simulator.dt``; None: it steps by the scene's), asked once."""
        if sim.key not in self._own_dt:
            row = row_file(f"table3_dam_{sim.key}") or row_file(f"table5_dam_{sim.key}")
            head = [f"experiment={row}"] if row else [f"model={sim.model}"]
            try:
                self._own_dt[sim.key] = build_simulator(
                    compose_config(head + sim.model_overrides(self.weights))
                ).dt
            except Exception as err:  # the row itself reports what is wrong with the model
                log.warning("cannot build %s to ask its time step: %s", sim.key, err)
                self._own_dt[sim.key] = None
        return self._own_dt[sim.key]

    def table2_runs(self) -> list[Run]:
        """Table 2 rows: every simulator with a Table 2 row (or no row files at all), on the timing scene."""
        runs = []
        for sim in all_simulators(self.profile.simulators):
            if not sim.appears_in(f"table2_{sim.key}"):
                continue
            runs.append(
                self.time_steps(Run(f"table2/{sim.key}", sim.label, sim, row_file(f"table2_{sim.key}"), []))
            )
        return runs

    def table4_runs(self) -> list[Run]:
        """Table 4's advection sequences: learned advection, exact collision and pressure, per (g, nu)."""
        p = self.profile
        sim = simulator(LEARNED_ADVECTION)
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
        sim = simulator(FGN)
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
        key = f"table3/dam/{FGN}"
        if key not in self.done:
            self.accuracy_runs("dam")
        return self.done[key]

    def tradeoff_runs(self) -> list[Run]:
        """MPS at looser PPE tolerances, larger dt and a coarser spacing.

        The trade-off's other points are the dam rows of Table 3 and Fig. 5.
        """
        p = self.profile
        mps = simulator(GROUND_TRUTH)
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
