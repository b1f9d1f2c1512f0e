"""Results for people (a fixed-width table) and for programs (JSON, written atomically).

JSON layout: one method -> one object (see :meth:`MethodResult.to_dict`) with at least
``method``, ``protocol``, ``num_queries``, ``recall_at_100_precision``, ``precision_at_max_recall``,
``auc_pr`` and ``recall_at_n`` (keyed "1", "5", "10", "20"); several methods in one run ->
``{"results": [one such object per method]}``.
"""

from __future__ import annotations

import json
import math
import os
from typing import Sequence

from fdnet.data.images import image_name
from fdnet.evaluation.experiment import MethodResult
from fdnet.io import atomic_write_text
from fdnet.metrics import PROTOCOLS

_COLUMNS = ("R@1", "R@5", "R@10", "R@20", "R@100P", "R@99P", "R@95P", "P@maxR", "AUC-PR", "ms/image", "ms/query")


def _number(value, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.{digits}f}"


def _per_rule(result: MethodResult, protocol: str) -> dict:
    """rule expression -> that rule's Metrics under ``protocol`` (one entry without several rules)."""
    return {rule: per[protocol] for rule, per in result.by_acceptance.items()} or {
        result.metrics[protocol].acceptance: result.metrics[protocol]
    }


def format_table(results: Sequence[MethodResult], protocol: str | None = None) -> str:
    """One row per method and acceptance rule (the rule whose scores the PR numbers threshold);
    the protocol (and its definition), data and ground truth in the header."""
    if not results:
        return "(no results)"
    protocol = protocol or results[0].protocols[0]
    first = results[0].metrics[protocol]
    lines = [f"protocol: {protocol} -- {PROTOCOLS[protocol]}"]
    if first.thresholds != "exact":
        lines.append(f"thresholds: {first.thresholds} over min-max-normalised best-match scores")
    if results[0].dataset:
        lines.append(f"data: {results[0].dataset}")
    lines.append(
        f"ground truth: {results[0].ground_truth.description}; {first.num_queries} queries "
        f"({first.num_queries_with_match} with a true match) x {results[0].ground_truth.num_references} "
        f"references"
    )
    width = max(8, *(len(r.method) for r in results))
    rule_width = max(6, *(len(rule) for r in results for rule in r.acceptance_rules))
    header = f"{'method':<{width}}  {'accept':<{rule_width}}  " + "  ".join(f"{c:>8}" for c in _COLUMNS)
    lines += [header, "-" * len(header)]
    for r in results:
        for rule, m in _per_rule(r, protocol).items():
            cells = [_number(m.recall_at_n.get(n)) for n in (1, 5, 10, 20)]
            cells += [
                _number(m.recall_at_100_precision),
                _number(m.recall_at_99_precision),
                _number(m.recall_at_95_precision),
                _number(m.precision_at_max_recall),
                _number(m.auc_pr),
            ]
            cells += [_number(r.timing.get("ms_per_image"), 2), _number(r.timing.get("ms_per_query"), 3)]
            lines.append(f"{r.method:<{width}}  {rule:<{rule_width}}  " + "  ".join(f"{c:>8}" for c in cells))
    notes = [f"{r.method}: {n}" for r in results for n in r.notes + r.metrics[protocol].notes]
    settings = sorted(
        {
            f"{name}: {', '.join(f'{k}={v}' for k, v in values.items() if v is not None)}"
            for r in results
            for d in r.decisions.values()
            for name, values in d.settings.items()
            if any(v is not None for v in values.values())
        }
    )
    rules = list(dict.fromkeys(rule for r in results for rule in (r.acceptance_rules or [first.acceptance])))
    if rules != ["raw"]:
        said = (
            ["raw is the field's protocol (the best match's similarity, as papers and VPR-Bench report)"]
            if "raw" in rules
            else []
        )
        others = [rule for rule in rules if rule != "raw"]
        if others:
            verb = "is an fdnet acceptance rule" if len(others) == 1 else "are fdnet acceptance rules"
            said.append(f"{', '.join(others)} {verb} (docs/decisions.md)")
        lines.append("accept: " + "; ".join(said))
    if settings:
        lines.append("acceptance settings: " + "; ".join(settings))
    lines += [f"note: {n}" for n in notes]
    return "\n".join(lines)


#: the evaluation JSON's format (``format``, ``format_version``)
JSON_FORMAT = "fdnet-evaluation"
JSON_FORMAT_VERSION = 2


def results_json(
    results: Sequence[MethodResult],
    protocol: str | None = None,
    include_curve: bool = True,
    command: str | None = None,
    settings: dict | None = None,
    predictions: int = 0,
    seeds=None,
) -> dict:
    """The JSON document, one schema whatever the number of methods: ``format``,
    ``format_version``, ``fdnet_version``, ``command``, ``protocol``, ``settings`` (what was
    asked) and ``results``, a list with one object per method. ``predictions`` > 0 adds to each
    result its per-query ``predictions``: the query's index and name, its ``predictions`` best
    reference indices (and names; :func:`fdnet.data.images.image_name`) with their scores and
    whether each is correct."""
    from fdnet.provenance import provenance
    from fdnet.version import __version__

    objects = []
    for r in results:
        item = r.to_dict(protocol, include_curve=include_curve)
        if predictions:
            item["predictions"] = _predictions(r, predictions)
        objects.append(item)
    return {
        "format": JSON_FORMAT,
        "format_version": JSON_FORMAT_VERSION,
        "fdnet_version": __version__,
        "command": command,
        "protocol": protocol or (results[0].protocols[0] if results else None),
        "settings": settings or {},
        "results": objects,
        "provenance": provenance(command, seeds=seeds, device=(settings or {}).get("device")),
    }


def _predictions(result: MethodResult, k: int) -> list[dict]:
    k = int(min(k, result.retrieved.shape[1]))
    top, scores = result.retrieved[:, :k], result.scores[:, :k]
    correct = result.ground_truth.correct_mask(top)
    queries = result.query_paths
    references = result.reference_paths
    out = []
    for q in range(len(top)):
        row = {
            "query_index": q,
            "top": [int(i) for i in top[q]],
            "scores": [float(v) for v in scores[q]],
            "correct": [bool(c) for c in correct[q]],
        }
        if queries is not None:
            row["query"] = image_name(queries[q])
        if references is not None:
            row["top_names"] = [image_name(references[i]) if i >= 0 else None for i in top[q]]
        out.append(row)
    return out


def format_results_table(results: Sequence[MethodResult], style: str, protocol: str | None = None) -> str:
    """A method x (data, rule) table of R@1, R@100P and AUC-PR to paste into a paper or a sheet:
    ``csv``, ``markdown`` or ``latex``."""
    import csv
    import io

    from fdnet.errors import ConfigError
    from fdnet.io import markdown_cell, spreadsheet_text

    if style not in TABLE_STYLES:
        raise ConfigError(f"--table {style!r}: choose one of {', '.join(TABLE_STYLES)}")
    protocol = protocol or results[0].protocols[0]
    header = ["method", "accept", "data", "R@1", "R@100P", "AUC-PR"]
    rows = []
    for r in results:
        for rule, m in _per_rule(r, protocol).items():
            rows.append(
                [
                    r.method,
                    rule,
                    r.dataset,
                    f"{m.recall_at_n.get(1, float('nan')):.3f}",
                    f"{m.recall_at_100_precision:.3f}",
                    f"{m.auc_pr:.3f}",
                ]
            )
    if style == "csv":  # names (a folder's, a method's) that a spreadsheet would run are quoted
        buffer = io.StringIO()
        writer = csv.writer(buffer, lineterminator="\n")
        writer.writerows([header, *([spreadsheet_text(c) for c in row[:3]] + row[3:] for row in rows)])
        return buffer.getvalue().rstrip("\n")
    if style == "markdown":  # a | in a name would shift the columns
        lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        return "\n".join(lines + ["| " + " | ".join(markdown_cell(c) for c in row) + " |" for row in rows])

    def tex(text: str) -> str:
        import re

        return re.sub(r"[\\&%$#_{}]", lambda m: "\\textbackslash{}" if m.group() == "\\" else "\\" + m.group(), text)

    lines = ["\\begin{tabular}{lllrrr}", "\\hline", " & ".join(header) + " \\\\", "\\hline"]
    lines += [" & ".join(tex(c) for c in row) + " \\\\" for row in rows]
    return "\n".join(lines + ["\\hline", "\\end{tabular}"])


#: the ``--table`` styles
TABLE_STYLES = ("csv", "markdown", "latex")


def json_fallback(value):
    """JSON fallback for what descriptor settings may hold (numpy scalars/arrays, paths)."""
    import numpy as np

    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


def write_json(
    path: str | os.PathLike,
    results: Sequence[MethodResult],
    protocol: str | None = None,
    include_curve: bool = True,
    command: str | None = None,
    settings: dict | None = None,
    predictions: int = 0,
    seeds=None,
) -> None:
    """Write :func:`results_json` to ``path`` atomically (a crash never leaves half a file)."""
    document = results_json(results, protocol, include_curve, command, settings, predictions, seeds)
    atomic_write_text(path, json.dumps(document, indent=2, allow_nan=False, default=json_fallback) + "\n")
