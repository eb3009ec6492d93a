"""Statistics that describe a generated dataset (``metadata.json``), computed from its files in one pass.

They describe the data (LagrangeBench keys included); a network's normalisation is fitted by its trainable
(:mod:`lagfluid.models.trainable`) and lives in its checkpoint.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from lagfluid.data.layout import GROUP, read_scene_info


class RunningStats:
    """Mean, standard deviation, min and max of a stream of values, merged batch by batch in float64.

    Values are (n,) for a scalar feature or (n, d) for a vector feature (per component).
    """

    def __init__(self) -> None:
        self.count = 0
        self.mean: np.ndarray | None = None
        self.m2: np.ndarray | None = None
        self.min: np.ndarray | None = None
        self.max: np.ndarray | None = None

    def update(self, values: np.ndarray) -> None:
        """Add a batch of values (Chan et al.'s parallel update: stable for any batch sizes)."""
        x = np.asarray(values, dtype=np.float64)
        n = x.shape[0]
        if n == 0:
            return
        mean, m2 = x.mean(axis=0), ((x - x.mean(axis=0)) ** 2).sum(axis=0)
        if self.count == 0:
            self.count, self.mean, self.m2 = n, mean, m2
            self.min, self.max = x.min(axis=0), x.max(axis=0)
            return
        total = self.count + n
        delta = mean - self.mean
        self.mean = self.mean + delta * n / total
        self.m2 = self.m2 + m2 + delta**2 * self.count * n / total
        self.min, self.max = np.minimum(self.min, x.min(axis=0)), np.maximum(self.max, x.max(axis=0))
        self.count = total

    def result(self) -> dict[str, Any]:
        """``mean``, ``std`` (population), ``min``, ``max``: floats or lists; ``count``."""
        if self.count == 0:
            return {"mean": None, "std": None, "min": None, "max": None, "count": 0}

        def out(a: np.ndarray) -> Any:
            return a.tolist() if a.ndim else float(a)

        return {
            "mean": out(self.mean),
            "std": out(np.sqrt(self.m2 / self.count)),
            "min": out(self.min),
            "max": out(self.max),
            "count": int(self.count),
        }


STATISTICS = {
    "speed": "|v^n| of the fluid particles (advection-net input; vel_scaler of the authors)",
    "velocity": "v^n of the fluid particles, per component, m/s",
    "acceleration": "advection label a = nu lap(v) + g, per component, m/s^2 (acc_scaler)",
    "acceleration_norm": "|a|, m/s^2",
    "pressure": "PPE solution on the unknowns (pressure-net label, before the clamp), Pa (prs_scaler)",
    "density_ratio": "n / n0 on the PPE unknowns (pressure-net input; dns_scaler)",
    "pressure_speed": "|v**| of the fluid PPE unknowns (pressure-net input)",
    "collision_speed": "|v*| in the collision systems, m/s",
    "collision_delta_velocity": "collision label v** - v*, per component, m/s",
}
"""Feature name -> what it measures (every entry of ``metadata.json["statistics"]``)."""


def dataset_statistics(paths: Iterable[str | os.PathLike]) -> dict[str, Any]:
    """Statistics of the features in :data:`STATISTICS` plus LagrangeBench's ``vel_*``/``acc_*`` over files.

    Returns:
        ``{"statistics": {feature: {mean, std, min, max, count}}, "vel_mean": [3], "vel_std": [3],
        "acc_mean": [3], "acc_std": [3]}``; LagrangeBench's are differences of positions between the uniformly
        spaced frames (m per frame), first (vel) and second (acc) order.
    """
    stats = {name: RunningStats() for name in STATISTICS}
    lb_vel, lb_acc = RunningStats(), RunningStats()
    for path in paths:
        path = Path(path)
        info = read_scene_info(path)
        with h5py.File(path, "r") as f:
            g, s = f[GROUP], f["samples"]
            nf, n0 = info.n_fluid, float(info.attrs["n0"])
            frames = s["frame"][()]
            vel = g["velocity"][()][frames].reshape(-1, 3)
            stats["velocity"].update(vel)
            stats["speed"].update(np.linalg.norm(vel, axis=1))
            acc = s["advection/acceleration"][()].reshape(-1, 3)
            stats["acceleration"].update(acc)
            stats["acceleration_norm"].update(np.linalg.norm(acc, axis=1))
            index = s["pressure/index"][()]
            stats["pressure"].update(s["pressure/pressure"][()])
            stats["density_ratio"].update(s["pressure/number_density"][()] / n0)
            offsets, p_vel = s["pressure/offsets"][()], s["pressure/velocity"][()]
            for k in range(len(frames)):
                rows = index[offsets[k] : offsets[k + 1]]
                fluid = rows[rows < nf]
                stats["pressure_speed"].update(np.linalg.norm(p_vel[k][fluid], axis=1))
            c = s["collision"]
            stats["collision_speed"].update(np.linalg.norm(c["velocity"][()].reshape(-1, 3), axis=1))
            stats["collision_delta_velocity"].update(c["delta_velocity"][()].reshape(-1, 3))
            uniform = int(info.attrs["steps"]) // int(info.attrs["sample_every"]) + 1
            pos = g["position"][: min(uniform, info.frames)].astype(np.float64)
            if pos.shape[0] >= 2:
                d1 = np.diff(pos, axis=0)
                lb_vel.update(d1.reshape(-1, 3))
                if pos.shape[0] >= 3:
                    lb_acc.update(np.diff(d1, axis=0).reshape(-1, 3))
    v, a = lb_vel.result(), lb_acc.result()
    return {
        "statistics": {name: st.result() for name, st in stats.items()},
        "vel_mean": v["mean"],
        "vel_std": v["std"],
        "acc_mean": a["mean"],
        "acc_std": a["std"],
    }
