"""What a report section is made of, shared by the experiments (which produce sections) and the
HTML writer (which renders them): the experiment order, output file names and block types.

An experiment's ``render(document)`` returns a list of blocks built only from its JSON document,
so the report can be rebuilt from the JSON files at any time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

#: the paper's experiments, run by default, in report order; each name is its JSON file, its HTML
#: section id and (but for those in EXPERIMENT_MODULES) its module under fdnet.reproduce
EXPERIMENTS = ("comparison", "lengths", "similarity", "disentanglement", "viewpoint", "runtime", "examples")
#: experiments run only when named in --experiments (they train several runs each); their sections
#: follow the paper's, and appear in a report once they have run
OPTIONAL_EXPERIMENTS = ("ablation",)
#: every experiment, in report order
ALL_EXPERIMENTS = EXPERIMENTS + OPTIONAL_EXPERIMENTS
#: experiment -> its module where the two names differ: the runtime experiment's module is named
#: for the paper's table it reproduces (the timing kernels it uses are fdnet.performance.timing)
EXPERIMENT_MODULES = {"runtime": "table5_runtime"}

MANIFEST = "reproduce.json"
REPORT = "report.html"


def experiment_module(name: str):
    """The module of experiment ``name``, imported when asked for (experiments import torch and
    matplotlib, which the report's readers need not)."""
    import importlib

    return importlib.import_module(f"fdnet.reproduce.{EXPERIMENT_MODULES.get(name, name)}")


@dataclass
class Heading:
    text: str


@dataclass
class Paragraph:
    text: str
    #: a remark set apart from the findings (caveats, what was not run and why)
    note: bool = False


@dataclass
class Table:
    header: list[str]
    rows: list[list[str]]
    caption: str = ""
    #: (row, column) cells marked as the best of their column
    marked: set[tuple[int, int]] = field(default_factory=set)


@dataclass
class Figure:
    #: PNG or JPEG path relative to the output folder
    path: str
    caption: str


def pair_name(query: str, reference: str) -> str:
    """How the report names an ordered pair: queries matched against the reference map."""
    return f"{query} \u2192 {reference}"


def number(value, digits: int = 3) -> str:
    """A table cell: fixed decimals, "-" for a missing or non-finite value."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.{digits}f}"


def best_cells(rows: list[list], columns: list[int], higher_is_better: bool = True) -> set[tuple[int, int]]:
    """The cells holding each column's best value (ties all marked); a column where every row
    has the same value, or none, marks nothing."""
    marked = set()
    for col in columns:
        values = [
            (r, row[col])
            for r, row in enumerate(rows)
            if isinstance(row[col], (int, float)) and math.isfinite(row[col])
        ]
        if len({v for _, v in values}) < 2:
            continue
        best = max(v for _, v in values) if higher_is_better else min(v for _, v in values)
        marked |= {(r, col) for r, v in values if v == best}
    return marked


def finite_or_none(value) -> float | None:
    """A float for JSON (which has no NaN or infinity): None where there is no number."""
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None
