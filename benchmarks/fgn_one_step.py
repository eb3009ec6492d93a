"""One-step accuracy of FGN's three networks on the held-out test split of a generated dataset.

Each network sees the test scenes' samples exactly as in training (its trainable's ``predict``,
:mod:`lagfluid.models.fgn.trainables`) and is
scored in physical units:

* advection: normalised MAE (paper eq. 32) of the acceleration, with gravity and viscosity drawn afresh
  per sample from the paper's Table 4 test ranges (g 1-100 m/s^2, nu 1e-4 to 0.1 m^2/s, log-uniform; a
  fixed seed, not the training draws), plus at water (g = 9.81, nu = 1e-6, the stored labels);
* collision: normalised MAE (eq. 32) of the velocity change, over the particles that collide;
* for both also ``rel_mae = sum_i ||error_i|| / sum_i ||target_i||`` (eq. 32 weights every particle's
  relative error alike, so particles with a tiny target dominate it);
* pressure: relative L2 error ``||p_pred - p||_2 / ||p||_2`` per sample against the PPE solution, and the
  Pearson correlation, mean over samples (the PPE residual of eq. 31 is measured on rollouts by
  ``task=evaluate``).

Usage::

    python -m benchmarks.fgn_one_step --weights lagfluid/weights/fgn --data data/cpu

Writes ``benchmarks/results/fgn_one_step.{md,csv}`` with provenance.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from statistics import mean, median
from typing import Any

import numpy as np
import torch
from hydra import compose, initialize_config_dir
from torch_geometric.data import Batch

from benchmarks.provenance import markdown_table, provenance, results_markdown, write_results
from lagfluid.metrics import normalized_mae
from lagfluid.models.fgn.networks import KINDS, load_network
from lagfluid.models.fgn.simulator import SHIPPED_WEIGHTS
from lagfluid.models.fgn.trainables import ResampledMaterials, build_trainables
from lagfluid.physics.settings import SolverSettings
from lagfluid.run import CONF_DIR

RESULTS = Path(__file__).resolve().parent / "results"
# The paper's Table 4 test materials: |g| in m/s^2 and nu in m^2/s (drawn log-uniformly here).
TABLE4_GRAVITY, TABLE4_VISCOSITY = (1.0, 100.0), (1.0e-4, 0.1)
HELD_OUT = "held-out g in [1, 100], nu in [1e-4, 0.1]"
WATER_GRAVITY, WATER_VISCOSITY = (
    (9.8065, 9.8065),
    (1.0e-6, 1.0e-6),
)  # the scenes' own: g + nu lap(v) as stored


def _physical(net: torch.nn.Module, kind: str, pred: torch.Tensor, target: torch.Tensor, item: Any) -> tuple:
    """Undo the standardisation of the trainable's ``predict`` outputs: (prediction, target) in SI units.

    An advection net ``linear_in_viscosity`` is trained on the Laplacian ``L``: both become the acceleration
    ``g + nu L`` of ``item`` (its gravity (1, 3), its viscosity (1,)), so every net is scored on ``a``.
    """
    if kind == "collision":  # scaled only: a velocity change has no offset
        return pred * net.target.std, target * net.target.std
    if kind == "pressure":  # (M,) <-> the (M, 1) the standardizer holds
        return (net.target.inverse(t.unsqueeze(1)).squeeze(1) for t in (pred, target))
    pred, target = net.target.inverse(pred), net.target.inverse(target)
    if getattr(net, "linear_in_viscosity", False):
        return (item.gravity + item.viscosity * t for t in (pred, target))
    return pred, target


def score(task: Any, net: torch.nn.Module, items: list) -> dict[str, float]:
    """Per-sample scores of ``net`` on ``items`` (PyG ``Data``) through trainable ``task``, averaged."""
    kind = task.name
    values: dict[str, list[float]] = {}
    with torch.no_grad():
        for item in items:
            pred, target = _physical(net, kind, *task.predict(net, Batch.from_data_list([item])), item)
            if kind == "pressure":
                p, y = pred.double().numpy(), target.double().numpy()
                values.setdefault("rel_l2", []).append(float(np.linalg.norm(p - y) / np.linalg.norm(y)))
                values.setdefault("corr", []).append(float(np.corrcoef(p, y)[0, 1]))
            else:
                if kind == "collision":
                    moving = target.norm(dim=1) > 0
                    if not bool(moving.any()):
                        continue
                    pred, target = pred[moving], target[moving]
                values.setdefault("nmae", []).append(normalized_mae(pred, target))
                # eq. 32 divides each error by its own target: particles that barely collide dominate it
                err, ref = (pred - target).norm(dim=1).sum(), target.norm(dim=1).sum()
                values.setdefault("rel_mae", []).append(float(err / ref))
    return (
        {k: mean(v) for k, v in values.items()}
        | {f"{k}_median": median(v) for k, v in values.items()}
        | {"n": len(next(iter(values.values()), []))}
    )


def one_step_rows(
    weights: str | os.PathLike, data: str, split: str = "test", max_samples: int = 100, seed: int = 12345
) -> list[dict[str, Any]]:
    """Every network's one-step scores on ``split`` of ``data``: a row per (network, case).

    Args:
        weights: directory of the three checkpoints.
        data: generated dataset (``task=generate`` out_dir).
        split: its split to score on.
        max_samples: the first this many samples of the split.
        seed: seed of the held-out material draws of the advection net.
    """
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["task=train", "model=fgn"])
    settings = SolverSettings.from_config(cfg.solver)
    trainables = build_trainables(cfg)
    rows = []
    for kind in KINDS:
        net, ckpt = load_network(Path(weights) / f"{kind}.pt", kind)
        samples = trainables[kind].samples(data, split=split)
        pick = range(min(len(samples), max_samples))
        variants = {"test split": samples}
        if kind == "advection":
            held_out = ResampledMaterials(
                samples, TABLE4_GRAVITY, TABLE4_VISCOSITY, True, settings, seed, fixed=True
            )
            water = samples  # the stored labels; a net trained on the Laplacian needs it computed
            if getattr(net, "linear_in_viscosity", False):
                water = ResampledMaterials(
                    samples, WATER_GRAVITY, WATER_VISCOSITY, False, settings, seed, fixed=True
                )
            variants = {HELD_OUT: held_out, "water (stored labels)": water}
        for name, dataset in variants.items():
            result = score(trainables[kind], net, [dataset[i] for i in pick])
            rows.append({"network": kind, "case": name, "step": ckpt["step"], **result})
            print(rows[-1], flush=True)
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default=str(SHIPPED_WEIGHTS), help="directory of the three checkpoints")
    ap.add_argument("--data", default="data/cpu", help="generated dataset (task=generate out_dir)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--max-samples", type=int, default=100)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--seed", type=int, default=12345, help="seed of the held-out material draws")
    ap.add_argument("--no-save", action="store_true")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    load = os.getloadavg()[0]
    rows = one_step_rows(args.weights, args.data, args.split, args.max_samples, args.seed)
    prov = provenance(
        "benchmarks.fgn_one_step", load, "cpu", weights=str(args.weights), data=args.data, split=args.split
    )
    header = ["network", "case", "step", "n", "nmae", "nmae_median", "rel_mae"]
    header += ["rel_l2", "rel_l2_median", "corr"]
    table_rows = [{k: r.get(k, "") for k in header} for r in rows]  # a network's columns, blank elsewhere
    body = markdown_table(table_rows, cell=lambda v: f"{v:.4g}" if isinstance(v, float) else str(v))
    intro = (
        f"# FGN networks, one step on the `{args.split}` split of `{args.data}`\n\n"
        "nmae: normalised MAE (eq. 32), mean over samples (median beside it); rel_mae: sum ||error|| / "
        "sum ||target|| per sample; rel_l2: "
        "||p - p_PPE|| / ||p_PPE|| per sample; corr: Pearson correlation with the PPE pressure."
    )
    if args.no_save:
        print(results_markdown(table_rows, intro, prov, body))
    else:
        print(write_results(RESULTS, "fgn_one_step", table_rows, intro, prov, body))


if __name__ == "__main__":
    main()
