"""Loop closure measured: every frame's decision against ground truth (:func:`evaluate_decisions`)
and the threshold that reaches a target precision on a traverse (:func:`calibrate_decisions`).

Queries are the traverse's frames in order, references the database's places by index; each
frame's true matches are cut to the places it could search. The metrics are those of
:mod:`fdnet.metrics` (recall over queries) over each frame's acceptance score and the
place its rule vouches for, so a loop's R@100P means what a pair's does.
"""

from __future__ import annotations

import math
from collections import Counter
from typing import TYPE_CHECKING, Sequence

import numpy as np

from fdnet.decisions.loop_records import FrameDecision
from fdnet.errors import DataError

if TYPE_CHECKING:
    from fdnet.decisions.loop_closure import LoopClosureDetector


def _evaluable(decisions: Sequence[FrameDecision], ground_truth):
    """(the frames that had a place to search, their ground truth cut to those places). Frames a
    gate held (uninformative) stay in: a revisit the detector could not close is a miss."""
    from fdnet.data.groundtruth import GroundTruth

    if ground_truth.num_queries != len(decisions):
        raise DataError(
            f"the ground truth has {ground_truth.num_queries} queries but the traverse has " f"{len(decisions)} frames"
        )
    evaluated = [d for d in decisions if d.searchable > 0]
    if not evaluated:
        raise DataError("no frame had a place to search (exclude-last covers the whole traverse): nothing to evaluate")
    positives = [ground_truth.positives[d.query_index] for d in evaluated]
    positives = [p[p < d.searchable] for p, d in zip(positives, evaluated)]
    truth = GroundTruth(
        positives,
        ground_truth.num_references,
        f"{ground_truth.description}; true matches cut to each frame's searchable places",
    )
    if not truth.has_match.any():
        raise DataError(
            f"no frame revisits a place it could search ({ground_truth.description}; frames after "
            "exclude-last): nothing to evaluate. Does the traverse return to a place it saw before?"
        )
    return evaluated, truth


def reachable_recall(evaluated: Sequence[FrameDecision], correct, revisit, score) -> dict:
    """Where the revisiting frames' recall goes, whatever the threshold: each revisit either
    vouched for the right place, vouched for a wrong one, was held by a gate (by reason: the
    robot still, an uninformative frame, a sequence not yet complete after a seam...) or had its
    candidate held back by the consistency gate. ``recall_ceiling`` (right / revisits) is the
    most recall any threshold can reach, R@100P included: it says how much of a shortfall is
    the ranking's and how much is frames that never decided."""
    revisit = np.asarray(revisit, dtype=bool)
    gate = np.array([d.gated for d in evaluated], dtype=object)
    decided = (gate == "") & np.isfinite(score)
    right = int((decided & correct & revisit).sum())
    revisits = int(revisit.sum())
    reasons = Counter(gate[revisit & (gate != "")])
    return {
        "revisits": revisits,
        "right_place": right,
        "wrong_place": int((decided & ~correct & revisit).sum()),
        "gated": dict(sorted(reasons.items())),
        "held_by_consistency": int((~decided & (gate == "") & revisit).sum()),
        "recall_ceiling": right / revisits if revisits else 0.0,
    }


def evaluate_decisions(decisions: Sequence[FrameDecision], ground_truth, threshold: float, rule: str) -> dict:
    """Every frame's decision against ``ground_truth`` (queries = this traverse's frames in
    order, references = the database's places by index), with the metrics of
    :func:`fdnet.metrics.evaluate_retrieval` over each frame's acceptance score and
    the place it vouches for (recall over queries: R@100P, R@99P, R@95P, P@maxR, AUC-PR,
    Recall@1), and the operating point at ``threshold`` (what the run accepted).

    A frame can only close a loop with a place it was allowed to search, so each frame's true
    matches are cut to the places searchable for it (its own last frames are no revisit); frames
    with nothing to search are left out (they can neither find nor miss anything).
    """
    from fdnet.metrics import RECALL_OVER_QUERIES, Accepted, evaluate_retrieval

    evaluated, truth = _evaluable(decisions, ground_truth)
    score = np.array([d.score for d in evaluated], dtype=np.float64)
    match = np.array([d.match for d in evaluated], dtype=np.int64)
    metrics = evaluate_retrieval(
        np.array([[d.best] for d in evaluated]),
        np.array([[d.best_similarity] for d in evaluated]),
        truth,
        protocol=RECALL_OVER_QUERIES,
        ns=(1,),
        accepted=Accepted(score, match, rule),
    )
    accepted = score >= float(threshold)
    correct = truth.correct_mask(match[:, None])[:, 0]
    true_closures = int((accepted & correct).sum())
    revisits = int(truth.has_match.sum())
    first_pass = ~truth.has_match
    gated = np.array([bool(d.gated) for d in evaluated])
    return {
        "frames": len(decisions),
        "frames_evaluated": len(evaluated),
        "frames_with_revisit": revisits,
        "ground_truth": truth.description,
        "metrics": metrics.to_dict(include_curve=False),
        "at_threshold": {
            "threshold": float(threshold),
            "accepted": int(accepted.sum()),
            "true": true_closures,
            "false": int(accepted.sum()) - true_closures,
            "precision": true_closures / int(accepted.sum()) if accepted.any() else 1.0,
            "recall": true_closures / revisits,
            # frames that revisit no searchable place (a route's first pass): every closure
            # accepted there is false; and the revisits: right, wrong place, or missed
            "first_pass": {"frames": int(first_pass.sum()), "accepted": int((accepted & first_pass).sum())},
            "revisits": {
                "frames": revisits,
                "true": true_closures,
                "wrong_place": int((accepted & ~correct & ~first_pass).sum()),
                "missed": int((~accepted & ~first_pass).sum()),
            },
        },
        "gated_frames": int(gated.sum()),
        "reachable": reachable_recall(evaluated, correct, truth.has_match, score),
        "note": (
            "recall_at_n and R@xP count the frames that revisit a place they could search; "
            "metrics.top1_accuracy counts every evaluated frame, the first pass included, where no "
            "answer can be right, so it is lower"
        ),
    }


def frame_outcomes(decisions: Sequence[FrameDecision], ground_truth):
    """(acceptance scores, whether the place each vouches for is right, the ground truth cut to
    what each could search) over the frames that had a place to search, as evaluation and
    calibration count them."""
    evaluated, truth = _evaluable(decisions, ground_truth)
    score = np.array([d.score for d in evaluated], dtype=np.float64)
    match = np.array([d.match for d in evaluated], dtype=np.int64)
    return score, truth.correct_mask(match[:, None])[:, 0], truth


def calibrate_decisions(
    decisions: Sequence[FrameDecision],
    ground_truth,
    detector: "LoopClosureDetector",
    target_precision: float,
    measured_on: dict | None = None,
):
    """A :class:`~fdnet.decisions.calibration.Calibration` of ``detector``'s rule from one
    traverse with ground truth: the threshold on its frames' acceptance scores that reaches
    ``target_precision`` with the largest recall
    (:func:`fdnet.decisions.calibration.choose_threshold`), over the same frames and true
    matches as :func:`evaluate_decisions`. Calibrating on the robot's own kind of traverse
    matters: a cross-condition pair has none of the look-alike places a traverse meets in its
    own recent past (docs/loop-closure.md)."""
    from datetime import datetime, timezone

    from fdnet.decisions.calibration import (
        Calibration,
        Threshold,
        check_target,
        choose_threshold,
        fit_probability,
        score_distribution,
        tail_threshold,
    )
    from fdnet.version import __version__

    target = check_target(target_precision)
    score, correct, truth = frame_outcomes(decisions, ground_truth)
    chosen = choose_threshold(score, correct, truth.has_match, target)
    notes = []
    # the exponential tail of the wrong scores: it raises a threshold for precision 1.0, and it
    # gives p_correct's top blocks the wrong frames the loop is expected to hold there
    wrong_tail = tail_threshold(score[~correct])
    tail = wrong_tail if target == 1.0 else None
    if tail is not None and math.isfinite(chosen.threshold) and tail["threshold"] > chosen.threshold:
        at = score >= tail["threshold"]
        right = int((at & correct).sum())
        notes.append(
            f"raised from {chosen.threshold:.6g} (just above this traverse's most confident wrong frame, "
            f"of {tail['wrong']}) to {tail['threshold']:.6g}, where fewer than one wrong closure is expected "
            f"among {tail['frames']} wrong frames (exponential tail of this traverse's wrong scores)"
        )
        chosen = Threshold(
            tail["threshold"],
            right / int(at.sum()) if at.any() else 1.0,
            right / max(int(truth.has_match.sum()), 1),
            int(at.sum()),
        )
    if not math.isfinite(chosen.threshold):
        notes.append(
            f"no threshold reaches precision {target:g} on this traverse (its most confident frame is "
            "already wrong): nothing will be accepted"
        )
    length = detector.sequence_length
    where = {
        "loop_closure": True,
        "ground_truth": truth.description,
        "exclude_last": detector.exclude_last,
        "gates": detector.gates.to_dict(),
        "frames": len(decisions),
        "frames_evaluated": len(score),
        "sequence_length": length,
        **({"wrong_score_tail": tail} if tail is not None else {}),
        **(measured_on or {}),
    }
    return Calibration(
        rule=detector.spec.name,
        settings=detector.spec.settings,
        threshold=chosen.threshold,
        target_precision=target,
        precision=chosen.precision,
        recall=chosen.recall,
        accepted=chosen.accepted,
        num_queries=len(score),
        method=detector.descriptor.name,
        fingerprint=detector.descriptor.fingerprint(),
        sequence_length=length,
        measured_on=where,
        created=datetime.now(timezone.utc).isoformat(timespec="seconds"),
        fdnet_version=__version__,
        notes=notes,
        probability=fit_probability(score, correct, wrong_tail),
        score_distribution=score_distribution(score, chosen.threshold),
    )
