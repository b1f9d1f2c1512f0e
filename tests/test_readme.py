"""The README's quick examples run as the README prints them.

The quick examples are the README's fenced command blocks that work on the synthetic route
(a block with ``fdnet synth``) or the ``tiny`` preset: each such block is run in order, in an
empty folder, through ``fdnet.cli.main``, exactly as written (continuation lines joined), and
every command must succeed and write what its ``--out`` names. Commands on real data or
trained runs elsewhere (``../shared/data``, ``runs/nordland``) are not quick examples.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"

#: fenced blocks of these languages hold shell commands (an unlabelled fence too)
SHELL_FENCES = ("", "bash", "sh", "shell", "console")


def command_blocks(text: str) -> list[list[str]]:
    """The ``fdnet ...`` commands of each fenced shell block (``$ `` prompts dropped, lines
    ending in a backslash joined with the next)."""
    blocks = []
    for language, body in re.findall(r"^```([A-Za-z]*)\n(.*?)^```", text, flags=re.S | re.M):
        if language.lower() not in SHELL_FENCES:
            continue
        joined = re.sub(r"\s*\\\n\s*", " ", body)
        commands = [line.strip().removeprefix("$ ").strip() for line in joined.splitlines()]
        commands = [c for c in commands if c.startswith("fdnet ")]
        if commands:
            blocks.append(commands)
    return blocks


def is_quick(block: list[str]) -> bool:
    return any(c.startswith("fdnet synth ") or "--preset tiny" in c for c in block)


def quick_examples() -> list[list[str]]:
    return [block for block in command_blocks(README.read_text()) if is_quick(block)]


def test_block_parser_joins_continuations_and_skips_other_languages():
    text = (
        "```\n$ fdnet synth --out r \\\n    --num-frames 3\nls\n```\n"
        "```python\nfdnet.load('x')\n```\n```bash\nfdnet train --data r --preset tiny --out x\n```\n"
    )
    assert command_blocks(text) == [
        ["fdnet synth --out r --num-frames 3"],
        ["fdnet train --data r --preset tiny --out x"],
    ]


def test_the_readme_has_quick_examples():
    blocks = quick_examples()
    assert blocks, "README.md has no fenced block on the synthetic route or the tiny preset"
    assert any(c.startswith("fdnet synth ") for block in blocks for c in block)


@pytest.mark.slow  # about 77 s for the README's synth + train tiny + reproduce block on 2 cores
@pytest.mark.parametrize("block", quick_examples(), ids=lambda block: block[0][:40])
def test_quick_example_runs_as_printed(block, tmp_path, monkeypatch):
    from fdnet.cli import main

    monkeypatch.chdir(tmp_path)
    for command in block:
        argv = shlex.split(command)[1:]
        assert main(argv) == 0, f"README command failed: {command}"
        if "--out" in argv:
            out = argv[argv.index("--out") + 1]
            assert (tmp_path / out).exists(), f"{command} wrote nothing at {out}"
