"""The packages import downwards only: cli -> services -> shared.

shared/ is the library every process loads, so it must not pull in a service or the
command line (that once made `import shared.cli` load the API); services must not depend
on the command that starts them. Read with `ast`, so imports inside functions count too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

# package -> the top-level packages it must never import
FORBIDDEN = {"shared": ("services", "cli"), "services": ("cli",)}


def imported_modules(source: str, module: str) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in `source`, the module `module`:
    `import x`, `from x import y`, relative imports resolved, and calls of
    importlib.import_module / __import__ with a literal (or f-string) name."""
    package = module.split(".")[:-1]
    found: list[tuple[int, str]] = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            name = ".".join([*base, *([node.module] if node.module else [])])
            found.append((node.lineno, name))
        elif isinstance(node, ast.Call) and _is_dynamic_import(node.func) and node.args:
            name = _literal_prefix(node.args[0])
            if name is not None:
                found.append((node.lineno, name))
    return sorted(found)  # ast.walk goes breadth-first; report in line order


def _is_dynamic_import(func: ast.expr) -> bool:
    if isinstance(func, ast.Name):
        return func.id in ("__import__", "import_module")
    return isinstance(func, ast.Attribute) and func.attr == "import_module"


def _literal_prefix(arg: ast.expr) -> str | None:
    """'services.x' from "services.x" or f"services.{role}.main"; None if not literal."""
    if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
        return arg.value
    if isinstance(arg, ast.JoinedStr) and arg.values and isinstance(arg.values[0], ast.Constant):
        return str(arg.values[0].value)
    return None


def violations(package: str) -> list[str]:
    bad = []
    for path in sorted((ROOT / package).rglob("*.py")):
        rel = path.relative_to(ROOT)
        module = ".".join(rel.with_suffix("").parts)
        for line, name in imported_modules(path.read_text(), module):
            if name.split(".")[0] in FORBIDDEN[package]:
                bad.append(f"{rel}:{line} imports {name}")
    return bad


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_package_imports_no_layer_above_it(package):
    assert (ROOT / package).is_dir()
    assert violations(package) == []


def test_the_check_sees_every_kind_of_import():
    source = """
import services.api.client
from services import router
from cli.main import main
def f():
    import cli
    from services.api.store import Store
import importlib
importlib.import_module(f"services.{role}.main")
__import__("cli.api")
from . import config
from .. import services
import shared.config
"""
    names = [name for _, name in imported_modules(source, "shared.sub.mod")]
    assert names == [
        "services.api.client",
        "services",
        "cli.main",
        "cli",
        "services.api.store",
        "importlib",
        "services.",
        "cli.api",
        "shared.sub",
        "shared",
        "shared.config",
    ]
