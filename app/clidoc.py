"""The command-line reference, docs/cli.md, rendered from the parser ``app.cli`` builds.

    .venv/bin/python -m probecal.app.clidoc > docs/cli.md

``tests/test_docs.py`` checks that the committed page equals what this prints, so the reference
never goes stale: change an option, then run the line above.
"""

from __future__ import annotations

import argparse
import sys

from probecal.app.cli import build_parser

HEADER = """# Command-line reference

<!-- Generated from app/cli.py by `.venv/bin/python -m probecal.app.clidoc > docs/cli.md`; do not edit. -->

Every command of `probecal`, with every option, as `probecal COMMAND --help` gives it. This page is
generated from the parser itself, and a test checks that it is current. Lengths are in mm, times in
s. Bad input exits with code 2 and one line naming the file and the problem.
"""


def _subcommands(parser: argparse.ArgumentParser) -> list[tuple[str, str, argparse.ArgumentParser]]:
    """(name, one-line help, parser) of each subcommand, in the order they were added."""
    found = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {choice.dest: choice.help or "" for choice in action._choices_actions}
            for name, sub in action.choices.items():
                found.append((name, helps.get(name, ""), sub))
    return found


def _metavar(action: argparse.Action) -> str:
    """How an option's value is written: its metavar, its choices, or its destination."""
    if action.nargs == 0:
        return ""
    if action.metavar is not None:
        names = action.metavar if isinstance(action.metavar, tuple) else (action.metavar,)
    elif action.choices is not None:
        names = ("{" + ",".join(str(c) for c in action.choices) + "}",)
    else:
        names = (action.dest.upper(),)
    if action.nargs in ("+", "*"):
        one = names[0]
        return f"{one} [{one}]" if action.nargs == "+" else f"[{one} ...]"
    if isinstance(action.nargs, int) and len(names) == 1:
        return " ".join(names * action.nargs)
    if action.nargs == "?":
        return f"[{names[0]}]"
    return " ".join(names)


def _help(action: argparse.Action, prog: str) -> str:
    text = action.help or ""
    if "%" in text:
        text = text % {**vars(action), "prog": prog}
    return " ".join(text.split()).replace("|", "\\|")


def _arguments(parser: argparse.ArgumentParser) -> tuple[list[argparse.Action], list[argparse.Action]]:
    """The positional arguments and the options, help left out."""
    positional: list[argparse.Action] = []
    options: list[argparse.Action] = []
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        (options if action.option_strings else positional).append(action)
    return positional, options


def _synopsis(prog: str, parser: argparse.ArgumentParser) -> str:
    positional, options = _arguments(parser)
    words = [prog]
    required = [a for a in options if a.required]
    words += [f"{a.option_strings[0]} {_metavar(a)}".strip() for a in required]
    groups = [g for g in parser._mutually_exclusive_groups if g.required]
    for group in groups:
        words.append("(" + " | ".join(f"{a.option_strings[0]} {_metavar(a)}".strip()
                                      for a in group._group_actions) + ")")
    grouped = {a for g in groups for a in g._group_actions}
    if any(not a.required and a not in grouped for a in options):
        words.append("[options]")
    words += [_metavar(a) for a in positional]
    return " ".join(words)


def _section(prog: str, summary: str, parser: argparse.ArgumentParser, level: int) -> list[str]:
    lines = [f"{'#' * level} `{prog}`", ""]
    if parser.description or summary:
        lines += [" ".join((parser.description or summary).split()), ""]
    subs = _subcommands(parser)
    if subs:
        lines += ["| command | what it does |", "|---|---|"]
        lines += [f"| `{prog} {name}` | {' '.join(text.split())} |" for name, text, _ in subs]
        lines.append("")
        for name, text, sub in subs:
            lines += _section(f"{prog} {name}", text, sub, level + 1)
        return lines
    lines += ["```text", _synopsis(prog, parser), "```", ""]
    positional, options = _arguments(parser)
    if not positional and not options:
        lines += [f"Its options are its own: `{prog} --help`." if prog.endswith("ursim") else "No options.", ""]
        return lines
    lines += ["| argument | what it is |", "|---|---|"]
    for action in positional:
        lines.append(f"| `{_metavar(action)}` | {_help(action, prog)} |")
    for action in options:
        name = ", ".join(action.option_strings)
        value = _metavar(action)
        lines.append(f"| `{name}{' ' + value if value else ''}` | {_help(action, prog)} |")
    lines.append("")
    return lines


def render(parser: argparse.ArgumentParser | None = None) -> str:
    """docs/cli.md: every command of the parser, its synopsis and its arguments, in markdown."""
    parser = parser or build_parser()
    lines = [HEADER]
    lines += ["| command | what it does |", "|---|---|"]
    subs = _subcommands(parser)
    lines += [f"| [`probecal {name}`](#{_anchor('probecal ' + name)}) | {' '.join(text.split())} |"
              for name, text, _ in subs]
    lines.append("")
    for name, text, sub in subs:
        lines += _section(f"probecal {name}", text, sub, 2)
    return "\n".join(lines).rstrip("\n") + "\n"


def _anchor(title: str) -> str:
    """GitHub's anchor for a heading `title` (in backticks): lower case, spaces to hyphens."""
    return "".join(c for c in title.lower().replace(" ", "-") if c.isalnum() or c in "-_")


if __name__ == "__main__":
    sys.stdout.write(render())
