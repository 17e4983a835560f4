"""Structure rules of the package, checked on its source: no module imports another's
private names, and a public constant is defined in one module only."""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "resloc"


def _modules() -> dict[str, ast.Module]:
    return {
        str(p.relative_to(SRC.parent)): ast.parse(p.read_text(encoding="utf-8"))
        for p in sorted(SRC.rglob("*.py"))
    }


def test_no_module_imports_a_private_name_of_another() -> None:
    bad = [
        f"{path}: from {node.module} import {alias.name}"
        for path, tree in _modules().items()
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("resloc")
        for alias in node.names
        if alias.name.startswith("_") and not alias.name.endswith("__")
    ]
    assert not bad, bad


def test_public_constants_are_defined_once() -> None:
    where: dict[str, list[str]] = defaultdict(list)
    for path, tree in _modules().items():
        for node in tree.body:
            targets = node.targets if isinstance(node, ast.Assign) else []
            if isinstance(node, ast.AnnAssign):
                targets = [node.target]
            for t in targets:
                if isinstance(t, ast.Name) and t.id.isupper() and not t.id.startswith("_"):
                    where[t.id].append(path)
    twice = {name: paths for name, paths in where.items() if len(paths) > 1}
    # COLORS (plots.py and report.py) goes when the plotting moves into one module.
    assert set(twice) <= {"COLORS"}, twice
