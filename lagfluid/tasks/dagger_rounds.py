"""``train.dagger.rounds=R``: DAgger for end-to-end models (GNS), with the MPS solver as the expert.

An end-to-end model trained on MPS's trajectories meets, in its own rollouts, states MPS never visits: on
the dam, GNS drives fluid into a wall it was never shown that close, and the guard stops it
(``benchmarks/results/wall_approach.md``). Round k of ``R`` (in a ``task=train`` run's ``out_dir``):

1. ``<out_dir>/dagger/round<k>/data``: the training dataset's own training scenes (same scene, seeds,
   steps, materials; fingerprints checked before anything runs) rolled out by the model with its weights
   of round k-1 (round 0: ``train.dagger.start_from``, or the run's own one-step training in ``out_dir``),
   labelled every ``train.dagger.every``-th frame by one MPS model step from the model's state, up to
   where the model's guard stops it (:mod:`lagfluid.tasks.generate.expert`; layout
   :mod:`lagfluid.data.expert_windows`);
2. each of the model's trainables fine-tuned from its round k-1 weights (``train.init_from``) on the
   original data and rounds 1..k's together (``train.extra_data``: DAgger's aggregation; validation stays
   on the original's valid split), ``train.dagger.iterations`` at ``train.dagger.lr_start`` decaying to
   ``train.lr_end``, with the profile's other settings (noise, pushforward), into
   ``<out_dir>/dagger/round<k>/<name>.pt``: each round folder is a complete ``model.weights``;
3. with ``train.dagger.dam_steps`` > 0, that round's rollout of the dam, complete or where the guard
   stopped it (:mod:`lagfluid.tasks.dagger_eval`, also for round 0), in ``<out_dir>/dagger/dam.csv``.

**The policy with exact stages after it.** With ``model.exact_after`` on, the rounds roll out the model
followed by those stages (the hybrid row the tables show, e.g. ``cconv_exact``) and label the hybrid's
states; the network trained is the model's own (the stages have no weights), so that it learns MPS's step
from the states the hybrid visits, and each round's dam rollout is the hybrid's.

Everything resumes: finished scenes are skipped, a fine-tune continues from its checkpoint (a finished one is
skipped), a dam rollout already measured for the same weights is not run again. The regenerated scenes must
be the dataset's: the command gives the settings it was generated with (``scene=random``).
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, open_dict

from lagfluid.errors import ConfigError
from lagfluid.registry import get_trainables
from lagfluid.tasks.dagger_eval import dam_result, scene_config, write_summary
from lagfluid.tasks.onpolicy_rounds import dataset_generate_config, generate_scenes, round_dir

log = logging.getLogger(__name__)

FOLDER = "dagger"
KEYS = (
    "rounds",
    "every",
    "horizon",
    "iterations",
    "lr_start",
    "jobs",
    "start_from",
    "dam_steps",
    "dam_scene",
)


@dataclass(frozen=True)
class DAgger:
    """``train.dagger``, checked.

    Attributes:
        rounds: R, the number of rounds (0: none).
        every: label every k-th frame the model made (1: each).
        horizon: model steps of MPS in each label (1; CConv, which trains on two-step unrolls: 2).
        iterations: fine-tuning iterations per round and trainable.
        lr_start: learning rate of each round's first iteration (decays to ``train.lr_end``).
        jobs: scenes rolled out at once, each in its own one-thread process.
        start_from: a folder of the model's weights for round 0; None: the run's one-step training.
        dam_steps: steps of the per-round rollout of ``dam_scene`` (0: none).
        dam_scene: the scene of that rollout.
    """

    rounds: int
    every: int = 1
    horizon: int = 1
    iterations: int = 1
    lr_start: float = 1e-4
    jobs: int = 1
    start_from: Path | None = None
    dam_steps: int = 0
    dam_scene: str = "dam"

    @classmethod
    def from_config(cls, cfg: DictConfig) -> DAgger:
        """Read ``cfg.train.dagger`` (absent: no rounds).

        Raises:
            ConfigError: an unknown key, a number out of range (named with its value), or a ``start_from``
                that is not a folder.
        """
        section = dict(cfg.train.get("dagger") or {})
        unknown = sorted(set(section) - set(KEYS))
        if unknown:
            raise ConfigError(f"train.dagger has no key {unknown[0]!r}; keys: {', '.join(KEYS)}")
        numbers = {"rounds": 0, "every": 1, "horizon": 1, "iterations": 1, "jobs": 1, "dam_steps": 0}
        values = {key: section.get(key, cls.__dataclass_fields__[key].default) for key in numbers}
        values["rounds"] = section.get("rounds") or 0
        for key, least in numbers.items():
            value = values[key]
            if isinstance(value, bool) or not isinstance(value, int) or value < least:
                raise ConfigError(f"train.dagger.{key} must be a whole number >= {least}, got {value!r}")
        lr_start = section.get("lr_start")
        lr_start = cfg.train.lr_start if lr_start is None else lr_start
        if isinstance(lr_start, bool) or not isinstance(lr_start, (int, float)) or not lr_start > 0:
            raise ConfigError(f"train.dagger.lr_start must be a number > 0, got {lr_start!r}")
        stride = cfg.train.get("frame_stride", 1)
        if values["rounds"] and stride != 1:  # else refused only at round 1's fine-tune, after its rollouts
            raise ConfigError(
                f"train.dagger labels the model's own steps, one stored frame each: train.frame_stride must "
                f"be 1 with rounds, got {stride!r}"
            )
        start = section.get("start_from")
        if start is not None and values["rounds"] and not Path(str(start)).is_dir():
            raise ConfigError(f"train.dagger.start_from={start} is not a folder of the model's weights")
        dam_scene = str(section.get("dam_scene") or "dam")
        if values["rounds"] and values["dam_steps"]:
            scene_config(dam_scene)  # an unknown scene fails now, not after the first round
        return cls(
            **values,
            lr_start=float(lr_start),
            start_from=None if start is None else Path(str(start)),
            dam_scene=dam_scene,
        )

    def weights(self, out_dir: Path, k: int) -> Path:
        """The folder of round ``k``'s weights (round 0: ``start_from`` or ``out_dir``)."""
        if k == 0:
            return self.start_from or out_dir
        return round_dir(out_dir, k, FOLDER)


def expert_data_config(
    cfg: DictConfig, policy: Path, data_dir: Path, every: int, horizon: int = 1
) -> DictConfig:
    """``cfg`` as the generation of the DAgger dataset ``data_dir``: the dataset's scenes, ``policy``'s model.

    The dataset's own generation settings (:func:`~lagfluid.tasks.onpolicy_rounds.dataset_generate_config`),
    moved by the model with the weights in ``policy`` (and ``cfg.model.exact_after``'s stages after each
    step, if on), labelled every ``every``-th frame by ``horizon`` model steps of MPS.
    """
    gen = dataset_generate_config(cfg, None, data_dir)
    with open_dict(gen):
        gen.data.policy = None  # the dataset's scenes as the solver made them; the model is the policy here
        gen.data.expert_every = every
        gen.data.expert_horizon = horizon
        gen.model.weights = str(policy)
    return gen


def _evaluate(
    cfg: DictConfig, settings: DAgger, out_dir: Path, k: int, results: list[dict[str, Any]]
) -> None:
    """Round ``k``'s dam rollout (when ``dam_steps`` > 0), added to ``results`` and to ``dam.csv``."""
    if not settings.dam_steps:
        return
    here = round_dir(out_dir, k, FOLDER) if k else out_dir / FOLDER / "round0"
    weights = settings.weights(out_dir, k)
    results.append(dam_result(cfg, k, weights, settings.dam_scene, settings.dam_steps, here / "dam"))
    write_summary(out_dir / FOLDER / "dam.csv", results)


def run_dagger(
    cfg: DictConfig,
    settings: DAgger,
    out_dir: Path,
    train_one: Callable[[DictConfig, Any, Path], dict[str, Any]],
) -> Path:
    """Run (or resume) every DAgger round after the start weights (module doc).

    Args:
        cfg: the ``task=train`` config.
        settings: its ``train.dagger`` (:meth:`DAgger.from_config`, rounds >= 1).
        out_dir: the run's folder.
        train_one: :func:`lagfluid.tasks.train.train_one` (passed in: this module is one of its callers').

    Returns:
        the last round's folder (a complete ``model.weights``).

    Raises:
        ConfigError: a network of the model missing from the start weights, or a split-step model.
    """
    from lagfluid.tasks.generate.expert import end_to_end_simulator, generate_expert, train_scenes
    from lagfluid.tasks.generate.spec import DataSpec

    model, names = str(cfg.model.name), list(get_trainables(str(cfg.model.name), cfg))
    start = settings.weights(out_dir, 0)
    missing = [name for name in names if not (start / f"{name}.pt").is_file()]
    if missing:
        raise ConfigError(
            f"train.dagger.rounds={settings.rounds}: the rounds start from model {model}'s weights, but "
            f"{', '.join(missing)}.pt is not in {start}; train it first or set train.dagger.start_from"
        )
    probe = copy.deepcopy(cfg)
    with open_dict(probe):
        probe.model.weights = str(start)
    end_to_end_simulator(probe)  # a split-step model fails here, before any rollout
    original = [str(d) for d in cfg.train.get("extra_data") or []]
    results: list[dict[str, Any]] = []
    _evaluate(cfg, settings, out_dir, 0, results)
    for k in range(1, settings.rounds + 1):
        previous, here = settings.weights(out_dir, k - 1), round_dir(out_dir, k, FOLDER)
        log.info("DAgger round %d of %d: %s's model rolls out the scenes", k, settings.rounds, previous)
        gen = expert_data_config(cfg, previous, here / "data", settings.every, settings.horizon)
        generate_scenes(gen, settings.jobs, generate_expert, train_scenes(DataSpec.from_config(gen)))
        tuned = copy.deepcopy(cfg)
        with open_dict(tuned):
            rounds = [str(round_dir(out_dir, j, FOLDER) / "data") for j in range(1, k + 1)]
            tuned.train.extra_data = [*original, *rounds]
            tuned.train.init_from = str(previous)
            tuned.train.lr_start = settings.lr_start
            for name in names:
                tuned.train.iterations[name] = settings.iterations
        trainables = get_trainables(model, tuned)
        for name in names:
            train_one(tuned, trainables[name], here)
        _evaluate(cfg, settings, out_dir, k, results)
    log.info("DAgger rounds done: %s", round_dir(out_dir, settings.rounds, FOLDER))
    return round_dir(out_dir, settings.rounds, FOLDER)
