"""The online loop-closure detector on made-up routes where the revisits are known."""

import csv
import json

import numpy as np
import pytest

from fdnet.data.groundtruth import GroundTruth
from fdnet.decisions.loop_closure import EVENT_COLUMNS, Closure, FrameDecision, LoopClosureDetector
from fdnet.decisions.loop_evaluation import evaluate_decisions
from fdnet.decisions.loop_events import EventLog
from fdnet.decisions.loop_gates import LoopGates
from fdnet.descriptors.classic import HOGDescriptor, RawThumbnail
from fdnet.errors import ConfigError, DataError
from fdnet.matching.database import PlaceDatabase

PLACES = 12


def traverse_settings(events_csv, events_jsonl=None, resume=False, batch_size=16, workers=None, **detector):
    """run_traverse's settings object from one flat set of keywords (the detector's fields among them)."""
    from fdnet.decisions.loop_settings import LoopClosureSettings, TraverseSettings
    from fdnet.descriptors.pipeline import PipelineSettings

    return TraverseSettings(
        events_csv,
        LoopClosureSettings(**detector),
        PipelineSettings(batch_size, workers),
        events_jsonl=events_jsonl,
        resume=resume,
    )


def places(seed=0, n=PLACES):
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, size=(32, 64, 3)).astype(np.uint8) for _ in range(n)]


def seen_again(image, seed):
    """The same place on another day: a little noise and a brightness change."""
    noise = np.random.default_rng(seed).normal(0, 12, size=image.shape)
    return np.clip(image * 0.9 + 10 + noise, 0, 255).astype(np.uint8)


def revisit_route(seed=0):
    """PLACES new places, then every one of them again in the same order."""
    first = places(seed)
    return first + [seen_again(im, 100 + i) for i, im in enumerate(first)]


def run(frames, **settings):
    settings = {"exclude_last": 3, "rule": "margin", "threshold": 0.2, **settings}
    detector = LoopClosureDetector(RawThumbnail(), **settings)
    events = [detector.process(image, name=f"frame_{i}") for i, image in enumerate(frames)]
    return detector, events


def test_a_route_that_revisits_its_places_closes_a_loop_at_every_revisit_and_nowhere_else():
    detector, events = run(revisit_route())
    assert all(e is None for e in events[:PLACES])
    closures = events[PLACES:]
    assert all(c is not None for c in closures)
    assert [c.match_index for c in closures] == list(range(PLACES))
    assert [c.query_index for c in closures] == list(range(PLACES, 2 * PLACES))
    assert all(c.score >= 0.2 and c.rule == "margin" and c.threshold == 0.2 for c in closures)
    assert detector.closures == closures and detector.places == 2 * PLACES


def test_sequence_scores_close_the_same_loops():
    detector, events = run(revisit_route(), sequence_length=4)
    assert all(e is None for e in events[:PLACES])
    assert [e.match_index for e in events[PLACES:]] == list(range(PLACES))
    # a sequence running off the start of the map counts its missing frames as neutral: the
    # first revisits' scores grow as the revisit's sequence fills (0.23, 0.48, 0.73, then ~0.98)
    scores = [d.score for d in detector.decisions[PLACES : PLACES + 4]]
    assert scores == sorted(scores) and scores[0] < 0.4 and scores[3] > 0.9


def test_the_detector_never_looks_at_a_future_frame():
    route = revisit_route()
    for rule, length in (("margin", 1), ("raw", 1), ("margin", 4)):
        kw = {"rule": rule, "sequence_length": length, "threshold": 0.2 if rule == "margin" else 0.6}
        reference, ref_events = run(route, **kw)
        for cut in (PLACES + 2, PLACES + 7):
            # the same frames up to `cut`, then an entirely different future
            changed = route[: cut + 1] + places(seed=99, n=len(route) - cut - 1)
            other, other_events = run(changed, **kw)
            assert other_events[: cut + 1] == ref_events[: cut + 1]
            # repr: exact for floats, and NaN (no candidate yet) equals NaN
            assert list(map(repr, other.decisions[: cut + 1])) == list(map(repr, reference.decisions[: cut + 1]))
            assert other.decisions[cut + 1 :] != reference.decisions[cut + 1 :]
        assert any(e is not None for e in ref_events)


def test_the_last_frames_are_never_candidates():
    detector, _ = run(revisit_route(), exclude_last=5)
    searchable = [d.searchable for d in detector.decisions]
    assert searchable == [0] * 6 + list(range(1, 2 * PLACES - 5))
    assert all(d.match < d.searchable for d in detector.decisions if d.match >= 0)
    # a frame with nothing to search decides nothing
    assert detector.decisions[0] == FrameDecision(0, -1, detector.decisions[0].score, False, 0)
    assert np.isnan(detector.decisions[0].score)


def test_a_database_from_an_earlier_session_is_searched_from_the_first_frame(tmp_path):
    route = revisit_route()
    path = tmp_path / "map.db"
    with LoopClosureDetector(RawThumbnail(), path, exclude_last=3, rule="margin", threshold=0.2) as first:
        assert [first.process(im, name=f"day1/{i}") for i, im in enumerate(route[:PLACES])] == [None] * PLACES
    with LoopClosureDetector(RawThumbnail(), path, exclude_last=3, rule="margin", threshold=0.2) as second:
        events = [second.process(im, name=f"day2/{i}", timestamp=float(i)) for i, im in enumerate(route[PLACES:])]
    assert [e.match for e in events] == [f"day1/{i}" for i in range(PLACES)]
    assert events[0].query_index == 0 and events[0].timestamp == 0.0
    with PlaceDatabase.open(path) as db:
        assert len(db) == 2 * PLACES
        assert db.metadata[PLACES + 1]["timestamp"] == 1.0


def test_time_neighbourhoods_use_the_frames_timestamps():
    route = revisit_route()
    detector = LoopClosureDetector(
        RawThumbnail(), exclude_last=3, rule="margin", rule_settings={"radius_s": 0.5}, threshold=0.2
    )
    events = [detector.process(im, timestamp=0.25 * i) for i, im in enumerate(route)]
    assert [e.match_index for e in events[PLACES:]] == list(range(PLACES))
    assert events[-1].match_timestamp == 0.25 * (PLACES - 1)


def test_events_carry_the_positions_of_frame_and_place(tmp_path):
    route = revisit_route()
    detector = LoopClosureDetector(RawThumbnail(), exclude_last=3, rule="margin", threshold=0.2)
    # the second pass drives the same line 1 m to the side
    events = [detector.process(im, position=(10.0 * (i % PLACES), float(i >= PLACES))) for i, im in enumerate(route)]
    closure = events[-1]
    assert (closure.x, closure.y, closure.match_x, closure.match_y) == (
        10.0 * (PLACES - 1),
        1.0,
        10.0 * (PLACES - 1),
        0.0,
    )
    with EventLog(tmp_path / "e.csv") as log:
        log.write(closure)
    row = next(csv.DictReader(open(tmp_path / "e.csv", newline="")))
    assert (row["x"], row["y"], row["match_x"], row["match_y"]) == ("110.000000", "1.000000", "110.000000", "0.000000")


def test_bad_input_is_refused_with_a_message():
    with pytest.raises(ConfigError, match="unknown acceptance rule 'best'"):
        LoopClosureDetector(RawThumbnail(), exclude_last=3, rule="best", threshold=0.1)
    with pytest.raises(ConfigError, match="threshold"):
        LoopClosureDetector(RawThumbnail(), exclude_last=3, rule="margin")
    with pytest.raises(ConfigError, match="exclude-last"):
        LoopClosureDetector(RawThumbnail(), exclude_last=-1, rule="margin", threshold=0.1)
    with pytest.raises(ConfigError, match="sequence length"):
        LoopClosureDetector(RawThumbnail(), exclude_last=1, rule="margin", threshold=0.1, sequence_length=0)
    db = PlaceDatabase.for_descriptor(RawThumbnail())
    with pytest.raises(ConfigError, match="fingerprint mismatch"):
        LoopClosureDetector(HOGDescriptor(), db, exclude_last=1, rule="margin", threshold=0.1)
    detector = LoopClosureDetector(RawThumbnail(), exclude_last=0, rule="margin", threshold=0.1)
    detector.process(places()[0], name="a")
    with pytest.raises(DataError, match="already holds a place named 'a'"):
        detector.process(places()[1], name="a")
    with pytest.raises(DataError, match=r"\(H, W, 3\)"):
        detector.process(np.zeros((5, 5)))


def test_a_rule_that_verifies_images_needs_frames_given_as_files():
    # without the recent-past exclusion the second frame searches the first
    detector = LoopClosureDetector(
        RawThumbnail(), rule="margin+verified", threshold=0.1, gates=LoopGates(similar_past=False)
    )
    detector.process(places()[0])
    with pytest.raises(ConfigError, match="no image file"):
        detector.process(places()[1])


def test_events_are_on_disk_when_written(tmp_path):
    event = Closure(5, "b.png", 1, "a.png", 0.25, 0.9, "margin", 0.2, 2.5, None)
    with EventLog(tmp_path / "e.csv", tmp_path / "e.jsonl") as log:
        log.write(event)
        # read through another handle while the log is still open: nothing waits in a buffer
        rows = list(csv.DictReader(open(tmp_path / "e.csv", newline="")))
        lines = (tmp_path / "e.jsonl").read_text().splitlines()
    assert tuple(rows[0]) == EVENT_COLUMNS
    assert rows == [
        {
            "query_index": "5",
            "query": "b.png",
            "match_index": "1",
            "match": "a.png",
            "score": "0.250000",
            "similarity": "0.900000",
            "rule": "margin",
            "threshold": "0.200000",
            "timestamp": "2.500000",
            "match_timestamp": "",
            "x": "",
            "y": "",
            "match_x": "",
            "match_y": "",
            "p_correct": "",
        }
    ]
    assert [json.loads(line) for line in lines] == [event.to_dict()]
    with pytest.raises(ConfigError, match="two different files"):
        EventLog(tmp_path / "x.csv", tmp_path / "x.csv")


def test_evaluation_by_hand():
    # frames 0..4; frame 3 revisits place 0, frame 4 revisits place 1; exclude-last cut applies
    decisions = [
        FrameDecision(0, -1, float("nan"), False, 0),
        FrameDecision(1, 0, 0.05, False, 1, 0, 0.5),  # no revisit: a false positive if accepted
        FrameDecision(2, 0, 0.30, True, 1, 0, 0.6),  # no revisit (its true match 1 is not searchable)
        FrameDecision(3, 0, 0.40, True, 2, 0, 0.9),  # correct
        FrameDecision(4, 2, 0.10, False, 3, 1, 0.8),  # rule vouches for 2, the truth is 1
    ]
    truth = GroundTruth([[], [], [1], [0], [1]], 5)
    out = evaluate_decisions(decisions, truth, threshold=0.2, rule="margin")
    assert out["frames_evaluated"] == 4 and out["frames_with_revisit"] == 2
    # sorted by score: 0.40 correct, 0.30 wrong -> R@100P = 1/2
    assert out["metrics"]["recall_at_100_precision"] == 0.5
    assert out["metrics"]["recall_at_n"]["1"] == 1.0  # best by similarity is right for frames 3 and 4
    assert out["at_threshold"] == {
        "threshold": 0.2,
        "accepted": 2,
        "true": 1,
        "false": 1,
        "precision": 0.5,
        "recall": 0.5,
        # frames 1 and 2 revisit nothing searchable: frame 2's closure is false
        "first_pass": {"frames": 2, "accepted": 1},
        "revisits": {"frames": 2, "true": 1, "wrong_place": 0, "missed": 1},
    }
    # whatever the threshold: frame 3 vouched for the right place, frame 4 for a wrong one
    assert out["reachable"] == {
        "revisits": 2,
        "right_place": 1,
        "wrong_place": 1,
        "gated": {},
        "held_by_consistency": 0,
        "recall_ceiling": 0.5,
    }
    with pytest.raises(DataError, match="3 queries but the traverse has 5"):
        evaluate_decisions(decisions, GroundTruth([[], [], []], 5), 0.2, "margin")
    with pytest.raises(DataError, match="no frame revisits"):
        evaluate_decisions(decisions, GroundTruth([[], [], [], [], []], 5), 0.2, "margin")


def test_reachable_recall_counts_gated_and_held_revisits():
    # four revisits: one right, one gated as still, one gated as uninformative, one whose candidate
    # the consistency gate held back (score -inf, no gate); a first-pass frame counts nowhere
    inf = float("inf")
    decisions = [
        FrameDecision(0, -1, float("nan"), False, 0),
        FrameDecision(1, 0, 0.5, True, 1, 0, 0.9),  # first pass: revisits nothing
        FrameDecision(2, 0, 0.4, True, 2, 0, 0.9),  # right
        FrameDecision(3, -1, -inf, False, 3, 1, 0.7, gated="still"),
        FrameDecision(4, -1, -inf, False, 4, 1, 0.2, gated="uninformative"),
        FrameDecision(5, 1, -inf, False, 5, 1, 0.8, rule_score=0.3),  # held by consistency
    ]
    truth = GroundTruth([[], [], [0], [1], [1], [1]], 6)
    out = evaluate_decisions(decisions, truth, threshold=0.2, rule="margin")
    assert out["reachable"] == {
        "revisits": 4,
        "right_place": 1,
        "wrong_place": 0,
        "gated": {"still": 1, "uninformative": 1},
        "held_by_consistency": 1,
        "recall_ceiling": 0.25,
    }
    assert out["metrics"]["recall_at_100_precision"] <= out["reachable"]["recall_ceiling"]


def calibration_for(descriptor, threshold=0.2, rule="margin", sequence_length=1):
    from fdnet.decisions.acceptance import parse_acceptance
    from fdnet.decisions.calibration import Calibration

    return Calibration(
        rule=rule,
        settings=parse_acceptance(rule).settings,
        threshold=threshold,
        target_precision=1.0,
        precision=1.0,
        recall=0.5,
        accepted=3,
        num_queries=10,
        method=descriptor.name,
        fingerprint=descriptor.fingerprint(),
        sequence_length=sequence_length,
    )


def test_a_calibration_gives_rule_and_threshold(tmp_path):
    from fdnet.decisions.calibration import save_calibration

    path = save_calibration(calibration_for(RawThumbnail()), tmp_path / "calibration.yaml")
    by_hand, expected = run(revisit_route())
    detector = LoopClosureDetector(RawThumbnail(), exclude_last=3, calibration=path)
    assert (detector.spec.name, detector.threshold) == ("margin", 0.2)
    assert [detector.process(im, name=f"frame_{i}") for i, im in enumerate(revisit_route())] == expected
    # the database's stored calibration is used when neither threshold nor calibration is given
    db = PlaceDatabase.for_descriptor(RawThumbnail())
    db.set_metadata("calibration", calibration_for(RawThumbnail(), threshold=0.35).to_dict())
    assert LoopClosureDetector(RawThumbnail(), db, exclude_last=3).threshold == 0.35


def test_a_calibration_of_another_model_sequence_length_or_rule_is_refused(tmp_path):
    from fdnet.decisions.calibration import save_calibration

    other = save_calibration(calibration_for(HOGDescriptor()), tmp_path / "hog.yaml")
    with pytest.raises(ConfigError, match="calibrated for method 'hog'"):
        LoopClosureDetector(RawThumbnail(), exclude_last=3, calibration=other)
    single = save_calibration(calibration_for(RawThumbnail()), tmp_path / "raw.yaml")
    with pytest.raises(ConfigError, match="sequence-length"):
        LoopClosureDetector(RawThumbnail(), exclude_last=3, calibration=single, sequence_length=5)
    with pytest.raises(ConfigError, match="calibrates rule 'margin'"):
        LoopClosureDetector(RawThumbnail(), exclude_last=3, calibration=single, rule="ratio")
    with pytest.raises(ConfigError, match="not both"):
        LoopClosureDetector(RawThumbnail(), exclude_last=3, calibration=single, threshold=0.1)


def test_storing_frames_in_batches_changes_no_decision(tmp_path):
    route = revisit_route()
    _, expected = run(route)
    detector = LoopClosureDetector(
        RawThumbnail(), tmp_path / "map.db", exclude_last=3, rule="margin", threshold=0.2, commit_every=5
    )
    events = [detector.process(im, name=f"frame_{i}") for i, im in enumerate(route[:7])]
    assert len(detector.database) == 5 and detector.places == 7  # two frames wait for the next batch
    events += [detector.process(im, name=f"frame_{i}") for i, im in enumerate(route[7:], start=7)]
    detector.close()
    assert events == expected
    with PlaceDatabase.open(tmp_path / "map.db") as db:
        assert db.names == [f"frame_{i}" for i in range(len(route))]


def test_calibrating_on_a_traverse_picks_the_threshold_of_the_target_precision():
    from fdnet.decisions.loop_evaluation import calibrate_decisions

    decisions = [
        FrameDecision(0, -1, float("nan"), False, 0),
        FrameDecision(1, 0, 0.05, False, 1, 0, 0.5),
        FrameDecision(2, 0, 0.30, False, 1, 0, 0.6),  # wrong: frame 2 revisits nothing it could search
        FrameDecision(3, 0, 0.40, False, 2, 0, 0.9),  # right
        FrameDecision(4, 1, 0.10, False, 3, 1, 0.8),  # right
    ]
    truth = GroundTruth([[], [], [1], [0], [1]], 5)
    detector = LoopClosureDetector(RawThumbnail(), exclude_last=1, rule="margin", threshold=float("inf"))
    exact = calibrate_decisions(decisions, truth, detector, 1.0)
    assert (exact.threshold, exact.precision, exact.recall) == (0.40, 1.0, 0.5)
    assert (exact.rule, exact.method, exact.sequence_length) == ("margin", "raw", 1)
    assert exact.fingerprint == RawThumbnail().fingerprint()
    loose = calibrate_decisions(decisions, truth, detector, 0.6)
    assert (loose.threshold, loose.recall) == (0.10, 1.0) and loose.precision == pytest.approx(2 / 3)
    # what it calibrates is what a detector then uses
    assert LoopClosureDetector(RawThumbnail(), exclude_last=1, calibration=exact).threshold == 0.40


def test_event_names_a_spreadsheet_would_run_are_quoted(tmp_path):
    event = Closure(5, "=b.png", 1, "@a.png", 0.25, 0.9, "margin", 0.2, None, None)
    with EventLog(tmp_path / "e.csv") as log:
        log.write(event)
    rows = list(csv.DictReader(open(tmp_path / "e.csv", newline="")))
    assert (rows[0]["query"], rows[0]["match"], rows[0]["score"]) == ("'=b.png", "'@a.png", "0.250000")


# ---------------------------------------------------------------------- the gates in the detector
def tunnel(n, seed):
    """n frames inside a tunnel: nearly black (mean about 8 of 255), the same faint lights each time."""
    lights = np.random.default_rng(1234).integers(0, 16, size=(32, 64, 3))
    noise = np.random.default_rng(seed).integers(0, 2, size=(n, 32, 64, 3))
    return [(lights + noise[i]).astype(np.uint8) for i in range(n)]


def stop(image, n, seed):
    """n frames of a robot standing still: the same view, a little sensor noise."""
    rng = np.random.default_rng(seed)
    return [
        np.clip(image.astype(int) + rng.integers(-2, 3, size=image.shape), 0, 255).astype(np.uint8) for _ in range(n)
    ]


def route_with_a_tunnel_a_stop_and_a_revisit():
    """places 0-11, a tunnel (12-16), new places (17-22), a stop (23-32), another tunnel (33-37),
    then places 0-11 again (38-49). Only 38-49 are revisits."""
    first = places(seed=0)
    more = places(seed=5, n=6)
    frames = first + tunnel(5, 1) + more + stop(places(seed=9, n=1)[0], 10, 2) + tunnel(5, 3)
    return frames + [seen_again(im, 200 + i) for i, im in enumerate(first)], len(frames)


def route_with_a_tunnel_a_stop_and_a_revisit_as_files(folder):
    """The same route written as PNG files in ``folder``: (frames, first revisit, folder)."""
    from PIL import Image

    frames, revisit = route_with_a_tunnel_a_stop_and_a_revisit()
    folder.mkdir()
    for i, image in enumerate(frames):
        Image.fromarray(image).save(folder / f"frame_{i:03d}.png")
    return frames, revisit, folder


@pytest.mark.parametrize("length", [1, 3])
def test_no_closure_from_a_tunnel_or_a_stop_and_the_revisit_closed(length):
    from fdnet.decisions.loop_gates import LoopGates

    frames, revisit = route_with_a_tunnel_a_stop_and_a_revisit()
    settings = {"exclude_last": 2, "rule": "raw", "threshold": 0.8, "sequence_length": length}
    gated, events = run(frames, **settings)
    closures = [e for e in events if e is not None]
    assert {c.query_index for c in closures} <= set(range(revisit, len(frames)))
    assert all(c.match_index == c.query_index - revisit for c in closures)
    assert len(closures) >= len(frames) - revisit - length  # every revisit once its sequence is in it
    assert gated.gate_counts["uninformative"] == 10 and gated.gate_counts["still_frames"] == 9
    # the same run with every gate off closes the second tunnel with the first and the stop with itself
    off = LoopGates(min_brightness=None, min_contrast=None, still_difference=None, similar_past=False)
    ungated, events = run(frames, gates=off, **settings)
    wrong = [e for e in events if e is not None and e.query_index < revisit]
    assert {e.query_index for e in wrong} & set(range(33, 38)) and {e.query_index for e in wrong} & set(range(23, 33))


def test_sequence_candidates_never_share_a_frame_with_the_query_sequence():
    frames = places(seed=3, n=40)
    for length, exclude in ((1, 0), (1, 4), (5, 0), (5, 3), (10, 2)):
        detector, _ = run(frames, exclude_last=exclude, sequence_length=length, rule="raw", threshold=2.0)
        for d in detector.decisions:
            # the query's sequence is frames t-L+1..t; a candidate ending at place r reads places
            # r-(L-1)*1.25..r; r < t-L+1-exclude keeps both apart by the exclusion window
            newest_searchable = d.searchable - 1
            assert newest_searchable < max(d.query_index - length + 1 - exclude, 0) or d.searchable == 0
            assert d.match < max(d.query_index - length + 1 - exclude, 0)


def test_uninformative_places_from_an_earlier_run_stay_out_of_the_map(tmp_path):
    frames, revisit = route_with_a_tunnel_a_stop_and_a_revisit()
    db = tmp_path / "map.db"
    with LoopClosureDetector(RawThumbnail(), db, exclude_last=2, rule="raw", threshold=0.8) as first:
        for i, image in enumerate(frames[:revisit]):
            first.process(image, name=f"day1_{i}")
    # a second session drives through the tunnel again: its frames neither match day 1's tunnel
    # (marked uninformative in the database) nor close anything themselves
    with LoopClosureDetector(RawThumbnail(), db, exclude_last=2, rule="raw", threshold=0.8) as second:
        events = [second.process(image, name=f"day2_{i}") for i, image in enumerate(tunnel(5, 7) + places(seed=0))]
    assert all(e is None for e in events[:5])
    assert [e.match_index for e in events[5:] if e is not None] == list(range(PLACES))


def test_resume_replays_to_the_events_of_an_uninterrupted_run(tmp_path):
    from fdnet.decisions.loop_traverse import run_traverse

    frames, revisit, folder = route_with_a_tunnel_a_stop_and_a_revisit_as_files(tmp_path / "route")
    settings = {"exclude_last": 2, "rule": "raw", "threshold": 0.8, "sequence_length": 3, "batch_size": 4, "workers": 0}
    whole = run_traverse(
        folder,
        RawThumbnail(),
        tmp_path / "whole.db",
        traverse_settings(events_csv=tmp_path / "whole.csv", events_jsonl=tmp_path / "whole.jsonl", **settings),
    )
    assert whole.closures >= 9 and revisit < 40

    class Killed(Exception):
        pass

    class DiesAfter(RawThumbnail):
        """Dies while describing the batch after ``frames`` frames, like a process killed there."""

        def __init__(self, frames):
            super().__init__()
            self.left = frames

        def describe(self, images):
            self.left -= len(images)
            if self.left < 0:
                raise Killed()
            return super().describe(images)

    for cut in (20, 40):  # batches of 4: in the first pass, and among the revisits
        db, csv_path, jsonl = tmp_path / f"cut{cut}.db", tmp_path / f"cut{cut}.csv", tmp_path / f"cut{cut}.jsonl"
        with pytest.raises(Killed):
            run_traverse(
                folder, DiesAfter(cut), db, traverse_settings(events_csv=csv_path, events_jsonl=jsonl, **settings)
            )
        with PlaceDatabase.open(db) as stored:
            assert len(stored) == cut
        # a kill between storing a frame and writing its event: the last event line is lost, and
        # a half line stands in for it
        lines = csv_path.read_text().splitlines(keepends=True)
        if len(lines) > 1:
            csv_path.write_text("".join(lines[:-1]) + lines[-1][:7])
        # without --resume the traverse is refused; with it, the events are those of one whole run
        with pytest.raises(DataError, match="give --resume"):
            run_traverse(folder, RawThumbnail(), db, traverse_settings(events_csv=csv_path, **settings))
        with PlaceDatabase.open(db) as handed:
            report = run_traverse(
                folder,
                RawThumbnail(),
                handed,
                traverse_settings(events_csv=csv_path, events_jsonl=jsonl, resume=True, **settings),
            )
            assert len(handed._map) == 0  # its places went to the detector once, not read again
        assert report.resumed_frames == cut and report.frames == len(frames)
        assert csv_path.read_text() == (tmp_path / "whole.csv").read_text()
        assert jsonl.read_text() == (tmp_path / "whole.jsonl").read_text()
        with PlaceDatabase.open(db) as stored, PlaceDatabase.open(tmp_path / "whole.db") as reference:
            assert stored.names == reference.names
            np.testing.assert_array_equal(stored.vectors, reference.vectors)
    with pytest.raises(ConfigError, match="needs the place database"):
        run_traverse(
            folder, RawThumbnail(), None, traverse_settings(events_csv=tmp_path / "x.csv", resume=True, **settings)
        )


@pytest.mark.parametrize("length", [1, 3])
def test_the_index_closes_the_same_loops_as_every_place(length):
    """search="index" (faiss IVF proposals, exact sequence scores of what it proposes) against
    search="exact" on a route with a tunnel, a stop and a revisit: the same closures."""
    frames, revisit = route_with_a_tunnel_a_stop_and_a_revisit()
    settings = {"exclude_last": 2, "rule": "raw", "threshold": 0.8, "sequence_length": length}
    exact, exact_events = run(frames, search="exact", **settings)
    indexed, indexed_events = run(frames, search="index", **settings)
    assert exact_events == indexed_events and any(e is not None for e in exact_events)
    assert indexed.candidates.indexed is not None and exact.candidates.indexed is None
    assert [d.match for d in indexed.decisions[revisit:]] == [d.match for d in exact.decisions[revisit:]]
    with pytest.raises(ConfigError, match="search must be one of"):
        run(frames[:2], search="faiss", **settings)


def test_auto_search_switches_to_the_index_at_its_size():
    frames = places(seed=4, n=30)
    detector, _ = run(frames, search="auto", index_from=20, rule="raw", threshold=2.0)
    indexed = detector.candidates.indexed
    assert indexed is not None and len(indexed) == 29  # every place but the newest
    small, _ = run(frames, search="auto", rule="raw", threshold=2.0)
    assert small.candidates.indexed is None


def test_resume_with_the_index_replays_the_same_events(tmp_path):
    from fdnet.decisions.loop_traverse import run_traverse

    frames, revisit, folder = route_with_a_tunnel_a_stop_and_a_revisit_as_files(tmp_path / "route")
    settings = {
        "exclude_last": 2,
        "rule": "raw",
        "threshold": 0.8,
        "sequence_length": 3,
        "batch_size": 4,
        "workers": 0,
        "search": "index",
    }
    whole = run_traverse(
        folder, RawThumbnail(), tmp_path / "whole.db", traverse_settings(events_csv=tmp_path / "whole.csv", **settings)
    )
    assert whole.closures >= 9
    # a run interrupted after 40 frames (among the revisits): the database holds those frames only
    with PlaceDatabase.open(tmp_path / "whole.db") as stored:
        vectors, names, metadata = stored.vectors, stored.names, stored.metadata
    with PlaceDatabase.create(tmp_path / "cut.db", RawThumbnail()) as cut:
        cut.add(vectors[:40], names[:40], metadata=metadata[:40])
    (tmp_path / "cut.csv").write_text("")
    run_traverse(
        folder,
        RawThumbnail(),
        tmp_path / "cut.db",
        traverse_settings(events_csv=tmp_path / "cut.csv", resume=True, **settings),
    )
    assert (tmp_path / "cut.csv").read_text() == (tmp_path / "whole.csv").read_text()


def test_an_array_and_the_same_pixels_as_a_file_give_the_same_decisions(tmp_path):
    """process(array) documented and equal to process(path): the array is resized as a file is
    (it gave 23 closures where the files gave 21 when arrays were resized another way)."""
    from PIL import Image

    rng = np.random.default_rng(5)
    big = [rng.integers(0, 256, size=(48, 96, 3)).astype(np.uint8) for _ in range(PLACES)]
    frames = big + [seen_again(im, 300 + i) for i, im in enumerate(big)]
    paths = []
    for i, image in enumerate(frames):
        paths.append(tmp_path / f"f{i:03d}.png")
        Image.fromarray(image).save(paths[-1])
    settings = {"exclude_last": 3, "rule": "margin", "threshold": 0.05}
    by_path = LoopClosureDetector(RawThumbnail(), **settings)
    by_array = LoopClosureDetector(RawThumbnail(), **settings)
    for path, image in zip(paths, frames):
        by_path.process(path, name=path.name)
        by_array.process(image, name=path.name)
    assert [repr(d) for d in by_path.decisions] == [repr(d) for d in by_array.decisions]
    assert len(by_path.closures) == len(by_array.closures) > 0
    with pytest.raises(DataError, match="must hold values in \\[0, 1\\]"):
        by_array.process(frames[0].astype(np.float32), name="scaled")
