"""fdnet.tasks.evaluate: the work of `fdnet evaluate` as one library call (no CLI)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fdnet.errors import ConfigError, FdnetError
from fdnet.tasks.evaluate import EvaluateSettings, evaluate_command

from conftest import write_day_dusk_route


@pytest.fixture
def route(tmp_path, rng):
    """10 random-texture places seen by day and, darker and noisier, at dusk."""
    return write_day_dusk_route(tmp_path / "route", rng)


def test_methods_on_images_give_results_table_and_json(route, tmp_path):
    out = tmp_path / "results.json"
    messages = []
    outcome = evaluate_command(
        EvaluateSettings(
            method="raw,sad", data=str(route), reference="day", query="dusk", workers=0, json=str(out), threads=1
        ),
        log=messages.append,
        show=lambda table: messages.append(("table", table)),
    )
    assert [r.method for r in outcome.results] == ["raw", "sad"]
    raw = outcome.results[0].metrics["recall-over-queries"]
    assert raw.num_queries == 10 and raw.recall_at_n[1] == 1.0  # same textures, darker: every place found
    assert outcome.table.startswith("protocol: recall-over-queries") and "raw" in outcome.table
    written = json.loads(out.read_text())
    assert [r["method"] for r in written["results"]] == ["raw", "sad"]
    assert written["format"] == "fdnet-evaluation" and written["settings"]["method"] == "raw,sad"
    assert messages[0] == (
        "evaluating raw, sad on route: dusk -> day, frame-aligned, tolerance 0 frames: " "10 queries x 10 references"
    )
    assert messages[-2:] == [("table", outcome.table), f"wrote {out}"]  # shown before the files are written


def test_a_similarity_matrix_against_frame_aligned_ground_truth(route, tmp_path):
    matrix = tmp_path / "s.npy"
    scores = np.eye(10)
    scores[3] = np.roll(scores[3], 1)  # query 3's best answer is the wrong place
    np.save(matrix, scores)
    outcome = evaluate_command(
        EvaluateSettings(similarity=str(matrix), data=str(route), reference="day", query="dusk", name="made")
    )
    (result,) = outcome.results
    assert result.method == "made"
    assert result.metrics["recall-over-queries"].recall_at_n[1] == pytest.approx(0.9)


@pytest.mark.parametrize(
    "settings, message",
    [
        (EvaluateSettings(), "nothing to evaluate"),
        (EvaluateSettings(method="raw", similarity="s.npy"), "not both"),
        (EvaluateSettings(method="raw", data="d", sequence_length=-1), "--sequence-length must be a whole number"),
        # one convention everywhere: 1 is single images, 0 means nothing
        (EvaluateSettings(method="raw", data="d", sequence_length=0), r"at least 1 \(1 = single images\), got 0"),
        (EvaluateSettings(method="raw", data="d", thresholds=1), "--thresholds must be at least 2"),
        (EvaluateSettings(method="raw"), "--method needs --data DIR"),
    ],
)
def test_bad_settings_are_refused(settings, message):
    with pytest.raises(ConfigError, match=message):
        evaluate_command(settings)


def test_an_unwritable_output_is_refused_before_any_image_is_described(route, tmp_path, monkeypatch):
    from fdnet.descriptors.classic import RawThumbnail

    def describe(self, images):
        raise AssertionError("images were described before the refusal")

    monkeypatch.setattr(RawThumbnail, "describe", describe)
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    with pytest.raises(FdnetError, match="JSON results"):
        evaluate_command(
            EvaluateSettings(
                method="raw", data=str(route), reference="day", query="dusk", workers=0, json=str(blocker / "r.json")
            )
        )
