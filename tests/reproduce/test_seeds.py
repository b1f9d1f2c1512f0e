"""``--seeds N`` on the ``ablation`` experiment (tiny runs): each variant trained here is trained N
times with seeds S, S+1, ..., and its numbers are the mean over those runs, with the spread and the
per-seed values beside; ``--seeds 1`` writes one run's numbers under the one-run keys."""

from __future__ import annotations

import dataclasses
import json
import re
import statistics

import pytest

from fdnet.errors import ConfigError
from fdnet.reproduce import reproduce
from fdnet.reproduce.ablation import VARIANTS
from fdnet.reproduce.ablation_report import METRICS
from fdnet.reproduce.seeds import seed_folder, spread, spread_text
from tests.reproduce.test_ablation import ablation, factory

#: the keys of a one-seed ablation.json, at each level (no seed keys: one run's numbers)
DOCUMENT_KEYS = {
    "experiment",
    "title",
    "paper",
    "fdnet_version",
    "command",
    "created",
    "dataset",
    "checkpoint",
    "protocol",
    "smoke_test",
    "variants",
    "removes",
    "acceptance",
    "groups",
    "train_frames",
    "provenance",
}
GROUP_KEYS = {"preset", "trained_here", "settings", "runs", "pairs", "figure", "missing"}
RUN_KEYS = {"variant", "removes", "run", "step", "seed", "schedule", "weights_stage", "differences_from_full"}
FULL_ROW_KEYS = {"variant", *METRICS, "pr_curve"}
VARIANT_ROW_KEYS = FULL_ROW_KEYS | {"against_full", "same_content_vectors_as_full"}


def test_two_seeds_train_each_variant_twice_and_report_mean_and_spread(route, tmp_path):
    out = tmp_path / "out"
    said = []
    reproduce(ablation(route, out, seeds=2), factory=factory, log=said.append)
    document = json.loads((out / "ablation.json").read_text())
    assert document["seeds"] == 2
    (group,) = document["groups"]
    assert group["seeds"] == {variant: [0, 1] for variant in VARIANTS}
    # one run per variant and seed, the seed read back from each run; the first in the one-seed folder
    assert [(r["variant"], r["seed"]) for r in group["runs"]] == [(v, s) for v in VARIANTS for s in (0, 1)]
    for run in group["runs"]:
        folder = out / "ablation-runs" / "tiny" / (run["variant"] + ("-seed1" if run["seed"] else ""))
        assert run["run"] == str(folder) and (folder / "checkpoints").is_dir()
        assert run["differences_from_full"] == []  # compared with the full run of the same seed
    assert document["provenance"]["seeds"]["tiny/no-critic"] == [0, 1]

    for pair in group["pairs"]:
        for row in pair["variants"]:
            assert [r["seed"] for r in row["per_seed"]] == [0, 1]
            for key in METRICS:
                values = [r[key] for r in row["per_seed"]]
                summary = row["spread"][key]
                assert summary["n"] + summary["missing"] == 2
                if None in values:
                    continue
                assert summary["n"] == 2 and row[key] == summary["mean"]
                assert summary["mean"] == pytest.approx(sum(values) / 2)
                assert summary["std"] == pytest.approx(statistics.stdev(values))
                assert (summary["min"], summary["max"]) == (min(values), max(values))
            if row["variant"] != "full":
                assert all(0.0 <= r["against_full"]["p_value"] <= 1.0 for r in row["per_seed"])

    html = (out / "report.html").read_text()
    section = html[html.index('<section id="ablation">') :]
    assert "over 2 seeds" in section and "each seed&#x27;s run" in section
    assert "does not measure" not in section
    # a table cell with a spread: mean ± std (min–max)
    assert re.search(r"<td[^>]*>\d\.\d{3} \u00b1 \d\.\d{3} \(\d\.\d{3}\u2013\d\.\d{3}\)</td>", section)

    # a rerun reuses all eight runs
    said.clear()
    reproduce(ablation(route, out, seeds=2), factory=factory, log=said.append)
    assert sum("finished run in" in line and "reused" in line for line in said) == 2 * len(VARIANTS)
    assert any("full (seed 1): finished run in" in line for line in said)

    # --seeds 1 on the same folder: the first seed's runs, reused, and exactly the keys of a one-seed document
    first = {
        (p["query"], v["variant"]): {k: v["per_seed"][0][k] for k in METRICS}
        for p in group["pairs"]
        for v in p["variants"]
    }
    said.clear()
    reproduce(ablation(route, out, seeds=1), factory=factory, log=said.append)
    assert sum("finished run in" in line for line in said) == len(VARIANTS)
    assert not any("training" in line or "seed 1" in line for line in said)
    single = json.loads((out / "ablation.json").read_text())
    assert set(single) == DOCUMENT_KEYS
    (group,) = single["groups"]
    assert set(group) == GROUP_KEYS and all(set(r) == RUN_KEYS for r in group["runs"])
    assert [r["variant"] for r in group["runs"]] == list(VARIANTS)
    assert single["provenance"]["seeds"]["tiny/full"] == 0
    for pair in group["pairs"]:
        for row in pair["variants"]:
            assert set(row) == (FULL_ROW_KEYS if row["variant"] == "full" else VARIANT_ROW_KEYS)
            assert {k: row[k] for k in METRICS} == first[(pair["query"], row["variant"])]
    assert "run-to-run variation, which this experiment does not measure" in (out / "report.html").read_text()


@pytest.mark.parametrize("seeds", [0, -1])
def test_seeds_below_one_are_refused_before_any_work(route, tmp_path, seeds):
    with pytest.raises(
        ConfigError, match=re.escape(f"--seeds must be a whole number >= 1 " f"(runs per trained variant), got {seeds}")
    ):
        reproduce(ablation(route, tmp_path / "out", seeds=seeds), factory=factory, log=lambda m: None)
    assert not (tmp_path / "out" / "ablation-runs").exists()


def test_the_spread_of_a_number_and_the_folders_of_the_seeds(tmp_path):
    assert spread([0.5, 0.7]) == {
        "n": 2,
        "mean": pytest.approx(0.6),
        "std": pytest.approx(0.1414213562),
        "min": 0.5,
        "max": 0.7,
        "missing": 0,
    }
    assert spread([0.5, None]) == {"n": 1, "mean": 0.5, "std": None, "min": 0.5, "max": 0.5, "missing": 1}
    assert spread([None, float("nan")])["mean"] is None
    assert spread_text(spread([0.5, 0.7])) == "0.600 \u00b1 0.141 (0.500\u20130.700)"
    assert spread_text(spread([None, None])) == "-"
    assert seed_folder(tmp_path / "full", 3, 3) == tmp_path / "full"
    assert seed_folder(tmp_path / "full", 3, 5) == tmp_path / "full-seed5"


def test_two_seeds_train_each_length_twice_and_report_mean_and_spread(route, tmp_path):
    from tests.reproduce.conftest import settings

    out = tmp_path / "out"
    lengths = settings(
        route,
        out,
        experiments=["lengths"],
        conditions=["day", "night"],
        frames="6:10",
        length_preset="tiny",
        length_train_frames="0:6",
        runtime_images=2,
        cache=out / "cache",
        seeds=2,
    )
    said = []
    reproduce(lengths, factory=factory, log=said.append)
    document = json.loads((out / "lengths.json").read_text())
    assert document["seeds"] == 2 and document["run_seeds"] == {str(n): [0, 1] for n in (256, 512, 1024, 2048)}
    assert (out / "length-runs" / "L512" / "checkpoints").is_dir()
    assert (out / "length-runs" / "L512-seed1" / "checkpoints").is_dir()
    assert document["provenance"]["seeds"]["L2048"] == [0, 1]
    assert len(document["accuracy"]) == 4 * 2 and len(document["timing"]) == 4  # timed once per length
    for entry in document["accuracy"]:
        assert [r["seed"] for r in entry["per_seed"]] == [0, 1]
        for key in ("recall_at_100_precision", "precision_at_max_recall", "recall_at_1", "auc_pr"):
            values = [r[key] for r in entry["per_seed"]]
            assert entry[key] == entry["spread"][key]["mean"] == pytest.approx(sum(values) / 2)
            assert entry["spread"][key]["std"] == pytest.approx(statistics.stdev(values))
    section = (out / "report.html").read_text()
    section = section[section.index('<section id="lengths">') :]
    assert "over 2 seeds" in section and "each seed&#x27;s run per vector length and pair" in section

    said.clear()
    reproduce(dataclasses.replace(lengths, seeds=1), factory=factory, log=said.append)
    assert sum("finished run in" in line for line in said) == 4 and not any("seed 1" in line for line in said)
    single = json.loads((out / "lengths.json").read_text())
    assert "seeds" not in single and "run_seeds" not in single
    assert set(single["provenance"]["seeds"]) == {"checkpoint"}
    assert all(
        set(a)
        == {
            "length",
            "reference",
            "query",
            "recall_at_100_precision",
            "precision_at_max_recall",
            "recall_at_1",
            "auc_pr",
        }
        for a in single["accuracy"]
    )
