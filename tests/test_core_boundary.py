"""core knows nothing of the command line: no module parses arguments and no message names an
option, since the console shows core's messages to operators who never typed one. Where an
option would help, core's error carries a remedy and the command line names the option
(``app.cli.REMEDY_OPTIONS``)."""

from __future__ import annotations

import ast
import pickle
import re
from pathlib import Path

import pytest

from probecal.app.cli import REMEDY_OPTIONS
from probecal.core.errors import InputError, Remedy

ROOT = Path(__file__).resolve().parent.parent
CORE_MODULES = sorted((ROOT / "core").rglob("*.py"))
OPTION = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]+")
"""A command-line option as a message would name it: --spacing, --start-depth-mm."""
PARSERS = {"argparse", "optparse", "getopt", "click"}


def _options_said(source: str) -> list[tuple[int, str]]:
    """(line, option) for every option named by a string constant of ``source`` that does not
    document: docstrings, and bare strings after an assignment (an attribute's), may."""
    tree = ast.parse(source)
    documentation = {id(node.value) for node in ast.walk(tree) if isinstance(node, ast.Expr)}
    return [(node.lineno, option) for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in documentation
            for option in OPTION.findall(node.value)]


def _imported(source: str) -> set[str]:
    """The top-level packages ``source`` imports, at the top or inside a function."""
    names = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names.add(node.module.split(".")[0])
    return names


def test_core_parses_no_arguments():
    assert [str(p.relative_to(ROOT)) for p in CORE_MODULES if PARSERS & _imported(p.read_text())] == []


def test_core_names_no_command_line_option_outside_its_documentation():
    said = [f"{path.relative_to(ROOT)}:{line}: {option}"
            for path in CORE_MODULES for line, option in _options_said(path.read_text())]
    assert said == []


@pytest.mark.parametrize("source, options", [
    ('raise InputError(path, "exists; --force overwrites it")', ["--force"]),
    ('x = f"check --speed and {n} --frame-rate"', ["--speed", "--frame-rate"]),
    ('def f():\n    """A docstring may name --spacing."""\n', []),
    ('X = 1\n"""So may an attribute\'s: --seed."""\n', []),
    ('x = "a dash -- aside, x--y, and ---"', []),
])
def test_the_check_finds_options_in_messages_not_in_documentation(source, options):
    assert [option for _, option in _options_said(source)] == options


def test_the_check_finds_a_parser_imported_anywhere():
    assert _imported("def main():\n    import argparse\n") == {"argparse"}
    assert _imported("from argparse import ArgumentParser\n") == {"argparse"}


def test_every_remedy_has_its_option_and_an_error_crosses_processes_with_its_remedies():
    assert set(REMEDY_OPTIONS) == set(Remedy)
    error = InputError("a.json", "made for other images", (Remedy.START_DEPTH, Remedy.FORCE))
    rebuilt = pickle.loads(pickle.dumps(error))
    assert (rebuilt.path, rebuilt.problem, rebuilt.remedies) == (error.path, error.problem, error.remedies)
    assert not OPTION.search(str(error))
