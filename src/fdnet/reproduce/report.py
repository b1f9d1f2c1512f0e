"""The HTML report of ``fdnet reproduce``: one self-contained file that opens offline.

Figures are embedded as ``data:image/png;base64`` URIs; the style sheet is inline; there are no
scripts and no external resources of any kind, so the file can be mailed or archived as it is.
The header says which dataset, protocol, checkpoint, fdnet version and command made the report;
every experiment is a ``<section id="NAME">`` (ids fixed, see
:data:`~fdnet.reproduce.sections.EXPERIMENTS`; an optional experiment's section once it has run)
whose tables carry the numbers, so the report reads without its figures. The report is rebuilt
from ``OUT/reproduce.json`` and ``OUT/<NAME>.json`` alone, so rerunning one experiment keeps the
sections of the others.
"""

from __future__ import annotations

import base64
import html
import json
import os
from pathlib import Path

from fdnet.errors import DataError
from fdnet.io import atomic_write_text
from fdnet.reproduce.sections import (
    ALL_EXPERIMENTS,
    EXPERIMENTS,
    MANIFEST,
    REPORT,
    Figure,
    Heading,
    Paragraph,
    Table,
    experiment_module,
)

#: the figure formats the report embeds, by their first bytes
IMAGE_TYPES = {b"\x89PNG\r\n\x1a\n": "image/png", b"\xff\xd8\xff": "image/jpeg"}

STYLE = """
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 0 auto; max-width: 1200px;
       padding: 1em 2em; color: #1d1d1f; line-height: 1.4; }
header { border-bottom: 2px solid #444; margin-bottom: 1em; }
h1 { margin-bottom: 0.2em; }
h2 { border-bottom: 1px solid #ccc; margin-top: 2em; }
table { border-collapse: collapse; margin: 0.6em 0 1.2em 0; font-size: 0.9em; }
th, td { border: 1px solid #bbb; padding: 0.25em 0.6em; text-align: right; }
th { background: #eee; }
td:first-child, th:first-child { text-align: left; }
td.best { font-weight: bold; background: #e3f4e1; }
caption { caption-side: top; text-align: left; font-weight: 600; padding-bottom: 0.3em; }
table.header td { text-align: left; }
figure { margin: 0.8em 0 1.6em 0; }
figure img { max-width: 100%; height: auto; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #444; }
p.note { color: #6b4e00; background: #fff8e1; padding: 0.4em 0.7em; border-left: 4px solid #f0c000; }
p.paper { color: #555; font-style: italic; }
code { background: #f3f3f3; padding: 0 0.2em; word-break: break-all; }
nav a { margin-right: 1em; }
"""


def _escape(text) -> str:
    return html.escape(str(text), quote=True)


def _image_uri(out: Path, relative: str) -> str | None:
    """The figure as a data URI, or None when the file is missing or neither PNG nor JPEG."""
    path = out / relative
    try:
        data = path.read_bytes()
    except OSError:
        return None
    for signature, mime in IMAGE_TYPES.items():
        if data.startswith(signature):
            return f"data:{mime};base64," + base64.b64encode(data).decode("ascii")
    return None


def _table(block: Table) -> str:
    parts = ["<table>"]
    if block.caption:
        parts.append(f"<caption>{_escape(block.caption)}</caption>")
    parts.append("<thead><tr>" + "".join(f"<th>{_escape(h)}</th>" for h in block.header) + "</tr></thead><tbody>")
    for r, row in enumerate(block.rows):
        cells = []
        for c, value in enumerate(row):
            if (r, c) in block.marked:
                cells.append(f'<td class="best">{_escape(value)}&nbsp;&#9733;</td>')
            else:
                cells.append(f"<td>{_escape(value)}</td>")
        parts.append("<tr>" + "".join(cells) + "</tr>")
    parts.append("</tbody></table>")
    return "".join(parts)


def _block(block, out: Path) -> str:
    if isinstance(block, Heading):
        return f"<h3>{_escape(block.text)}</h3>"
    if isinstance(block, Paragraph):
        return f'<p class="note">{_escape(block.text)}</p>' if block.note else f"<p>{_escape(block.text)}</p>"
    if isinstance(block, Table):
        return _table(block)
    if isinstance(block, Figure):
        uri = _image_uri(out, block.path)
        if uri is None:
            return f'<p class="note">Figure {_escape(block.path)} is missing; rerun this experiment to draw it.</p>'
        return (
            f'<figure><img src="{uri}" alt="{_escape(block.caption)}">'
            f"<figcaption>{_escape(block.caption)}</figcaption></figure>"
        )
    raise TypeError(f"unknown report block {block!r}")


def _read_json(path: Path) -> dict | None:
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DataError(
            f"{path}: cannot read this experiment's results ({exc}); rerun it with " f"--experiments {path.stem}"
        ) from exc


def _header(manifest: dict | None, shown: list[str]) -> str:
    if manifest is None:
        return '<header><h1>fdnet reproduce</h1><p class="note">No run manifest (reproduce.json) found.</p></header>'
    pairs = "; ".join(
        f"{_escape(p['query'])} &rarr; {_escape(p['reference'])} ({p['num_queries']} queries x "
        f"{p['num_references']} references)"
        for p in manifest.get("pairs", [])
    )
    rows = [
        ("dataset", _escape(manifest.get("dataset", "")) + " &mdash; " + _escape(manifest.get("dataset_format", ""))),
        ("condition pairs (query &rarr; reference)", pairs),
        (
            "protocol",
            f"<b>{_escape(manifest.get('protocol', ''))}</b>: "
            f"{_escape(manifest.get('protocol_definition', ''))}; "
            f"thresholds: {_escape(manifest.get('thresholds', ''))}",
        ),
        ("checkpoint (FDNet run)", _escape(manifest.get("checkpoint") or "none")),
        ("fdnet version", _escape(manifest.get("fdnet_version", ""))),
        ("command", f"<code>{_escape(manifest.get('command', ''))}</code>"),
        ("created", _escape(manifest.get("created", ""))),
    ]
    if manifest.get("smoke_test"):
        rows.insert(0, ("smoke test", f"<b>{_escape(manifest['smoke_test'])}</b>"))
    body = "".join(f"<tr><th>{k}</th><td>{v}</td></tr>" for k, v in rows)
    nav = "".join(f'<a href="#{name}">{name}</a>' for name in shown)
    return (
        f"<header><h1>fdnet reproduce: the paper's experiments</h1>"
        f'<table class="header"><tbody>{body}</tbody></table><nav>{nav}</nav></header>'
    )


def _section(name: str, number: int, document: dict | None, manifest: dict | None, out: Path) -> str:
    module = experiment_module(name)
    parts = [
        f'<section id="{name}"><h2>{number}. {_escape(module.TITLE)}</h2>',
        f'<p class="paper">Paper: {_escape(module.PAPER)}</p>',
    ]
    if document is None:
        # what it needs besides the command's own flags (the lengths study: its four runs)
        extra = getattr(module, "RERUN_FLAGS", "")
        parts.append(
            f'<p class="note">Not run yet: rerun the command with <code>--experiments {name}'
            f'{" " + _escape(extra) if extra else ""}</code>.</p>'
        )
    elif document.get("not_run"):
        parts.append(f'<p class="note">Not run: {_escape(document["not_run"])}</p>')
    else:
        if manifest and document.get("command") and document.get("command") != manifest.get("command"):
            parts.append(
                f'<p class="note">This section was made by another command, at '
                f'{_escape(document.get("created", ""))}: <code>{_escape(document["command"])}</code></p>'
            )
        try:
            blocks = module.render(document)
        except (KeyError, TypeError, ValueError, IndexError):
            # written by another version of fdnet, or edited: say so rather than lose the report
            blocks = [
                Paragraph(
                    f"{name}.json does not hold what this version of fdnet writes; rerun the "
                    f"command with --experiments {name} to remake this section.",
                    note=True,
                )
            ]
        parts.extend(_block(block, out) for block in blocks)
    parts.append("</section>")
    return "\n".join(parts)


def render_report(out: str | os.PathLike) -> str:
    """The report's HTML from the JSON files in ``out``."""
    out = Path(out)
    manifest = _read_json(out / MANIFEST)
    documents = {name: _read_json(out / f"{name}.json") for name in ALL_EXPERIMENTS}
    # the paper's experiments always (a placeholder for one not run yet); an optional one once it ran
    shown = [
        name
        for name in ALL_EXPERIMENTS
        if name in EXPERIMENTS or documents[name] is not None or name in (manifest or {}).get("experiments_run", [])
    ]
    sections = [_section(name, i, documents[name], manifest, out) for i, name in enumerate(shown, start=1)]
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        "<title>fdnet reproduce report</title>"
        f"<style>{STYLE}</style></head><body>\n{_header(manifest, shown)}\n"
        + "\n".join(sections)
        + "\n</body></html>\n"
    )


def write_report(out: str | os.PathLike) -> Path:
    """Render and write ``out/report.html`` atomically; returns its path."""
    path = Path(out) / REPORT
    atomic_write_text(path, render_report(out))
    return path
