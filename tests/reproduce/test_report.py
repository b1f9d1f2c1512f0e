"""The HTML report from JSON alone: every section in place, figures embedded, nothing external,
text escaped, a missing figure said rather than shown broken."""

from __future__ import annotations

import base64
import io
import json
import re

import numpy as np
from PIL import Image

from fdnet.reproduce.report import write_report
from fdnet.reproduce.sections import EXPERIMENTS, MANIFEST


def result(method: str, r100p: float, r1: float) -> dict:
    return {
        "method": method,
        "recall_at_100_precision": r100p,
        "precision_at_max_recall": 0.5,
        "auc_pr": 0.4,
        "recall_at_n": {"1": r1, "5": 0.9, "10": 1.0, "20": 1.0},
    }


def write_run(out, figure: bool = True) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / MANIFEST).write_text(
        json.dumps(
            {
                "fdnet_version": "0.1.0",
                "command": "fdnet reproduce --data d --out o",
                "dataset": "d<&>",
                "dataset_format": "folders",
                "protocol": "recall-over-queries",
                "protocol_definition": "definition",
                "thresholds": "500 uniform",
                "checkpoint": "runs/x",
                "pairs": [{"query": "night<b>", "reference": "day", "num_queries": 3, "num_references": 3}],
            }
        )
    )
    if figure:
        (out / "figures" / "comparison").mkdir(parents=True)
        Image.fromarray(np.full((20, 30, 3), 200, np.uint8)).save(out / "figures" / "comparison" / "pr.png")
    (out / "comparison.json").write_text(
        json.dumps(
            {
                "command": "fdnet reproduce --data d --out o",
                "paper_dataset": None,
                "skipped": [],
                "pairs": [
                    {
                        "reference": "day",
                        "query": "night<b>",
                        "ground_truth": "frame-aligned",
                        "num_queries": 3,
                        "num_queries_with_match": 3,
                        "num_references": 3,
                        "paper": None,
                        "paper_source": None,
                        "figure": "figures/comparison/pr.png",
                        "results": [result("fdnet", 0.25, 0.75), result("sad", 0.5, 0.5)],
                    }
                ],
            }
        )
    )
    (out / "lengths.json").write_text(json.dumps({"not_run": "needs four FDNet runs"}))


def test_every_section_and_embedded_figures(tmp_path):
    write_run(tmp_path)
    html = write_report(tmp_path).read_text()
    assert [m for m in re.findall(r'<section id="(\w+)">', html)] == list(EXPERIMENTS)
    # self-contained: no scripts, no links or sources other than embedded data
    assert "<script" not in html and "<link" not in html and "url(" not in html
    sources = re.findall(r'src="([^"]*)"', html)
    assert len(sources) == 1 and sources[0].startswith("data:image/png;base64,")
    png = Image.open(io.BytesIO(base64.b64decode(sources[0].split(",", 1)[1])))
    assert png.size == (30, 20)
    # best of each column marked; the tables read without the figure
    assert '<td class="best">0.500&nbsp;&#9733;</td>' in html and '<td class="best">0.750&nbsp;&#9733;</td>' in html
    assert "Not run: needs four FDNet runs" in html
    assert "Not run yet: rerun the command with <code>--experiments similarity</code>" in html
    # the lengths study alone needs its runs: the hint says how, so the command it gives works
    (tmp_path / "lengths.json").unlink()
    html = write_report(tmp_path).read_text()
    assert (
        "rerun the command with <code>--experiments lengths --length-preset cpu --length-train-frames "
        "START:END (or --length-runs"
    ) in html
    assert "night&lt;b&gt;" in html and "night<b>" not in html and "d&lt;&amp;&gt;" in html
    assert "fdnet reproduce --data d --out o" in html


def test_a_missing_figure_is_said_not_shown_broken(tmp_path):
    write_run(tmp_path, figure=False)
    html = write_report(tmp_path).read_text()
    assert "<img" not in html
    assert "Figure figures/comparison/pr.png is missing" in html


def test_the_papers_numbers_stand_beside_ours_labelled_as_the_papers(tmp_path):
    from fdnet.paper import paper_pair

    write_run(tmp_path)
    document = json.loads((tmp_path / "comparison.json").read_text())
    source, numbers = paper_pair("nordland", "summer", "winter")
    document["paper_dataset"] = "nordland"
    document["pairs"][0].update(paper=numbers, paper_source=source)
    (tmp_path / "comparison.json").write_text(json.dumps(document))
    html = write_report(tmp_path).read_text()
    start = html.index('<section id="comparison">')
    table = html[start : html.index("</table>", start)]
    assert "<th>paper R@100P</th><th>paper P@maxR</th>" in table
    assert "<td>fdnet</td>" in table and "<td>0.337</td><td>0.038</td>" in table  # FDNet_512, summer-winter
    assert "netvlad (NetVLAD, paper only)" in table
    assert "paper Table 3, Nordland summer-winter, the paper&#x27;s own numbers" in table
    # and what differs between the paper's numbers and ours is said beside them
    assert "What differs: the paper trained at 224x224 on its own frames" in table


def test_a_section_from_another_version_is_said_not_fatal(tmp_path):
    write_run(tmp_path)
    (tmp_path / "similarity.json").write_text(json.dumps({"pairs": [{"unexpected": 1}]}))
    html = write_report(tmp_path).read_text()
    assert "similarity.json does not hold what this version of fdnet writes" in html
    assert '<td class="best">0.750&nbsp;&#9733;</td>' in html  # the other sections are still there
