r"""Variants of one rollout, each timed over the whole run, alternated: ``python -m benchmarks.whole_run``.

    python -m benchmarks.whole_run --model fgn --scene dam_large --repeats 2 --threads 2 --name skin_fgn \\
        --variant skin0.15 solver.neighbors.skin_fraction=0.15 \\
        --variant skin0.3 solver.neighbors.skin_fraction=0.3 \\
        --variant thp env.THP_MEM_ALLOC_ENABLE=1

Each ``--variant NAME [SETTING ...]`` is a rollout of ``--model`` on ``--scene`` for ``--steps`` steps with
those settings: Hydra overrides (``key=value``) or environment variables (``env.NAME=value``). Every run is a
fresh ``python -m lagfluid.run`` process; the variants run in turn and the whole round ``--repeats`` times
(alternated, so each sees the machine's conditions of the same minutes; one untimed 2-step run first builds
the compiled kernels). Per variant: the median over repeats of the run's mean step (what the whole run
costs per step), each stage's mean, the Verlet list's searches, and the rollout's metrics (the Verlet list is
exact: the same pairs at any skin, so rollouts agree to rounding).

Writes ``benchmarks/results/<name>.{md,csv}`` with provenance; the rollouts go to a scratch folder (removed).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from statistics import median

from benchmarks.provenance import provenance, write_results

RESULTS = Path(__file__).resolve().parent / "results"
ENV = "env."


def split_settings(settings: list[str]) -> tuple[list[str], dict[str, str]]:
    """A variant's settings as (Hydra overrides, environment variables); ``env.NAME=value`` is the latter.

    Raises:
        SystemExit: a setting without ``=``.
    """
    overrides, env = [], {}
    for s in settings:
        key, eq, value = s.partition("=")
        if not eq or not key:
            raise SystemExit(f"--variant setting {s!r}: expected key=value or env.NAME=value")
        if key.startswith(ENV):
            env[key[len(ENV) :]] = value
        else:
            overrides.append(s)
    return overrides, env


def run_once(args: argparse.Namespace, settings: list[str], out: Path, scene: str, steps: int) -> dict:
    """One rollout in a fresh process; its metrics.json."""
    overrides, env = split_settings(settings)
    cmd = [
        sys.executable, "-m", "lagfluid.run", f"model={args.model}", f"scene={scene}", f"steps={steps}",
        f"threads={args.threads}", f"write_every={max(1, steps // 10)}", "progress=false", f"out_dir={out}",
        *overrides,
    ]  # fmt: skip
    done = subprocess.run(cmd, env={**os.environ, **env}, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    if done.returncode:
        raise SystemExit(f"benchmarks.whole_run: {' '.join(cmd)} failed:\n{done.stderr.decode()[-2000:]}")
    return json.loads((out / "metrics.json").read_text())


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="fgn")
    ap.add_argument("--scene", default="dam_large")
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--name", required=True, help="results file stem")
    ap.add_argument("--about", default="", help="a paragraph: what the variants compare")
    ap.add_argument(
        "--variant", nargs="+", action="append", required=True, metavar=("NAME", "SETTING"),
        help="a name, then Hydra overrides (key=value) and environment variables (env.NAME=value)",
    )  # fmt: skip
    args = ap.parse_args(argv)
    variants = {v[0]: v[1:] for v in args.variant}
    if len(variants) != len(args.variant):
        raise SystemExit(f"--variant names must differ, got {[v[0] for v in args.variant]}")
    for settings in variants.values():
        split_settings(settings)  # refuse a malformed setting before any run
    load = os.getloadavg()[0]
    scratch = Path(tempfile.mkdtemp(prefix="whole_run-"))
    found: dict[str, list[dict]] = {name: [] for name in variants}
    try:
        run_once(args, next(iter(variants.values())), scratch / "warm", "dam_small", 2)
        for r in range(args.repeats):
            for name, settings in variants.items():
                found[name].append(run_once(args, settings, scratch / f"{name}-{r}", args.scene, args.steps))
                print(f"whole_run: {name} repeat {r} done", file=sys.stderr, flush=True)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    rows = []
    for name, runs in found.items():
        stages = runs[0]["stage_mean_s"]
        rows.append(
            {
                "variant": name,
                "settings": " ".join(variants[name]),
                "ms_per_step_mean": round(1e3 * median(m["time_per_step_mean_s"] for m in runs), 1),
                "ms_per_step_mean_each": " ".join(f"{1e3 * m['time_per_step_mean_s']:.1f}" for m in runs),
                "stages_ms_mean": " ".join(
                    f"{k}={1e3 * median(m['stage_mean_s'][k] for m in runs):.1f}" for k in stages
                ),
                "list_rebuilds": runs[0].get("list_rebuilds", ""),
                "steps": runs[0]["steps"],
                "complete": runs[0]["complete"],
                "density_error_mean": round(runs[0]["density_error"]["mean"], 5),
            }
        )
    intro = (
        f"# {args.name}: `{args.model}` on `{args.scene}` over {args.steps} steps, variants alternated\n\n"
        f"{args.about}\n\n"
        "Each variant rolled out in a fresh process, the variants in turn, the round "
        f"{args.repeats} times ({args.threads} threads). `ms_per_step_mean`: the median over repeats of the "
        "whole run's mean step (each repeat in `ms_per_step_mean_each`); `stages_ms_mean`: each stage's mean "
        "per step (median over repeats); `list_rebuilds`: the Verlet list's searches in the run."
    )
    prov = provenance("benchmarks.whole_run", load, "cpu", model=args.model, scene=args.scene)
    print(write_results(RESULTS, args.name, rows, intro, prov))


if __name__ == "__main__":
    main()
