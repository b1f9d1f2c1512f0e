"""`fdnet table`: results of several evaluate JSONs (and a reproduce comparison) merged into one
methods x datasets table, the best of each column marked (fdnet.evaluation.tables)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fdnet.cli import main


def _evaluate(tmp_path, name: str, scores: dict, protocol: str = "recall-over-queries", accept: str = "raw,margin"):
    """An evaluate JSON of precomputed matrices, one per method: 4 queries x 4 references, query i
    true at reference i; ``scores[method]`` = how many queries get their true place first."""
    paths = []
    for method, right in scores.items():
        s = np.full((4, 4), 0.1)
        for q in range(4):
            s[q, q if q < right else (q + 1) % 4] = 0.9 - 0.1 * q
        npy = tmp_path / f"{name}_{method}.npy"
        np.save(npy, s)
        paths.append((method, npy))
    csv = tmp_path / "gt.csv"
    csv.write_text("query_index,reference_indices\n0,0\n1,1\n2,2\n3,3\n")
    documents = []
    for method, npy in paths:
        out = tmp_path / f"{name}_{method}.json"
        assert (
            main(
                [
                    "evaluate",
                    "--similarity",
                    str(npy),
                    "--ground-truth",
                    str(csv),
                    "--name",
                    method,
                    "--protocol",
                    protocol,
                    "--accept",
                    accept if protocol != "vprbench" else "raw",
                    "--json",
                    str(out),
                ]
            )
            == 0
        )
        documents.append(json.loads(out.read_text()))
    merged = dict(documents[0], results=[d["results"][0] for d in documents])
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps(merged))
    return path


@pytest.fixture
def two_datasets(tmp_path, capsys):
    a = _evaluate(tmp_path, "nordland", {"fdnet": 3, "trunk": 2})
    b = _evaluate(tmp_path, "gardens", {"fdnet": 2, "trunk": 4, "hog": 1})
    capsys.readouterr()
    return a, b


def test_methods_by_datasets_with_the_best_of_each_column_marked(two_datasets, tmp_path, capsys):
    a, b = two_datasets
    assert main(["table", f"Nordland={a}", f"Gardens Point={b}", "--metrics", "R@1", "--format", "markdown"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "| method (R@1) | Nordland | Gardens Point |"
    assert lines[2:] == ["| fdnet | **0.750** | 0.500 |", "| trunk | 0.500 | **1.000** |", "| hog | - | 0.250 |"]
    out = tmp_path / "t.csv"
    assert (
        main(
            [
                "table",
                f"Nordland={a}",
                f"Gardens Point={b}",
                "--metrics",
                "R@1,R@5",
                "--format",
                "csv",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    rows = out.read_text().splitlines()
    assert rows[0] == "method,Nordland R@1,Nordland R@5,Gardens Point R@1,Gardens Point R@5"
    assert rows[1].startswith("fdnet,0.750*,1.000*,0.500,1.000*") and rows[3] == "hog,-,-,0.250,1.000*"
    assert main(["table", f"Nordland={a}", f"Gardens_Point={b}", "--format", "latex"]) == 0
    latex = capsys.readouterr().out
    assert "\\multicolumn{3}{c}{Gardens\\_Point}" in latex and "method & R@1 & R@100P & AUC-PR" in latex
    assert "trunk & 0.500 &" in latex and "\\textbf{1.000}" in latex and latex.rstrip().endswith("\\end{tabular}")


def test_names_a_spreadsheet_would_run_or_that_split_markdown_columns_are_escaped(tmp_path, capsys):
    a = _evaluate(tmp_path, "route", {"=HYPERLINK(1)": 3, "a|b": 2})
    capsys.readouterr()
    out = tmp_path / "t.csv"
    assert main(["table", f"@cmd={a}", "--metrics", "R@1", "--format", "csv", "--out", str(out)]) == 0
    rows = out.read_text().splitlines()
    assert rows[0] == "method (R@1),'@cmd" and rows[1].startswith("'=HYPERLINK(1),0.750")
    capsys.readouterr()
    assert main(["table", f"x|y={a}", "--metrics", "R@1", "--format", "markdown"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "| method (R@1) | x\\|y |" and lines[3].startswith("| a\\|b |")


def test_the_acceptance_rule_chooses_the_pr_numbers(two_datasets, capsys):
    a, _ = two_datasets
    assert main(["table", str(a), "--metrics", "AUC-PR", "--format", "csv"]) == 0
    raw = capsys.readouterr().out
    assert main(["table", str(a), "--metrics", "AUC-PR", "--format", "csv", "--accept", "margin"]) == 0
    margin = capsys.readouterr().out
    doc = json.loads(a.read_text())
    assert f"{doc['results'][0]['auc_pr']:.3f}" in raw.splitlines()[1]
    assert f"{doc['results'][0]['per_acceptance']['margin']['auc_pr']:.3f}" in margin.splitlines()[1]


def test_a_reproduce_comparison_gives_a_column_per_pair(two_datasets, tmp_path, capsys):
    a, _ = two_datasets
    doc = json.loads(a.read_text())
    comparison = tmp_path / "comparison.json"
    comparison.write_text(
        json.dumps(
            {
                "experiment": "comparison",
                "protocol": doc["protocol"],
                "pairs": [
                    {"reference": "summer", "query": "winter", "results": doc["results"]},
                    {"reference": "summer", "query": "night", "results": doc["results"][:1]},
                ],
            }
        )
    )
    assert main(["table", f"NL={comparison}", "--metrics", "R@1", "--format", "csv"]) == 0
    rows = capsys.readouterr().out.splitlines()
    assert rows == ["method (R@1),NL winter->summer,NL night->summer", "fdnet,0.750*,0.750*", "trunk,0.500,-"]


@pytest.mark.parametrize(
    "case, message",
    [
        ("same", "two results of fdnet on 'X'"),
        ("protocols", "results under different protocols"),
        ("metric", "--metrics R@2: choose from"),
        ("rule", "has no R@100P under --accept ratio (its rules: raw, margin)"),
        ("other", "reproduce's 'ablation' experiment holds no per-method results"),
        ("missing", "no such file"),
    ],
)
def test_what_cannot_share_a_table_is_refused(two_datasets, tmp_path, capsys, case, message):
    a, b = two_datasets
    other = tmp_path / "ablation.json"
    other.write_text(json.dumps({"experiment": "ablation", "rows": []}))
    vprbench = _evaluate(tmp_path, "vpr", {"fdnet": 1}, protocol="vprbench")
    capsys.readouterr()
    argv = {
        "same": [f"X={a}", f"X={b}"],
        "protocols": [str(a), str(vprbench)],
        "metric": [str(a), "--metrics", "R@1,R@2"],
        "rule": [str(a), "--accept", "ratio"],
        "other": [str(other)],
        "missing": [str(tmp_path / "nope.json")],
    }[case]
    out = tmp_path / "t.md"
    assert main(["table", *argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet table: error: ") and message in err and "Traceback" not in err
    assert not out.exists()
