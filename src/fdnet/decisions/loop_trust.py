"""What a loop-closure run trusts and how far: the acceptance rule and threshold (given, or from a
calibration file, a run directory or the database), the gates a loop calibration was measured
with, and the check that a run's scores still look like those its calibration was set against.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from fdnet.decisions.acceptance import AcceptanceSpec, parse_acceptance
from fdnet.decisions.calibration import checked_calibration
from fdnet.decisions.loop_gates import LoopGates
from fdnet.errors import ConfigError, DataError

logger = logging.getLogger("fdnet.decisions.loop_closure")

#: file name of a loop calibration in a run directory (``fdnet loop-closure --calibrate-out RUN_DIR``),
#: which loop closure with ``--checkpoint RUN_DIR`` uses when given no threshold
LOOP_CALIBRATION_FILE = "loop-calibration.yaml"

#: rejected frames after which a run compares its scores with its calibration's, and how often
DRIFT_AFTER, DRIFT_EVERY = 200, 50


def resolve_calibration(calibration, source: str | None):
    """(a Calibration, where it came from) for a Calibration, a calibration file or a run
    directory (its loop calibration, else its pair calibration, in RUN or RUN/best); (None,
    source) for None."""
    from fdnet.decisions.calibration import CALIBRATION_FILE, Calibration, load_calibration, stored_in_run

    if calibration is None or isinstance(calibration, Calibration):
        return calibration, source
    path = Path(calibration)
    if path.is_dir():
        found = stored_in_run(path, (LOOP_CALIBRATION_FILE, CALIBRATION_FILE))
        if found is None:
            raise DataError(
                f"{path}: no {LOOP_CALIBRATION_FILE} or {CALIBRATION_FILE} in this run directory (or its "
                "best/): calibrate on a loop with ground truth first, e.g. `fdnet loop-closure --data "
                f"ROUTE --conditions A,B --calibrate-out {path} ...`"
            )
        path = found
    return load_calibration(path), str(path)


def decision_rule(descriptor, sequence_length: int, rule, rule_settings, threshold, calibration, source=None):
    """(the acceptance spec, the threshold, the checked Calibration or None) of a detector: from
    ``calibration`` (which must be this model's and sequence length's, and agree with ``rule``
    when one is named), else ``rule`` and ``threshold``."""
    if calibration is not None:
        if threshold is not None:
            raise ConfigError(
                "give a threshold or a calibration file, not both (the calibration sets the " "threshold)"
            )
        calibrated, source = checked_calibration(calibration, descriptor, sequence_length, source)
        spec = calibrated.spec
        where = calibrated.measured_on or {}
        if not where.get("loop_closure"):
            logger.warning(
                f"{source}: this calibration was measured on a pair of traverses, not on a loop: "
                "in loop closure the robot's own recent frames are look-alikes a pair never shows, "
                "and its precision is not reached there (docs/loop-closure.md). Calibrate on a loop: "
                "fdnet loop-closure ... --ground-truth CSV --calibrate-out FILE"
            )
        logger.info(
            f"{source}: threshold {calibrated.threshold:.6g} of rule {spec.name} reached precision "
            f"{calibrated.precision:.3f} at recall {calibrated.recall:.3f} on {calibrated.accepted} "
            f"accepted of {calibrated.num_queries} frames where it was measured"
        )
        if rule is not None or rule_settings:
            wanted = (
                rule if isinstance(rule, AcceptanceSpec) else parse_acceptance(str(rule or spec.name), rule_settings)
            )
            if wanted.to_dict() != spec.to_dict():
                raise ConfigError(
                    f"{source}: calibrates rule {spec.name!r} with settings {spec.settings}, "
                    f"but rule {wanted.name!r} with settings {wanted.settings} was asked for; "
                    "its threshold means nothing for another rule"
                )
        return spec, float(calibrated.threshold), calibrated
    if threshold is None:
        raise ConfigError(
            "a loop closure needs an acceptance threshold: give one (--threshold T), a "
            "calibration file (--calibration FILE), or a database holding a calibration "
            "(`fdnet calibrate --db`); or calibrate on a loop with ground truth first, e.g. "
            "`fdnet loop-closure --data ROUTE --conditions A,B --calibrate-out RUN_DIR ...`, which "
            f"writes RUN_DIR/{LOOP_CALIBRATION_FILE} that runs with --checkpoint RUN_DIR use"
        )
    # +inf accepts nothing: a run that only measures (e.g. to calibrate: calibrate_decisions)
    if (
        isinstance(threshold, bool)
        or not isinstance(threshold, (int, float, np.floating, np.integer))
        or math.isnan(float(threshold))
        or float(threshold) == -math.inf
    ):
        raise ConfigError(f"threshold must be a number (+inf accepts nothing), got {threshold!r}")
    if rule is None:
        raise ConfigError("name the acceptance rule (e.g. rule='margin'); `fdnet loop-closure --accept RULE`")
    spec = rule if isinstance(rule, AcceptanceSpec) else parse_acceptance(str(rule), rule_settings)
    return spec, float(threshold), None


def calibrated_gates(calibration, gates: LoopGates | None, source: str | None) -> LoopGates:
    """The gates: given, else those a loop calibration was measured with (its threshold holds
    for them: the consistency gate changes what a score means), else the defaults. Gates
    that differ from a loop calibration's are refused."""
    calibrated = None
    if calibration is not None:
        stored = (calibration.measured_on or {}).get("gates")
        calibrated = LoopGates.from_dict(stored) if stored else None
    if gates is None:
        return calibrated or LoopGates()
    if calibrated is not None and calibrated != gates:
        changed = {k: (v, gates.to_dict()[k]) for k, v in calibrated.to_dict().items() if gates.to_dict()[k] != v}
        raise ConfigError(
            f"{source or 'the calibration'}: was measured with loop gates "
            + ", ".join(f"{k}={a}" for k, (a, _) in changed.items())
            + ", but "
            + ", ".join(f"{k}={b}" for k, (_, b) in changed.items())
            + " were asked for; its threshold holds for its own gates (leave the gates out to "
            "use them)"
        )
    return gates


class DriftCheck:
    """Warns once when a run's rejected scores reach into the upper tail of those its
    calibration loop rejected more often than they did there
    (:func:`fdnet.decisions.calibration.tail_departure`): this route's wrong candidates stand
    out more than the ones the threshold was set against, so its precision may not hold here.
    ``add`` takes each score under the threshold and counts it against the stored tail
    quantiles (constant work per frame, nothing kept per frame); ``drift`` is None until it
    warned."""

    def __init__(self, calibration, source: str):
        from fdnet.decisions.calibration import tail_quantiles

        self.calibration = calibration
        self.source = source
        self.stored = (calibration.score_distribution or {}) if calibration is not None else {}
        self.tails = tail_quantiles(self.stored)
        self.above = [0] * len(self.tails)
        self.count = 0
        self.drift: dict | None = None

    def add(self, score: float) -> None:
        from fdnet.decisions.calibration import tail_departure_of_counts

        if not self.tails or self.drift is not None:
            return
        self.count += 1
        for i, (_, quantile) in enumerate(self.tails):
            self.above[i] += score > quantile
        n = self.count
        if n < DRIFT_AFTER or n % DRIFT_EVERY:
            return
        departed = tail_departure_of_counts(self.tails, self.above, n)
        if departed is None:
            return
        stored = self.stored
        self.drift = {**departed, "frames": n, "calibration_frames": int(stored.get("frames", 0))}
        where = (self.calibration.measured_on or {}).get("ground_truth") or "its calibration loop"
        logger.warning(
            f"{self.source}: {100 * departed['share']:.0f} % of the scores this run rejected in its first "
            f"{n} rejections lie above {departed['quantile']:.4g}, where {100 * departed['expected']:.0f} % "
            f"did on the loop it was calibrated on ({where}; {stored.get('frames', 0)} rejections; "
            f"z = {departed['z']:.1f}): this route's wrong candidates stand out more than those the "
            "threshold was set against, so its precision may not hold here; calibrate on a loop like "
            "this one (--calibrate-out) when you can"
        )
