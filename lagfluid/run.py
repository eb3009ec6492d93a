"""Command line: ``python -m lagfluid.run task=simulate|generate|train|evaluate model=... scene=...``.

Hydra composes ``conf/config.yaml`` with one file per group (``model/ scene/ solver/ train/ data/
experiment/``) in struct mode, so a misspelt key fails. Names of models and scenes are checked
*before* Hydra runs, so ``model=foo`` exits with one line naming the bad value and the available
names instead of Hydra's multi-line report.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
from collections.abc import Sequence
from pathlib import Path

import hydra
from omegaconf import DictConfig, open_dict

from lagfluid.errors import LagfluidError, Terminated
from lagfluid.memory import keep_freed_memory
from lagfluid.plugin_configs import CONF_DIR

log = logging.getLogger("lagfluid")

TASKS = ("simulate", "generate", "train", "evaluate", "export")


def _group_names(group: str) -> list[str]:
    """Options of a config group: ``conf/<group>/*.yaml`` and the plugins' (lagfluid.plugin_configs)."""
    from lagfluid.plugin_configs import group_options

    return group_options(group, CONF_DIR)


def available_models() -> list[str]:
    """Models selectable with ``model=``: config files in ``conf/model`` plus plugin simulators."""
    from lagfluid.registry import available_simulators

    return sorted(set(_group_names("model")) | set(available_simulators()))


CONFIG_GROUPS = ("scene", "data", "solver", "train", "experiment")  # besides model: conf/<group>/*.yaml


def help_config_groups() -> str:
    """The ``--help`` lines ``group: option, ...`` of every config group, plugins' options included.

    Hydra's own list (``$APP_CONFIG_GROUPS``) is made before the plugins' config folders join its search path
    (``hydra.searchpath`` applies only when composing), so it missed ``model=gns`` and ``train=gns_cpu``;
    ``conf/config.yaml``'s ``hydra.help.template`` shows this list instead (resolver
    ``${lagfluid.config_groups:}``).
    """
    from lagfluid.registry import trainable_models

    lines = [f"{group}: {', '.join(_group_names(group))}" for group in ("data", "experiment")]
    lines.append(f"model: {', '.join(available_models())}")
    lines.append(f"  (task=train trains: {', '.join(trainable_models())})")
    lines += [f"{group}: {', '.join(_group_names(group))}" for group in ("scene", "solver", "train")]
    return "\n".join(lines)


def check_command_line(argv: Sequence[str]) -> str | None:
    """Return a one-line error for an unknown ``task=``, config group value or key, else None.

    The groups: ``model=`` (configs and registered plugins), ``scene=``, ``data=``, ``solver=``, ``train=``,
    ``experiment=`` (core and plugin config folders).

    ``stage=`` is checked by ``task=train`` against the model's trainables (from the registry).
    A misspelt top-level key (``stepz=3``) gets the closest valid keys instead of Hydra's advice to append it
    (``+stepz=3``, which struct mode then refuses); a ``+key=value`` that appends a new top-level key is
    refused the same way: nothing reads it.
    """
    known = {
        "model": available_models,
        "task": lambda: list(TASKS),
        **{group: (lambda group=group: _group_names(group)) for group in CONFIG_GROUPS},
    }
    for arg in argv:
        key, sep, value = arg.partition("=")
        if sep and not key.startswith(("++", "~", "-")):  # not a forced add, a deletion, a flag
            unknown = _unknown_key(key.removeprefix("+"), appended=key.startswith("+"))
            if unknown:
                return unknown
        key = key.lstrip("+~")
        unknown = _unknown_exact_after_key(key)
        if unknown:
            return unknown
        if not sep or key not in known or "," in value:  # multirun sweeps are checked per job
            continue
        names = known[key]()
        if value not in names:
            return f"lagfluid: unknown {key} '{value}'; available: {', '.join(names)}"
    return None


def check_out_dir_argument(argv: Sequence[str]) -> str | None:
    """A one-line error when the command's ``out_dir=`` cannot become a folder we write into, else None.

    Checked before Hydra, which makes the folder first and would fail with a traceback (a file there, a file
    on the way, a folder without write permission).
    """
    for arg in argv:
        key, _, value = arg.partition("=")
        if key.lstrip("+") != "out_dir" or not value or "${" in value or "," in value:
            continue
        path = Path(value).expanduser().absolute()
        if path.exists() and not path.is_dir():
            return f"lagfluid: out_dir={value} is a file, not a folder"
        ancestor = next(p for p in (path, *path.parents) if p.exists())
        if not ancestor.is_dir():
            return f"lagfluid: out_dir={value} cannot be made: {ancestor} is a file"
        if not os.access(ancestor, os.W_OK | os.X_OK):
            return f"lagfluid: out_dir={value} cannot be made or written: {ancestor} is not writable"
    return None


def _unknown_exact_after_key(key: str) -> str | None:
    """The one-line error for ``model.exact_after.<key>`` that the node does not have, else None.

    Hydra's own (struct mode) is a multi-line message, or with ``+`` a key nothing would read; the keys
    are ``conf/config.yaml``'s (:mod:`lagfluid.models.exact_after` reads them).
    """
    prefix = "model.exact_after."
    if not key.startswith(prefix):
        return None
    from omegaconf import OmegaConf

    keys = list(OmegaConf.load(CONF_DIR / "config.yaml").model.exact_after)
    name = key.removeprefix(prefix)
    if name in keys:
        return None
    return f"lagfluid: model.exact_after has no key '{name}'; keys: {', '.join(keys)}"


def _unknown_key(key: str, appended: bool) -> str | None:
    """The one-line error for ``key=...`` when ``key`` is not in ``conf/config.yaml``, else None.

    Checked: top-level keys, and keys inside its own sections (``evaluate.horizons``, ``animation.fps``).
    Keys inside a config group (``scene.fluid_size``) depend on the option chosen and are left to Hydra, as
    are ``hydra.*`` and ``key@package`` forms. ``appended``: the key came as ``+key=...``.
    """
    import difflib

    from omegaconf import OmegaConf

    if "@" in key or "/" in key:
        return None
    parts = key.split(".")
    if parts[0] in ("hydra", "model", *CONFIG_GROUPS):
        return None  # Hydra's own settings, or a config group and the keys of the option chosen
    node = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "config.yaml"))  # interpolations unresolved
    for depth, part in enumerate(parts):
        if not isinstance(node, dict):
            return None  # below a value that is not a section (evaluate.reference is null): Hydra decides
        names = sorted(k for k in node if depth or k not in ("defaults", "hydra"))
        names = sorted({*names, *([] if depth else ["model", *CONFIG_GROUPS])})  # config.yaml has model: too
        if part not in names:
            prefix = ".".join([*parts[:depth], ""])
            close = difflib.get_close_matches(part, names, n=3, cutoff=0.6)
            near = f"closest: {', '.join(prefix + c for c in close)}; " if close else ""
            where = f"keys of {prefix[:-1]}" if depth else "top-level keys"
            added = f" (+{key}=... adds a key nothing reads)" if appended else ""
            return f"lagfluid: unknown key '{key}'{added}; {near}{where}: {', '.join(sorted(names))}"
        node = node[part]
    return None


def _register_plugin_configs() -> None:
    """Give plugin simulators without a config file a minimal ``model/<name>`` node."""
    from hydra.core.config_store import ConfigStore

    from lagfluid.registry import available_simulators

    store = ConfigStore.instance()
    for name in set(available_simulators()) - set(_group_names("model")):
        store.store(group="model", name=name, node={"name": name})


def dispatch(cfg: DictConfig) -> None:
    """Run the task named by ``cfg.task``; a multirun job writes into its own folder under ``out_dir``."""
    from lagfluid.tasks.config import check_run_numbers, multirun_out_dir

    check_run_numbers(cfg)
    job_dir = multirun_out_dir(cfg)
    if job_dir is not None:
        with open_dict(cfg):
            cfg.out_dir = str(job_dir)
    if cfg.task == "simulate":
        from lagfluid.tasks.simulate import simulate

        simulate(cfg)
    elif cfg.task == "generate":
        from lagfluid.tasks.generate import generate

        generate(cfg)
    elif cfg.task == "train":
        from lagfluid.tasks.train import train

        train(cfg)
    elif cfg.task == "evaluate":
        from lagfluid.tasks.evaluate.task import evaluate_task

        evaluate_task(cfg)
    elif cfg.task == "export":
        from lagfluid.tasks.export import export_task

        export_task(cfg)
    else:  # guarded by check_command_line and the config
        raise LagfluidError(f"unknown task '{cfg.task}'; available: {', '.join(TASKS)}")


def _raise_terminated(signum: int, frame: object) -> None:
    raise Terminated(f"stopped by {signal.Signals(signum).name} (a timeout, the scheduler or docker stop)")


def stop_hint(cfg: DictConfig) -> str:
    """What a stopped run leaves to continue from: ``task=simulate`` with its ``resume.pt``, else ''."""
    from lagfluid.tasks.simulate_resume import CHECKPOINT

    if cfg.get("task") != "simulate" or not (Path(str(cfg.out_dir)) / CHECKPOINT).is_file():
        return ""
    return f"; add resume=true to the same command to continue it from {Path(str(cfg.out_dir)) / CHECKPOINT}"


def stop_line(err: KeyboardInterrupt) -> str:
    """The one line printed for Ctrl-C or SIGTERM (:class:`Terminated`), with the run's resume hint."""
    hint = getattr(err, "hint", "")
    if isinstance(err, Terminated):
        return f"lagfluid: {err}{hint}"
    return f"lagfluid: interrupted (Ctrl-C){hint}"


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def _hydra_main(cfg: DictConfig) -> None:
    signal.signal(signal.SIGTERM, _raise_terminated)  # stop like Ctrl-C: outputs kept, the reason written
    try:
        dispatch(cfg)
    except LagfluidError as err:
        # One clear line; the full traceback is in the log file for whoever needs it.
        log.debug("failed", exc_info=True)
        log.error("%s", err)
        sys.exit(1)
    except KeyboardInterrupt as err:  # one line from main(), naming what continues the run
        log.debug("stopped", exc_info=True)
        err.hint = stop_hint(cfg)  # type: ignore[attr-defined]
        raise


def limit_openmp(argv: Sequence[str]) -> None:
    """With ``threads=N`` on the command line, tell OpenMP before torch loads it (unless already set).

    ``OMP_NUM_THREADS=N``, and for ``N = 1`` ``OMP_WAIT_POLICY=PASSIVE``: ``torch.set_num_threads`` does not
    reach every OpenMP team (fbgemm's parallel sort behind PyG's sparse ops still ran a second thread that
    spin-waited at its barrier), and two ``threads=1`` trainings on a 2-core machine ran 3-8x slower per
    iteration than with these set (``docs/training.md``).
    """
    for arg in argv:
        key, sep, value = arg.partition("=")
        if key.lstrip("+") == "threads" and sep and value.isdigit() and int(value) >= 1:
            os.environ.setdefault("OMP_NUM_THREADS", value)
            if int(value) == 1:
                os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _register_help_resolver() -> None:
    """Register ``${lagfluid.config_groups:}``, read only by ``--help`` (``hydra.help.template``).

    Registered here, not in ``lagfluid/__init__``: the package's base layer may not import the tasks.
    """
    from omegaconf import OmegaConf

    if not OmegaConf.has_resolver("lagfluid.config_groups"):
        OmegaConf.register_new_resolver("lagfluid.config_groups", help_config_groups)


_register_help_resolver()


def main() -> None:
    """Entry point of ``python -m lagfluid.run``."""
    limit_openmp(sys.argv[1:])  # first: before anything imports torch
    keep_freed_memory()  # before the first large allocation
    try:
        _main(sys.argv[1:])
    except KeyboardInterrupt as err:  # Ctrl-C (SIGINT) or SIGTERM: one line, the shell's exit status
        sys.stderr.write(stop_line(err) + "\n")
        sys.exit(128 + (signal.SIGTERM if isinstance(err, Terminated) else signal.SIGINT))


def _main(argv: Sequence[str]) -> None:
    """Check the command line, then run Hydra (which reads ``sys.argv`` itself)."""
    try:
        problem = check_command_line(argv)
        _register_plugin_configs()
    except LagfluidError as err:  # a broken plugin (its configs, its entry point): one line, not a traceback
        problem = f"lagfluid: {err}"
    if problem:
        sys.stderr.write(problem + "\n")  # before Hydra has set up logging: one plain line
        sys.exit(2)
    problem = check_out_dir_argument(argv)
    if problem:
        sys.stderr.write(problem + "\n")
        sys.exit(1)
    _hydra_main()


if __name__ == "__main__":
    main()
