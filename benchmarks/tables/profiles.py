"""How big each part of the tables is (the full and the quick profile), and how long a profile takes."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from benchmarks.tables.simulators import all_simulators

PARTS = ("table2", "table3", "table4", "table5", "fig5", "tradeoff")
# What a run without --only makes: every part.
DEFAULT_PARTS = PARTS

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


# ------------------------------------------------------------------------------------------- profiles
@dataclass(frozen=True)
class Profile:
    """How big each part is. The row files hold the full profile; other profiles override them.

    Attributes:
        name: ``full`` or ``quick`` (the run folder under ``runs/tables``).
        prefix: file prefix in ``benchmarks/results``.
        dam_scene: scene of the dam collapse rows (Tables 1/3, Fig. 5, trade-off).
        dam_duration: simulated seconds of those rows (a multiple of every dt used, as the two below).
        frame_interval: seconds between compared frames (a multiple of every dt used: the scenes' 2 ms,
            the fig5 and trade-off dts, and the own dt of every model that steps by its training frames'
            spacing, e.g. 4 or 8 ms).
        waterfall: overrides of the water-fall scene (its reduced size), None = no water-fall rows.
        waterfall_duration: simulated seconds of the water-fall rows.
        timing_scene: scene of Table 2.
        timing_warmup: steps run before the timed ones (lazy set-up, first neighbour list, PPE warm start);
            at least a simulator's ``history_length`` + 1 (its start-up steps are never timed:
            :func:`benchmarks.tables.bench.timing_warmup`).
        timing_steps: timed steps (a row file may ask for fewer: ``table.timing_steps``).
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
        "the paper's 80,000 are a GPU size), 0.6 s; Table 2 on dam_large (40,000)"
    ),
)

# Every duration and the frame interval are multiples of each dt the quick rows use: 1, 2, 4, 10 and 20 ms
# (MPS, FGN, Fig. 5, the trade-off) and 8 ms (a model stepping by 4 solver steps of 2 ms).
QUICK = Profile(
    name="quick",
    prefix="tables_quick",
    dam_scene="dam_small",
    dam_duration=0.12,
    frame_interval=0.04,
    waterfall=("scene.scale=0.25",),
    waterfall_duration=0.08,
    timing_scene="dam_small",
    timing_warmup=2,
    timing_steps=5,
    table4_scene="dam_small",
    table4_duration=0.04,
    # a smoke run: the lowest and highest gravity only and no 0.5 ms Fig. 5 rollout, ~15 s saved of the
    # ~2.1 min the whole zoo takes on this profile at one thread (the full profile keeps all ten and 0.5 ms)
    table4_materials=(MATERIALS[0], MATERIALS[-1]),
    fig5_dts=(0.001, 0.002, 0.004, 0.01, 0.02),
    mps_dts=(0.004,),
    ppe_tols=(1e-2, 1e-1),
    coarse=((2, None),),
    description=(
        "QUICK profile (CI smoke run, not the paper's setting): dam_small (640 fluid particles) for 0.12 s, "
        "water fall at quarter size (1,200) for 0.08 s, frames every 40 ms, Table 2 on dam_small (not ~40k), "
        "2 advection sequences of 0.04 s"
    ),
)

# Wall time per fluid particle per step of a row (rollout, evaluation and, for MPS, its reference) and per
# row and frame, fitted to a full run on the project's 2-core CPU (see benchmarks/results/tables_runtime.md).
_US_PER_PARTICLE_STEP = {"mps": 42.0, "learned": 18.0}
_ROW_OVERHEAD_S = 1.0
_FRAME_OVERHEAD_S_PER_1K = 0.03  # per stored frame and 1,000 fluid particles (metrics of model and MPS)


def estimate_seconds(profile: Profile, parts: Sequence[str] = DEFAULT_PARTS) -> float:
    """Expected runtime of ``parts`` of ``profile`` from the per-particle-step costs above.

    Follows :func:`benchmarks.tables.cli.run_all`: the dam rows run for every part but Table 2, Fig. 5's
    rows for Fig. 5 and the trade-off.
    """
    parts = set(parts)
    listed = all_simulators(profile.simulators)
    sims = sum(s.appears_in(f"table3_dam_{s.key}") for s in listed)  # the dam rows
    timed = sum(s.appears_in(f"table2_{s.key}") for s in listed)
    ablations = sum(bool(s.rows) and s.appears_in(f"table5_dam_{s.key}") for s in listed)
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
    if "table5" in parts:  # the ablation rows; FGN's and MPS's are Table 3's
        nw, cases = fluid("waterfall", p.waterfall or ()), ((n, p.dam_duration),)
        cases += ((nw, p.waterfall_duration),) if p.waterfall else ()
        for nc, duration in cases:
            steps = round(duration / dt)
            total += ablations * row(nc, steps, round(duration / p.frame_interval) + 1, learned)
        if p.waterfall and "table3" not in parts:  # then FGN and MPS on the water fall too
            steps = round(p.waterfall_duration / dt)
            frames = round(p.waterfall_duration / p.frame_interval) + 1
            total += steps * nw * mps + row(nw, steps, frames, mps) + row(nw, steps, frames, learned)
    if "table2" in parts:
        nt = fluid(p.timing_scene)
        total += (p.timing_warmup + p.timing_steps) * nt * (mps + (timed - 1) * learned) + 2 * timed
    if "table4" in parts:
        n4, s4 = fluid(p.table4_scene), round(p.table4_duration / dt)
        total += len(p.table4_materials) * (s4 * n4 * mps + row(n4, s4, 11, mps))
    return total
