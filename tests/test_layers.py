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


def _tests_the_fusion_method(node: ast.Compare) -> bool:
    """``... .fusion <op> ...`` or a comparison with a ``FusionMethod`` member."""
    for operand in (node.left, *node.comparators):
        if isinstance(operand, ast.Attribute) and operand.attr == "fusion":
            return True
        if any(isinstance(n, ast.Name) and n.id == "FusionMethod" for n in ast.walk(operand)):
            return True
    return False


def test_fusion_and_detector_options_are_dispatched_only_by_their_strategies() -> None:
    """No comparison with the fusion method or a FusionMethod member, and no ``hasattr``
    probing, outside the modules that declare the strategies."""
    allowed = {"resloc/cl/fusion.py", "resloc/cl/fusion_methods.py"}
    bad = []
    for path, tree in _modules().items():
        if path in allowed:
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.Compare) and _tests_the_fusion_method(node):
                bad.append(f"{path}:{node.lineno}")
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "hasattr":
                bad.append(f"{path}:{node.lineno} hasattr")
    assert not bad, bad


def _tests_an_innovation_norm(node: ast.Compare) -> bool:
    """A comparison with an ``InnovationNorm`` member (``norm is InnovationNorm.NIS``)."""
    return any(
        isinstance(n, ast.Name) and n.id == "InnovationNorm"
        for operand in (node.left, *node.comparators)
        for n in ast.walk(operand)
    )


#: Modules that still branch on a norm's name instead of asking its rule
#: (``resloc.cl.detection.CHI_SQUARE_NORMS``); each is to move there, and no other may join them.
NORM_BRANCHES_TO_MOVE = {
    "resloc/world/adversary.py",  # the stealthy attacker's own copy of each norm's metric
}


def test_detector_norms_are_dispatched_only_where_declared() -> None:
    """No comparison with an InnovationNorm member outside the module that declares the
    norms (the gate's false-alarm check and threshold ask ``CHI_SQUARE_NORMS``)."""
    branching = {
        path
        for path, tree in _modules().items()
        for node in ast.walk(tree)
        if isinstance(node, ast.Compare) and _tests_an_innovation_norm(node)
    }
    assert branching - NORM_BRANCHES_TO_MOVE <= {"resloc/cl/detector.py"}, branching
