"""Benchmarks pass settings in as values: none assigns a module global of probecal."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _probecal_names(tree: ast.Module) -> set[str]:
    """Names a script binds to something imported from probecal."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.asname or a.name.split(".")[0] for a in node.names if a.name.startswith("probecal")}
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("probecal"):
            names |= {a.asname or a.name for a in node.names}
    return names


def _assigned_attributes(tree: ast.Module) -> list[ast.Attribute]:
    targets: list[ast.expr] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign):
            targets += node.targets
        elif isinstance(node, (ast.AugAssign, ast.AnnAssign)):
            targets.append(node.target)
    flat = [t for target in targets for t in (target.elts if isinstance(target, ast.Tuple) else [target])]
    return [t for t in flat if isinstance(t, ast.Attribute)]


def test_no_benchmark_assigns_a_probecal_module_global():
    found = []
    for script in sorted((ROOT / "benchmarks").glob("*.py")):
        tree = ast.parse(script.read_text())
        imported = _probecal_names(tree)
        for target in _assigned_attributes(tree):
            base = target.value
            while isinstance(base, ast.Attribute):
                base = base.value
            if isinstance(base, ast.Name) and base.id in imported:
                found.append(f"{script.name}:{target.lineno}: {ast.unparse(target)}")
    assert not found, "benchmarks assign probecal's module globals:\n" + "\n".join(found)
