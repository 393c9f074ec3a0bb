"""Every code block of the README runs as written from an empty folder.

Python blocks run in a fresh interpreter, bash blocks in `bash -e`, each in a
new empty folder. A block that installs the package or runs for many minutes
or serves until Ctrl-C carries the marker `<!-- not run by tests: REASON -->` on the line before its
fence (the league's server blocks are run by tests/test_league_web.py instead); the fast test below keeps those few and their reasons honest.
"""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"
MARKER = re.compile(r"^<!-- not run by tests: (?P<reason>.+) -->$")
FENCE = re.compile(r"^```(?P<lang>\w*)$")


def readme_blocks() -> list[dict]:
    """The README's fenced code blocks: {"line", "lang", "code", "skip" (the marker's reason or None)}."""
    lines, blocks, k = README.read_text().splitlines(), [], 0
    while k < len(lines):
        opening = FENCE.match(lines[k])
        if not opening:
            k += 1
            continue
        end = next(j for j in range(k + 1, len(lines)) if lines[j] == "```")
        marker = MARKER.match(lines[k - 1]) if k else None
        blocks.append({"line": k + 1, "lang": opening["lang"], "code": "\n".join(lines[k + 1:end]) + "\n",
                       "skip": marker["reason"] if marker else None})
        k = end + 1
    return blocks


CODE = [b for b in readme_blocks() if b["lang"] in ("python", "bash")]


def test_the_readme_blocks_are_python_or_bash_and_few_are_not_run():
    blocks = readme_blocks()
    assert {b["lang"] for b in blocks} <= {"python", "bash", ""}  # "": the layout tree, not code
    skipped = [b for b in CODE if b["skip"]]
    assert len(skipped) <= 5 and all(any(word in b["skip"] for word in ("install", "minutes", "server"))
                                     for b in skipped)
    assert any(b["lang"] == "python" and not b["skip"] for b in CODE)
    assert any("league" in b["code"] and not b["skip"] for b in CODE)


@pytest.mark.slow
@pytest.mark.parametrize("block", CODE, ids=[f"line{b['line']}-{b['lang']}" for b in CODE])
def test_a_readme_block_runs_as_written_from_an_empty_folder(block, tmp_path):
    if block["skip"]:
        pytest.skip(f"README line {block['line']}: {block['skip']}")
    command = [sys.executable, "-c", block["code"]] if block["lang"] == "python" else ["bash", "-e", "-c",
                                                                                        block["code"]]
    run = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=900,
                         stdin=subprocess.DEVNULL)
    assert run.returncode == 0, f"README line {block['line']}:\n{run.stdout[-3000:]}\n{run.stderr[-3000:]}"
