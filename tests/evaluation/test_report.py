"""Report table and JSON writer."""

from __future__ import annotations

import json
import re

import numpy as np

from fdnet.data.groundtruth import GroundTruth
from fdnet.evaluation.experiment import ScoringSettings, evaluate_matrix
from fdnet.evaluation.report import format_table, results_json, write_json
from fdnet.metrics import VPRBENCH

REQUIRED = {
    "recall_at_100_precision",
    "precision_at_max_recall",
    "auc_pr",
    "recall_at_n",
    "protocol",
    "method",
    "num_queries",
}


def _results():
    s = np.eye(5) + 0.01 * np.arange(5)
    gt = GroundTruth.aligned(5, 5, 0)
    return [
        evaluate_matrix(s, gt, "perfect", ScoringSettings((VPRBENCH,))),
        evaluate_matrix(np.roll(s, 1, axis=1), gt, "shifted", ScoringSettings((VPRBENCH,))),
    ]


def test_table_names_protocol_and_methods():
    table = format_table(_results())
    assert table.splitlines()[0].startswith("protocol: vprbench")
    rows = {line.split()[0]: line.split() for line in table.splitlines()[3:]}
    assert "R@100P" in table and "ms/query" in table
    # columns: method, acceptance rule, R@1, ...
    assert rows["perfect"][1] == "raw" and rows["perfect"][2] == "1.000" and rows["shifted"][2] == "0.000"


def test_json_one_and_several(tmp_path):
    document = results_json(_results()[:1])
    assert document["format"] == "fdnet-evaluation" and len(document["results"]) == 1  # one schema
    one = document["results"][0]
    assert REQUIRED <= set(one)
    assert set(one["recall_at_n"]) == {"1", "5", "10", "20"}
    assert one["protocol"] == "vprbench" and one["auc_pr"] == 1.0
    path = tmp_path / "out" / "results.json"
    write_json(path, _results())
    several = json.loads(path.read_text())
    assert [r["method"] for r in several["results"]] == ["perfect", "shifted"]
    assert all(REQUIRED <= set(r) for r in several["results"])
    assert list(tmp_path.joinpath("out").iterdir()) == [path]  # no temporary file left behind


def test_json_accepts_numpy_and_path_settings(tmp_path):
    from pathlib import Path

    result = _results()[0]
    result.settings = {"size": np.int64(3), "mean": np.zeros(2, dtype=np.float32), "weights": Path("/w.pt")}
    write_json(tmp_path / "r.json", [result])
    written = json.loads((tmp_path / "r.json").read_text())["results"][0]
    assert written["settings"] == {"size": 3, "mean": [0.0, 0.0], "weights": "/w.pt"}


def test_paper_tables_quote_formulas_in_csv_and_escape_pipes_in_markdown():
    """A folder name reaches the table's data column: in CSV a cell starting with '=' is run by a
    spreadsheet; in Markdown a '|' starts another column."""
    import csv
    import io

    from fdnet.evaluation.report import format_results_table
    from fdnet.io import from_spreadsheet_text

    s = np.eye(5) + 0.01 * np.arange(5)
    result = evaluate_matrix(s, GroundTruth.aligned(5, 5, 0), "perfect", ScoringSettings((VPRBENCH,)))
    result.dataset = '=HYPERLINK("http://x")|b'
    rows = list(csv.reader(io.StringIO(format_results_table([result], "csv"))))
    assert rows[1][2] == "'" + result.dataset and from_spreadsheet_text(rows[1][2]) == result.dataset
    markdown = format_results_table([result], "markdown").splitlines()
    cells = re.split(r"(?<!\\)\|", markdown[2])[1:-1]
    assert len(cells) == len(markdown[0].split("|")[1:-1]) == 6
    assert "\\|b" in cells[2]
