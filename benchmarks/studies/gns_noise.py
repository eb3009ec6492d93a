r"""A brief sweep of GNS's training noise: short trainings, then rollouts against the held-out MPS frames.

For every ``--noise`` value (``train.noise_std``, l0) GNS is trained with ``train=gns_cpu`` shortened to
``--iterations`` (the same network unless ``--model`` overrides it), then rolled out from frame
``--frame`` of the valid and test scenes (its history from the file, ``scene=trajectory``) for ``--steps``
frames, and compared with the stored MPS frames: position RMSE after 1, 10 and ``--steps`` frames, the mean
Chamfer distance, and the step at which the rollout guard stopped it, if it did. Writes
``benchmarks/results/gns_noise.{md,csv}``::

    python -m benchmarks.studies.gns_noise --data data/cpu --noise 0 0.03 0.09 0.27 \\
        --iterations 400 --threads 1
"""

from __future__ import annotations

import argparse
import csv
import os
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.gns_one_step import rollout_errors
from benchmarks.provenance import markdown_table, provenance, write_results
from benchmarks.tables.config import compose_config
from lagfluid.data.datasets import load_metadata
from lagfluid.models.checkpoint import read_checkpoint
from lagfluid.tasks.train import train

RESULTS = Path(__file__).resolve().parents[1] / "results"  # benchmarks/results, where its results are cited


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default="data/cpu", help="generated dataset (task=generate data=cpu)")
    parser.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.03, 0.09, 0.27], help="l0")
    parser.add_argument("--iterations", type=int, default=400)
    parser.add_argument("--model", nargs="*", default=[], help="model.gns overrides, e.g. latent=32")
    parser.add_argument("--frame", type=int, default=20, help="rollout start frame of the held-out scenes")
    parser.add_argument("--steps", type=int, default=50, help="rollout frames")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--runs-dir", default="runs/gns_noise")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    load = os.getloadavg()[0]
    meta = load_metadata(args.data)
    scenes = [Path(args.data) / meta["splits"][s][0] for s in ("valid", "test")]
    common = [
        "model=gns",
        "train=gns_cpu",
        f"data.out_dir={args.data}",
        f"train.iterations={{gns: {args.iterations}}}",
        f"train.pushforward.start={args.iterations // 3}",
        "progress=false",
        f"threads={args.threads}",
        *[f"model.gns.{kv}" for kv in args.model],
    ]
    rows = []
    for noise in args.noise:
        out = Path(args.runs_dir) / f"noise_{noise:g}"
        start = time.perf_counter()
        cfg = compose_config([*common, "task=train", f"train.noise_std={noise}", f"out_dir={out}"])
        train(cfg)
        seconds = time.perf_counter() - start
        with open(out / "gns_loss.csv") as f:
            last = list(csv.DictReader(f))[-1]
        # the standardised loss is in units of the noise-widened std: back to m/s^2 to compare across noise
        acc_std = np.asarray(read_checkpoint(out / "gns.pt")["meta"]["stats"]["acceleration_std"])
        valid_rms = float(np.sqrt(float(last["valid_loss"]) * np.mean(acc_std**2)))
        row = {"noise_std_l0": noise, "train_s": round(seconds), "valid_rms_acc_m_s2": valid_rms}
        for scene in scenes:
            errs = rollout_errors([*common, f"model.weights={out}"], scene, args.frame, args.steps)
            row.update({f"{scene.stem}_{k}": v for k, v in errs.items()})
        print(row, flush=True)
        rows.append(row)

    prov = provenance("benchmarks.studies.gns_noise", load)
    intro = (
        "# GNS training noise: a brief sweep\n\n"
        f"`train=gns_cpu` shortened to {args.iterations} iterations per value (model overrides: "
        f"{args.model or 'none'}), then rollouts of {args.steps} frames (8 ms) from frame {args.frame} of "
        "the valid and test scenes against the stored MPS frames. RMSE: fluid position error (mm) after k "
        "frames; Chamfer: mean over the frames (mm); stopped: the frame at which the rollout guard stopped "
        "it (nan: ran to the end). valid_rms_acc: the noise-free one-step RMS acceleration error on the "
        "valid split (m/s^2)."
    )
    body = markdown_table(rows, cell=lambda v: f"{v:.4g}" if isinstance(v, float) else str(v), align="---:")
    write_results(RESULTS, "gns_noise", rows, intro, prov, body)
    print(f"wrote {RESULTS / 'gns_noise.md'}")


if __name__ == "__main__":
    main()
