"""Which simulators the tables compare, in which order and under which label: registry plus row files.

A simulator of the tables is a key ``K`` with row files in Hydra's ``experiment`` group: ``table2_K``
(Table 2), ``table3_<case>_K`` (Tables 1/3, one per case) and ``table5_<case>_K`` (the Table 5 ablations,
beside Table 3's FGN and MPS rows of the case). Each row file says how the tables show it::

    table: {label: "hybrid: learned pressure", order: 2, weights: fgn}

``label`` names the row (default: the key), ``order`` places it (smallest first; rows without one follow,
by key), ``weights`` says which weights the tables pass (:data:`WEIGHTS`), ``note`` is a sentence the
parts print under a table the key appears in (e.g. what its weights are). Every row file of a key gives
the same ``label``, ``order``, ``weights`` and ``note``. ``timing_steps`` (a ``table2_K`` file only) caps
the steps Table 2 times for the key at that many (the profile's number when it is smaller), for a network
too slow to time the profile's number of steps; Table 2 prints every row's warm-up and timed steps.

A key appears in the tables it has row files for: a key with only ``table2_K`` is timed in Table 2 and
appears nowhere else (e.g. an untrained network of some size: a time per step, no accuracy to report);
it is then in neither Tables 1/3 nor the trade-off. A registered simulator that no row file runs
(``lagfluid.registry.available_simulators``) is listed after them, appears in every table and is run as
``model=<name>`` with its defaults. So a new simulator is a registry entry plus its row files; nothing in
``benchmarks/`` names it.

The block is read from each row *composed by Hydra* (not from the yaml file): the tables then see every
row Hydra can run (``conf/experiment/``, a plugin's config folder on the search path, a ConfigStore node)
and the model the row really composes to. Config files may add keys in struct mode (only command-line
overrides need ``+``), so ``table`` needs no declaration in ``config.yaml``; a run of the row carries it
unused.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cache
from typing import Any

from omegaconf import OmegaConf

from benchmarks.tables.config import compose_config, experiment_names
from lagfluid.errors import ConfigError
from lagfluid.registry import available_simulators

# Published weights (the FGN authors', DeepLagrangianFluids') ship in the package as their models' defaults,
# so their rows are ``weights: none``. A row whose weights are missing (a model without shipped weights) is
# skipped with the loader's reason (``Run.skipped``), not failed.
WEIGHTS = {
    "none": "the row's own config (MPS; a model that finds its own weights, shipped or published)",
    "fgn": "--weights DIR when given (FGN's three checkpoints), else the model's default (shipped weights)",
}

# Table 3's cases: the row files ``table3_<case>_<key>``.
CASES = ("dam", "waterfall")

# The rows the paper's parts single out: its ground truth, its model, and the hybrid whose advection net
# Table 4 rolls out on held-out materials.
GROUND_TRUTH, FGN, LEARNED_ADVECTION = "mps", "fgn", "hybrid_advection"

_ROW = re.compile(rf"^table(?:2|[35]_(?:{'|'.join(CASES)}))_(?P<key>.+)$")
_BLOCK_KEYS = {"label", "order", "weights", "note", "timing_steps"}


@dataclass(frozen=True)
class Simulator:
    """One simulator of the tables: its key (row files ``table3_<case>_<key>``, ``table2_<key>``).

    Attributes:
        key: the rows' key (``hybrid_pressure``).
        label: the tables' name of it (``hybrid: learned pressure``).
        model: the registered simulator its rows compose to (``model=...``), used for a row without a file.
        weights: which weights the tables pass, a key of :data:`WEIGHTS`.
        note: a sentence on the row for the parts' text ('' when none).
        timing_steps: at most this many timed steps in Table 2 (None: the profile's number).
        rows: the key's row files (``table2_<key>``, ...); empty for a registered simulator without any,
            which then appears in every table.
    """

    key: str
    label: str
    model: str
    weights: str = "none"
    note: str = ""
    timing_steps: int | None = None
    rows: tuple[str, ...] = field(default=(), compare=False, repr=False)

    def appears_in(self, row: str) -> bool:
        """Whether the tables run this key's row ``row`` (``table2_<key>``, ``table3_dam_<key>``, ...).

        A key with row files appears in the tables it has files for; one without appears in all of them.
        """
        return not self.rows or row in self.rows

    def model_overrides(self, weights_dir: str | None) -> list[str]:
        """The ``model.weights`` override of this simulator's rows (``weights_dir``: ``--weights``)."""
        if self.weights == "fgn" and weights_dir:
            return [f"model.weights={weights_dir}"]
        return []


@cache
def _row(name: str) -> tuple[str, dict[str, Any]]:
    """The model name and the ``table`` block of ``experiment=<name>``, checked.

    Raises:
        ConfigError: the row does not compose, or its block has an unknown key or a bad value.
    """
    try:
        cfg = compose_config([f"experiment={name}"])
    except Exception as err:
        raise ConfigError(f"row file experiment={name} does not compose: {err}") from err
    block = cfg.get("table")
    block = {} if block is None else OmegaConf.to_container(block, resolve=True)
    if not isinstance(block, dict) or set(block) - _BLOCK_KEYS:
        raise ConfigError(
            f"experiment={name}: table must be a mapping of {sorted(_BLOCK_KEYS)}, got {block!r}"
        )
    weights = block.get("weights", "none")
    if weights not in WEIGHTS:
        raise ConfigError(f"experiment={name}: table.weights '{weights}' is not one of {', '.join(WEIGHTS)}")
    order = block.get("order", math.inf)
    if not isinstance(order, (int, float)) or isinstance(order, bool):
        raise ConfigError(f"experiment={name}: table.order must be a number, got {order!r}")
    if not isinstance(block.get("note", ""), str):
        raise ConfigError(f"experiment={name}: table.note must be a sentence, got {block['note']!r}")
    if "timing_steps" in block:
        steps = block["timing_steps"]
        if not name.startswith("table2_"):
            raise ConfigError(f"experiment={name}: table.timing_steps is for a Table 2 row (table2_<key>)")
        if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
            raise ConfigError(f"experiment={name}: table.timing_steps must be an integer >= 1, got {steps!r}")
    return str(cfg.model.name), block


def _from_rows(key: str, names: Sequence[str]) -> tuple[float, Simulator]:
    """The simulator ``key`` as its row files ``names`` describe it, and its order.

    Raises:
        ConfigError: two row files of the key disagree (label, order, weights or model).
    """
    seen: dict[tuple[str, str, str, float, str], str] = {}
    timing_steps = None
    for name in names:
        model, block = _row(name)
        described = (str(block.get("label", key)), model, block.get("weights", "none"))
        seen.setdefault((*described, block.get("order", math.inf), block.get("note", "")), name)
        timing_steps = block.get("timing_steps", timing_steps)  # only table2_<key> may hold it (_row)
    if len(seen) > 1:
        described = "; ".join(f"{n}: label, model, weights, order, note = {v}" for v, n in seen.items())
        raise ConfigError(f"the row files of '{key}' describe it differently ({described})")
    (label, model, weights, order, note), _ = next(iter(seen.items()))
    return float(order), Simulator(key, label, model, weights, note, timing_steps, tuple(sorted(names)))


def all_simulators(keys: Sequence[str] | None = None) -> list[Simulator]:
    """Every simulator with row files (by ``order``), then every registered one without (by name).

    Args:
        keys: keep only these keys (None: all).

    Raises:
        ConfigError: a row file that does not compose or whose ``table`` block is bad.
    """
    rows: dict[str, list[str]] = {}
    for name in experiment_names():
        match = _ROW.match(name)
        if match:
            rows.setdefault(match["key"], []).append(name)
    described = sorted(
        (_from_rows(key, names) for key, names in rows.items()), key=lambda o: (o[0], o[1].key)
    )
    sims = [sim for _, sim in described]
    known = {s.model for s in sims}
    sims += [Simulator(n, n, n) for n in available_simulators() if n not in known]
    return [s for s in sims if keys is None or s.key in keys]


def simulator(key: str) -> Simulator:
    """The simulator ``key`` of :func:`all_simulators`.

    Raises:
        ConfigError: no simulator has that key (the message lists them).
    """
    sims = all_simulators()
    for sim in sims:
        if sim.key == key:
            return sim
    raise ConfigError(f"no simulator '{key}' in the tables; available: {', '.join(s.key for s in sims)}")
