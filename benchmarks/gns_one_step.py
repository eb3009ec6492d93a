"""GNS's accuracy on the held-out test scene: one step, and rollouts against the stored MPS frames.

* **One step**: every window of the test split as in training without noise (the trainable's ``predict``,
  :mod:`baselines.gns.trainable`): the RMS error of the fluid's acceleration (m/s^2) and that error over
  the target's RMS (a relative error), and the position error one frame later (mm).
* **Rollouts** from frames ``--frames`` of the test scene (history from the file) for ``--steps`` frames
  of 8 ms, against the stored frames: position RMSE after 1, 10 and ``--steps`` frames, mean Chamfer
  distance, and where the rollout guard stopped it (:func:`rollout_errors`).

Usage::

    python -m benchmarks.gns_one_step --weights baselines/gns/weights --data data/cpu

Writes ``benchmarks/results/gns_one_step.{md,csv}`` with provenance.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import h5py
import numpy as np
import torch
from torch_geometric.data import Batch

from benchmarks.provenance import markdown_table, provenance, write_results
from benchmarks.tables.config import compose_config
from lagfluid.data.datasets import TrajectoryWindows, load_metadata
from lagfluid.errors import RolloutError
from lagfluid.metrics import chamfer_distance
from lagfluid.registry import get_trainables
from lagfluid.rollout import rollout
from lagfluid.tasks.config import (
    at_simulator_time_step,
    build_initial_state,
    build_simulator,
    initial_history,
    run_guard,
)

RESULTS = Path(__file__).resolve().parent / "results"


def one_step(weights: Path, data: str) -> dict[str, float]:
    """RMS acceleration error (m/s^2), relative error and one-frame position error (mm) on the test split."""
    from baselines.gns.simulator import load_gns  # a GNS benchmark: the plugin is installed with lagfluid

    net = load_gns(weights / "gns.pt").eval()
    cfg = compose_config(["model=gns", f"model.weights={weights}", f"model.gns.history={net.history}"])
    trainable = get_trainables("gns", cfg)["gns"]  # eval mode: no noise, no pushforward
    test = TrajectoryWindows(data, "test", history=net.history)
    err2 = tgt2 = pos2 = count = 0.0
    dt = float(net.frame_dt)
    with torch.no_grad():
        for k in range(len(test)):
            batch = Batch.from_data_list([test[k]])
            pred, target = trainable.predict(net, batch)
            acc_pred, acc = net.acceleration.inverse(pred), net.acceleration.inverse(target)
            err2 += float(((acc_pred - acc) ** 2).sum())
            tgt2 += float((acc**2).sum())
            pos2 += float((((acc_pred - acc) * dt * dt) ** 2).sum())  # semi-implicit Euler: dx = da dt^2
            count += acc.shape[0]
    return {
        "windows": len(test),
        "rms_acceleration_error_m_s2": (err2 / count) ** 0.5,
        "relative_acceleration_error": (err2 / tgt2) ** 0.5,
        "position_error_1_frame_mm": 1e3 * (pos2 / count) ** 0.5,
    }


def rollout_errors(overrides: list[str], scene: Path, frame: int, steps: int) -> dict[str, float]:
    """Roll GNS out from ``frame`` of ``scene`` and compare each frame with the file's."""
    cfg = compose_config([*overrides, "scene=trajectory", f"scene.path={scene}", f"scene.frame={frame}"])
    sim = build_simulator(cfg)
    state = at_simulator_time_step(build_initial_state(cfg), sim, cfg)
    with h5py.File(scene, "r") as f:
        truth = f["00000/position"][frame : frame + steps + 1]
    steps = truth.shape[0] - 1
    frames: list[np.ndarray] = []
    stopped = float("nan")
    try:
        rollout(
            sim,
            state,
            steps,
            guard=run_guard(cfg, sim),
            history=initial_history(cfg, sim),
            on_frame=lambda s: frames.append(s.pos[: s.n_fluid].cpu().numpy()),
        )
    except RolloutError as err:
        stopped = float(len(frames))
        print(f"  stopped: {err}", flush=True)

    def rmse(k: int) -> float:
        if k >= len(frames):
            return float("nan")
        return float(np.sqrt(((frames[k] - truth[k]) ** 2).sum(axis=1).mean()))

    chamfer = [chamfer_distance(p, t) for p, t in zip(frames[1:], truth[1 : len(frames)], strict=False)]
    return {
        "rmse_1_mm": 1e3 * rmse(1),
        "rmse_10_mm": 1e3 * rmse(10),
        f"rmse_{steps}_mm": 1e3 * rmse(steps),
        "chamfer_mean_mm": 1e3 * float(np.mean(chamfer)) if chamfer else float("nan"),
        "stopped_at_frame": stopped,
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", default="baselines/gns/weights", help="folder holding gns.pt")
    parser.add_argument("--data", default="data/cpu")
    parser.add_argument("--frames", type=int, nargs="+", default=[10, 40], help="rollout start frames")
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    load = os.getloadavg()[0]
    weights = Path(args.weights)
    scene = Path(args.data) / load_metadata(args.data)["splits"]["test"][0]
    row: dict[str, float | str] = {"weights": str(weights / "gns.pt"), **one_step(weights, args.data)}
    overrides = ["model=gns", f"model.weights={weights}", f"threads={args.threads}", "progress=false"]
    for frame in args.frames:
        errs = rollout_errors(overrides, scene, frame, args.steps)
        row.update({f"from_{frame}_{k}": v for k, v in errs.items()})
    prov = provenance("benchmarks.gns_one_step", load)
    intro = (
        "# GNS accuracy on the held-out test scene\n\n"
        f"Test scene `{scene}`. One step: every test window, no noise; errors over the fluid particles. "
        f"Rollouts of {args.steps} frames (8 ms) from frames {args.frames} against the stored MPS frames "
        "(history from the file): position RMSE after k frames and mean Chamfer distance (mm), the frame at "
        "which the rollout guard stopped it (nan: ran to the end)."
    )
    quantities = [{"quantity": k, "value": f"{v:.4g}" if isinstance(v, float) else v} for k, v in row.items()]
    body = markdown_table(quantities, align="---:", left=("quantity",))  # one row: shown transposed
    print(write_results(RESULTS, "gns_one_step", [row], intro, prov, body))


if __name__ == "__main__":
    main()
