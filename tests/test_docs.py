"""The design document is the repository's own (``docs/architecture.md``), and it names files that exist.

A user's clone has no ``../shared``: a pointer to a design document there (``DESIGN.md``, "DESIGN
convention 5") sends a reader nowhere. These tests read the files as text; nothing is imported.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ARCHITECTURE = REPO / "docs" / "architecture.md"

# Where the project's own text lives, and which of its files are text worth reading.
SCANNED = ("lagfluid", "baselines", "benchmarks", "tests", "docs", "conf", "README.md", "pyproject.toml")
SUFFIXES = (".py", ".md", ".yaml", ".toml")
# A pointer to the outside design document: the word DESIGN in capitals (as "DESIGN.md", "DESIGN 5" were
# written), any "design.md", or a path into ../shared that names a markdown file.
OUTSIDE_DESIGN = re.compile(r"design\.md|\.\./shared/\S*\.md|\bDESIGN\b", re.IGNORECASE)
CAPITALS_ONLY = re.compile(r"\bDESIGN\b")  # "by design" is English, not a pointer
# The two files that must spell the pattern out: this one, and the plant that puts a pointer back.
SPELL_IT_OUT = {"tests/test_docs.py", "tests/plant_bugs.py"}
# A repository path inside backticks: one of the top-level folders, then a path (letters, digits, ./_-*).
REPO_PATH = re.compile(r"(?<![\w./-])((?:lagfluid|baselines|benchmarks|tests|docs|conf)/[\w./*-]*)")
TOP_FILES = re.compile(r"(?<![\w./-])(README\.md|pyproject\.toml)(?![\w.])")
ANCHOR = re.compile(r"docs/architecture\.md#([\w-]+)")


def project_files() -> list[str]:
    """Repository-relative paths of the scanned text files: tracked, or new and not ignored by git.

    Outside a git checkout (an unpacked sdist) every file under the scanned folders.
    """
    try:
        listed = subprocess.run(
            ["git", "ls-files", "--cached", "--others", "--exclude-standard", "--", *SCANNED],
            cwd=REPO,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.splitlines()
    except (OSError, subprocess.CalledProcessError):
        listed = [
            p.relative_to(REPO).as_posix()
            for name in SCANNED
            for p in ([REPO / name] if (REPO / name).is_file() else (REPO / name).rglob("*"))
        ]
    return sorted(path for path in set(listed) if path.endswith(SUFFIXES) and (REPO / path).is_file())


def design_pointers(path: str, text: str) -> list[str]:
    """``"path:line: text"`` for every line of ``text`` that points to a design document outside the repo."""
    found = []
    for number, line in enumerate(text.splitlines(), 1):
        for match in OUTSIDE_DESIGN.finditer(line):
            word = match.group(0)
            if word.lower() == "design" and not CAPITALS_ONLY.fullmatch(word):
                continue
            found.append(f"{path}:{number}: {line.strip()}")
            break
    return found


def backticked_paths(markdown: str) -> list[str]:
    """Every repository path written inside backticks in ``markdown`` (commands included), in order."""
    paths = []
    for span in re.findall(r"`([^`\n]+)`", markdown):
        paths += REPO_PATH.findall(span) + TOP_FILES.findall(span)
    return paths


def missing_paths(paths: list[str], root: Path = REPO) -> list[str]:
    """The ``paths`` (relative to ``root``; ``*`` globs allowed) that name nothing in ``root``."""
    missing = []
    for path in dict.fromkeys(p.rstrip(".") for p in paths):
        exists = any(root.glob(path)) if "*" in path else (root / path).exists()
        if not exists:
            missing.append(path)
    return missing


def heading_anchors(markdown: str) -> set[str]:
    """GitHub anchors of the ``#`` headings of ``markdown``: lower case, no punctuation, ``-`` for spaces."""
    anchors = set()
    prose = re.sub(r"^```.*?^```", "", markdown, flags=re.MULTILINE | re.DOTALL)  # "# x" in code: no heading
    for title in re.findall(r"^#+\s+(.+?)\s*$", prose, flags=re.MULTILINE):
        slug = re.sub(r"[^\w\- ]", "", title.strip().lower())
        anchors.add(slug.replace(" ", "-"))
    return anchors


# --- the repository -------------------------------------------------------------------------------


def test_nothing_points_to_a_design_document_outside_the_repository():
    files = [p for p in project_files() if p not in SPELL_IT_OUT]
    assert "lagfluid/integrate.py" in files and "README.md" in files  # the scan sees the tree
    found = [hit for p in files for hit in design_pointers(p, (REPO / p).read_text(encoding="utf-8"))]
    assert not found, "pointers outside the repository (use docs/architecture.md):\n" + "\n".join(found)


def test_every_path_in_the_architecture_document_exists():
    paths = backticked_paths(ARCHITECTURE.read_text(encoding="utf-8"))
    assert len(paths) > 50  # the document names the files it describes
    assert missing_paths(paths) == []


def test_every_anchor_pointing_into_the_architecture_document_exists():
    anchors = heading_anchors(ARCHITECTURE.read_text(encoding="utf-8"))
    cited = {
        (p, a)
        for p in project_files()
        for a in ANCHOR.findall((REPO / p).read_text(encoding="utf-8"))
        if p not in SPELL_IT_OUT
    }
    assert cited, "the code points into docs/architecture.md by section"
    assert sorted((p, a) for p, a in cited if a not in anchors) == []


# --- the checks themselves, on made-up text -------------------------------------------------------


def test_design_pointers_are_found_and_plain_english_is_not():
    text = "ok by design\nDESIGN convention 5 says\nsee ../shared/DESIGN.md\nsee Design.md\n"
    assert [hit.split(":")[1] for hit in design_pointers("x.py", text)] == ["2", "3", "4"]
    assert design_pointers("x.py", "weights in ../shared/reference/fgn_original/checkpoints\n") == []


def test_backticked_paths_are_found_in_commands_and_checked(tmp_path):
    text = "`pytest -q tests/test_a.py::test_b` and `lagfluid/x.py`, `benchmarks/results/r*.md`, `README.md`"
    paths = backticked_paths(text)
    assert paths == ["tests/test_a.py", "lagfluid/x.py", "benchmarks/results/r*.md", "README.md"]
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "test_a.py").write_text("")
    assert missing_paths(paths, tmp_path) == ["lagfluid/x.py", "benchmarks/results/r*.md", "README.md"]


def test_heading_anchors_follow_github():
    markdown = "# A model in the zoo\n```bash\n# a comment\n```\n## Why the compiled backends exist\n"
    assert heading_anchors(markdown) == {
        "a-model-in-the-zoo",
        "why-the-compiled-backends-exist",
    }
