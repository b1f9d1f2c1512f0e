"""Calibrate an acceptance rule on an evaluation split: describe the split's images, score every
query with the rule (:mod:`fdnet.decisions.acceptance`) and choose the threshold that reaches a
target precision (:func:`fdnet.decisions.calibration.choose_threshold`). ``fdnet calibrate``'s
work; the :class:`~fdnet.decisions.calibration.Calibration` it returns is what every command
applies."""

from __future__ import annotations

import math
from datetime import datetime, timezone
from typing import Callable, Sequence

from fdnet.decisions.acceptance import (
    AcceptanceSpec,
    Candidates,
    decide,
    parse_acceptance,
)
from fdnet.decisions.calibration import (
    Calibration,
    candidate_specs,
    check_target,
    choose_threshold,
)
from fdnet.descriptors.pipeline import PipelineSettings
from fdnet.evaluation.experiment import ScoringSettings, evaluate_method
from fdnet.matching.sequence import check_sequence_length
from fdnet.version import __version__


def calibrate(descriptor, split, spec: AcceptanceSpec | str, target_precision: float, sequence_length: int = 1,
              pipeline: PipelineSettings | None = None, log: Callable[[str], None] | None = None,
              choose: dict[str, Sequence] | None = None) -> Calibration:
    """Run ``descriptor`` on ``split`` (an :class:`~fdnet.data.split.EvaluationSplit`), score every
    query with ``spec`` and choose the threshold reaching ``target_precision``. ``pipeline``: how
    images are decoded and described (default: batches of 64, no progress bar).

    ``choose`` (e.g. ``{"radius": [0, 1, 2, 3, 5]}``) also chooses rule settings on this split:
    every combination is scored on the same candidates (retrieved once, as deep as the deepest
    needs) and the one whose threshold reaches the target with the largest recall is kept (ties:
    the first listed); the recall of every combination is recorded in the calibration's
    ``measured_on`` (with the split, its ground truth and the sequence length; a caller adds
    where the data came from)."""
    target = check_target(target_precision)
    sequence_length = check_sequence_length(sequence_length)
    if isinstance(spec, str):
        spec = parse_acceptance(spec)
    specs = candidate_specs(spec, choose)
    for candidate in specs:  # e.g. radius_m on image folders: refused before anything is described
        candidate.check_available({"images"}, "calibration on image folders")
    say = log or (lambda message: None)
    deepest = max(specs, key=lambda s: s.depth)
    result = evaluate_method(descriptor, split, ScoringSettings(acceptance=[deepest]),
                             pipeline, sequence_length=sequence_length, log=log)
    gt = split.ground_truth
    candidates = Candidates(result.retrieved, result.scores, similarity_ceiling=float(descriptor.similarity_ceiling),
                            query_paths=result.query_paths, reference_paths=result.reference_paths)
    tried = []
    best = None
    for candidate in specs:
        decision = decide(candidate, candidates)
        correct = gt.correct_mask(decision.match[:, None])[:, 0]
        threshold = choose_threshold(decision.score, correct, gt.has_match, target)
        tried.append(({k: candidate.settings[n][k] for n, _ in candidate.parts for k in (choose or {})
                       if k in candidate.settings[n]}, threshold))
        if best is None or threshold.recall > best[1].recall:
            best = (candidate, threshold)
    spec, chosen = best
    notes = []
    if choose:
        say("; ".join(f"{', '.join(f'{k}={v}' for k, v in values.items())}: recall {t.recall:.3f}"
                      for values, t in tried) + f" -> chosen {tried[specs.index(spec)][0]}")
    if not math.isfinite(chosen.threshold):
        notes.append(f"no threshold reaches precision {target:g} on this split (the most confident query is "
                     f"already wrong): nothing will be accepted")
        say(notes[-1])
    where = {"data": split.description, "ground_truth": gt.description, "num_references": int(gt.num_references),
             "sequence_length": int(sequence_length)}
    if choose:
        where["chosen_from"] = [{**values, "recall": t.recall, "precision": t.precision} for values, t in tried]
    return Calibration(
        rule=spec.name, settings=spec.settings, threshold=chosen.threshold, target_precision=target,
        precision=chosen.precision, recall=chosen.recall, accepted=chosen.accepted,
        num_queries=int(gt.num_queries), method=descriptor.name, fingerprint=descriptor.fingerprint(),
        sequence_length=int(sequence_length), measured_on=where,
        created=datetime.now(timezone.utc).isoformat(timespec="seconds"), fdnet_version=__version__, notes=notes)
