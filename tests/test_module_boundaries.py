"""What one module shares with another is public: no module imports another module's underscore
names (a split that needs them is a split along the wrong seam)."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE_ROOT = Path(__file__).resolve().parents[1] / "src" / "fdnet"


def private_imports(source: str) -> list[str]:
    """``module:name`` of each underscore name a source imports from an fdnet module (dunder
    names such as ``__version__`` are public)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("fdnet"):
            found += [
                f"{node.module}:{alias.name}"
                for alias in node.names
                if alias.name.startswith("_") and not alias.name.startswith("__")
            ]
    return found


def test_no_module_imports_another_modules_private_names():
    offenders = {
        str(path.relative_to(PACKAGE_ROOT)): names
        for path in sorted(PACKAGE_ROOT.rglob("*.py"))
        if (names := private_imports(path.read_text()))
    }
    assert not offenders, f"underscore names imported across modules (make them public): {offenders}"


def test_private_import_finder_finds_planted_ones():
    source = (
        "from fdnet.a import _hidden, shown\nfrom fdnet.version import __version__\n"
        "def f():\n    from fdnet.b import _late\n"
    )
    assert private_imports(source) == ["fdnet.a:_hidden", "fdnet.b:_late"]
