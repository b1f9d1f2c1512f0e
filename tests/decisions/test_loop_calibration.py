"""A loop calibration carries what it assumes: p_correct per closure, the scores it rejected (a
run whose rejected scores reach further into their tail warns once), its sequence length and
gates; a run directory serves as a calibration."""

import logging
import math

import numpy as np
import pytest

from fdnet.decisions.calibration import (
    Calibration,
    expected_wrong,
    fit_probability,
    load_calibration,
    save_calibration,
    score_distribution,
    tail_departure,
    tail_threshold,
)
from fdnet.decisions.loop_closure import LOOP_CALIBRATION_FILE, LoopClosureDetector
from fdnet.decisions.loop_evaluation import calibrate_decisions
from fdnet.errors import DataError
from fdnet.performance.loop_benchmark import StoredVectors
from tests.decisions.test_loop_recency import drive, revisit_truth, slow_route


def test_p_correct_is_non_decreasing_and_a_lower_bound_of_each_block():
    scores = np.r_[np.linspace(0, 1, 100), np.linspace(2, 3, 20), np.linspace(4, 5, 300)]
    right = np.r_[np.zeros(100, bool), np.ones(20, bool), np.ones(300, bool)]
    fit = fit_probability(scores, right)
    p = np.asarray(fit["p_correct"])
    assert (np.diff(p) >= 0).all() and p.max() < 1.0 and p.min() == 0.0
    calibration = Calibration("margin", {}, 0.5, 1.0, 1.0, 1.0, 1, 1, "m", "f", probability=fit)
    # 320 right in a row above score 2: the 95 % lower bound of 320/320 (0.9907)
    assert 0.99 < calibration.p_correct([4.5])[0] < 0.992
    assert calibration.p_correct([-math.inf])[0] == 0.0 and calibration.p_correct([0.5])[0] == 0.0
    # a handful of right answers proves little
    small = fit_probability(np.r_[np.zeros(5), np.ones(20)], np.r_[np.zeros(5, bool), np.ones(20, bool)])
    assert 0.85 < max(small["p_correct"]) < 0.87
    assert fit_probability(np.ones(3), np.ones(3, bool)) == {}


def test_p_correct_counts_the_wrong_frames_the_wrong_score_tail_expects_in_a_block():
    # 900 wrong frames' scores with an exponential tail (its quantiles), 300 right ones above all
    # of them: by their count alone the top block is 300 right in a row (0.9901); the tail of the
    # wrong scores expects half a wrong frame up there, so the block may not claim 0.99
    wrong = -np.log((np.arange(900) + 0.5) / 900)
    right = wrong.max() + np.linspace(0.01, 1.0, 300)
    scores = np.r_[wrong, right]
    correct = np.r_[np.zeros(900, bool), np.ones(300, bool)]
    tail = tail_threshold(wrong)
    expected = expected_wrong(tail, float(right.min()))
    assert 0.3 < expected < 0.7
    assert expected_wrong(tail, float(right.min()), float(right.max())) < expected
    assert expected_wrong(None, 0.0) == 0.0 and expected_wrong(tail, tail["u"] - 1.0, tail["u"]) == 0.0
    plain, with_tail = fit_probability(scores, correct), fit_probability(scores, correct, tail)
    assert max(plain["p_correct"]) > 0.99 > max(with_tail["p_correct"])
    assert with_tail["wrong_score_tail"]["k"] == tail["k"]
    assert with_tail["scores"] == plain["scores"]
    # the tail never makes p_correct higher, and a calibration stores and reads it back
    assert all(a >= b for a, b in zip(plain["p_correct"], with_tail["p_correct"]))
    calibration = Calibration("margin", {}, 0.5, 1.0, 1.0, 1.0, 1, 1, "m", "f", probability=with_tail)
    assert Calibration.from_dict(calibration.to_dict()).probability["wrong_score_tail"] == with_tail["wrong_score_tail"]


def test_p_correct_expects_the_wrong_frames_of_a_route_of_a_thousand():
    # 300 right frames above the wrong ones' exponential tail, drawn from 3000 wrong frames or from
    # 300: the top block counts the wrong frames the tail expects above it on a route of 1000
    # wrong frames (the threshold's), so the 300-frame loop's expectation is scaled up 10/3
    from scipy.stats import beta

    from fdnet.decisions.calibration import EXTRAPOLATE_TO, P_CORRECT_CONFIDENCE

    right = np.linspace(0.01, 1.0, 300) + 9.0  # above the largest of 3000 wrong (8.7)
    for frames, scale in ((3000, 1.0), (300, EXTRAPOLATE_TO / 300)):
        wrong = -np.log((np.arange(frames) + 0.5) / frames)
        tail = tail_threshold(wrong)
        assert tail["wrong"] == frames
        fit = fit_probability(np.r_[wrong, right], np.r_[np.zeros(frames, bool), np.ones(300, bool)], tail)
        expected = expected_wrong(tail, float(right.min())) * scale
        assert max(fit["p_correct"]) == pytest.approx(beta.ppf(1.0 - P_CORRECT_CONFIDENCE, 300, expected + 1))


def test_score_distribution_and_a_departure_into_its_tail():
    rng = np.random.default_rng(0)
    stored = score_distribution(np.r_[rng.normal(0, 1, 1000), -math.inf, 5.0], below=4.0)
    assert stored["frames"] == 1000 and len(stored["quantiles"]) == len(stored["levels"]) == 19
    assert tail_departure(stored, rng.normal(0, 1, 500)) is None
    assert tail_departure(stored, rng.normal(-1, 0.5, 500)) is None  # one-sided: lighter costs recall only
    heavier = tail_departure(stored, rng.normal(0, 1.6, 500))
    assert heavier is not None and heavier["share"] > 2 * heavier["expected"]


def calibrated(tmp_path, n=80):
    first, second = slow_route(n=n)
    detector = drive(first, second)
    calibration = calibrate_decisions(detector.decisions, revisit_truth(n), detector, 1.0)
    return calibration, first, second


def test_a_loop_calibration_stores_p_correct_and_its_scores_and_closures_carry_p_correct(tmp_path):
    calibration, first, second = calibrated(tmp_path)
    assert calibration.probability["scores"] and calibration.score_distribution["frames"] > 20
    path = save_calibration(calibration, tmp_path / "cal.yaml")
    loaded = load_calibration(path)
    assert loaded.probability == calibration.probability
    assert loaded.score_distribution == calibration.score_distribution
    # another loop of the same kind: every closure carries the fitted probability
    other_first, other_second = slow_route(n=80, seed=3)
    detector = LoopClosureDetector(StoredVectors(64), calibration=str(path))
    assert detector.sequence_length == 10  # the calibration's, not the API's single images
    for i, vector in enumerate(np.concatenate([other_first, other_second])):
        detector.process_vector(vector, name=f"f{i}", new_segment=i == 80)
    assert detector.closures
    for closure in detector.closures:
        assert closure.p_correct == pytest.approx(float(loaded.p_correct([closure.score])[0]))


def test_a_run_directory_is_a_calibration(tmp_path):
    calibration, *_ = calibrated(tmp_path)
    run = tmp_path / "run"
    (run / "best").mkdir(parents=True)
    with pytest.raises(DataError, match=f"no {LOOP_CALIBRATION_FILE}"):
        LoopClosureDetector(StoredVectors(64), calibration=run)
    save_calibration(calibration, run / LOOP_CALIBRATION_FILE)
    detector = LoopClosureDetector(StoredVectors(64), calibration=run)
    assert detector.threshold == calibration.threshold and detector.sequence_length == 10


def test_a_run_whose_scores_depart_from_the_calibration_warns_once(tmp_path, caplog):
    calibration, first, second = calibrated(tmp_path, n=150)
    path = save_calibration(calibration, tmp_path / "cal.yaml")

    def run(frames):
        caplog.clear()
        detector = LoopClosureDetector(StoredVectors(64), calibration=str(path))
        with caplog.at_level(logging.WARNING, logger="fdnet"):
            for i, vector in enumerate(frames):
                detector.process_vector(vector, name=f"f{i}", new_segment=i == len(frames) // 2)
        return detector, [r.getMessage() for r in caplog.records if "depart" in r.getMessage()]

    # the same kind of route: no warning
    same, warnings = run(np.concatenate(slow_route(n=150, seed=5)))
    assert same.drift is None and not warnings
    # a robot slower for its frame rate than on the calibration loop: its own look-alikes stand
    # out more, and its rejected scores reach the calibration loop's top 5 % four times as often
    other, warnings = run(np.concatenate(slow_route(n=150, seed=5, persistence=0.97)))
    assert other.drift is not None and other.drift["share"] > 0.15 and len(warnings) == 1
    assert str(path) in warnings[0] and "stand out more" in warnings[0]


def test_a_threshold_for_precision_one_is_set_for_a_thousand_wrong_frames_not_just_this_loops():
    from fdnet.decisions.calibration import tail_threshold

    rng = np.random.default_rng(0)
    # an exponential tail of scale 1: fewer than one of 1000 draws above ln(1000) ~ 6.9
    tail = tail_threshold(rng.exponential(1.0, 200))
    assert 5.5 < tail["threshold"] < 8.5 and 0.7 < tail["beta"] < 1.4
    assert tail_threshold(rng.exponential(1.0, 10)) is None
    # on a loop where the most confident wrong frame already lies above that level, it is kept
    calibration, *_ = calibrated(None, n=80)
    assert calibration.threshold > calibration.measured_on["wrong_score_tail"]["threshold"]
    assert not calibration.notes
    # where it lies below, the threshold is raised to it, and the calibration says so
    from fdnet.decisions.loop_evaluation import calibrate_decisions

    first, second = slow_route(n=150, seed=2)
    detector = drive(first, second)
    raised = calibrate_decisions(detector.decisions, revisit_truth(150), detector, 1.0)
    tail = raised.measured_on["wrong_score_tail"]
    assert raised.threshold == tail["threshold"] and "raised from" in raised.notes[0]
    assert raised.precision == 1.0
