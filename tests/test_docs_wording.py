"""The docs, sources, tests and benchmarks speak to the project's users.

No file in README.md, CHANGELOG.md, docs/, src/, tests/ or benchmarks/ numbers past work the
way a work log does (a numbered session or issue), and none names an absolute folder of a
developer's machine as the place where data or scripts live. Examples of what is meant are built from pieces below,
so that this file does not trip its own check.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

#: the words are split so that this file's own text does not match
_SESSION = "sess" + "ion"
_ISSUE = "iss" + "ue"
_WORK_DIR = "/" + "work" + "/"
_HOME_DIR = "/" + "home" + "/"

FORBIDDEN = (
    (re.compile(rf"\b{_SESSION}s? [0-9]+", re.IGNORECASE), "numbered work session"),
    (re.compile(rf"\b{_ISSUE}s? #?[0-9]+", re.IGNORECASE), "numbered issue"),
    (re.compile(re.escape(_WORK_DIR), re.IGNORECASE), "absolute developer path"),
    (re.compile(re.escape(_HOME_DIR), re.IGNORECASE), "absolute developer path"),
)

#: folders that hold generated files, never written by hand
SKIPPED_DIRS = {"__pycache__", ".pytest_cache", ".mypy_cache", ".ruff_cache"}


def checked_files(root: Path = REPO_ROOT) -> list[Path]:
    """README.md, CHANGELOG.md, docs/**/*.md, src/**/*.py, tests/**/*.py and every text file
    under benchmarks/."""
    files = [root / "README.md", root / "CHANGELOG.md"]
    files += sorted((root / "docs").rglob("*.md"))
    files += sorted((root / "src").rglob("*.py"))
    files += sorted((root / "tests").rglob("*.py"))
    files += sorted(p for p in (root / "benchmarks").rglob("*") if p.is_file())
    return [p for p in files if p.is_file() and not SKIPPED_DIRS.intersection(p.relative_to(root).parts)]


def read_text(path: Path) -> str | None:
    """The file's text, or None for a binary file (a NUL byte or not UTF-8)."""
    data = path.read_bytes()
    if b"\0" in data:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


def offenders_in_text(text: str) -> list[tuple[int, str, str]]:
    """(line number, what was found, why) for every forbidden wording in ``text``."""
    found = []
    for number, line in enumerate(text.splitlines(), start=1):
        for pattern, why in FORBIDDEN:
            for match in pattern.finditer(line):
                found.append((number, match.group(0), why))
    return found


def test_the_checked_files_are_the_projects():
    files = {p.relative_to(REPO_ROOT).as_posix() for p in checked_files()}
    assert "README.md" in files
    assert "docs/results.md" in files
    assert "tests/test_docs_wording.py" in files
    assert any(f.startswith("src/fdnet/") for f in files)


@pytest.mark.parametrize(
    "line",
    [
        "## " + _SESSION.capitalize() + " 8: the start chosen over trunk blocks",
        "repeats " + _SESSION + " 4's `nres` to the last digit",
        "as in " + _SESSION + "s 4-6",
        "the targets of " + _ISSUE + " 18",
        _ISSUE.capitalize() + " #11's Gardens Point target",
        "data in " + _WORK_DIR + "shared/data",
        "scripts in " + _HOME_DIR + "someone/scripts",
    ],
)
def test_the_check_finds_work_log_wording(line):
    assert offenders_in_text("first line\n" + line + "\n"), line


@pytest.mark.parametrize(
    "line",
    [
        "the residual-head run `nres` (section 'A content head that starts at the trunk')",
        "every wall time of this section",
        "fdnet demo --out demo-out",
        "--data ../shared/data/nordland_trimmed",
    ],
)
def test_the_check_lets_descriptive_wording_through(line):
    assert offenders_in_text(line) == []


def test_no_work_log_numbering_or_developer_paths():
    offenders = []
    for path in checked_files():
        text = read_text(path)
        if text is None:
            continue
        for number, found, why in offenders_in_text(text):
            offenders.append(f"{path.relative_to(REPO_ROOT).as_posix()}:{number}: {found!r} ({why})")
    assert not offenders, (
        "user-facing files must describe past runs, not number them, and must not name a "
        "developer's folders:\n" + "\n".join(offenders)
    )
