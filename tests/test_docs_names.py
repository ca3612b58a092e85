"""The docs name code that exists: every `cli.x.y`-style dotted name in README.md and
docs/ resolves (a module, then attributes), and every `tests/test_x.py` they cite is a
file. Docs are references; a renamed function must not leave them pointing at nothing
(docs/reliability.md once named `cli.local._rows` after its rename to `run_rows`)."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
# (not followed by "/": `macb.io/worker` is a Kubernetes label)
DOTTED = re.compile(r"`((?:cli|shared|services|macb)(?:\.[A-Za-z_][A-Za-z0-9_]*)+)(?![\w/])")
TEST_FILE = re.compile(r"\btests/(test_[A-Za-z0-9_]+\.py)\b")
# The thesis's own repository's tests, which docs/fidelity.md cites beside ours.
THESIS_TESTS = {"test_maddpg_countbased.py", "test_simple_maddpg_countbased.py"}


def named(pattern: re.Pattern[str]) -> list[tuple[str, str]]:
    """(doc, name) for each distinct name `pattern` finds in the docs."""
    seen = {}
    for doc in DOCS:
        for name in pattern.findall(doc.read_text()):
            seen.setdefault(name, doc.relative_to(ROOT).as_posix())
    return sorted((doc, name) for name, doc in seen.items())


def resolves(dotted: str) -> bool:
    """Whether the longest importable prefix of `dotted` has the rest as attributes."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        for attr in parts[cut:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def test_the_docs_name_some_code():
    """The patterns find what the docs cite (an empty list would pass the tests below)."""
    assert len(named(DOTTED)) >= 10 and len(named(TEST_FILE)) >= 20


@pytest.mark.parametrize(("doc", "dotted"), named(DOTTED))
def test_each_dotted_name_in_the_docs_resolves(doc, dotted):
    assert resolves(dotted), f"{doc} names `{dotted}`, which does not resolve"


def test_each_test_file_the_docs_cite_exists():
    cited = [(d, f) for d, f in named(TEST_FILE) if f not in THESIS_TESTS]
    missing = [(d, f) for d, f in cited if not (ROOT / "tests" / f).is_file()]
    assert not missing, f"docs cite test files that do not exist: {missing}"


def test_each_test_function_the_docs_name_is_defined():
    """A test the docs give as the evidence of a behaviour exists under that name."""
    names = named(re.compile(r"\b(test_[A-Za-z0-9_]+)\b(?!\.py)"))
    source = "\n".join(p.read_text() for p in (ROOT / "tests").rglob("*.py"))
    defined = set(re.findall(r"def (test_[A-Za-z0-9_]+)", source))
    assert len(names) >= 20
    missing = [(d, n) for d, n in names if n not in defined]
    assert not missing, f"docs name tests that do not exist: {missing}"


def test_each_function_cited_beside_its_file_is_defined_there():
    """`path/x.py` `Name` (or `Name.attr`), the docs' way of citing code without line
    numbers (which drift): the file defines Name (a def, class, field or assignment),
    and attr."""
    cited = re.compile(
        r"`((?:cli|shared|services|macb|benchmarks|tests)/[\w/]+\.py)` "
        r"`([A-Za-z_]\w*)(?:\.([A-Za-z_]\w*))?`"
    )
    found, missing = 0, []
    for doc in DOCS:
        for path, name, attr in cited.findall(doc.read_text()):
            found += 1
            file = ROOT / path
            source = file.read_text() if file.is_file() else ""
            for x in filter(None, (name, attr)):
                rule = rf"^\s*(?:async\s+)?(?:def|class)\s+{x}\b|^\s*{x}\s*[:=]"
                if not re.search(rule, source, re.M):
                    missing.append((doc.relative_to(ROOT).as_posix(), path, x))
    assert found >= 20
    assert not missing, f"docs cite names their files do not define: {missing}"


def test_the_docs_cite_our_code_by_name_not_by_line():
    """Line numbers drift with every change; a name is checked above. (The thesis's own
    tests, another repository, are cited by line: they do not change.)"""
    by_line = re.compile(r"\b((?:cli|shared|services|macb|benchmarks)/[\w/]+\.py:\d+)")
    found = named(by_line)
    assert not found, f"docs cite our code by line number: {found}"
