"""The layout shows the pipeline: core's stages import only lower stages and no module imports
itself back through others (docs/index.md, "Where things are in the code"). ruff and mypy are no
tests here: they are ``./run.sh lint``, the stage ``./run.sh test`` runs before the suite."""

from __future__ import annotations

import ast
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
STAGES = ("geometry", "io", "build", "robot", "twin", "acquisition", "temporal", "calibration", "volume")
"""core's subpackages, lowest first: each may import the ones before it, never one after."""


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return "probecal." + ".".join(parts)


def _imports(path: Path) -> set[str]:
    """Every probecal module ``path`` imports, at the top or inside a function."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("probecal."):
            found.add(node.module)
            found.update(f"{node.module}.{a.name}" for a in node.names)  # submodules named this way
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("probecal."))
    return found


def _graph(package: str) -> dict[str, set[str]]:
    modules = {_module_name(p): p for p in sorted((ROOT / package).rglob("*.py"))}
    return {name: {m for m in _imports(path) if m in modules and m != name} for name, path in modules.items()}


def _stage(module: str) -> int | None:
    parts = module.split(".")
    return STAGES.index(parts[2]) if len(parts) > 2 and parts[2] in STAGES else None


def test_core_stages_import_only_lower_stages():
    upward = [
        f"{module} imports {target}"
        for module, targets in _graph("core").items()
        for target in targets
        if _stage(module) is not None and _stage(target) is not None and _stage(target) > _stage(module)
    ]
    assert upward == []


def test_core_never_imports_the_app():
    for path in (ROOT / "core").rglob("*.py"):
        assert not any(m.startswith("probecal.app") for m in _imports(path)), path


def _fail_on_cycle(graph: dict[str, set[str]]) -> None:
    """Fail the test with the first import cycle found in ``graph`` (depth-first)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(module: str, path: list[str]) -> None:
        state[module] = 1
        for target in sorted(graph[module]):
            if state.get(target) == 1:
                cycle = path[path.index(target):] + [target] if target in path else [module, target]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if target not in state:
                visit(target, path + [target])
        state[module] = 2

    for module in graph:
        if module not in state:
            visit(module, [module])


def test_no_import_cycle():
    for package in ("core", "app"):
        _fail_on_cycle(_graph(package))


def test_core_root_holds_at_most_three_modules_and_every_stage_says_what_it_does():
    assert len(list((ROOT / "core").glob("*.py"))) <= 3
    for stage in STAGES:
        init = ROOT / "core" / stage / "__init__.py"
        assert ast.get_docstring(ast.parse(init.read_text())), init
    assert sorted(p.name for p in (ROOT / "core").iterdir() if p.is_dir() and p.name != "__pycache__") == sorted(STAGES)



TOP_LEVEL = {".ci", ".gitignore", "pyproject.toml", "README.md", "CHANGELOG.md", "LICENSE", "run.sh", "core", "app",
             "static", "sessions", "docs", "tests", "benchmarks"}
"""What the repository holds at its top: the design card's folders and files."""


def test_the_top_level_holds_only_the_design_cards_folders():
    if not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    listed = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    top = {name.split("/")[0] for name in listed.split("\0") if name}
    assert top <= TOP_LEVEL, sorted(top - TOP_LEVEL)


def test_calibration_functions_stay_short():
    """A pipeline is a sequence of named steps: no function of core/calibration runs past 80 lines,
    and calibrate_session, the sequence itself, fits in 40."""
    lengths = {f"{path.name}:{node.name}": node.end_lineno - node.lineno + 1
               for path in sorted((ROOT / "core" / "calibration").glob("*.py"))
               for node in ast.walk(ast.parse(path.read_text()))
               if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno is not None}
    assert {name: n for name, n in lengths.items() if n > 80} == {}
    assert lengths["solve.py:calibrate_session"] <= 40
