"""The manual in docs/ stays true: its command blocks run, its links resolve, its command-line
reference is the parser's own, and every evidence table names the script that writes it.

A ```bash block in docs/ runs, in the order docs/index.md lists the pages, in one shared folder
(so a page may use the sessions an earlier page made). A block that needs real hardware starts
with a visible ``# not run: REASON`` line instead; the install block of getting-started.md
(``./run.sh serve``, ``./run.sh test``) is checked by starting the console, and CI runs the second.
"""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
BLOCK = re.compile(r"^```(\w*)\n(.*?)^```", re.DOTALL | re.MULTILINE)
NOT_RUN = re.compile(r"^# not run: \S.*")
MAX_NOT_RUN = 3
TABLE_HEADER = re.compile(r"^<!-- table: (benchmarks/[\w./-]+\.py)(?: [^>]*)? -->$")
LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)|!\[[^\]]*\]\(([^)\s]+)\)")


def pages() -> list[Path]:
    """Every markdown page of the manual, in the order docs/index.md lists them, then the rest."""
    index = DOCS / "index.md"
    listed = [index]
    for match in LINK.finditer(index.read_text()):
        target = (match.group(1) or match.group(2)).split("#")[0]
        path = (DOCS / target).resolve()
        if target and path.suffix == ".md" and path.is_relative_to(DOCS) and path not in listed:
            listed.append(path)
    rest = sorted(p.resolve() for p in DOCS.rglob("*.md") if p.resolve() not in listed)
    return listed + rest


def bash_blocks(page: Path) -> list[str]:
    return [body for lang, body in BLOCK.findall(page.read_text()) if lang in ("bash", "sh", "shell")]


def is_install_block(block: str) -> bool:
    return all(line.startswith("./run.sh ") for line in block.strip().splitlines())


def runnable() -> list[tuple[Path, str]]:
    """(page, block) of every block the docs test runs, in order."""
    return [(page, block) for page in pages() for block in bash_blocks(page)
            if not NOT_RUN.match(block) and not is_install_block(block)]


def test_every_page_is_in_the_index():
    index_text = (DOCS / "index.md").read_text()
    for page in DOCS.rglob("*.md"):
        if page.name != "index.md" or page.parent != DOCS:
            assert str(page.relative_to(DOCS)) in index_text, f"docs/index.md does not list {page.relative_to(DOCS)}"


def test_blocks_not_run_are_few_and_say_why():
    marked = [(page, block) for page in pages() for block in bash_blocks(page) if NOT_RUN.match(block)]
    assert len(marked) <= MAX_NOT_RUN, [str(p.relative_to(ROOT)) for p, _ in marked]
    for page, block in marked:
        assert "hardware" in block.splitlines()[0] or "robot" in block.splitlines()[0], (page, block.splitlines()[0])
    for page in pages():
        for lang, _body in BLOCK.findall(page.read_text()):
            assert lang, f"{page.relative_to(ROOT)}: a code block without a language (bash runs; text does not)"


def markdown_files() -> list[Path]:
    return [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted(DOCS.rglob("*.md"))]


def anchors(page: Path) -> set[str]:
    """GitHub's anchors for the headings of ``page``."""
    found = set()
    for line in page.read_text().splitlines():
        match = re.match(r"#+ (.*)", line)
        if match:
            title = match.group(1).strip().lower().replace(" ", "-")
            found.add("".join(c for c in title if c.isalnum() or c in "-_"))
    return found


@pytest.mark.parametrize("page", markdown_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page):
    text = BLOCK.sub("", page.read_text())
    for match in LINK.finditer(text):
        target = match.group(1) or match.group(2)
        if re.match(r"[a-z]+:", target):
            continue
        path, _, anchor = target.partition("#")
        resolved = (page.parent / path).resolve() if path else page
        assert resolved.exists(), f"{page.relative_to(ROOT)}: {target} does not exist"
        assert resolved.is_relative_to(ROOT), f"{page.relative_to(ROOT)}: {target} lies outside the repository"
        if anchor and resolved.suffix == ".md":
            assert anchor in anchors(resolved), f"{page.relative_to(ROOT)}: no heading #{anchor} in {path or page.name}"


@pytest.mark.parametrize("page", markdown_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_nothing_outside_the_repository_is_cited(page):
    text = page.read_text()
    assert "../shared" not in text and "shared/data" not in text, page
    assert not re.search(r"\bSPEC\b", text), page


def test_every_picture_in_docs_img_is_shown():
    text = "".join(page.read_text() for page in markdown_files())
    for picture in sorted((DOCS / "img").iterdir()):
        assert f"img/{picture.name}" in text, f"no page shows docs/img/{picture.name}"


def test_every_evidence_table_names_the_script_that_writes_it():
    tables = 0
    for page in sorted((DOCS / "evidence").rglob("*.md")):
        lines = page.read_text().splitlines()
        for i, line in enumerate(lines):
            if line.startswith("|") and (i == 0 or not lines[i - 1].startswith("|")):
                tables += 1
                header = lines[i - 1] if i else ""
                match = TABLE_HEADER.match(header)
                where = f"{page.relative_to(ROOT)}:{i + 1}"
                assert match, f"{where}: the table lacks a '<!-- table: benchmarks/... -->' header"
                script = ROOT / match.group(1)
                assert script.is_file(), f"{where}: no {match.group(1)}"
                source = script.read_text()
                assert "WRITE_DOCS" in source and "write_table(" in source, \
                    f"{where}: {match.group(1)} cannot write its table (evidence.py's --write-docs)"
                command = header.removeprefix("<!-- table: ").removesuffix(" -->")
                assert f"`.venv/bin/python {command}`" in lines[i - 2], f"{where}: no visible 'Made by' line"
    assert tables >= 10


def test_the_cli_reference_is_generated_from_the_parser():
    from probecal.app.clidoc import render

    committed = (DOCS / "cli.md").read_text()
    assert committed == render(), "docs/cli.md is stale: .venv/bin/python -m probecal.app.clidoc > docs/cli.md"


def test_every_readme_block_is_run_or_marked():
    """README's blocks: the two commands (as getting-started.md's, run below), the command line
    (tests/test_readme.py runs it) and the real-data recipe, which fetches from GitHub."""
    blocks = bash_blocks(ROOT / "README.md")
    install = [b for b in blocks if is_install_block(b)]
    marked = [b for b in blocks if b.startswith("# not run by the tests: ")]
    tutorial = [b for b in blocks if "probecal simulate calibration" in b]
    assert len(install) == 1 and len(marked) == 1 and len(tutorial) == 1 and len(blocks) == 3
    assert "git clone" in marked[0] and "probecal" not in marked[0].split("\n", 1)[1].replace("probecal.core", "")
    assert install == [b for b in bash_blocks(DOCS / "getting-started.md") if is_install_block(b)]


def test_the_install_block_is_the_two_commands():
    blocks = [b for b in bash_blocks(DOCS / "getting-started.md") if is_install_block(b)]
    assert len(blocks) == 1
    commands = [line.split("#")[0].split() for line in blocks[0].strip().splitlines()]
    assert commands == [["./run.sh", "serve"], ["./run.sh", "test"]]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_the_install_block_runs():
    """./run.sh serve answers on its port (here a free one). ./run.sh test is what CI runs (.ci/run),
    so every CI run runs the second command; running it again here would lint and test twice."""
    assert (ROOT / ".ci" / "run").read_text().strip().splitlines()[-1] == "exec ./run.sh test"
    port = _free_port()
    server = subprocess.Popen([str(ROOT / "run.sh"), "serve", "--port", str(port)], cwd=ROOT,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    try:
        deadline = time.monotonic() + 180
        while True:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=5) as page:
                    assert page.status == 200
                    break
            except OSError:
                assert server.poll() is None, server.stderr.read().decode()[-2000:]
                assert time.monotonic() < deadline, "./run.sh serve did not answer"
                time.sleep(0.5)
    finally:
        os.killpg(server.pid, 15)
        server.wait(timeout=30)


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_the_docs_command_blocks_run_in_order(plus_data, tmp_path):
    script = ["set -euo pipefail"]
    for page, block in runnable():
        script += [f"echo '### {page.relative_to(ROOT)}' >&2", block]
    (tmp_path / "docs.sh").write_text("\n".join(script) + "\n")
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
           "PROBECAL_PLUS_DATA": str(Path(plus_data).resolve())}
    result = subprocess.run(["bash", str(tmp_path / "docs.sh")], cwd=tmp_path, env=env, capture_output=True,
                            text=True, timeout=580)
    pages_run = re.findall(r"^### (.*)$", result.stderr, re.MULTILINE)
    assert result.returncode == 0, f"failed in {pages_run[-1:]}:\n" + result.stdout[-2000:] + result.stderr[-3000:]
    for made in ("sessions/first/calibration.json", "out/phantom/frame.stl", "sessions/first/phantom_check.json",
                 "sessions/plus-validation/manifest.json", "first.igs.mha", "lab-calibration.json",
                 "cont-latency.json", "out/vol/report.json"):
        assert (tmp_path / made).is_file(), made
    assert "Calibration usable" in result.stdout and "image corners off by" in result.stdout


def test_a_benchmark_writes_its_table_under_the_header_of_its_command(tmp_path):
    from benchmarks.evidence import command_line, markdown_table, write_table

    page = tmp_path / "page.md"
    page.write_text("# Page\n\nMade by it:\n<!-- table: benchmarks/bench_x.py --seeds 2 -->\n"
                    "| a |\n|---|\n| 1 |\n\nAfter.\n")
    command = command_line(["/repo/benchmarks/bench_x.py", "--seeds", "2", "--write-docs"])
    assert command == "benchmarks/bench_x.py --seeds 2"
    assert write_table(command, markdown_table(["a", "b"], [["2", "3"]]), tmp_path) == page
    assert page.read_text() == ("# Page\n\nMade by it:\n<!-- table: benchmarks/bench_x.py --seeds 2 -->\n"
                                "| a | b |\n|---|---|\n| 2 | 3 |\n\nAfter.\n")
    with pytest.raises(ValueError, match="0 evidence pages"):
        write_table("benchmarks/bench_x.py", [], tmp_path)
