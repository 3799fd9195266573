"""The shape of service/: packages by concern, imports that only point down, HTTP kept in api/.

Read from the source with ``ast`` (nothing is imported), so a violation fails here whichever
test runs first. Every import counts, also the ones deferred into a function: a deferred import
hides a circle from the interpreter, not from the reader. Importing ``service.a.b`` also runs
``service/a/__init__.py``, so each module depends on its packages' ``__init__`` as well.

The checks run on the real tree and, to show that each can fail, on small trees written in a
temporary folder with one violation each.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SERVICE = Path(__file__).resolve().parents[1] / "service"
MAX_TOP_LEVEL = 10  # entries directly under service/ (files and folders), __init__.py included
HTTP_PACKAGES = ("api", "serve")  # may import service.api (serve starts the app)
HTTP_LIBRARIES = ("fastapi", "starlette")  # what only service.api may import
FORBIDDEN = ("torch", "training")  # the service stays torch-free; training imports service, not back


def module_name(root: Path, path: Path) -> str:
    """``service/a/b.py`` -> ``service.a.b``; ``service/a/__init__.py`` -> ``service.a``."""
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def modules(root: Path) -> dict[str, Path]:
    """Every Python module under ``root``, by dotted name."""
    return {module_name(root, p): p for p in sorted(root.rglob("*.py")) if "__pycache__" not in p.parts}


def imported_names(path: Path, name: str) -> list[str]:
    """Absolute names of everything ``path`` imports (``from x import y`` gives ``x.y`` and ``x``)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    is_package = path.name == "__init__.py"
    found: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against this module's package
                base = name.split(".")
                base = base[: len(base) - node.level + (1 if is_package else 0)]
                prefix = ".".join(base + ([node.module] if node.module else []))
            else:
                prefix = node.module or ""
            found.append(prefix)
            found += [f"{prefix}.{alias.name}" for alias in node.names]
    return found


def import_graph(root: Path) -> dict[str, set[str]]:
    """Module -> the modules of ``root``'s package it imports (its packages' ``__init__`` too)."""
    mods = modules(root)
    graph: dict[str, set[str]] = {}
    for name, path in mods.items():
        edges: set[str] = set()
        for target in imported_names(path, name):
            parts = target.split(".")
            # The longest prefix that is a module of ours, and every package above it.
            for i in range(len(parts), 0, -1):
                if ".".join(parts[:i]) in mods:
                    edges.update(".".join(parts[:j]) for j in range(1, i + 1) if ".".join(parts[:j]) in mods)
                    break
        # Importing a module runs its packages' __init__ first.
        parts = name.split(".")
        edges.update(".".join(parts[:j]) for j in range(1, len(parts)) if ".".join(parts[:j]) in mods)
        edges.discard(name)
        graph[name] = edges
    return graph


def unit(root: Path, name: str) -> str:
    """The package of a module for the package graph: ``service.a`` for anything under service/a/,
    the module itself for a top-level module (``service.settings``) or the root package."""
    parts = name.split(".")
    if len(parts) >= 2 and (root / parts[1]).is_dir():
        return ".".join(parts[:2])
    return name


def package_graph(root: Path, graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """The import graph between packages (and top-level modules), without self-edges.

    The root package ``service`` (its ``__init__`` runs before any of its modules) is left out:
    every module depends on it, and it imports none of them.
    """
    top = root.name
    packages: dict[str, set[str]] = {}
    for name, targets in graph.items():
        src = unit(root, name)
        packages.setdefault(src, set())
        packages[src].update(unit(root, t) for t in targets if t != top and unit(root, t) != src)
    packages.pop(top, None)
    return packages


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle as ``[a, b, ..., a]``, or None when the graph has none."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return [*path[path.index(nxt):], nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def http_imports_outside_api(root: Path) -> list[str]:
    """``module -> import`` for each import of ``service.api`` or a web framework outside api/
    (and, for ``service.api``, outside serve/, which starts the app)."""
    top = root.name
    found = []
    for name, path in modules(root).items():
        package = name.split(".")[1] if "." in name else ""
        for target in imported_names(path, name):
            head = target.split(".")[0]
            is_api = target == f"{top}.api" or target.startswith(f"{top}.api.")
            if (is_api and package not in HTTP_PACKAGES) or (head in HTTP_LIBRARIES and package != "api"):
                found.append(f"{name} -> {target}")
    return sorted(set(found))


def forbidden_imports(root: Path) -> list[str]:
    """``module -> import`` for each import of torch or training under ``root``."""
    return sorted({f"{name} -> {target}" for name, path in modules(root).items()
                   for target in imported_names(path, name) if target.split(".")[0] in FORBIDDEN})


def top_level_entries(root: Path) -> list[str]:
    """What a reader sees in service/: files and folders, without caches and hidden ones."""
    return sorted(p.name for p in root.iterdir() if p.name != "__pycache__" and not p.name.startswith("."))


def packages_without_docstring(root: Path) -> list[str]:
    """Folders of Python modules whose ``__init__.py`` is missing or has no docstring."""
    missing = []
    for folder in sorted({p.parent for p in root.rglob("*.py") if "__pycache__" not in p.parts}):
        init = folder / "__init__.py"
        if not init.is_file() or not ast.get_docstring(ast.parse(init.read_text())):
            missing.append(str(folder.relative_to(root.parent)))
    return missing


# --- the real tree ---------------------------------------------------------------------------


def test_no_import_circle_between_modules():
    assert find_cycle(import_graph(SERVICE)) is None, find_cycle(import_graph(SERVICE))


def test_no_import_circle_between_packages():
    packages = package_graph(SERVICE, import_graph(SERVICE))
    assert find_cycle(packages) is None, find_cycle(packages)


def test_only_the_http_packages_know_http():
    assert http_imports_outside_api(SERVICE) == []


def test_no_torch_and_no_training_under_service():
    assert forbidden_imports(SERVICE) == []


def test_top_level_is_small():
    entries = top_level_entries(SERVICE)
    assert len(entries) <= MAX_TOP_LEVEL, f"{len(entries)} in service/, at most {MAX_TOP_LEVEL}: {entries}"


def test_every_package_says_what_it_owns():
    assert packages_without_docstring(SERVICE) == []


# --- each check fails on a tree with one violation -------------------------------------------


def write_tree(tmp_path: Path, files: dict[str, str]) -> Path:
    """A package ``service`` under ``tmp_path`` with ``files`` (path under service/ -> source)."""
    root = tmp_path / "service"
    for rel, source in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(source)
    return root


CLEAN = {
    "__init__.py": '"""Root."""\n',
    "errors.py": "",
    "core/__init__.py": '"""Core."""\n',
    "core/a.py": "from service.errors import x\n",
    "core/b.py": "from service.core import a\n",
    "api/__init__.py": '"""HTTP."""\n',
    "api/app.py": "import fastapi\nfrom service.core.b import y\n",
}


def test_a_clean_tree_passes(tmp_path):
    root = write_tree(tmp_path, CLEAN)
    graph = import_graph(root)
    assert graph["service.core.b"] == {"service", "service.core", "service.core.a"}
    assert find_cycle(graph) is None
    assert find_cycle(package_graph(root, graph)) is None
    assert http_imports_outside_api(root) == forbidden_imports(root) == packages_without_docstring(root) == []


@pytest.mark.parametrize("deferred", [False, True])
def test_a_module_circle_is_found(tmp_path, deferred):
    back = "def f():\n    from service.core.b import y\n" if deferred else "from service.core import b\n"
    root = write_tree(tmp_path, {**CLEAN, "core/a.py": back})
    cycle = find_cycle(import_graph(root))
    assert cycle is not None and cycle[0] == cycle[-1] and set(cycle) == {"service.core.a", "service.core.b"}


def test_a_package_circle_is_found(tmp_path):
    root = write_tree(tmp_path, {**CLEAN, "other/__init__.py": '"""Other."""\n',
                                 "other/c.py": "from service.core.a import x\n",
                                 "core/d.py": "from service.other.c import z\n"})
    graph = import_graph(root)
    assert find_cycle(graph) is None  # no circle between modules ...
    cycle = find_cycle(package_graph(root, graph))
    assert cycle is not None and set(cycle) == {"service.core", "service.other"}


def test_a_relative_import_counts(tmp_path):
    root = write_tree(tmp_path, {**CLEAN, "core/a.py": "from . import b\n"})
    cycle = find_cycle(import_graph(root))
    assert cycle is not None and set(cycle) == {"service.core.a", "service.core.b"}


def test_a_core_import_of_api_or_fastapi_is_found(tmp_path):
    root = write_tree(tmp_path, {**CLEAN, "core/a.py": "from service.api.app import render\n",
                                 "core/b.py": "def f():\n    from starlette.requests import Request\n"})
    assert http_imports_outside_api(root) == ["service.core.a -> service.api.app",
                                              "service.core.a -> service.api.app.render",
                                              "service.core.b -> starlette.requests",
                                              "service.core.b -> starlette.requests.Request"]


def test_torch_and_training_imports_are_found(tmp_path):
    root = write_tree(tmp_path, {**CLEAN, "core/a.py": "def f():\n    import torch\n",
                                 "core/b.py": "from training.models import g\n"})
    assert forbidden_imports(root) == ["service.core.a -> torch", "service.core.b -> training.models",
                                       "service.core.b -> training.models.g"]


def test_a_package_without_docstring_is_found(tmp_path):
    root = write_tree(tmp_path, {**CLEAN, "core/__init__.py": "x = 1\n", "bare/m.py": ""})
    assert packages_without_docstring(root) == ["service/bare", "service/core"]


def test_a_crowded_top_level_is_counted(tmp_path):
    root = write_tree(tmp_path, {**CLEAN, **{f"m{i}.py": "" for i in range(8)}})
    (root / "__pycache__").mkdir()
    assert len(top_level_entries(root)) == 12
