"""Evidence tables written by the benchmarks that measure them.

Every table in ``docs/evidence/`` sits under a header naming the command that made it,
``<!-- table: benchmarks/bench_x.py ARGS -->``. A benchmark run with ``--write-docs`` replaces the
table under the header of its own command line with the figures it just measured, so a page never
holds a figure that no run printed.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

EVIDENCE = Path(__file__).resolve().parents[1] / "docs" / "evidence"
WRITE_DOCS = "--write-docs"


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    """The lines of a markdown table."""
    return [f"| {' | '.join(header)} |", "|" + "---|" * len(header), *(f"| {' | '.join(row)} |" for row in rows)]


def command_line(argv: Sequence[str] = tuple(sys.argv)) -> str:
    """The command a table's header names: the script from the repository's root and its
    arguments, without ``--write-docs``."""
    return " ".join([f"benchmarks/{Path(argv[0]).name}", *(a for a in argv[1:] if a != WRITE_DOCS)])


def write_table(command: str, table: list[str], evidence: Path = EVIDENCE) -> Path:
    """Replace the table under ``<!-- table: COMMAND -->`` in the evidence page that has it;
    ValueError when no page, or more than one, has that header."""
    header = f"<!-- table: {command} -->"
    pages = [p for p in sorted(evidence.glob("*.md")) if header in p.read_text().splitlines()]
    if len(pages) != 1:
        raise ValueError(f"{len(pages)} evidence pages have the header {header!r} (one must)")
    lines = pages[0].read_text().splitlines()
    start = lines.index(header) + 1
    end = start
    while end < len(lines) and lines[end].startswith("|"):
        end += 1
    pages[0].write_text("\n".join([*lines[:start], *table, *lines[end:]]) + "\n")
    return pages[0]
