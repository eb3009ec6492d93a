"""``benchmarks/`` holds what a user reruns, ``benchmarks/studies/`` the one-off studies; the docs run both.

A new script at ``benchmarks/``'s root is a deliberate choice: it joins :data:`ROOT` here, or it is a study
and goes to ``benchmarks/studies/``. Every ``python -m benchmarks...`` a document tells a user to run names
a module that exists (a moved study's old path would send the user to ``No module named ...``).
"""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BENCHMARKS = REPO / "benchmarks"

# What a user reruns, kept at benchmarks/'s root: the tables and their Pareto front, speed, validation,
# extremes, provenance (the writer), the checks of issue 35 and the GPU scripts.
ROOT = {
    "__init__.py",
    "provenance.py",
    "pareto.py",
    "tables",
    "validate_mps",
    "extremes.py",
    "fgn_speed.py",
    "mps_speed.py",
    "neighbors.py",
    "whole_run.py",
    "two_trees.py",
    "host_syncs.py",
    "cconv_layer.py",
    "gns_edge_layer.py",
    "fgn_vs_mps.py",
    "fgn_one_step.py",
    "gns_one_step.py",
    "fgn_recipe.py",
    "exact_after.py",
    "levers.py",
    "dagger_rounds.py",
    "unseen_obstacles.py",
    "wall_approach.py",
    "cconv_finetune_loss.py",
    "gpu_check.sh",
    "gpu_day.sh",
    "gpu_train.sh",
    "device_wheels.sh",
    "results",
    "studies",
}

# The documents that tell a user what to run (benchmarks/results/*.md are records of past runs: their
# commands are provenance and keep the module names of their day).
DOCUMENTS = ["README.md", "docs/*.md", "lagfluid/weights/**/MODEL_CARD.md", "baselines/**/MODEL_CARD.md"]
RUN = re.compile(r"python -m (benchmarks(?:\.\w+)+)(?![.\w<])")  # not a pattern such as studies.<name>


def studies() -> list[str]:
    """The modules of ``benchmarks/studies/``, as ``benchmarks.studies.<name>``."""
    return sorted(
        f"benchmarks.studies.{p.stem}" for p in (BENCHMARKS / "studies").glob("*.py") if p.stem != "__init__"
    )


def module_exists(dotted: str, root: Path = REPO) -> bool:
    """Whether ``python -m <dotted>`` finds a module under ``root``: ``a/b.py`` or ``a/b/__main__.py``."""
    path = root.joinpath(*dotted.split("."))
    return path.with_suffix(".py").is_file() or (path / "__main__.py").is_file()


def runs_in_documents(root: Path = REPO) -> dict[str, list[str]]:
    """Every ``python -m benchmarks...`` module the documents name, with the documents naming it."""
    found: dict[str, list[str]] = {}
    for pattern in DOCUMENTS:
        for doc in sorted(root.glob(pattern)):
            for module in RUN.findall(doc.read_text()):
                found.setdefault(module, []).append(str(doc.relative_to(root)))
    return found


def test_benchmarks_root_holds_only_what_a_user_reruns():
    entries = {p.name for p in BENCHMARKS.iterdir() if p.name != "__pycache__"}
    assert entries - ROOT == set(), "new at benchmarks/'s root: add it to ROOT or move it to studies/"
    assert ROOT - entries == set(), "ROOT names what benchmarks/ no longer holds"


def test_studies_is_a_package_of_the_moved_studies():
    assert (BENCHMARKS / "studies" / "__init__.py").is_file()
    assert {"benchmarks.studies.gns_noise", "benchmarks.studies.acceleration_noise"} <= set(studies())
    assert "benchmarks.studies.resting_variants" in studies()


@pytest.mark.parametrize("module", studies())
def test_every_study_answers_help(module, capsys):
    main = importlib.import_module(module).main
    with pytest.raises(SystemExit) as done:
        main(["--help"])
    assert done.value.code == 0
    assert capsys.readouterr().out.startswith("usage: ")


def test_every_benchmark_the_documents_run_exists():
    found = runs_in_documents()
    assert "benchmarks.studies.resting_variants" in found and "benchmarks.tables" in found
    missing = {m: docs for m, docs in found.items() if not module_exists(m)}
    assert not missing, f"documents run modules that do not exist: {missing}"


def test_module_exists_finds_files_and_packages_and_not_the_old_paths(tmp_path):
    (tmp_path / "benchmarks" / "studies").mkdir(parents=True)
    (tmp_path / "benchmarks" / "studies" / "noise.py").write_text("")
    (tmp_path / "benchmarks" / "tables").mkdir()
    (tmp_path / "benchmarks" / "tables" / "__main__.py").write_text("")
    assert module_exists("benchmarks.studies.noise", tmp_path)
    assert module_exists("benchmarks.tables", tmp_path)
    assert not module_exists("benchmarks.noise", tmp_path)
    assert not module_exists("benchmarks.studies", tmp_path)  # a package without __main__ does not run
