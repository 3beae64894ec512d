"""The house's rules, checked on the source itself: which room may import which, and no import cycle anywhere.

The import graph is read from the code with `ast`, every import statement included: those inside functions (a
lazy import is still a dependency) and those under `if TYPE_CHECKING:` (marked as such, for the rules about what a
process loads at run time).
"""

from __future__ import annotations

import ast
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("service", "workers", "bench")


@dataclass(frozen=True)
class Import:
    module: str
    """The imported module, or for `from x import y` where y is a module, x.y."""
    type_only: bool
    line: int


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@cache
def _modules() -> dict[str, Path]:
    return {_module_name(path): path for package in PACKAGES for path in (REPO / package).rglob("*.py")}


def _type_checking_lines(tree: ast.Module) -> set[int]:
    lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and ast.unparse(node.test) in ("TYPE_CHECKING", "typing.TYPE_CHECKING"):
            for child in node.body:
                lines.update(range(child.lineno, (child.end_lineno or child.lineno) + 1))
    return lines


@cache
def imports_of(module: str) -> tuple[Import, ...]:
    """Every module `module` imports (absolute names; relative imports resolved)."""
    path = _modules()[module]
    tree = ast.parse(path.read_text(), filename=str(path))
    type_only = _type_checking_lines(tree)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*parts, *([node.module] if node.module else [])])
            names = [base, *(f"{base}.{alias.name}" for alias in node.names if f"{base}.{alias.name}" in _modules())]
        else:
            continue
        found += [Import(name, node.lineno in type_only, node.lineno) for name in names]
    return tuple(found)


def _ours(name: str) -> str | None:
    """The module of ours that `name` is or lies in (`service.store.models.Camera` -> service.store.models)."""
    while name and name not in _modules():
        name = name.rpartition(".")[0]
    return name or None


def _edges(module: str, *, runtime_only: bool = False) -> Iterator[str]:
    for found in imports_of(module):
        target = _ours(found.module)
        if target is not None and target != module and not (runtime_only and found.type_only):
            yield target


def _closure(roots: Iterable[str], *, runtime_only: bool = False) -> set[str]:
    seen, stack = set(), list(roots)
    while stack:
        module = stack.pop()
        if module not in seen:
            seen.add(module)
            stack += _edges(module, runtime_only=runtime_only)
    return seen


def _external(modules: Iterable[str], *, runtime_only: bool = False) -> set[str]:
    """Top-level names of the third-party packages these modules import."""
    return {
        found.module.split(".")[0]
        for module in modules
        for found in imports_of(module)
        if _ours(found.module) is None and not (runtime_only and found.type_only)
    }


def _in(module: str, *packages: str) -> bool:
    return any(module == package or module.startswith(f"{package}.") for package in packages)


def _offenders(sources: Iterable[str], forbidden: tuple[str, ...]) -> dict[str, list[str]]:
    found = {module: sorted({f.module for f in imports_of(module) if _in(f.module, *forbidden)}) for module in sources}
    return {module: names for module, names in found.items() if names}


# --------------------------------------------------------------------------------------------------- direction


def test_service_never_imports_workers_or_bench() -> None:
    """Workers are thin adapters that import the service; the benchmarks sit beside it. Never the reverse."""
    service = [m for m in _modules() if _in(m, "service")]
    assert _offenders(service, ("workers", "bench")) == {}


def test_the_shared_base_imports_no_room() -> None:
    """The store (schema, sessions, migrations), the plain values and the settings are what the rooms share: they
    import nothing of the rooms, so every room can use them."""
    base = [m for m in _modules() if _in(m, "service.store", "service.domain", "service.settings")]
    allowed = ("service.store", "service.domain", "service.settings", "service.geometry")
    offenders = {module: sorted(t for t in _edges(module) if not _in(t, *allowed)) for module in base}
    assert {module: names for module, names in offenders.items() if names} == {}


def test_the_pure_parts_never_reach_the_store() -> None:
    """Keypoints, measuring, the pictures and `posemetry analyze` work on plain values: nothing they import, even
    for type checking and however indirectly, is the store or SQLAlchemy."""
    pure = [m for m in _modules() if _in(m, "service.render", "service.analyze")]
    pure += ["service.frames.keypoints", "service.frames.measure", "service.domain"]
    reached = _closure(pure)
    assert sorted(m for m in reached if _in(m, "service.store")) == []
    assert "sqlalchemy" not in _external(reached)


def test_the_api_never_loads_the_queue() -> None:
    """The app hands work on through the Dispatcher protocol (service.dispatch): it loads neither the Redis client
    nor the queue's code, nor any of the workers' (`posemetry api` passes the Redis dispatcher in)."""
    loaded = _closure(["service.app"], runtime_only=True)
    assert sorted(m for m in loaded if _in(m, "service.queue", "workers", "bench")) == []
    assert "redis" not in _external(loaded, runtime_only=True)


def test_geometry_is_pure() -> None:
    """service.geometry is numpy/scipy only: importable and testable without a database, Redis or a model."""
    allowed = {
        "numpy",
        "scipy",
        "service",
        "__future__",
        "dataclasses",
        "typing",
        "collections",
        "math",
        "functools",
        "bisect",
    }
    for module in (m for m in _modules() if _in(m, "service.geometry")):
        for found in imports_of(module):
            root = found.module.split(".")[0]
            assert root in allowed, f"{module} imports {found.module}"
            if root == "service":
                assert _in(found.module, "service.geometry"), f"{module} imports {found.module}"


# --------------------------------------------------------------------------------------------------- cycles


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of the graph as a path (first module repeated at the end), or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(module: str) -> list[str] | None:
        state[module] = 1
        path.append(module)
        for target in sorted(graph.get(module, ())):
            if state.get(target) == 1:
                return [*path[path.index(target) :], target]
            if target not in state and (found := visit(target)) is not None:
                return found
        path.pop()
        state[module] = 2
        return None

    for module in sorted(graph):
        if module not in state and (found := visit(module)) is not None:
            return found
    return None


def test_the_cycle_finder_finds_cycles() -> None:
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_no_import_cycle_anywhere() -> None:
    """No module imports, however indirectly and wherever in its body, a module that imports it back."""
    graph = {module: set(_edges(module)) for module in _modules()}
    assert _cycle(graph) is None
