"""The package boundaries the design relies on, checked on the source itself."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _imported_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


def test_service_never_imports_workers() -> None:
    offenders = {
        str(path.relative_to(REPO)): sorted(m for m in _imported_modules(path) if m.split(".")[0] == "workers")
        for path in (REPO / "service").rglob("*.py")
    }
    assert {path: mods for path, mods in offenders.items() if mods} == {}


def test_geometry_is_pure() -> None:
    """service.geometry is numpy/scipy only: importable and testable without a database, Redis or a model."""
    allowed = {"numpy", "scipy", "service", "__future__", "dataclasses", "typing", "collections", "math", "functools"}
    for path in (REPO / "service" / "geometry").rglob("*.py"):
        for module in _imported_modules(path):
            root = module.split(".")[0]
            assert root in allowed, f"{path.name} imports {module}"
            if root == "service":
                assert module.startswith("service.geometry"), f"{path.name} imports {module}"
