"""Calibration: the threshold reaching a target precision, its storage and its checks."""

import math

import numpy as np
import pytest
from PIL import Image

from fdnet.data.dataset import RouteDataset
from fdnet.data.split import aligned_split
from fdnet.decisions.acceptance import Candidates, parse_acceptance
from fdnet.decisions.calibration import (
    Calibration,
    apply_threshold,
    check_target,
    choose_threshold,
    load_calibration,
    save_calibration,
)
from fdnet.descriptors import create
from fdnet.descriptors.pipeline import PipelineSettings
from fdnet.errors import ConfigError, DataError
from fdnet.tasks.calibrate import calibrate

# scores best first: right, right, wrong, right, right, wrong, right
SCORES = np.array([0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3])
CORRECT = np.array([1, 1, 0, 1, 1, 0, 1], bool)
HAS_MATCH = np.ones(7, bool)


def test_threshold_for_precision_one_stops_before_the_first_wrong():
    t = choose_threshold(SCORES, CORRECT, HAS_MATCH, 1.0)
    assert (t.threshold, t.precision, t.recall, t.accepted) == (0.8, 1.0, 2 / 7, 2)


def test_threshold_for_a_lower_target_takes_the_largest_recall_reaching_it():
    # precision at each threshold: 1, 1, 2/3, 3/4, 4/5, 4/6, 5/7 -> >= 0.75: 0.5 (recall 4/7)
    t = choose_threshold(SCORES, CORRECT, HAS_MATCH, 0.75)
    assert t.threshold == 0.5 and t.precision == pytest.approx(0.8) and t.recall == pytest.approx(4 / 7)
    # >= 0.7: 0.3 reaches 5/7 = 0.714 with all recall
    assert choose_threshold(SCORES, CORRECT, HAS_MATCH, 0.7).threshold == 0.3


def test_nothing_reaches_the_target_when_the_most_confident_is_wrong():
    t = choose_threshold(SCORES, ~CORRECT, HAS_MATCH, 1.0)
    assert t.threshold == math.inf and t.recall == 0.0 and t.accepted == 0


def test_rejected_queries_are_never_accepted():
    scores = SCORES.copy()
    scores[2] = -np.inf  # the first wrong one is rejected by a gate
    t = choose_threshold(scores, CORRECT, HAS_MATCH, 1.0)
    assert t.threshold == 0.5 and t.recall == pytest.approx(4 / 7)


@pytest.mark.parametrize("target", [0.0, -0.5, 1.01, float("nan"), True])
def test_target_outside_0_1_is_an_error(target):
    with pytest.raises(ConfigError, match=r"must be in \(0, 1\]"):
        check_target(target)
    with pytest.raises(ConfigError, match=r"must be in \(0, 1\]"):
        choose_threshold(SCORES, CORRECT, HAS_MATCH, target)


def make_split(tmp_path, n=24, unrelated=(3, 8, 15, 20)):
    """Two conditions of n random-texture places; the listed query frames show unrelated
    textures, so their best matches are wrong."""
    rng = np.random.default_rng(1)
    for condition in ("map", "now"):
        (tmp_path / condition).mkdir()
    for i in range(n):
        place = rng.integers(0, 256, size=(24, 32, 3))
        query = (
            rng.integers(0, 256, size=(24, 32, 3))
            if i in unrelated
            else np.clip(place * 0.25 + rng.normal(0, 90, place.shape), 0, 255)
        )
        Image.fromarray(place.astype(np.uint8)).save(tmp_path / "map" / f"{i:03d}.png")
        Image.fromarray(query.astype(np.uint8)).save(tmp_path / "now" / f"{i:03d}.png")
    return aligned_split(RouteDataset.from_folder(tmp_path, ["map", "now"]), "map", "now", 0)


@pytest.mark.parametrize("rule", ["raw", "margin", "ratio"])
@pytest.mark.parametrize("target", [1.0, 0.9])
def test_calibration_reaches_its_target_on_its_split(tmp_path, rule, target):
    split = make_split(tmp_path)
    descriptor = create("raw")
    cal = calibrate(
        descriptor,
        split,
        parse_acceptance(rule, ["radius=1"] if rule != "raw" else []),
        target,
        pipeline=PipelineSettings(workers=0),
    )
    assert cal.precision >= target and cal.accepted > 0
    assert cal.rule == rule and cal.method == "raw" and cal.fingerprint == descriptor.fingerprint()
    assert cal.measured_on["ground_truth"].startswith("frame-aligned")
    # applying the threshold to the same split's scores gives back the precision and recall stored
    from fdnet.evaluation.experiment import ScoringSettings, evaluate_method

    result = evaluate_method(descriptor, split, ScoringSettings(acceptance=[cal.spec]), PipelineSettings(workers=0))
    decision = result.decisions[rule]
    reached = apply_threshold(
        cal,
        decision.score,
        split.ground_truth.correct_mask(decision.match[:, None])[:, 0],
        split.ground_truth.has_match,
    )
    assert reached["precision"] == pytest.approx(cal.precision) and reached["recall"] == pytest.approx(cal.recall)
    # the calibration's own decide() agrees
    _, accepted = cal.decide(Candidates(result.retrieved, result.scores))
    assert int(accepted.sum()) == cal.accepted


def test_yaml_round_trip_and_checks(tmp_path):
    split = make_split(tmp_path)
    raw, hog = create("raw"), create("hog")
    cal = calibrate(
        raw,
        split,
        parse_acceptance("margin", ["radius=2"]),
        1.0,
        sequence_length=3,
        pipeline=PipelineSettings(workers=0),
    )
    path = save_calibration(cal, tmp_path / "cal.yaml")
    back = load_calibration(path)
    assert back == cal and back.spec.settings["margin"]["radius"] == 2
    (tmp_path / "run").mkdir()
    save_calibration(cal, tmp_path / "run")
    assert load_calibration(tmp_path / "run") == cal  # a run directory holds calibration.yaml
    back.check(raw, sequence_length=3)
    with pytest.raises(ConfigError, match="another model"):
        back.check(hog, sequence_length=3)
    with pytest.raises(ConfigError, match="--sequence-length 3, used with 1"):
        back.check(raw, sequence_length=1)
    # JSON form (a place database's metadata) keeps an infinite threshold
    never = Calibration(**{**cal.__dict__, "threshold": math.inf})
    assert Calibration.from_dict(never.to_dict(json_safe=True)).threshold == math.inf


@pytest.mark.parametrize(
    "text, message",
    [
        ("just text", "not an fdnet calibration"),
        ("format: fdnet-calibration\nversion: 1\nrule: margin\n", "lacks settings, threshold"),
        ("format: fdnet-calibration\nversion: 7\n", "format version 7"),
        (
            "format: fdnet-calibration\nversion: 1\nrule: nope\nsettings: {}\nthreshold: 1\ntarget_precision: 1\n"
            "method: raw\nfingerprint: x\n",
            "unknown acceptance rule 'nope'",
        ),
        (
            "format: fdnet-calibration\nversion: 1\nrule: raw\nsettings: {raw: {}}\nthreshold: 1\ntarget_precision: 2\n"
            "method: raw\nfingerprint: x\n",
            r"must be in \(0, 1\]",
        ),
        ("{{{", "not valid YAML"),
    ],
)
def test_bad_calibration_files_name_the_file(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises((DataError, ConfigError), match=message) as info:
        load_calibration(path)
    assert str(path) in str(info.value)
    with pytest.raises(DataError, match="not found"):
        load_calibration(tmp_path / "missing.yaml")


GOOD = (
    "format: fdnet-calibration\nversion: 1\nrule: margin\nsettings: {margin: {radius: 3}}\nthreshold: 0.2\n"
    "target_precision: 1.0\nmethod: raw\nfingerprint: abc\n"
)


@pytest.mark.parametrize(
    "edit, message",
    [
        ("sequence_length: ten", "sequence_length must be a whole number"),
        ("sequence_length: -4", "sequence_length must be a whole number"),
        ("accepted: many", "accepted must be a whole number"),
        ("fingerprint: 123", "fingerprint must be text"),
        ("rule: [margin]", "rule must be text"),
        ("threshold: -.inf", "threshold is -inf"),
        ("notes: [[a, b]]", "notes must be a list of text lines"),
        ("measured_on: somewhere", "measured_on must map"),
    ],
)
def test_hand_edited_calibration_values_are_refused_on_loading(tmp_path, edit, message):
    key = edit.split(":")[0]
    lines = [line for line in GOOD.splitlines() if not line.startswith(key + ":")]
    path = tmp_path / "edited.yaml"
    path.write_text("\n".join(lines + [edit]) + "\n")
    with pytest.raises(DataError, match=message) as info:
        load_calibration(path)
    assert str(path) in str(info.value)
    path.write_text(GOOD)
    assert load_calibration(path).threshold == 0.2


def test_calibration_can_choose_the_radius_on_its_split(tmp_path):
    split = make_split(tmp_path)
    descriptor = create("raw")
    chosen = calibrate(
        descriptor,
        split,
        parse_acceptance("margin"),
        1.0,
        pipeline=PipelineSettings(workers=0),
        choose={"radius": [0, 1, 4]},
    )
    tried = chosen.measured_on["chosen_from"]
    assert [t["radius"] for t in tried] == [0, 1, 4]
    best = max(tried, key=lambda t: t["recall"])
    assert chosen.recall == best["recall"] and chosen.settings["margin"]["radius"] == best["radius"]
    # each value tried is what calibrating with that radius alone gives
    for t in tried:
        alone = calibrate(
            descriptor,
            split,
            parse_acceptance("margin", [f"radius={t['radius']}"]),
            1.0,
            pipeline=PipelineSettings(workers=0),
        )
        assert alone.recall == t["recall"]
    with pytest.raises(ConfigError, match="has no setting 'radius'"):
        calibrate(
            descriptor,
            split,
            parse_acceptance("raw"),
            1.0,
            pipeline=PipelineSettings(workers=0),
            choose={"radius": [1]},
        )


def test_a_neighbourhood_in_metres_is_refused_before_describing(tmp_path):
    split = make_split(tmp_path)

    class Untouchable(type(create("raw"))):
        def describe(self, images):
            raise AssertionError("described before the rule was checked")

    with pytest.raises(ConfigError, match="radius_m: calibration on image folders has no positions"):
        calibrate(
            Untouchable(),
            split,
            parse_acceptance("margin"),
            1.0,
            pipeline=PipelineSettings(workers=0),
            choose={"radius_m": [1.0, 2.0]},
        )
