"""The package's structure: no import cycles, inference never imports training code, the
pretrained backbone is a leaf.

Imports are read from the source with ``ast`` (module-level and function-level imports alike: a
lazy import is still a dependency), at module granularity.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE_ROOT = Path(__file__).resolve().parents[1] / "src" / "fdnet"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE_ROOT.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def all_modules() -> dict[str, Path]:
    return {module_name(p): p for p in PACKAGE_ROOT.rglob("*.py")}


def imports_of(path: Path, modules: dict[str, Path]) -> set[str]:
    """fdnet modules ``path`` imports (``from fdnet.a import b`` counts fdnet.a.b when that is a
    module, else fdnet.a)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    this = module_name(path)
    package = this if path.name == "__init__.py" else this.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("fdnet"):
                    found.add(alias.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                target = f"{base}.{node.module}" if node.module else base
            else:
                target = node.module or ""
            if not target.startswith("fdnet"):
                continue
            for alias in node.names:
                candidate = f"{target}.{alias.name}"
                found.add(candidate if candidate in modules else target)
    return {m for m in found if m in modules and m != this}


def import_graph() -> dict[str, set[str]]:
    modules = all_modules()
    return {name: imports_of(path, modules) for name, path in modules.items()}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt) :] + [nxt]
            if nxt not in state:
                cycle = visit(nxt)
                if cycle:
                    return cycle
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state:
            cycle = visit(node)
            if cycle:
                return cycle
    return None


def reachable(graph: dict[str, set[str]], start: str) -> set[str]:
    seen, todo = set(), [start]
    while todo:
        node = todo.pop()
        for nxt in graph.get(node, ()):
            if nxt not in seen:
                seen.add(nxt)
                todo.append(nxt)
    return seen


def test_no_import_cycle_among_fdnet_modules():
    cycle = find_cycle(import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_cycle_finder_finds_a_planted_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


#: the modules that may write to the console: the command line, and the logging handler it installs
CONSOLE_WRITERS = ("fdnet.cli", "fdnet.logs")


def console_writes(source: str) -> list[int]:
    """Lines of ``source`` that call ``print(...)`` or ``sys.stdout/sys.stderr.write(...)``."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        if isinstance(func, ast.Name) and func.id == "print":
            found.append(node.lineno)
        elif (
            isinstance(func, ast.Attribute)
            and func.attr == "write"
            and isinstance(func.value, ast.Attribute)
            and func.value.attr in ("stdout", "stderr")
            and isinstance(func.value.value, ast.Name)
            and func.value.value.id == "sys"
        ):
            found.append(node.lineno)
    return found


def test_library_code_logs_and_never_prints():
    """Library modules log through ``logging`` (the CLI shows it, see fdnet.logs) or take a
    ``log`` callable; only the command line writes to the console itself."""
    offenders = [
        f"{name}:{line}"
        for name, path in sorted(all_modules().items())
        if not any(name == w or name.startswith(w + ".") for w in CONSOLE_WRITERS)
        for line in console_writes(path.read_text())
    ]
    assert not offenders, f"print() or sys.stdout/stderr.write() in library code: {offenders}"


def test_console_write_finder_finds_planted_ones():
    source = "import sys\nprint('x')\nsys.stderr.write('y')\nlog.info('z')\nfile.write('w')\n"
    assert console_writes(source) == [2, 3]


INFERENCE_ENTRY_POINTS = [
    "fdnet",  # fdnet.load
    "fdnet.export",
    "fdnet.descriptors.registry",
    "fdnet.methods.fdnet.descriptor",
    "fdnet.methods.calc.descriptor",
    "fdnet.methods.netvlad.descriptor",
    "fdnet.matching.database",
    "fdnet.cli.extract",
    "fdnet.cli.evaluate",
    "fdnet.cli.match",
    "fdnet.cli.export",
]


@pytest.mark.parametrize("entry", INFERENCE_ENTRY_POINTS)
def test_inference_never_imports_training_code(entry):
    graph = import_graph()
    assert entry in graph, f"{entry} is not a module of the package"
    reached = reachable(graph, entry) | {entry}
    training = sorted(
        m for m in reached if m == "fdnet.training" or m.startswith("fdnet.training.") or m.endswith(".training")
    )
    assert not training, f"{entry} reaches training code: {training}"


def test_pretrained_backbone_is_a_leaf():
    graph = import_graph()
    inside = sorted(m for m in graph["fdnet.backbones"] if m not in ("fdnet.errors",))
    assert not inside, f"fdnet.backbones imports {inside}; it must depend on nothing but fdnet.errors"


def test_every_trained_method_is_one_package_with_the_same_parts():
    for method in ("fdnet", "calc", "netvlad"):
        folder = PACKAGE_ROOT / "methods" / method
        for part in ("config", "model", "descriptor", "training"):
            assert (folder / f"{part}.py").is_file(), f"fdnet.methods.{method} has no {part} module"


#: the longest a function in src/fdnet may be, in lines from ``def`` to its last line
MAX_FUNCTION_LINES = 100


def long_functions(source: str, limit: int = MAX_FUNCTION_LINES) -> list[tuple[str, int, int]]:
    """(name, first line, length) of each function or method in ``source`` longer than ``limit``."""
    return [
        (node.name, node.lineno, node.end_lineno - node.lineno + 1)
        for node in ast.walk(ast.parse(source))
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno + 1 > limit
    ]


def test_no_function_is_longer_than_100_lines():
    offenders = [
        f"{name}:{fn} (line {line}, {length} lines)"
        for name, path in sorted(all_modules().items())
        for fn, line, length in long_functions(path.read_text())
    ]
    assert not offenders, f"functions longer than {MAX_FUNCTION_LINES} lines: {offenders}"


def test_long_function_finder_finds_a_planted_one():
    body = "".join(f"        x{i} = {i}\n" for i in range(3))
    source = f"def short():\n    pass\n\nclass A:\n    def long(self):\n{body}"
    assert long_functions(source, limit=3) == [("long", 5, 4)]
    assert long_functions(source, limit=4) == []


#: the most parameters a function outside the command line takes: settings travel as objects
MAX_PARAMETERS = 8
#: constructors still taking their settings one by one (none: every method takes its settings
#: dataclass; the list may only shrink)
WIDE_CONSTRUCTORS: set[str] = set()


def wide_functions(source: str, limit: int = MAX_PARAMETERS) -> list[tuple[str, int, int]]:
    """(name, line, parameters) of each function in ``source`` taking more than ``limit``
    parameters (self and cls not counted; ``*args``/``**kwargs`` not counted)."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            a = node.args
            names = [x.arg for x in (*a.posonlyargs, *a.args, *a.kwonlyargs) if x.arg not in ("self", "cls")]
            if len(names) > limit:
                out.append((node.name, node.lineno, len(names)))
    return out


def test_no_function_outside_the_command_line_takes_more_than_8_parameters():
    wide = [
        (name, fn, line, count)
        for name, path in sorted(all_modules().items())
        if not name.startswith("fdnet.cli")
        for fn, line, count in wide_functions(path.read_text())
    ]
    offenders = [
        f"{name}:{fn} (line {line}, {count} parameters)"
        for name, fn, line, count in wide
        if not (fn == "__init__" and name in WIDE_CONSTRUCTORS)
    ]
    assert not offenders, f"functions taking more than {MAX_PARAMETERS} parameters (use a settings object): {offenders}"
    # a constructor that no longer needs its exemption leaves the list
    assert WIDE_CONSTRUCTORS == {name for name, fn, _, _ in wide if fn == "__init__"}


def test_wide_function_finder_finds_a_planted_one():
    source = "def wide(a, b, c, *, d=1):\n    pass\n\nclass A:\n    def ok(self, a, b, c):\n        pass\n"
    assert wide_functions(source, limit=3) == [("wide", 1, 4)]
    assert wide_functions(source, limit=4) == []


#: The package's floors, bottom to top, in the order of its pipeline (sources and data, descriptors,
#: matching, the pure metrics, decisions, training as a side path, evaluation, the tasks that drive
#: them, the methods that train on it all, performance, the paper's experiments, the command line).
#: A module imports only modules of its own floor or below, at module level or inside a function.
FLOORS = (
    (
        "ground",
        (
            "fdnet.errors",
            "fdnet.version",
            "fdnet.io",
            "fdnet.logs",
            "fdnet.config",
            "fdnet.progress",
            "fdnet.backbones",
            "fdnet.paper",
            "fdnet.torchrun",
            "fdnet.provenance",
        ),
    ),
    ("data", ("fdnet.data",)),
    ("runs", ("fdnet.runs",)),
    ("descriptors", ("fdnet.descriptors",)),
    ("matching", ("fdnet.matching",)),
    ("metrics", ("fdnet.metrics",)),
    ("decisions", ("fdnet.decisions",)),
    ("training", ("fdnet.training",)),
    ("evaluation", ("fdnet.evaluation",)),
    ("tasks", ("fdnet.tasks",)),
    ("methods", ("fdnet.methods",)),
    ("performance", ("fdnet.performance",)),
    ("reproduce", ("fdnet.reproduce",)),
    ("applications", ("fdnet.export", "fdnet.demo")),
    ("cli", ("fdnet.cli", "fdnet.__main__")),
    ("api", ("fdnet",)),  # the package root: fdnet.load, which reaches a trained method
)


def floor_of(module: str) -> int:
    """The floor a module stands on: that of the longest prefix FLOORS names."""
    best, floor = -1, None
    for level, (_, prefixes) in enumerate(FLOORS):
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > best:
                best, floor = len(prefix), level
    assert floor is not None, f"{module} stands on no floor: add it to FLOORS"
    return floor


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    return [
        f"{a} ({FLOORS[floor_of(a)][0]}) imports {b} ({FLOORS[floor_of(b)][0]})"
        for a in sorted(graph)
        for b in sorted(graph[a])
        if floor_of(b) > floor_of(a)
    ]


def test_no_module_imports_from_a_floor_above_its_own():
    offenders = upward_imports(import_graph())
    assert not offenders, "imports that run up a floor:\n" + "\n".join(offenders)


def test_upward_import_finder_sees_function_local_imports():
    assert upward_imports({"fdnet.data.planted": {"fdnet.cli"}}) == [
        "fdnet.data.planted (data) imports fdnet.cli (cli)"
    ]
    assert upward_imports({"fdnet.cli.match": {"fdnet.data.images"}}) == []
    # the command line imports its task inside run(): the graph has that import all the same
    modules = all_modules()
    assert "fdnet.tasks.match" in imports_of(modules["fdnet.cli.match"], modules)


#: the longest a source file in src/fdnet may be
MAX_FILE_LINES = 600


def test_no_source_file_is_longer_than_600_lines():
    offenders = [
        f"{name} ({n} lines)"
        for name, path in sorted(all_modules().items())
        if (n := len(path.read_text().splitlines())) > MAX_FILE_LINES
    ]
    assert not offenders, f"files longer than {MAX_FILE_LINES} lines (split them by responsibility): {offenders}"
