"""Papers' tables: results of several ``fdnet evaluate --json`` (and ``fdnet reproduce``'s
``comparison.json``) merged into one methods x datasets table, chosen metrics as columns, the
best value of every column marked (``fdnet table``).

A result is one method on one dataset. Its dataset is the result's own ``dataset`` description
(for a precomputed similarity matrix, which has none, the file's name), or the label given with
the file (``LABEL=FILE.json``; a reproduce comparison adds each pair, ``LABEL query->reference``).
Two results of one method on one dataset, or results under different protocols, are refused:
they could not share a cell or a column.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import os
import re
from pathlib import Path
from typing import Sequence

from fdnet.errors import ConfigError

#: the table styles
FORMATS = ("latex", "markdown", "csv")
#: metrics a column can show: name -> (where in a result, higher is better)
METRICS = {
    "R@1": ("recall_at_n", "1", True),
    "R@5": ("recall_at_n", "5", True),
    "R@10": ("recall_at_n", "10", True),
    "R@20": ("recall_at_n", "20", True),
    "R@100P": ("pr", "recall_at_100_precision", True),
    "R@99P": ("pr", "recall_at_99_precision", True),
    "R@95P": ("pr", "recall_at_95_precision", True),
    "P@maxR": ("pr", "precision_at_max_recall", True),
    "AUC-PR": ("pr", "auc_pr", True),
    "ms/image": ("timing", "ms_per_image", False),
    "ms/query": ("timing", "ms_per_query", False),
}
DEFAULT_METRICS = ("R@1", "R@100P", "AUC-PR")
#: how a CSV cell marks the best value of its column (the other styles use bold)
CSV_BEST_MARK = "*"


@dataclasses.dataclass(frozen=True)
class Entry:
    """One method's result on one dataset, read from ``source``."""

    method: str
    dataset: str
    protocol: str
    result: dict
    source: str


@dataclasses.dataclass(frozen=True)
class ResultsTable:
    """Methods (rows, in order of first appearance) x datasets x metrics; ``values[(method,
    dataset, metric)]`` is a number or absent."""

    methods: list
    datasets: list
    metrics: list
    values: dict
    protocol: str
    acceptance: str | None

    def best(self, dataset: str, metric: str) -> float | None:
        higher = METRICS[metric][2]
        found = [self.values[(m, dataset, metric)] for m in self.methods if (m, dataset, metric) in self.values]
        if not found:
            return None
        return max(found) if higher else min(found)


def parse_metrics(text: str | Sequence[str] | None) -> list[str]:
    """``R@1,AUC-PR`` -> the metric names; an unknown name is refused with the list."""
    names = [n.strip() for n in (text.split(",") if isinstance(text, str) else text or DEFAULT_METRICS) if n.strip()]
    unknown = [n for n in names if n not in METRICS]
    if unknown or not names:
        raise ConfigError(f"--metrics {','.join(unknown) or '(none)'}: choose from {', '.join(METRICS)}")
    if len(set(names)) != len(names):
        raise ConfigError(f"--metrics names a metric twice: {','.join(names)}")
    return names


def _source(item: str) -> tuple[str | None, str]:
    """``LABEL=FILE`` or ``FILE`` -> (label or None, file); a file whose name holds '=' is read
    as a file when it exists."""
    label, sep, path = item.partition("=")
    if sep and label and not Path(item).exists():
        return label, path
    return None, item


def _load(path: str) -> dict:
    try:
        with open(path, encoding="utf-8") as f:
            document = json.load(f)
    except FileNotFoundError as exc:
        raise ConfigError(f"{path}: no such file") from exc
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: not a JSON file ({exc})") from exc
    if not isinstance(document, dict):
        raise ConfigError(f"{path}: not a results JSON (fdnet evaluate --json or fdnet reproduce's comparison.json)")
    return document


def read_entries(item: str) -> list[Entry]:
    """The results of one ``[LABEL=]FILE``: an evaluate JSON (one or several methods) or a
    reproduce ``comparison.json`` (every pair)."""
    label, path = _source(item)
    document = _load(path)
    if document.get("format") == "fdnet-evaluation" or "results" in document and "experiment" not in document:
        groups = [(None, document.get("results"), document.get("protocol"))]
    elif document.get("experiment") == "comparison":
        groups = [
            (f"{p.get('query')}->{p.get('reference')}", p.get("results"), document.get("protocol"))
            for p in document.get("pairs") or []
        ]
    elif "experiment" in document:
        raise ConfigError(
            f"{path}: reproduce's {document['experiment']!r} experiment holds no per-method results on "
            "a dataset; give its comparison.json or an fdnet evaluate --json file"
        )
    elif "method" in document and "recall_at_n" in document:  # one result object
        groups = [(None, [document], document.get("protocol"))]
    else:
        raise ConfigError(f"{path}: not a results JSON (fdnet evaluate --json or fdnet reproduce's comparison.json)")
    entries = []
    for pair, results, protocol in groups:
        if not isinstance(results, list) or not all(isinstance(r, dict) and "method" in r for r in results):
            raise ConfigError(f"{path}: its results are not a list of method results")
        for r in results:
            if label:
                dataset = f"{label} {pair}" if pair else label
            else:
                dataset = r.get("dataset") or (f"{Path(path).stem} {pair}" if pair else Path(path).stem)
            entries.append(Entry(str(r["method"]), dataset, str(r.get("protocol") or protocol), r, path))
    if not entries:
        raise ConfigError(f"{path}: holds no results")
    return entries


def _value(entry: Entry, metric: str, acceptance: str | None) -> float | None:
    section, key, _ = METRICS[metric]
    r = entry.result
    if section == "recall_at_n":
        value = (r.get("recall_at_n") or {}).get(key)
    elif section == "timing":
        value = (r.get("timing") or {}).get(key)
    elif acceptance is None or acceptance == r.get("acceptance"):
        value = r.get(key)
    else:
        per = (r.get("per_acceptance") or {}).get(acceptance)
        if per is None:
            rules = ", ".join(dict.fromkeys([r.get("acceptance") or "?", *(r.get("per_acceptance") or {})]))
            raise ConfigError(
                f"{entry.source}: {entry.method} on {entry.dataset} has no {metric} under --accept "
                f"{acceptance} (its rules: {rules}); evaluate with --accept {acceptance}"
            )
        value = per.get(key)
    if value is None or isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return None
    return float(value)


def build_table(
    items: Sequence[str], metrics: str | Sequence[str] | None = None, acceptance: str | None = None
) -> ResultsTable:
    """Read every ``[LABEL=]FILE`` of ``items`` and merge their results: rows are methods,
    columns datasets x ``metrics``. PR metrics are those of ``acceptance`` (default: each result's
    own first rule, ``raw`` unless evaluate was told otherwise)."""
    if not items:
        raise ConfigError("give at least one results JSON")
    chosen = parse_metrics(metrics)
    entries = [e for item in items for e in read_entries(item)]
    protocols = {e.protocol for e in entries}
    if len(protocols) > 1:
        said = "; ".join(f"{p}: {next(e.source for e in entries if e.protocol == p)}" for p in sorted(protocols))
        raise ConfigError(f"results under different protocols ({said}) do not share a table")
    seen: dict = {}
    values: dict = {}
    for e in entries:
        key = (e.method, e.dataset)
        if key in seen:
            raise ConfigError(
                f"two results of {e.method} on {e.dataset!r} ({seen[key]} and {e.source}): one cell "
                "cannot hold both; label the files (LABEL=FILE.json) or leave one out"
            )
        seen[key] = e.source
        for metric in chosen:
            value = _value(e, metric, acceptance)
            if value is not None:
                values[(e.method, e.dataset, metric)] = value
    methods = list(dict.fromkeys(e.method for e in entries))
    datasets = list(dict.fromkeys(e.dataset for e in entries))
    return ResultsTable(methods, datasets, chosen, values, protocols.pop(), acceptance)


def _cells(table: ResultsTable, digits: int) -> list[list[tuple[str, bool]]]:
    """Per method, per (dataset, metric): (text, is the column's best)."""
    rows = []
    for method in table.methods:
        row = []
        for dataset in table.datasets:
            for metric in table.metrics:
                value = table.values.get((method, dataset, metric))
                if value is None:
                    row.append(("-", False))
                    continue
                text = f"{value:.{digits}f}"
                best = table.best(dataset, metric)
                row.append((text, text == f"{best:.{digits}f}"))  # ties at the printed precision all marked
        rows.append(row)
    return rows


def _latex_escape(text: str) -> str:
    specials = {"\\": r"\textbackslash{}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}"}
    return re.sub(r"[\\&%$#_{}~^]", lambda m: specials.get(m.group(), "\\" + m.group()), text)


def format_table(table: ResultsTable, style: str, digits: int = 3) -> str:
    """``table`` as ``latex`` (booktabs-free tabular, a dataset header spanning its metrics, the
    best of each column in bold), ``markdown`` (best in bold) or ``csv`` (best marked with a
    trailing ``*``)."""
    if style not in FORMATS:
        raise ConfigError(f"--format {style!r}: choose one of {', '.join(FORMATS)}")
    cells = _cells(table, digits)
    multi = len(table.metrics) > 1
    headers = [(f"{d} {m}" if multi else d) for d in table.datasets for m in table.metrics]
    first = "method" if multi else f"method ({table.metrics[0]})"
    if style == "csv":
        from fdnet.io import spreadsheet_text

        # names (methods, datasets: folder names) as text no spreadsheet evaluates; numbers as they are
        buffer = io.StringIO()
        writer = csv.writer(buffer, lineterminator="\n")
        writer.writerow([spreadsheet_text(first), *(spreadsheet_text(h) for h in headers)])
        for method, row in zip(table.methods, cells):
            writer.writerow([spreadsheet_text(method), *(t + (CSV_BEST_MARK if b else "") for t, b in row)])
        return buffer.getvalue().rstrip("\n")
    if style == "markdown":
        from fdnet.io import markdown_cell

        lines = [
            f"| {markdown_cell(first)} | " + " | ".join(markdown_cell(h) for h in headers) + " |",
            "|---|" + "---:|" * len(headers),
        ]
        for method, row in zip(table.methods, cells):
            lines.append(f"| {markdown_cell(method)} | " + " | ".join(f"**{t}**" if b else t for t, b in row) + " |")
        return "\n".join(lines)
    width = len(table.datasets) * len(table.metrics)
    lines = ["\\begin{tabular}{l" + "r" * width + "}", "\\hline"]
    if multi:
        span = len(table.metrics)
        lines.append(
            " & " + " & ".join(f"\\multicolumn{{{span}}}{{c}}{{{_latex_escape(d)}}}" for d in table.datasets) + " \\\\"
        )
        lines.append(
            "method & " + " & ".join(_latex_escape(m) for _ in table.datasets for m in table.metrics) + " \\\\"
        )
    else:
        lines.append(
            f"method ({_latex_escape(table.metrics[0])}) & "
            + " & ".join(_latex_escape(d) for d in table.datasets)
            + " \\\\"
        )
    lines.append("\\hline")
    for method, row in zip(table.methods, cells):
        lines.append(
            _latex_escape(method) + " & " + " & ".join(f"\\textbf{{{t}}}" if b else t for t, b in row) + " \\\\"
        )
    return "\n".join(lines + ["\\hline", "\\end{tabular}"])


def table_command(
    items: Sequence[str],
    style: str = "markdown",
    metrics: str | Sequence[str] | None = None,
    acceptance: str | None = None,
    out: str | os.PathLike | None = None,
    digits: int = 3,
) -> str:
    """The work of ``fdnet table``: merge ``items``' results, format them as ``style`` and, with
    ``out``, write the text there atomically. Returns the text."""
    from fdnet.io import atomic_write_text, ensure_writable

    if style not in FORMATS:
        raise ConfigError(f"--format {style!r}: choose one of {', '.join(FORMATS)}")
    if isinstance(digits, bool) or not isinstance(digits, int) or not 0 <= digits <= 6:
        raise ConfigError(f"--digits must be a whole number from 0 to 6, got {digits!r}")
    if out is not None:
        ensure_writable(out, what="table")
    text = format_table(build_table(items, metrics, acceptance), style, digits)
    if out is not None:
        atomic_write_text(out, text + "\n")
    return text
