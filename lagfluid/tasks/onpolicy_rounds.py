"""``train.onpolicy.rounds=R``: DAgger after the one-step training, with the MPS solver as the expert.

A network trained on the solver's trajectories meets, in its own rollouts, states the solver never visits
(a learned pressure that under-corrects leaves the fluid more compressed than MPS ever is). Round k of
``R`` (in a ``task=train`` run's ``out_dir``):

1. ``<out_dir>/onpolicy/round<k>/data``: the training dataset's own scenes (same scene, seeds, steps,
   materials) rolled out by the run's model with its networks of round k-1 (round 0: the one-step trained
   ones in ``out_dir``, or ``train.onpolicy.start_from``'s: a folder of the model's weights, shipped or
   another run's, and then nothing is trained in ``out_dir`` first), each sample labelled by the exact MPS
   stage at the model's own state (``data.policy=model``, :mod:`lagfluid.tasks.generate.policy`);
2. each of ``train.onpolicy.trainables`` (the pressure net by default) fine-tuned on it (with
   ``train.onpolicy.aggregate``: on rounds 1..k's data together) from its round k-1 weights:
   ``train.onpolicy.iterations`` at ``train.onpolicy.lr_start`` decaying to ``train.lr_end``, PPE term
   at ``train.onpolicy.ppe_weight``, into ``<out_dir>/onpolicy/round<k>/<name>.pt``; the model's
   other networks are copied beside it (no optimizer state), so each round folder is a complete
   ``model.weights`` for the next round, for ``task=evaluate`` and for the export.

Everything resumes: finished scenes are skipped by ``task=generate``, a fine-tune continues from its
checkpoint, a finished one is skipped. The regenerated scenes must be the dataset's: the command has to
give the settings the dataset was generated with (``scene=random``); the scenes' fingerprints are checked
before any simulation. What each round bought on the dam: ``benchmarks/results/fgn_recipe.md``.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict

from lagfluid.data.datasets import load_metadata
from lagfluid.data.layout import scene_path
from lagfluid.errors import ConfigError, LagfluidError
from lagfluid.models.checkpoint import export_weights
from lagfluid.registry import get_trainables

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OnPolicy:
    """``train.onpolicy``, checked.

    Attributes:
        rounds: R, the number of rounds (0: none).
        trainables: the networks fine-tuned in each round (names of the model's trainables).
        iterations: fine-tuning iterations per round and trainable.
        lr_start: learning rate of each round's first iteration (decays to ``train.lr_end``).
        ppe_weight: the pressure net's PPE term while fine-tuning (``train.ppe_weight``'s meaning).
        aggregate: round k fine-tunes on the union of rounds 1..k's data (DAgger's aggregation) instead
            of round k's alone.
        jobs: scenes generated at once, each in its own one-thread process (one per core pays: the
            solver's step scales poorly over threads).
        start_from: a folder of the model's weights for round 0 (each of its trainables' ``<name>.pt``);
            None: the run's one-step training in ``out_dir``.
    """

    rounds: int
    trainables: tuple[str, ...]
    iterations: int
    lr_start: float
    ppe_weight: float
    aggregate: bool = False
    jobs: int = 1
    start_from: Path | None = None

    @classmethod
    def from_config(cls, cfg: DictConfig, model_trainables: Sequence[str]) -> OnPolicy:
        """Read ``cfg.train.onpolicy`` (absent: no rounds).

        Raises:
            ConfigError: a negative or fractional number of rounds or iterations, a learning rate <= 0,
                a trainable the model does not have, or a ``start_from`` that is not a folder.
        """
        section = cfg.train.get("onpolicy") or {}
        rounds, iterations = section.get("rounds", 0) or 0, section.get("iterations", 1)
        jobs = section.get("jobs", 1)
        for key, value, least in (("rounds", rounds, 0), ("iterations", iterations, 1), ("jobs", jobs, 1)):
            if isinstance(value, bool) or not isinstance(value, int) or value < least:
                raise ConfigError(f"train.onpolicy.{key} must be a whole number >= {least}, got {value!r}")
        names = tuple(str(n) for n in section.get("trainables") or ())
        unknown = [n for n in names if n not in model_trainables]
        if rounds and (unknown or not names):
            raise ConfigError(
                f"train.onpolicy.trainables={list(names)}: model {cfg.model.name} trains "
                f"{', '.join(model_trainables)}"
            )
        lr_start = float(section.get("lr_start") or cfg.train.lr_start)
        if not lr_start > 0:
            raise ConfigError(f"train.onpolicy.lr_start must be > 0, got {lr_start}")
        start = section.get("start_from")
        if start is not None and rounds and not Path(str(start)).is_dir():
            raise ConfigError(f"train.onpolicy.start_from={start} is not a folder of the model's weights")
        return cls(
            rounds,
            names,
            int(iterations),
            lr_start,
            float(section.get("ppe_weight") or 0.0),
            bool(section.get("aggregate", False)),
            int(jobs),
            None if start is None else Path(str(start)),
        )

    def weights(self, out_dir: Path, k: int) -> Path:
        """The folder of round ``k``'s weights (round 0: ``start_from`` or ``out_dir``)."""
        if k == 0:
            return self.start_from or out_dir
        return round_dir(out_dir, k)


def round_dir(out_dir: Path, k: int, folder: str = "onpolicy") -> Path:
    """Round ``k``'s folder (its data and networks); round 0 is ``out_dir`` itself.

    ``folder``: the rounds' folder in ``out_dir`` (``dagger`` for :mod:`lagfluid.tasks.dagger_rounds`).
    """
    return out_dir if k == 0 else out_dir / folder / f"round{k}"


def dataset_generate_config(cfg: DictConfig, policy_dir: Path | None, data_dir: Path) -> DictConfig:
    """``cfg`` as the ``task=generate`` of the training dataset's scenes (``policy_dir``: its networks).

    ``policy_dir=None``: the dataset itself (moved by the solver), to check that this config makes it.
    """
    gen = copy.deepcopy(cfg)
    with open_dict(gen):
        gen.task = "generate"
        gen.steps = int(cfg.data.steps)
        gen.num_scenes = int(cfg.data.num_scenes)
        gen.data.scene_index = None
        gen.data.out_dir = str(data_dir)
        if policy_dir is not None:
            gen.data.name = f"{cfg.data.name}_onpolicy"
            gen.data.policy = "model"
            gen.data.next_steps = 0  # the trajectory is the model's: no windows for trajectory learners
            gen.model.weights = str(policy_dir)
    return gen


def generate_scenes(
    gen: DictConfig, jobs: int, make: Callable[[DictConfig], Any] | None = None, scenes: Sequence[int] = ()
) -> None:
    """``make(gen)``: with ``jobs`` > 1 its scenes first, one one-thread process each.

    Args:
        gen: the generation config (``data.scene_index`` set per job).
        jobs: processes at once.
        make: the generation task (default :func:`lagfluid.tasks.generate.generate`; a DAgger dataset's:
            :func:`lagfluid.tasks.generate.expert.generate_expert`).
        scenes: the scene indices ``make`` generates (default: all ``gen.num_scenes``).
    """
    from lagfluid.tasks.generate import generate

    make = make or generate
    scenes = list(scenes) or list(range(int(gen.num_scenes)))
    if jobs > 1:
        from joblib import Parallel, delayed, parallel_config

        def one_scene(k: int) -> DictConfig:
            plain = OmegaConf.to_container(gen, resolve=True)  # nothing left to resolve in the worker
            plain["data"]["scene_index"], plain["threads"] = k, 1  # type: ignore[index]
            return OmegaConf.create(plain)

        # inner_max_num_threads: OMP_NUM_THREADS=1 in each worker, so no OpenMP thread spins beside it
        log.info("%d scenes, %d at a time (joblib reports each on stderr)", len(scenes), jobs)
        with parallel_config(backend="loky", inner_max_num_threads=1):
            Parallel(n_jobs=jobs, verbose=10)(delayed(make)(one_scene(k)) for k in scenes)
    make(gen)  # what no job made (none, unless one failed), then metadata.json


def check_same_scenes(cfg: DictConfig, option: str = "train.onpolicy.rounds") -> None:
    """Refuse a command that would not regenerate the training dataset's own scenes.

    ``option``: the rounds' key, for the message (``train.dagger.rounds``).

    Raises:
        ConfigError: a scene of ``data.out_dir`` was made with other settings than this command's
            (another ``scene=``, seed, steps, dt or solver), named with the dataset's scene builder.
    """
    from lagfluid.tasks.generate.scene import scene_done
    from lagfluid.tasks.generate.spec import DataSpec

    data_dir = Path(str(cfg.data.out_dir))
    spec = DataSpec.from_config(dataset_generate_config(cfg, None, data_dir))
    for k in range(spec.num_scenes):
        try:
            same = scene_done(scene_path(data_dir, k), spec.fingerprint(k))
        except LagfluidError:  # made with another configuration
            same = False
        if not same:
            builder = load_metadata(data_dir).get("scene", {}).get("builder", "?")
            raise ConfigError(
                f"{option} regenerates the scenes of {data_dir} moved by the model, but this "
                f"command does not make scene {k} as it was made (scene={cfg.scene.name}; the dataset's is "
                f"scene={builder}); give the settings the dataset was generated with"
            )


def run_rounds(
    cfg: DictConfig,
    settings: OnPolicy,
    out_dir: Path,
    train_one: Callable[[DictConfig, Any, Path], dict[str, Any]],
) -> Path:
    """Run (or resume) every round after the one-step training in ``out_dir``.

    Args:
        cfg: the ``task=train`` config.
        settings: its ``train.onpolicy`` (:meth:`OnPolicy.from_config`, rounds >= 1).
        out_dir: the run's folder, holding each of the model's one-step trained ``<name>.pt`` (unless
            ``settings.start_from`` holds round 0's).
        train_one: :func:`lagfluid.tasks.train.train_one` (passed in: this module is one of its callers').

    Returns:
        the last round's folder (a complete ``model.weights``).

    Raises:
        ConfigError: a network of the model missing from round 0's folder, or a command that does not
            regenerate the dataset's scenes (:func:`check_same_scenes`).
    """
    model = str(cfg.model.name)
    owned = list(get_trainables(model, cfg))
    start = settings.weights(out_dir, 0)
    missing = [name for name in owned if not (start / f"{name}.pt").is_file()]
    if missing:
        files = f"{', '.join(n + '.pt' for n in missing)} {'is' if len(missing) == 1 else 'are'}"
        hint = (
            "set train.onpolicy.start_from to a folder that has them"
            if settings.start_from
            else "train stage=all (or those stages) first"
        )
        raise ConfigError(
            f"train.onpolicy.rounds={settings.rounds}: the rounds roll out the run's own model, but "
            f"{files} not in {start}; {hint}"
        )
    for k in range(1, settings.rounds + 1):
        previous, here = settings.weights(out_dir, k - 1), settings.weights(out_dir, k)
        data_dir = here / "data"
        here.mkdir(parents=True, exist_ok=True)
        log.info(
            "on-policy round %d of %d: %s's model rolls out the scenes into %s",
            k,
            settings.rounds,
            previous,
            data_dir,
        )
        generate_scenes(dataset_generate_config(cfg, previous, data_dir), settings.jobs)
        tuned = copy.deepcopy(cfg)
        with open_dict(tuned):
            tuned.data.out_dir = str(data_dir)
            if settings.aggregate:
                tuned.train.extra_data = [str(round_dir(out_dir, j) / "data") for j in range(1, k)]
            tuned.train.init_from = str(previous)
            tuned.train.lr_start = settings.lr_start
            tuned.train.ppe_weight = settings.ppe_weight
            for name in settings.trainables:
                tuned.train.iterations[name] = settings.iterations
        trainables = get_trainables(model, tuned)
        for name in settings.trainables:
            train_one(tuned, trainables[name], here)
        # the model's other networks beside them, once: their bytes are in the next round's data fingerprint
        others = [n for n in owned if n not in settings.trainables and not (here / f"{n}.pt").is_file()]
        if others:
            export_weights(start, here, kinds=others)
    log.info("on-policy rounds done: %s", round_dir(out_dir, settings.rounds))
    return round_dir(out_dir, settings.rounds)
