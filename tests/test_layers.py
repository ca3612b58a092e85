"""The packages import downwards only: macb -> cli -> services -> shared.

shared/ is the library every process loads, so it must not pull in a service or the
command line (that once made `import shared.cli` load the API); services must not depend
on the command that starts them. Read with `ast`, so imports inside functions count too.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

# package -> the top-level packages it must never import
# (macb/, the Python API, is the top: it reads runs through the report's functions in cli/.)
FORBIDDEN = {
    "shared": ("services", "cli", "macb"),
    "services": ("cli", "macb"),
    "cli": ("macb",),
}


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


# Inside shared/, each layer imports only the layers below it (a layer may import
# itself). The math knows no environment, the environments no config, the wire no
# learner: each can be read, tested and replaced with what is under it.
SHARED_LAYERS: dict[str, tuple[str, ...]] = {
    "shared.core": (),  # math and learners: numpy and torch only
    "shared.envs": ("shared.core",),  # tasks and their worlds
    "shared.config": ("shared.core", "shared.envs"),  # the experiment schema
    "shared.metrics": (),  # a metric row's fields
    "shared.groups": ("shared.config",),  # which runs may share a group
    "shared.persist": ("shared.core", "shared.config"),  # files that outlive a process
    "shared.run": ("shared.core", "shared.envs", "shared.config"),  # a run's parts
    "shared.settings": (),  # the MACB_* variables (pydantic-settings)
    "shared.procs": (),  # child processes started and ended by PID (stdlib)
    "shared.net": ("shared.config", "shared.groups", "shared.settings"),  # wire, bus, watcher
}
# What shared.core may import from outside the standard library.
CORE_THIRD_PARTY = {"numpy", "torch"}


def _unit(module: str) -> str | None:
    """The layer of a module of shared/: shared.core.learners.batched -> shared.core."""
    parts = module.split(".")
    return ".".join(parts[:2]) if parts[0] == "shared" and len(parts) > 1 else None


def _modules(package: str) -> dict[str, Path]:
    found = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def _runtime_imports(path: Path, module: str) -> list[tuple[int, str]]:
    """imported_modules without those under `if TYPE_CHECKING:` (never executed)."""
    tree = ast.parse(path.read_text())
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip |= {n.lineno for stmt in node.body for n in ast.walk(stmt) if hasattr(n, "lineno")}
    is_package = path.name == "__init__.py"
    name = f"{module}.__init__" if is_package else module
    return [(line, m) for line, m in imported_modules(path.read_text(), name) if line not in skip]


def _resolve(name: str, modules: dict[str, Path], names: list[str]) -> list[str]:
    """The modules an import statement loads: `from a.b import c` is a.b.c when c is a
    module, else a.b."""
    out = [f"{name}.{n}" for n in names if f"{name}.{n}" in modules]
    return out or ([name] if name in modules else [])


def import_graph() -> dict[str, set[str]]:
    modules = {
        m: p for pkg in ("shared", "services", "cli", "macb") for m, p in _modules(pkg).items()
    }
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for module, path in modules.items():
        tree = ast.parse(path.read_text())
        lines = dict(_runtime_imports(path, module))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.lineno in lines:
                graph[module] |= set(
                    _resolve(lines[node.lineno], modules, [a.name for a in node.names])
                )
            elif isinstance(node, ast.Import) and node.lineno in lines:
                graph[module] |= {a.name for a in node.names if a.name in modules}
        graph[module].discard(module)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every strongly connected group of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                found.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_module_imports_itself_through_others():
    assert cycles(import_graph()) == []


def test_the_cycle_check_finds_a_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [["a", "b", "c"]]


def layer_violations() -> list[str]:
    bad = []
    for module, path in _modules("shared").items():
        unit = _unit(module)
        if unit is None:
            continue
        assert unit in SHARED_LAYERS, f"{path.relative_to(ROOT)}: in no layer of SHARED_LAYERS"
        allowed = {unit, *SHARED_LAYERS[unit]}
        for line, name in _runtime_imports(path, module):
            top = name.split(".")[0]
            target = _unit(name)
            if top == "shared" and target is not None and target not in allowed:
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
            outside = top not in ("shared", "__future__", *CORE_THIRD_PARTY)
            outside = outside and top not in sys.stdlib_module_names
            if unit == "shared.core" and outside:
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
    return bad


def test_each_layer_of_shared_imports_only_the_layers_below_it():
    assert layer_violations() == []


def module_level_imports(path: Path, module: str, modules: dict[str, Path]) -> set[str]:
    """The modules of `modules` that `path` (the module `module`) imports at module level:
    in its body and in the `if`/`try`/`with` blocks there (`if TYPE_CHECKING:` too: a
    type checker follows those), never inside a function or class body. `from p import
    n` is an import of the package p (its __init__ runs, and n may be a name it
    defines), and of p.n when that is a module too."""
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    found: set[str] = set()

    def visit(body: list[ast.stmt]) -> None:
        for node in body:
            if isinstance(node, ast.Import):
                found.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = package[: len(package) - node.level + 1] if node.level else []
                name = ".".join([*base, *([node.module] if node.module else [])])
                found.add(name)
                found.update(f"{name}.{a.name}" for a in node.names)
            elif isinstance(node, ast.If | ast.Try | ast.With):
                for block in ("body", "orelse", "finalbody"):
                    visit(getattr(node, block, []))
                for handler in getattr(node, "handlers", []):
                    visit(handler.body)

    visit(ast.parse(path.read_text()).body)
    return {m for m in found if m in modules and m != module}


def module_level_graph(package: str) -> dict[str, set[str]]:
    modules = _modules(package)
    return {m: module_level_imports(p, m, modules) for m, p in modules.items()}


def test_no_module_of_shared_imports_itself_at_module_level():
    """A module-level cycle makes the import order matter (a half-initialised module
    seen from the other side) and the modules one unit; imports inside functions, which
    run after every module has loaded, are left out."""
    assert cycles(module_level_graph("shared")) == []


def test_the_module_level_check_sees_a_package_imported_by_its_module(tmp_path, monkeypatch):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("from pkg.a import f\n")
    (pkg / "a.py").write_text("from pkg import b\n\ndef f():\n    import pkg.c\n")
    (pkg / "b.py").write_text("")
    (pkg / "c.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import pkg.a\n"
    )
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    graph = module_level_graph("pkg")
    assert graph == {
        "pkg": {"pkg.a"},
        "pkg.a": {"pkg", "pkg.b"},
        "pkg.b": set(),
        "pkg.c": {"pkg.a"},
    }
    assert cycles(graph) == [["pkg", "pkg.a"]]
