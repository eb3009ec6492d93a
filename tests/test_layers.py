"""Dependencies point one way (docs/architecture.md#layers): a test reading every import of ``lagfluid/``.

Nothing is imported: each module's source is parsed and every ``import``/``from ... import`` in it,
at module level or inside a function, is checked against the table below. Run it as a test
(``pytest tests/test_layers.py``) or as a report for humans::

    python -m tests.test_layers

which prints the layers, every violation, and the largest module of lagfluid/baselines/benchmarks.
"""

from __future__ import annotations

import ast
import sys
from dataclasses import dataclass
from fnmatch import fnmatchcase
from pathlib import Path

# ---------------------------------------------------------------------------------------------------
# The rule, as data. Layers from the top down; a module is in the layer whose pattern names it most
# specifically (an exact name beats a wildcard, a longer wildcard beats a shorter one).
LAYERS: dict[str, tuple[str, ...]] = {
    "tasks": (
        "lagfluid.run",
        "lagfluid.retrain",  # the retrain-everything sweep of lagfluid.run
        "lagfluid.multirun_timer",  # a Hydra callback of every multirun
        "lagfluid.config",  # a run's setup from its config, shared by the tasks
        "lagfluid.outputs",  # a run's output files, replaced together
        "lagfluid.locks",  # the locks on what a run writes, and their Hydra callback
        "lagfluid.simulate",
        "lagfluid.simulate.*",
        "lagfluid.simulate_resume",  # task=simulate's resume=true checkpoints
        "lagfluid.generate",
        "lagfluid.generate.*",
        "lagfluid.train",
        "lagfluid.train.*",
        "lagfluid.onpolicy_rounds",  # task=train's DAgger rounds (generate, then fine-tune)
        "lagfluid.dagger_rounds",  # task=train's DAgger rounds of end-to-end models
        "lagfluid.dagger_eval",  # their per-round dam rollout
        "lagfluid.evaluate*",
        "lagfluid.tables*",
        "lagfluid.export",
        "lagfluid.export.*",  # task=export: ParaView series and animations of rollout files
        "lagfluid.distributed",  # task=train under torchrun
        "lagfluid.tasks",
        "lagfluid.tasks.*",
    ),
    "rollout": ("lagfluid.rollout",),
    "models": ("lagfluid.models", "lagfluid.models.*"),
    "physics": ("lagfluid.physics", "lagfluid.physics.*"),
    "metrics": ("lagfluid.metrics",),
    "data": ("lagfluid.data", "lagfluid.data.*"),
    "registry": ("lagfluid.registry",),
    "scenes": ("lagfluid.scenes", "lagfluid.scenes.*"),
    "viz": ("lagfluid.viz",),
    "operators": (
        "lagfluid.physics.operators",
        "lagfluid.physics._*_numba",
        "lagfluid.neighbors",
        "lagfluid.neighbors.*",
        "lagfluid.neighbor_list",
        "lagfluid.pair_kernels",
        "lagfluid._pair_kernels_numba",
        "lagfluid.integrate",
    ),
    # plugin_configs: the config-resolver lagfluid/__init__ registers (stdlib and errors only)
    # progress: the rollout's and the trainer's bar or log lines (tqdm and logging only)
    # device_constants: small constant tensors cached per device (torch only)
    # memory: the allocator setting and a rollout's memory estimate (stdlib, numpy; the state for its types),
    # asked by the tasks and by each simulator's memory_needed
    "base": (
        "lagfluid",
        "lagfluid.memory",
        "lagfluid.state",
        "lagfluid.errors",
        "lagfluid.plugin_configs",
        "lagfluid.progress",
        "lagfluid.device_constants",
    ),
}

# What each layer may import besides its own modules.
MAY_IMPORT: dict[str, frozenset[str]] = {
    "tasks": frozenset(LAYERS) - {"tasks"},
    # the loop and guard only: files, metrics and the registry are the tasks'
    "rollout": frozenset({"models", "base"}),
    # a model's trainables provide their datasets, hence data
    "models": frozenset({"physics", "data", "operators", "base"}),
    # physics never imports models
    "physics": frozenset({"operators", "base"}),
    # simulator-neutral: no models, no split-step stages, no MPS or PPE references
    "metrics": frozenset({"operators", "base"}),
    # formats only: never tasks, rollout, models or physics
    "data": frozenset({"operators", "base"}),
    # module level only: built-ins are loaded lazily by string, inside functions
    "registry": frozenset({"base"}),
    # a scene may be read from a stored trajectory (scene=trajectory)
    "scenes": frozenset({"data", "operators", "base"}),
    "viz": frozenset({"base"}),
    "operators": frozenset({"base"}),
    "base": frozenset(),
}

# Layers whose imports inside functions are not checked (lazy loading is their job).
LAZY_INSIDE_FUNCTIONS: frozenset[str] = frozenset({"registry"})

# Top-level packages lagfluid never imports: plugins import lagfluid and are found by entry point;
# benchmarks and tests are not installed with the package.
OUTSIDE: tuple[str, ...] = ("baselines", "benchmarks", "tests")

# ---------------------------------------------------------------------------------------------------

REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Violation:
    """One import that breaks the rule."""

    importer: str
    imported: str
    line: int
    rule: str

    def __str__(self) -> str:
        return f"{self.importer} (line {self.line}) imports {self.imported}: {self.rule}"


def module_name(path: str) -> tuple[str, bool]:
    """``"lagfluid/physics/__init__.py"`` -> ``("lagfluid.physics", True)`` (name, is a package)."""
    parts = list(Path(path).with_suffix("").parts)
    is_package = parts[-1] == "__init__"
    if is_package:
        parts = parts[:-1]
    return ".".join(parts), is_package


def layer_of(module: str, layers: dict[str, tuple[str, ...]] = LAYERS) -> str | None:
    """The layer holding ``module``, or ``None`` when no pattern names it."""
    best: tuple[int, int, str] | None = None  # (exact, pattern length, layer)
    for layer, patterns in layers.items():
        for pattern in patterns:
            if fnmatchcase(module, pattern):
                key = (int(pattern == module), len(pattern), layer)
                best = key if best is None or key[:2] > best[:2] else best
    return None if best is None else best[2]


def _imports(tree: ast.Module, package: str) -> list[tuple[str, int, bool]]:
    """Every imported dotted name in ``tree`` as ``(name, line, inside a function)``.

    ``from a import b`` yields ``a.b`` (resolved to ``a`` later when ``b`` is not a module); relative
    imports are resolved against ``package``.
    """
    found: list[tuple[str, int, bool]] = []

    def visit(node: ast.AST, in_function: bool) -> None:
        if isinstance(node, ast.Import):
            found.extend((alias.name, node.lineno, in_function) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(base_parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            found.extend((f"{base}.{alias.name}", node.lineno, in_function) for alias in node.names)
        inside = in_function or isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda)
        for child in ast.iter_child_nodes(node):
            visit(child, inside)

    visit(tree, False)
    return found


def _resolve(name: str, modules: set[str]) -> str:
    """The longest prefix of ``name`` that is a known module (``name`` itself when none is)."""
    parts = name.split(".")
    for end in range(len(parts), 0, -1):
        candidate = ".".join(parts[:end])
        if candidate in modules:
            return candidate
    return name


def import_graph(sources: dict[str, str]) -> dict[str, list[tuple[str, int, bool]]]:
    """``{module: [(imported lagfluid/outside module, line, inside a function), ...]}``.

    Args:
        sources: ``{path relative to the repository root: source text}`` of every module of the package.
    """
    names = {path: module_name(path) for path in sources}
    modules = {name for name, _ in names.values()}
    graph: dict[str, list[tuple[str, int, bool]]] = {}
    for path, text in sources.items():
        name, is_package = names[path]
        package = name if is_package else name.rpartition(".")[0]
        edges = []
        for imported, line, in_function in _imports(ast.parse(text, filename=path), package):
            top = imported.split(".")[0]
            if top == "lagfluid" or top in OUTSIDE:
                edges.append((_resolve(imported, modules), line, in_function))
        graph[name] = list(dict.fromkeys(edges))  # ``from a import b, c`` is one edge
    return graph


def check(
    sources: dict[str, str],
    layers: dict[str, tuple[str, ...]] = LAYERS,
    may_import: dict[str, frozenset[str]] = MAY_IMPORT,
) -> list[Violation]:
    """Every import in ``sources`` that breaks the layer rule (``sources`` as for :func:`import_graph`)."""
    violations = []
    for importer, edges in sorted(import_graph(sources).items()):
        source_layer = layer_of(importer, layers)
        if source_layer is None:
            violations.append(Violation(importer, "-", 0, "the module is in no layer: add it to LAYERS"))
            continue
        for imported, line, in_function in edges:
            if imported.split(".")[0] in OUTSIDE:
                rule = f"lagfluid never imports {', '.join(OUTSIDE)} (plugins are found by entry point)"
                violations.append(Violation(importer, imported, line, rule))
                continue
            if in_function and source_layer in LAZY_INSIDE_FUNCTIONS:
                continue
            target_layer = layer_of(imported, layers)
            if target_layer is None or target_layer == source_layer:
                continue  # an unknown target is reported as its own module's "no layer"
            if target_layer not in may_import[source_layer]:
                allowed = ", ".join(sorted(may_import[source_layer])) or "nothing"
                where = " at module level" if source_layer in LAZY_INSIDE_FUNCTIONS else ""
                rule = f"layer '{source_layer}' may not import layer '{target_layer}'{where}"
                rule += f" (allowed: {allowed})"
                violations.append(Violation(importer, imported, line, rule))
    return violations


def package_sources(root: Path = REPO, package: str = "lagfluid") -> dict[str, str]:
    """``{relative path: source}`` of every ``.py`` file of ``package`` under ``root``."""
    return {
        path.relative_to(root).as_posix(): path.read_text(encoding="utf-8")
        for path in sorted((root / package).rglob("*.py"))
    }


def largest_module(root: Path = REPO, packages: tuple[str, ...] = ("lagfluid", "baselines", "benchmarks")):
    """``(relative path, line count)`` of the longest ``.py`` file in ``packages`` (those that exist)."""
    sizes = [
        (len(path.read_text(encoding="utf-8").splitlines()), path.relative_to(root).as_posix())
        for package in packages
        if (root / package).is_dir()
        for path in (root / package).rglob("*.py")
    ]
    lines, path = max(sizes)
    return path, lines


# --- the tree ---------------------------------------------------------------------------------------


def test_lagfluid_imports_point_one_way():
    new = check(package_sources())
    assert not new, "imports against the layer rule (tests/test_layers.py):\n" + "\n".join(map(str, new))


def test_every_layer_has_its_rule():
    assert set(MAY_IMPORT) == set(LAYERS)
    for layer, allowed in MAY_IMPORT.items():
        assert allowed <= set(LAYERS) - {layer}, layer


# --- the checker, on synthetic module maps ---------------------------------------------------------


def test_checker_accepts_downward_imports():
    sources = {
        "lagfluid/__init__.py": "",
        "lagfluid/state.py": "from lagfluid.errors import SceneError\n",
        "lagfluid/errors.py": "",
        "lagfluid/physics/__init__.py": "",
        "lagfluid/physics/operators.py": "from lagfluid import pair_kernels\nimport lagfluid.state\n",
        "lagfluid/pair_kernels.py": "import numpy\n",
        "lagfluid/physics/mps.py": "from . import operators as ops\nfrom .operators import x\n",
        "lagfluid/models/__init__.py": "",
        "lagfluid/models/mps.py": "from lagfluid.physics.mps import A\n",
        "lagfluid/rollout.py": "import lagfluid\nfrom lagfluid.models.mps import B\n",
        "lagfluid/run.py": "def main():\n    from lagfluid.rollout import rollout\n",
    }
    assert check(sources) == []


def test_checker_names_importer_imported_and_rule():
    sources = {
        "lagfluid/physics/__init__.py": "",
        "lagfluid/physics/learned.py": "import torch\n\nfrom lagfluid.models.fgn import AdvectionNet\n",
        "lagfluid/models/__init__.py": "",
        "lagfluid/models/fgn.py": "",
    }
    (v,) = check(sources)
    assert (v.importer, v.imported, v.line) == ("lagfluid.physics.learned", "lagfluid.models.fgn", 3)
    assert "layer 'physics' may not import layer 'models'" in str(v)


def test_checker_sees_function_level_and_relative_imports():
    sources = {
        "lagfluid/data/__init__.py": "",
        "lagfluid/data/store.py": "def f():\n    if True:\n        from ..rollout import rollout\n",
        "lagfluid/rollout.py": "",
        "lagfluid/metrics.py": "class A:\n    def g(self):\n        from .physics import ppe\n",
        "lagfluid/physics/__init__.py": "",
        "lagfluid/physics/ppe.py": "",
    }
    found = {(v.importer, v.imported, v.line) for v in check(sources)}
    assert found == {
        ("lagfluid.data.store", "lagfluid.rollout", 3),
        ("lagfluid.metrics", "lagfluid.physics.ppe", 3),
    }


def test_checker_registry_is_lazy_only_inside_functions():
    sources = {
        "lagfluid/registry.py": "from lagfluid.errors import E\ndef f():\n    import lagfluid.scenes\n",
        "lagfluid/errors.py": "",
        "lagfluid/scenes/__init__.py": "",
    }
    assert check(sources) == []
    sources["lagfluid/registry.py"] += "from lagfluid.models import fgn\n"
    sources["lagfluid/models/__init__.py"] = ""
    (v,) = check(sources)
    assert v.imported == "lagfluid.models" and "at module level" in v.rule


def test_checker_forbids_baselines_and_unknown_modules():
    sources = {
        "lagfluid/viz.py": "def f():\n    import baselines.gns\n",
        "lagfluid/newthing.py": "",
    }
    found = {(v.importer, v.imported): v.rule for v in check(sources)}
    assert set(found) == {("lagfluid.newthing", "-"), ("lagfluid.viz", "baselines.gns")}
    assert "no layer" in found[("lagfluid.newthing", "-")]
    assert "never imports baselines" in found[("lagfluid.viz", "baselines.gns")]


def test_layer_of_prefers_the_most_specific_pattern():
    assert layer_of("lagfluid.physics.operators") == "operators"
    assert layer_of("lagfluid.physics._ppe_numba") == "operators"
    assert layer_of("lagfluid.physics.ppe") == "physics"
    assert layer_of("lagfluid.evaluate_tables") == "tasks"
    assert layer_of("lagfluid.trainables") is None


def main() -> int:
    """Print the layers, every violation and the largest module."""
    print("layers, top down (each may import its own and the listed layers):")
    for layer, patterns in LAYERS.items():
        print(f"  {layer:<10} {', '.join(patterns)}")
        print(f"  {'':<10} -> {', '.join(sorted(MAY_IMPORT[layer])) or 'nothing'}")
    violations = check(package_sources())
    print(f"\nviolations: {len(violations)}")
    for v in violations:
        print(f"  {v}")
    path, lines = largest_module()
    print(f"\nlargest module: {path} ({lines} lines)")
    return int(bool(violations))


if __name__ == "__main__":
    sys.exit(main())
