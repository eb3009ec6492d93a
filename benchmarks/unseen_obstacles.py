"""The end-to-end rows on obstacle scenes no model trained on: complete or not, Chamfer to MPS, wall approach.

Every model of the zoo was trained on ``scene=random`` (seeds 0-11 of ``data=cpu``: an 80 x 80 x 40 l0 tank,
one 25 x 25 x 10 l0 block, one or two floor-standing boxes, vertical cylinders, spheres or wedges) or, for
the FGN authors' weights, on their own random scenes. :data:`SCENES` are scenes none of them saw, each
defined here from the repository alone:

* ``random_s1000``: ``scene=random`` at seed 1000 (training used 0-11) in a smaller tank, two obstacles;
* ``dam_cone``: a dam column whose front runs into a cone and a square pillar turned 45 degrees about the
  vertical (no training obstacle is conical or off the lattice's axes) (``scene=mesh``);
* ``fall_torus``: a block falling onto a torus lying on the floor (a ring with a hole) and past a capsule
  lying on its side (``scene=mesh``).

The mesh scenes' STL files are written by :func:`write_meshes` into the runs folder (never the repository),
in a folder named by the digest of their bytes, so a changed geometry is a new scene path and never reuses a
cached MPS reference of the old one.

For each scene and row (:data:`ROWS`: the tables' keys, labels from their row files
``table3_dam_<key>``), ``task=evaluate`` for ``--duration`` s with frames every 40 ms, against the scene's
MPS reference at 2 ms (computed once, cached in ``--reference-dir``). A row reports complete or the step the
rollout guard stopped it at, the mean and largest Chamfer distance to MPS over the frames it stored, the
mean density error, and how close its fluid came to the boundary particles
(:func:`benchmarks.wall_approach.boundary_distances` on its ``rollout.h5``: the smallest distance and the
share of particle-frames within 0.5 and 0.7 l0), with MPS's own reference rollout as a row of its own.

A row whose simulator is not in this checkout, or whose weights file is missing
(:class:`~lagfluid.models.checkpoint.MissingWeightsError`), is reported as skipped with the reason. A row
whose folder already holds ``metrics.json`` is read, not run again (so the script resumes, and a row added
later, e.g. the fine-tuned CConv, runs alone).

Usage::

    nice -n 10 python -m benchmarks.unseen_obstacles --runs-dir runs/unseen_obstacles [--rows gns_exact ...]

Writes ``benchmarks/results/unseen_obstacles.{md,csv}`` (provenance, each row's command) and
``unseen_obstacles_scenes.png`` (each scene's initial fluid and obstacles, side and top view).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shlex
import subprocess
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import OmegaConf

from benchmarks.exact_after import BOTH, result_row
from benchmarks.provenance import provenance, write_results
from benchmarks.tables.config import compose_config, hydra_value, steps_in
from benchmarks.tables.simulators import Simulator, all_simulators
from benchmarks.wall_approach import boundary_distances, summary
from lagfluid.data.store import read_trajectory
from lagfluid.models.checkpoint import MissingWeightsError
from lagfluid.models.exact_after import ExactAfterOptions
from lagfluid.scenes.library import random_layout
from lagfluid.state import ParticleState, ParticleType
from lagfluid.tasks.config import build_initial_state, build_simulator, scene_params

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
NAME = "unseen_obstacles"
FRAME_INTERVAL = 0.04  # s, as the tables
L0 = 0.05  # m, every scene's particle spacing (the training data's)

ROWS = (
    "gns_unroll_exact",
    "gns_dagger_exact",
    "gns_exact",
    "cconv_exact",
    "cconv_original_exact",
    "cconv_finetuned_exact",
    "cconv_finetuned_collision",
    "gns_unroll",
    "gns_dagger",
    "gns",
    "cconv",
    "cconv_original",
    "cconv_finetuned",
    "fgn",
    "fgn_original",
)
"""The rows, new ones (an end-to-end model + MPS's exact stages after each step) first."""

EXACT_SUFFIX = "_exact"
# The runs need only the metrics and the rollout: no figures, no one-step errors (an exact MPS step per frame)
EVALUATE = ("evaluate.figures=false", "evaluate.one_step=false", "progress=false")


# ------------------------------------------------------------------------------------------- scenes
@dataclass(frozen=True)
class TestScene:
    """One scene nobody trained on.

    Attributes:
        name: short name (run folders, the table's scene column).
        description: what it is, for the results.
        overrides: the scene's ``lagfluid.run`` overrides, given the folder its meshes may be written to.
    """

    name: str
    description: str
    overrides: Callable[[Path], list[str]]


def _box(lower: Sequence[float], upper: Sequence[float]):
    """An axis-aligned box mesh (trimesh) from ``lower`` to ``upper``, m."""
    import trimesh

    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    mesh = trimesh.creation.box(extents=upper - lower)
    mesh.apply_translation((lower + upper) / 2)
    return mesh


def dam_cone_meshes() -> dict[str, Any]:
    """A 2 x 1 x 1.8 m tank; a 0.5 x 1 x 0.8 m column at x = 0; a cone and a 45-degree pillar in its path.

    Returns:
        ``{"container": mesh, "fluid": mesh, "obstacles": [cone, pillar]}`` (trimesh meshes, m). The cone
        (base radius 0.3 m at the floor, apex 0.45 m up, at (1.05, 0.35)) and the pillar (a 0.24 m square
        turned 45 degrees about z, 0.5 m high, at (1.45, 0.7)) reach 0.2 m into the floor, so no floor is
        built under them.
    """
    import trimesh

    sink = 0.2
    cone = trimesh.creation.cone(radius=0.3 * (0.45 + sink) / 0.45, height=0.45 + sink, sections=64)
    cone.apply_translation([1.05, 0.35, -sink])
    pillar = _box([-0.12, -0.12, -sink], [0.12, 0.12, 0.5])
    pillar.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 4, [0, 0, 1]))
    pillar.apply_translation([1.45, 0.7, 0.0])
    return {
        "container": _box([0, 0, 0], [2.0, 1.0, 1.8]),  # above the open top's 2 x 0.8 m: no lid
        "fluid": _box([0, 0, 0], [0.5, 1.0, 0.8]),
        "obstacles": [cone, pillar],
    }


def fall_torus_meshes() -> dict[str, Any]:
    """A 1.8 m tank; a 0.8 x 0.8 x 0.4 m block 0.45 m up, over a torus on the floor; a capsule on its side.

    Returns:
        as :func:`dam_cone_meshes`: the torus (ring radius 0.35 m, tube radius 0.12 m, centre (0.9, 0.9),
        2 cm into the floor) under the block's centre, the capsule (radius 0.1 m, 1.2 m long along x,
        1 cm into the floor) at y = 1.5 m.
    """
    import trimesh

    torus = trimesh.creation.torus(major_radius=0.35, minor_radius=0.12, major_sections=64, minor_sections=24)
    torus.apply_translation([0.9, 0.9, 0.1])
    capsule = trimesh.creation.capsule(height=1.0, radius=0.1, count=[32, 16])  # along z, 1.2 m end to end
    capsule.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    capsule.apply_translation([0.9, 1.5, 0.09])
    return {
        "container": _box([0, 0, 0], [1.8, 1.8, 1.8]),
        "fluid": _box([0.5, 0.5, 0.45], [1.3, 1.3, 0.85]),
        "obstacles": [torus, capsule],
    }


def write_meshes(folder: Path, name: str, meshes: dict[str, Any]) -> dict[str, Any]:
    """Write ``meshes`` as STL into ``folder/<name>-<digest of their bytes>/``; return their paths.

    The digest puts a changed geometry at a new path, so the MPS reference cache (keyed by the scene's
    config, paths included) never serves a reference of another geometry. Files already there are kept.

    Returns:
        ``{"container": path, "fluid": path, "obstacles": [path, ...]}`` (str).
    """
    blobs = {"container": meshes["container"].export(file_type="stl")}
    blobs["fluid"] = meshes["fluid"].export(file_type="stl")
    for i, mesh in enumerate(meshes["obstacles"]):
        blobs[f"obstacle_{i}"] = mesh.export(file_type="stl")
    digest = hashlib.sha256(b"".join(blobs[k] for k in sorted(blobs))).hexdigest()[:10]
    out = folder / f"{name}-{digest}"
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    for key, blob in blobs.items():
        path = out / f"{key}.stl"
        if not path.is_file():
            part = path.with_name(path.name + ".part")
            part.write_bytes(blob)
            os.replace(part, path)
        paths[key] = str(path)
    n = len(meshes["obstacles"])
    return {
        "container": paths["container"],
        "fluid": paths["fluid"],
        "obstacles": [paths[f"obstacle_{i}"] for i in range(n)],
    }


def mesh_overrides(name: str, make: Callable[[], dict[str, Any]]) -> Callable[[Path], list[str]]:
    """The overrides of a ``scene=mesh`` scene whose meshes ``make`` returns (written on first use)."""

    def overrides(folder: Path) -> list[str]:
        paths = write_meshes(folder, name, make())
        return [
            "scene=mesh",
            f"scene.container={paths['container']}",
            f"scene.fluid={paths['fluid']}",
            f"scene.obstacles={hydra_value(paths['obstacles'])}",
        ]

    return overrides


RANDOM = {"seed": 1000, "tank_size": [40, 40], "wall_height": 24, "fluid_size": [16, 16, 8], "n_obstacles": 2}
"""``scene=random``'s options for ``random_s1000``: a seed far from training's 0-11, a smaller tank."""


def _random_overrides(folder: Path) -> list[str]:
    del folder  # built from its options alone
    return ["scene=random", *(f"scene.{k}={hydra_value(v)}" for k, v in RANDOM.items())]


SCENES: dict[str, TestScene] = {
    s.name: s
    for s in (
        TestScene(
            "random_s1000",
            "`scene=random` at seed 1000 (training: seeds 0-11), in a 40 x 40 l0 tank with walls to 24 l0 "
            "(training: 80 x 80 x 40) with a 16 x 16 x 8 l0 block (training 25 x 25 x 10) and two obstacles, "
            f"lattice units: {random_layout(**RANDOM).description}",
            _random_overrides,
        ),
        TestScene(
            "dam_cone",
            "`scene=mesh`: a dam column (0.5 x 1 x 0.8 m at the x = 0 wall of a 2 x 1 m tank) whose front "
            "runs into a cone (base radius 0.3 m, 0.45 m high, at x = 1.05 m) and a square pillar turned "
            "45 degrees about the vertical (0.24 m across, 0.5 m high, at x = 1.45 m); no training obstacle "
            "is a cone or off the lattice's axes, no training scene is a column at a wall",
            mesh_overrides("dam_cone", dam_cone_meshes),
        ),
        TestScene(
            "fall_torus",
            "`scene=mesh`: a 0.8 x 0.8 x 0.4 m block released 0.45 m above the floor of a 1.8 x 1.8 m tank, "
            "over a torus lying on the floor (ring radius 0.35 m, tube radius 0.12 m: the fluid falls into "
            "its hole and over its rim), beside a capsule lying on its side (radius 0.1 m, 1.2 m long); "
            "neither shape is a training kind",
            mesh_overrides("fall_torus", fall_torus_meshes),
        ),
    )
}


def obstacle_mask(state: ParticleState) -> np.ndarray:
    """(N,) True for the wall particles of the obstacles: inside the domain's walls and above its floor.

    The tank's inner wall layers lie on the domain box's faces (``state.bounds``), so a wall particle more
    than half a spacing inside every side wall and above the floor belongs to an obstacle.
    """
    pos = state.pos.double().numpy()
    lower, upper = state.bounds.double().numpy()
    half = 0.5 * state.params.l0
    inside = np.all((pos[:, :2] > lower[:2] + half) & (pos[:, :2] < upper[:2] - half), axis=1)
    return (state.ptype.numpy() == ParticleType.WALL) & inside & (pos[:, 2] > lower[2] + half)


# ------------------------------------------------------------------------------------------- rows
@dataclass(frozen=True)
class Row:
    """One simulator row: what it runs as and how the table names it.

    Attributes:
        key: the tables' key (``cconv_exact``).
        label: the tables' label (``CConv (CPU training) + exact collision + MPS pressure``).
        model: the registered model it composes to.
        overrides: its ``model.*`` overrides (``model.exact_after.collision=true``, ...).
        skip: why it cannot run in this checkout ('' when it can).
    """

    key: str
    label: str
    model: str = ""
    overrides: tuple[str, ...] = ()
    skip: str = ""


def _flat(node: Any, prefix: str = "") -> dict[str, Any]:
    """A nested dict as ``{"a.b": value}`` (lists are values)."""
    if not isinstance(node, dict):
        return {prefix: node}
    out: dict[str, Any] = {}
    for k, v in node.items():
        out.update(_flat(v, f"{prefix}.{k}" if prefix else str(k)))
    return out


def model_overrides(experiment: str, model: str) -> tuple[str, ...]:
    """The ``model.*`` overrides that make ``model=<model>`` what row file ``experiment`` composes."""
    row = _flat(OmegaConf.to_container(compose_config([f"experiment={experiment}"]).model, resolve=True))
    plain = _flat(OmegaConf.to_container(compose_config([f"model={model}"]).model, resolve=True))
    return tuple(f"model.{k}={hydra_value(v)}" for k, v in row.items() if k not in plain or plain[k] != v)


def resolve_row(key: str, sims: dict[str, Simulator]) -> Row:
    """The row ``key``: a simulator of the tables (its Tables 1/3 row file's model overrides and label).

    A key ``<base>_exact`` without a simulator of its own is ``<base>`` with :data:`BOTH`, labelled so; a
    key with neither is a row to skip, with the reason.
    """
    if key in sims:
        sim = sims[key]
        files = [r for r in sim.rows if r.startswith("table3_")]
        return Row(key, sim.label, sim.model, model_overrides(files[0], sim.model) if files else ())
    base = key.removesuffix(EXACT_SUFFIX)
    if key.endswith(EXACT_SUFFIX) and base in sims:
        plain = resolve_row(base, sims)
        label = ExactAfterOptions(collision=True, pressure=True).label(plain.label)
        return Row(key, label, plain.model, (*plain.overrides, *BOTH))
    return Row(
        key,
        key,
        skip=f"no simulator '{key}' in this checkout (no row file table3_dam_{key}, no registered model)",
    )


def row_dt(row: Row, scene: list[str]) -> tuple[float | None, str]:
    """The time step ``row`` rolls out by on ``scene``, or None and why it cannot run (missing weights).

    Builds the simulator (its weights are loaded): a missing weights file is a reason to skip the row;
    any other error is raised.
    """
    cfg = compose_config([f"model={row.model}", *row.overrides, *scene])
    try:
        own = build_simulator(cfg).dt
    except MissingWeightsError as err:
        return None, f"weights missing: {err}"
    return float(own) if own is not None else scene_params(cfg).dt, ""


def command(row: Row, scene: list[str], dt: float, out: Path, args: argparse.Namespace) -> list[str]:
    """The ``task=evaluate`` command of one row on one scene: ``args.duration`` s, frames every 40 ms."""
    steps = steps_in(args.duration, dt, f"{row.key}: duration")
    every = steps_in(FRAME_INTERVAL, dt, f"{row.key}: frame interval")
    return [
        *("python", "-m", "lagfluid.run", "task=evaluate", f"model={row.model}", *row.overrides, *scene),
        *(f"steps={steps}", f"write_every={every}", f"threads={args.threads}", *EVALUATE),
        f"evaluate.reference_dir={args.reference_dir}",
        f"out_dir={out}",
    ]


def wall_columns(trajectory: dict[str, Any]) -> dict[str, Any]:
    """Wall approach of a rollout: the smallest fluid-boundary distance and the shares within 0.5, 0.7 l0.

    Args:
        trajectory: :func:`lagfluid.data.store.read_trajectory`'s dict (with its ``l0`` attribute).
    """
    distances = boundary_distances(trajectory, float(trajectory["attrs"]["l0"]))
    s = summary("", distances, len(trajectory["position"]))
    return {
        "closest to a boundary particle (l0)": f"{s['min']:.3f}",
        "particle-frames < 0.5 / 0.7 l0": f"{s['< 0.5 l0']} / {s['< 0.7 l0']}",
    }


def table_row(scene: str, row: Row, metrics: dict[str, Any], wall: dict[str, Any], cmd: list[str]) -> dict:
    """One line of the table: :func:`benchmarks.exact_after.result_row`'s columns under the row's label."""
    r = result_row(metrics, cmd)
    return {
        "scene": scene,
        "simulator": row.label,
        "run as": r["simulator"],
        "dt (ms)": r["dt (ms)"],
        "rollout": r["rollout"],
        "Chamfer to MPS mean / max (mm)": r["Chamfer to MPS mean / max (mm)"],
        "density error mean (MPS)": r["density error mean (MPS)"],
        **wall,
        "command": r["command"],
    }


def skipped_row(scene: str, row: Row, reason: str) -> dict[str, Any]:
    """A table line for a row that did not run: the reason in the rollout column, the rest empty."""
    return {
        "scene": scene,
        "simulator": row.label,
        "run as": row.model or "-",
        "dt (ms)": "",
        "rollout": f"skipped: {reason}",
        "Chamfer to MPS mean / max (mm)": "",
        "density error mean (MPS)": "",
        "closest to a boundary particle (l0)": "",
        "particle-frames < 0.5 / 0.7 l0": "",
        "command": "",
    }


def reference_row(scene: str, metrics: dict[str, Any]) -> dict[str, Any]:
    """MPS's own line for ``scene``, from the reference rollout a row's ``metrics`` was compared with."""
    path = metrics["reference"]["path"]
    trajectory = read_trajectory(path)
    density = metrics["summary"]["density_error"]["reference"]["mean"]
    return {
        "scene": scene,
        "simulator": "MPS (the reference)",
        "run as": "mps",
        "dt (ms)": f"{1e3 * float(trajectory['attrs']['dt']):g}",
        "rollout": "complete",
        "Chamfer to MPS mean / max (mm)": "-",
        "density error mean (MPS)": f"({density:.4f})",
        **wall_columns(trajectory),
        "command": f"computed by the scene's first task=evaluate, cached: `{path}`",
    }


def run_row(scene: TestScene, row: Row, args: argparse.Namespace) -> tuple[dict, dict | None]:
    """Run (or read) ``row`` on ``scene``: its table line and its ``metrics.json`` (None when skipped).

    Raises:
        SystemExit: the run wrote no ``metrics.json`` (it failed; its output says why).
    """
    if row.skip:
        return skipped_row(scene.name, row, row.skip), None
    overrides = scene.overrides(Path(args.runs_dir) / "meshes")
    out = Path(args.runs_dir) / scene.name / row.key
    metrics_path = out / "metrics.json"
    if metrics_path.is_file():  # resumed: the metrics say what ran, the command is rebuilt from them
        metrics = json.loads(metrics_path.read_text())
        dt = float(metrics["dt"])
    else:
        dt, reason = row_dt(row, overrides)
        if dt is None:
            return skipped_row(scene.name, row, reason), None
    cmd = command(row, overrides, dt, out, args)
    if not metrics_path.is_file():
        print(f"[{NAME}] {shlex.join(cmd)}", flush=True)
        env = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
        subprocess.run([sys.executable, *cmd[1:]], cwd=REPO, env=env, check=False)
        if not metrics_path.is_file():
            raise SystemExit(f"[{NAME}] {out} holds no metrics.json: the run failed (see its output)")
        metrics = json.loads(metrics_path.read_text())
    line = table_row(scene.name, row, metrics, wall_columns(read_trajectory(out / "rollout.h5")), cmd)
    print(f"[{NAME}] {scene.name}, {row.label}: {line['rollout']}", flush=True)
    return line, metrics


# ------------------------------------------------------------------------------------------- figure
def scene_figure(path: Path, states: dict[str, ParticleState]) -> None:
    """Each scene's initial fluid (blue) and obstacle wall particles (grey): side (x-z) and top (x-y) view."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(states), figsize=(4.2 * len(states), 6.4), squeeze=False)
    for col, (name, state) in enumerate(states.items()):
        pos = state.pos.double().numpy()
        fluid = state.ptype.numpy() == ParticleType.FLUID
        solid = obstacle_mask(state)
        lower, upper = state.bounds.double().numpy()
        top = pos[~fluid, 2].max()  # the walls' top (the domain box is raised above it)
        for ax, (a, b), view in zip(axes[:, col], ((0, 2), (0, 1)), ("side (x-z)", "top (x-y)"), strict=True):
            for mask, colour, label in ((fluid, "tab:blue", "fluid"), (solid, "0.2", "obstacles")):
                ax.scatter(pos[mask, a], pos[mask, b], s=0.4, c=colour, label=label, rasterized=True)
            hi = top if b == 2 else upper[b]
            ax.add_patch(plt.Rectangle((lower[a], lower[b]), upper[a] - lower[a], hi - lower[b], fill=False))
            ax.set_aspect("equal")
            ax.set_title(f"{name}: {view}", fontsize=9)
            ax.set_xlabel(f"{'xyz'[a]} (m)", fontsize=8)
            ax.set_ylabel(f"{'xyz'[b]} (m)", fontsize=8)
            ax.tick_params(labelsize=7)
    axes[0, 0].legend(loc="upper right", fontsize=7, markerscale=12)
    fig.suptitle("Scenes no model trained on: initial fluid and obstacles (tank walls as the outline)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def build_states(names: Sequence[str], folder: Path) -> dict[str, ParticleState]:
    """The initial states of the scenes ``names`` (meshes written to ``folder``)."""
    states = {}
    for name in names:
        cfg = compose_config(SCENES[name].overrides(folder))
        states[name] = build_initial_state(cfg)
    return states


# ------------------------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    ap.add_argument("--rows", nargs="+", default=list(ROWS), help="the tables' keys")
    ap.add_argument("--duration", type=float, default=0.6, help="s of each scene (a multiple of 40 ms)")
    ap.add_argument("--runs-dir", default=f"runs/{NAME}")
    ap.add_argument("--name", default=NAME, help="results file name (a subset of rows beside the full table)")
    ap.add_argument("--reference-dir", default="runs/reference", help="the MPS references' cache")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--note-file", default=None, help="a markdown file added under the table's intro")
    ap.add_argument("--results", default=str(RESULTS))
    args = ap.parse_args(argv)
    load = os.getloadavg()[0]
    sims = {s.key: s for s in all_simulators()}
    rows = [resolve_row(key, sims) for key in args.rows]
    states = build_states(args.scenes, Path(args.runs_dir) / "meshes")
    Path(args.results).mkdir(parents=True, exist_ok=True)
    scene_figure(Path(args.results) / f"{NAME}_scenes.png", states)
    lines: dict[str, list[dict]] = {name: [] for name in args.scenes}
    reference: dict[str, dict] = {}
    stops: list[str] = []
    for row in rows:  # row by row: the new rows on every scene come first
        for name in args.scenes:
            line, metrics = run_row(SCENES[name], row, args)
            lines[name].append(line)
            if metrics is None:
                continue
            if metrics["frames_compared"] > reference.get(name, {}).get("frames_compared", 0):
                reference[name] = metrics  # MPS's density error over the most frames a row compared
            if not metrics["complete"]:
                stops.append(f"- {name}, {row.label}: {metrics['stop_reason']}")
    table = []
    for name in args.scenes:
        if name in reference:
            table.append(reference_row(name, reference[name]))
        table += lines[name]
    counts = {n: f"{s.n_fluid:,} fluid, {s.num_particles - s.n_fluid:,} boundary" for n, s in states.items()}
    intro = (
        "# End-to-end rows on obstacle scenes no model trained on\n\n"
        f"`task=evaluate` for {args.duration:g} s, frames every {1e3 * FRAME_INTERVAL:g} ms, against one MPS "
        "reference per scene at 2 ms; each model steps by its own dt. Chamfer: mean and largest over the "
        "stored frames of the symmetric mean nearest-neighbour distance to MPS's fluid (a stopped run over "
        "the frames it stored); density error: mean |n/n0 - 1| over the interior fluid. Wall approach "
        "(`benchmarks/wall_approach.py`) over the row's own stored frames: the smallest distance from a "
        "fluid particle to a boundary (wall, dummy or obstacle) particle and the share of particle-frames "
        "closer than 0.5 and 0.7 l0 (the training data: `wall_approach.md`). "
        f"`benchmarks/unseen_obstacles.py`; the scenes' initial geometry: `{NAME}_scenes.png`.\n\n"
        "**Scenes**\n\n"
        + "\n".join(f"- `{n}` ({counts[n]}): {SCENES[n].description}." for n in args.scenes)
        + (f"\n\n{Path(args.note_file).read_text().strip()}" if args.note_file else "")
        + ("\n\n**Where the stopped rows stopped**\n\n" + "\n".join(stops) if stops else "")
    )
    prov = provenance(f"benchmarks.{NAME}", load, runs=str(args.runs_dir))
    print(write_results(Path(args.results), args.name, table, intro, prov))


if __name__ == "__main__":
    main()
