"""DeepLagrangianFluids' loss on held-out windows: their published CConv before and after fine-tuning here.

The windows of `experiment=finetune_cconv_dlf` (`data=dlf_frames`: a state and the next F stored frames,
20 ms apart, one step of their network each; F = 2, their unroll, and 6, the shipped fine-tune's), of the
valid and the test scenes (never trained on), unturned, in their axes and wall weighting. Each network's loss
is the training's (`dlf_loss` of `baselines/cconv/trainable.py`: `128 mean exp(-n/40) |dx|^0.5` summed over
the F steps), averaged over every window of the split; the last-step error is the mean displacement error of
step F in mm.

Usage::

    python -m benchmarks.cconv_finetune_loss [--weights DIR] [--data data/dlf_frames] [--frames 2 6]

Writes ``benchmarks/results/cconv_finetune_loss.{md,csv}`` with provenance.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import torch
from torch_geometric.loader import DataLoader

from baselines.cconv.simulator import DLF_WEIGHTS, FINETUNED, load_cconv
from baselines.cconv.trainable import CConvTrainable, dlf_loss
from benchmarks.provenance import provenance, write_results
from benchmarks.tables.config import compose_config

RESULTS = Path(__file__).resolve().parent / "results"
REPO = RESULTS.parents[1]


def split_losses(
    trainable: CConvTrainable, net: torch.nn.Module, data: Path, split: str
) -> tuple[float, float]:
    """Mean loss over every window of ``split`` and the mean last-step displacement error (mm)."""
    loader = DataLoader(trainable.windows(data, split), batch_size=2)
    net.eval()
    losses, errors = [], []
    with torch.no_grad():
        for batch in loader:
            pred, target = trainable.predict(net, batch)
            losses.append(float(dlf_loss(pred, target)))
            unit_mm = 1e3 * net.length_unit
            errors.append(float((pred[:, -1, :3] - target[:, -1, :3]).norm(dim=-1).mean()) * unit_mm)
    return sum(losses) / len(losses), sum(errors) / len(errors)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--weights", default=str(FINETUNED.relative_to(REPO)), help="a folder holding the fine-tuned cconv.pt"
    )
    ap.add_argument("--frames", type=int, nargs="+", default=[2, 6], help="unroll lengths F of the windows")
    ap.add_argument("--data", default="data/dlf_frames")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--results", default=str(RESULTS))
    args = ap.parse_args(argv)
    if min(args.frames) < 1:
        ap.error(f"--frames must be >= 1, got {min(args.frames)}")
    torch.set_num_threads(args.threads)
    load = os.getloadavg()[0]
    tuned, _ = load_cconv(Path(args.weights) / "cconv.pt")
    rows = []
    for frames in args.frames:
        cfg = compose_config(["experiment=finetune_cconv_dlf", f"train.unroll_frames={frames}"])
        trainable = CConvTrainable(cfg)
        start = trainable.build_network()  # their published weights with the data's gravity
        for label, net in (("DLF's weights (start)", start), ("fine-tuned here", tuned)):
            row = {"network": label, "frames F": frames}
            for split in ("valid", "test"):
                loss, error = split_losses(trainable, net, Path(args.data), split)
                row[f"{split} loss"] = f"{loss:.3f}"
                row[f"{split} step-F error (mm)"] = f"{error:.2f}"
            rows.append(row)
            print(row, flush=True)
    intro = (
        "# CConv: DeepLagrangianFluids' weights before and after fine-tuning here\n\n"
        + __doc__.split("\n\n")[1].replace("\n", " ")
        + f"\n\nStart: `{DLF_WEIGHTS.name}` (their published file); fine-tuned: `{args.weights}/cconv.pt`."
    )
    frames = " ".join(map(str, args.frames))
    command = f"python -m benchmarks.cconv_finetune_loss --weights {args.weights} --data {args.data}"
    command += f" --frames {frames}"
    prov = provenance("benchmarks.cconv_finetune_loss", load, command=command, data=str(args.data))
    print(write_results(Path(args.results), "cconv_finetune_loss", rows, intro, prov))


if __name__ == "__main__":
    main()
