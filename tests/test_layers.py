"""Dependencies point one way (docs/architecture.md#layers): a test that reads every import with ``ast``.

Nothing is imported: each module of ``lagfluid/``, the plugins (``baselines/``, ``tests/plugins/``) and
``benchmarks/`` is parsed and every ``import``/``from ... import`` in it, at module level or inside a
function, is checked against the table below: a layer imports only the layers it lists, the plugins only the
public surface :mod:`lagfluid.zoo`, no two modules import each other through any chain (a circle), and
every pattern of the table names a module. Run it as a test (``pytest tests/test_layers.py``) or as a
report for humans::

    python -m tests.test_layers

which prints the layers, every violation and circle, and the largest module of lagfluid/baselines/benchmarks.
"""

from __future__ import annotations

import ast
import itertools
import sys
from dataclasses import dataclass
from fnmatch import fnmatchcase
from pathlib import Path

# ---------------------------------------------------------------------------------------------------
# The rule, as data. Layers from the top down: a layer imports only layers listed below it (checked). A
# module is in the layer whose pattern names it most specifically (an exact name beats a wildcard, a longer
# wildcard beats a shorter one); every pattern names at least one module (checked).
LAYERS: dict[str, tuple[str, ...]] = {
    # the tables, speed and validation harnesses and studies: not installed, free to import anything
    "benchmarks": ("benchmarks", "benchmarks.*"),
    # models outside lagfluid, found by entry point (the baselines, the test plugin): the zoo only
    "plugins": ("baselines", "baselines.*", "tests.plugins.*"),
    # the public plugin surface: names re-exported from the layers below, never from the tasks
    "zoo": ("lagfluid.zoo",),
    # the two commands: python -m lagfluid.run (every task) and python -m lagfluid.retrain (a sweep of it)
    "commands": ("lagfluid.run", "lagfluid.retrain"),
    # task=<name> is lagfluid/tasks/<name>, beside their config, outputs, locks, resume and training rounds
    "tasks": ("lagfluid.tasks", "lagfluid.tasks.*"),
    "rollout": ("lagfluid.rollout",),
    "models": ("lagfluid.models", "lagfluid.models.*"),
    "physics": ("lagfluid.physics", "lagfluid.physics.*"),
    "metrics": ("lagfluid.metrics",),
    "registry": ("lagfluid.registry",),
    "scenes": ("lagfluid.scenes", "lagfluid.scenes.*"),
    "data": ("lagfluid.data", "lagfluid.data.*"),
    "viz": ("lagfluid.viz",),
    # the MPS operators (carved out of physics/: the data, the scenes and the metrics use them) and the update
    "operators": ("lagfluid.physics.operators", "lagfluid.physics._*_numba", "lagfluid.integrate"),
    # radius graphs, the Verlet list, edge geometry, CSR matrices, compiled pair kernels and their dispatch
    "neighbors": ("lagfluid.neighbors", "lagfluid.neighbors.*"),
    # plugin_configs: the config folders (core and plugins') and the resolver lagfluid/__init__ registers
    # (stdlib and errors only)
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

# Patterns that take modules out of a folder's layer into another (every other pattern names a module at
# lagfluid's root, or a whole folder as "lagfluid.<folder>" and "lagfluid.<folder>.*": checked).
CARVED_OUT: tuple[str, ...] = ("lagfluid.physics.operators", "lagfluid.physics._*_numba")

_LAGFLUID = tuple(layer for layer in LAYERS if layer not in ("benchmarks", "plugins"))

# What each layer may import besides its own modules.
MAY_IMPORT: dict[str, frozenset[str]] = {
    "benchmarks": frozenset(LAYERS) - {"benchmarks"},
    # what a plugin needs of lagfluid is re-exported there; a plugin never imports another's internals
    "plugins": frozenset({"zoo"}),
    # nothing of the tasks or commands (a plugin is no task), nothing in lagfluid imports the zoo
    "zoo": frozenset(_LAGFLUID) - {"zoo", "commands", "tasks"},
    "commands": frozenset(_LAGFLUID) - {"zoo", "commands"},
    "tasks": frozenset(_LAGFLUID) - {"zoo", "commands", "tasks"},
    # the loop and guard only: files, metrics and the registry are the tasks'
    "rollout": frozenset({"models", "base"}),
    # a model's trainables provide their datasets, hence data
    "models": frozenset({"physics", "data", "operators", "neighbors", "base"}),
    # physics never imports models
    "physics": frozenset({"operators", "neighbors", "base"}),
    # simulator-neutral: no models, no split-step stages, no MPS or PPE references
    "metrics": frozenset({"operators", "neighbors", "base"}),
    # module level only: built-ins are loaded lazily by string, inside functions
    "registry": frozenset({"base"}),
    # a scene may be read from a stored trajectory (scene=trajectory)
    "scenes": frozenset({"data", "operators", "neighbors", "base"}),
    # formats only: never tasks, rollout, models or physics
    "data": frozenset({"operators", "neighbors", "base"}),
    "viz": frozenset({"base"}),
    "operators": frozenset({"neighbors", "base"}),
    # the search knows particles and their types, nothing of physics or models
    "neighbors": frozenset({"base"}),
    "base": frozenset(),
}

# Layers whose imports inside functions are not checked against the table (lazy loading is their job); the
# circle check sees them all the same.
LAZY_INSIDE_FUNCTIONS: frozenset[str] = frozenset({"registry"})

# Top-level packages lagfluid never imports: plugins import lagfluid and are found by entry point;
# benchmarks and tests are not installed with the package.
OUTSIDE: tuple[str, ...] = ("baselines", "benchmarks", "tests")

# What the test reads: the package, the plugins and the benchmarks (tests/ besides its plugins may import
# anything and is imported by nothing).
SCANNED: tuple[str, ...] = ("lagfluid", "baselines", "benchmarks", "tests/plugins")

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
            top = imported.split(".")[0]
            if importer.split(".")[0] == "lagfluid" and top in OUTSIDE:
                rule = f"lagfluid never imports {', '.join(OUTSIDE)} (plugins are found by entry point)"
                violations.append(Violation(importer, imported, line, rule))
                continue
            if in_function and source_layer in LAZY_INSIDE_FUNCTIONS:
                continue
            target_layer = layer_of(imported, layers)
            if target_layer is None and top == "tests":
                rule = "the tests are no layer: nothing outside them imports them (their plugins aside)"
                violations.append(Violation(importer, imported, line, rule))
                continue
            if target_layer is None or target_layer == source_layer:
                continue  # an unknown target is reported as its own module's "no layer"
            if target_layer not in may_import[source_layer]:
                allowed = ", ".join(sorted(may_import[source_layer])) or "nothing"
                where = " at module level" if source_layer in LAZY_INSIDE_FUNCTIONS else ""
                rule = f"layer '{source_layer}' may not import layer '{target_layer}'{where}"
                rule += f" (allowed: {allowed})"
                violations.append(Violation(importer, imported, line, rule))
    return violations


def circles(sources: dict[str, str]) -> list[list[tuple[str, int, bool]]]:
    """Every import circle in ``sources``: one shortest loop per strongly connected group of modules.

    Imports inside functions count (they only postpone the circle to the first call). A module importing
    itself or its own package's name is no circle.

    Returns:
        Per circle the ``(module, line of its import of the next, inside a function)`` steps, starting at
        the group's first module by name and coming back to it.
    """
    graph = {
        module: {target: (line, inside) for target, line, inside in reversed(edges) if target != module}
        for module, edges in import_graph(sources).items()
    }
    found = []
    for group in _strongly_connected(graph):
        start = min(group)
        # breadth first from start inside the group until it comes back: a shortest loop through start
        came_from: dict[str, str] = {}
        frontier = [start]
        while start not in came_from:
            reached = []
            for module in frontier:
                for target in sorted(graph[module]):
                    if target in group and target not in came_from:
                        came_from[target] = module
                        reached.append(target)
            frontier = reached
        back = [start]
        while came_from[back[-1]] != start:
            back.append(came_from[back[-1]])
        loop = [start, *reversed(back[1:]), start]
        found.append([(a, *graph[a][b]) for a, b in itertools.pairwise(loop)])
    return found


def _strongly_connected(graph: dict[str, dict[str, tuple[int, bool]]]) -> list[set[str]]:
    """The groups of two or more modules of ``graph`` that reach each other (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    groups = []

    def visit(module: str) -> None:
        index[module] = low[module] = len(index)
        stack.append(module)
        for target in graph[module]:
            if target not in graph:
                continue  # a third-party or unknown name
            if target not in index:
                visit(target)
                low[module] = min(low[module], low[target])
            elif target in stack:
                low[module] = min(low[module], index[target])
        if low[module] == index[module]:
            group = set()
            while not group or module not in group:
                group.add(stack.pop())
            if len(group) > 1:
                groups.append(group)

    for module in sorted(graph):
        if module not in index:
            visit(module)
    return groups


def describe_circle(circle: list[tuple[str, int, bool]]) -> str:
    """``a (line 3) -> b (line 131, inside a function) -> a``."""
    steps = [f"{m} (line {line}{', inside a function' if inside else ''})" for m, line, inside in circle]
    return " -> ".join([*steps, circle[0][0]])


def dead_patterns(sources: dict[str, str], layers: dict[str, tuple[str, ...]] = LAYERS) -> list[str]:
    """The patterns of ``layers`` that name no module of ``sources``."""
    modules = list(import_graph(sources))
    return [
        f"{layer}: {pattern}"
        for layer, patterns in layers.items()
        for pattern in patterns
        if not any(fnmatchcase(module, pattern) for module in modules)
    ]


def folder_problems(
    sources: dict[str, str],
    layers: dict[str, tuple[str, ...]] = LAYERS,
    carved_out: tuple[str, ...] = CARVED_OUT,
) -> list[str]:
    """Where the table does not state lagfluid's folders as folders.

    Each folder ``lagfluid/<f>/`` must be named as a whole, ``lagfluid.<f>`` and ``lagfluid.<f>.*`` in one
    layer; every other pattern names a module at lagfluid's root, or is one of ``carved_out``. A table that
    lists a folder's modules one by one (a new module would fall in no layer) is named here.
    """
    parts = [Path(path).with_suffix("").parts for path in sources if path.startswith("lagfluid/")]
    folders = {p[1] for p in parts if len(p) > 2}
    root_modules = {p[1] for p in parts if len(p) == 2 and p[1] != "__init__"}
    layer_of_pattern = {pattern: layer for layer, patterns in layers.items() for pattern in patterns}
    problems = [
        f"lagfluid/{folder}/: name it as a folder, 'lagfluid.{folder}' and 'lagfluid.{folder}.*' in one layer"
        for folder in sorted(folders)
        if layer_of_pattern.get(f"lagfluid.{folder}") is None
        or layer_of_pattern.get(f"lagfluid.{folder}") != layer_of_pattern.get(f"lagfluid.{folder}.*")
    ]
    for pattern, layer in layer_of_pattern.items():
        name = pattern.split(".")
        if name[0] != "lagfluid" or len(name) == 1 or pattern in carved_out:
            continue
        whole = name[1] in folders and (len(name) == 2 or name[2:] == ["*"])
        if not whole and not (len(name) == 2 and name[1] in root_modules):
            problems.append(f"{layer}: {pattern} names modules inside a folder, not the folder")
    return problems


def upward_rules(
    layers: dict[str, tuple[str, ...]] = LAYERS, may_import: dict[str, frozenset[str]] = MAY_IMPORT
) -> list[str]:
    """Every ``may_import`` entry that lets a layer import itself or one listed above it."""
    order = list(layers)
    return [
        f"{layer} may import {allowed}, listed above it"
        for layer, allowed_set in may_import.items()
        for allowed in sorted(allowed_set)
        if order.index(allowed) <= order.index(layer)
    ]


def package_sources(root: Path = REPO, packages: tuple[str, ...] = SCANNED) -> dict[str, str]:
    """``{relative path: source}`` of every ``.py`` file under the folders ``packages`` of ``root``."""
    return {
        path.relative_to(root).as_posix(): path.read_text(encoding="utf-8")
        for package in packages
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


def test_imports_point_one_way():
    """lagfluid by its layers, the plugins through lagfluid.zoo only, the benchmarks above both."""
    new = check(package_sources())
    assert not new, "imports against the layer rule (tests/test_layers.py):\n" + "\n".join(map(str, new))


def test_no_import_circles():
    found = circles(package_sources())
    assert not found, "import circles:\n" + "\n".join(map(describe_circle, found))


def test_every_pattern_names_a_module():
    dead = dead_patterns(package_sources())
    assert not dead, "patterns of LAYERS that match no module (remove them):\n" + "\n".join(dead)


def test_the_table_states_folders():
    problems = folder_problems(package_sources())
    assert not problems, "LAYERS names lagfluid's folders by their modules:\n" + "\n".join(problems)


def test_every_layer_has_its_rule_and_imports_only_layers_below_it():
    assert set(MAY_IMPORT) == set(LAYERS)
    assert not upward_rules(), "LAYERS lists them top down:\n" + "\n".join(upward_rules())


# --- the checker, on synthetic module maps ---------------------------------------------------------


def test_checker_accepts_downward_imports():
    sources = {
        "lagfluid/__init__.py": "",
        "lagfluid/state.py": "from lagfluid.errors import SceneError\n",
        "lagfluid/errors.py": "",
        "lagfluid/physics/__init__.py": "",
        "lagfluid/physics/operators.py": "from lagfluid.neighbors import csr\nimport lagfluid.state\n",
        "lagfluid/neighbors/csr.py": "import numpy\n",
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


def test_checker_holds_plugins_to_the_zoo_and_lets_benchmarks_import_anything():
    sources = {
        "lagfluid/zoo.py": "from lagfluid.models.fgn.networks import Standardizer\n",
        "lagfluid/models/__init__.py": "",
        "lagfluid/models/fgn/__init__.py": "",
        "lagfluid/models/fgn/networks.py": "",
        "baselines/gns/network.py": "from lagfluid.zoo import Standardizer\nfrom . import graph\n",
        "baselines/gns/graph.py": "def f():\n    from lagfluid.models.fgn.networks import Standardizer\n",
        "benchmarks/study.py": "import baselines.gns.network\nfrom lagfluid.models.fgn import networks\n",
        "tests/plugins/tiny/model.py": "from lagfluid.zoo import Standardizer\nimport benchmarks.study\n",
    }
    found = {(v.importer, v.imported, v.line): v.rule for v in check(sources)}
    assert found == {
        ("baselines.gns.graph", "lagfluid.models.fgn.networks", 2): (
            "layer 'plugins' may not import layer 'models' (allowed: zoo)"
        ),
        ("tests.plugins.tiny.model", "benchmarks.study", 2): (
            "layer 'plugins' may not import layer 'benchmarks' (allowed: zoo)"
        ),
    }


def test_checker_forbids_the_zoo_to_import_tasks_and_tasks_to_import_the_zoo():
    sources = {
        "lagfluid/zoo.py": "from lagfluid.tasks.config import scene_params\nimport lagfluid.run\n",
        "lagfluid/tasks/config.py": "",
        "lagfluid/tasks/simulate.py": "import lagfluid.zoo\nfrom lagfluid import run\n",
        "lagfluid/run.py": "def main():\n    from lagfluid.tasks import simulate\n    import lagfluid.zoo\n",
    }
    found = {(v.importer, v.imported): v.rule for v in check(sources)}
    assert set(found) == {
        ("lagfluid.zoo", "lagfluid.tasks.config"),
        ("lagfluid.zoo", "lagfluid.run"),
        ("lagfluid.tasks.simulate", "lagfluid.zoo"),
        ("lagfluid.tasks.simulate", "lagfluid.run"),
        ("lagfluid.run", "lagfluid.zoo"),
    }
    assert "layer 'zoo' may not import layer 'tasks'" in found[("lagfluid.zoo", "lagfluid.tasks.config")]
    assert "layer 'zoo' may not import layer 'commands'" in found[("lagfluid.zoo", "lagfluid.run")]
    task = "lagfluid.tasks.simulate"
    assert "layer 'tasks' may not import layer 'zoo'" in found[(task, "lagfluid.zoo")]
    assert "layer 'tasks' may not import layer 'commands'" in found[(task, "lagfluid.run")]
    assert "layer 'commands' may not import layer 'zoo'" in found[("lagfluid.run", "lagfluid.zoo")]


def test_circles_are_found_through_function_level_imports_as_a_shortest_loop():
    sources = {
        "lagfluid/models/__init__.py": "",
        "lagfluid/models/checkpoint.py": "import torch\nfrom lagfluid.models.training_range import r\n",
        "lagfluid/models/training_range.py": "def f():\n    from lagfluid.models.checkpoint import read\n",
        "lagfluid/a.py": "import lagfluid.b\nimport lagfluid.c\n",
        "lagfluid/b.py": "import lagfluid.c\n",
        "lagfluid/c.py": "from lagfluid import a\n",
        "lagfluid/d.py": "import lagfluid.a\nimport lagfluid.d\n",  # into a circle, and itself: not one
    }
    found = sorted(circles(sources))
    assert found == [
        [("lagfluid.a", 2, False), ("lagfluid.c", 1, False)],  # a -> c -> a, not a -> b -> c -> a
        [("lagfluid.models.checkpoint", 2, False), ("lagfluid.models.training_range", 2, True)],
    ]
    assert describe_circle(found[1]) == (
        "lagfluid.models.checkpoint (line 2) -> lagfluid.models.training_range (line 2, inside a function) "
        "-> lagfluid.models.checkpoint"
    )
    del sources["lagfluid/models/training_range.py"]
    sources["lagfluid/c.py"] = ""
    assert circles(sources) == []


def test_dead_patterns_and_upward_rules_are_named():
    sources = {"lagfluid/rollout.py": "", "lagfluid/state.py": ""}
    layers = {"rollout": ("lagfluid.rollout", "lagfluid.tasks.*"), "base": ("lagfluid.state",)}
    assert dead_patterns(sources, layers) == ["rollout: lagfluid.tasks.*"]
    assert upward_rules(layers, {"rollout": frozenset({"base"}), "base": frozenset()}) == []
    assert upward_rules(layers, {"rollout": frozenset(), "base": frozenset({"rollout"})}) == [
        "base may import rollout, listed above it"
    ]


def test_a_folder_listed_module_by_module_is_named():
    sources = {
        "lagfluid/__init__.py": "",
        "lagfluid/run.py": "",
        "lagfluid/tasks/__init__.py": "",
        "lagfluid/tasks/train.py": "",
        "lagfluid/tasks/simulate.py": "",
        "lagfluid/neighbors/__init__.py": "",
        "lagfluid/neighbors/verlet.py": "",
    }
    layers = {
        "commands": ("lagfluid.run",),
        "tasks": ("lagfluid.tasks", "lagfluid.tasks.train", "lagfluid.tasks.simulate"),
        "neighbors": ("lagfluid.neighbors", "lagfluid.neighbors.*"),
        "base": ("lagfluid",),
    }
    assert folder_problems(sources, layers, carved_out=()) == [
        "lagfluid/tasks/: name it as a folder, 'lagfluid.tasks' and 'lagfluid.tasks.*' in one layer",
        "tasks: lagfluid.tasks.train names modules inside a folder, not the folder",
        "tasks: lagfluid.tasks.simulate names modules inside a folder, not the folder",
    ]
    layers["tasks"] = ("lagfluid.tasks", "lagfluid.tasks.*")
    layers["operators"] = ("lagfluid.neighbors.verlet",)
    assert folder_problems(sources, layers, carved_out=()) == [
        "operators: lagfluid.neighbors.verlet names modules inside a folder, not the folder"
    ]
    assert folder_problems(sources, layers, carved_out=("lagfluid.neighbors.verlet",)) == []


def test_layer_of_prefers_the_most_specific_pattern():
    assert layer_of("lagfluid.physics.operators") == "operators"
    assert layer_of("lagfluid.physics._ppe_numba") == "operators"
    assert layer_of("lagfluid.physics.ppe") == "physics"
    assert layer_of("lagfluid.tasks.evaluate.task") == "tasks"
    assert layer_of("lagfluid.neighbors.pair_kernels") == "neighbors"
    assert layer_of("lagfluid.evaluate_tables") is None  # a module at the root in no layer
    assert layer_of("lagfluid.trainables") is None


def main() -> int:
    """Print the layers, every violation, circle and dead pattern, and the largest module."""
    print("layers, top down (each may import its own and the listed layers):")
    for layer, patterns in LAYERS.items():
        print(f"  {layer:<10} {', '.join(patterns)}")
        print(f"  {'':<10} -> {', '.join(sorted(MAY_IMPORT[layer])) or 'nothing'}")
    sources = package_sources()
    graph = import_graph(sources)
    arrows = sum(len({target for target, _, _ in edges if target in graph}) for edges in graph.values())
    print(f"\nmodules read: {len(graph)} ({', '.join(SCANNED)}), imports between them: {arrows}")
    problems = [
        ("violations", list(map(str, check(sources)))),
        ("circles", list(map(describe_circle, circles(sources)))),
        ("patterns naming no module", dead_patterns(sources)),
        ("folders not named as folders", folder_problems(sources)),
        ("rules pointing up", upward_rules()),
    ]
    for title, lines in problems:
        print(f"\n{title}: {len(lines)}")
        for line in lines:
            print(f"  {line}")
    path, size = largest_module()
    print(f"\nlargest module: {path} ({size} lines)")
    return int(any(lines for _, lines in problems))


if __name__ == "__main__":
    sys.exit(main())
