"""Calibrated acceptance: the threshold on an acceptance score that reaches a target precision.

:func:`choose_threshold` is the pure part: given each query's acceptance score, whether the match
it vouches for is right, and which queries have a true match, it takes the threshold of the exact
recall-over-queries PR curve (:func:`fdnet.metrics.pr_curve_over_queries`) with the
largest recall among the points whose precision reaches the target; among thresholds with that
recall, the highest (the fewest accepted queries). Accepting ``score >= threshold`` on the same
data gives exactly the precision and recall stored with it. When even the most confident query
is wrong at the target (e.g. precision 1.0 and a wrong best), the threshold is +inf: nothing is
accepted (recall 0), and the calibration says so.

:func:`calibrate` runs a method on a validation split (:func:`fdnet.evaluation.experiment.
evaluate_method`, with sequence matching when asked), applies the rule and chooses the threshold;
the :class:`Calibration` records the rule and its settings, the threshold, the target, the
precision and recall reached, what it was measured on (data, split, tolerance, sequence length),
the method's name and its descriptor's fingerprint (``Descriptor.fingerprint()``). It is written as
YAML (:func:`save_calibration`; ``calibration.yaml`` in a run directory) or into a place
database's metadata (``PlaceDatabase.set_metadata("calibration", ...)``). Applying it to another
model (another fingerprint), or with another sequence length, is an error, not a silent misuse
(:meth:`Calibration.check`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from fdnet.decisions.acceptance import (
    AcceptanceSpec,
    Candidates,
    Decision,
    decide,
    parse_acceptance,
)
from fdnet.errors import ConfigError, DataError

#: file name of a calibration inside a run directory
CALIBRATION_FILE = "calibration.yaml"
#: key of the calibration in a place database's metadata
DATABASE_KEY = "calibration"
FORMAT = "fdnet-calibration"
FORMAT_VERSION = 1


def check_target(target: float, what: str = "--target-precision") -> float:
    """A target precision in (0, 1], else ConfigError."""
    if (
        isinstance(target, bool)
        or not isinstance(target, (int, float))
        or not math.isfinite(target)
        or not 0.0 < float(target) <= 1.0
    ):
        raise ConfigError(f"{what} {target!r}: a precision must be in (0, 1] (e.g. 1.0, 0.99, 0.95)")
    return float(target)


@dataclass(frozen=True)
class Threshold:
    threshold: float
    precision: float
    recall: float
    accepted: int


def choose_threshold(scores: np.ndarray, correct: np.ndarray, has_match: np.ndarray, target: float) -> Threshold:
    """The threshold reaching ``target`` precision with the largest recall (see the module
    docstring). ``scores`` (Q,) acceptance scores (-inf = rejected), ``correct`` (Q,) whether the
    match each score vouches for is right, ``has_match`` (Q,) queries with a true match."""
    from fdnet.metrics import pr_curve_over_queries

    target = check_target(target)
    scores = np.asarray(scores, dtype=np.float64)
    curve, _ = pr_curve_over_queries(scores, correct, has_match)
    real = np.isfinite(curve.thresholds)
    # a hair of slack so that 99 right of 100 counts as 0.99 despite float division
    ok = real & (curve.precision >= target - 1e-12)
    if not ok.any():
        return Threshold(math.inf, 1.0, 0.0, 0)
    best_recall = curve.recall[ok].max()
    candidates = np.flatnonzero(ok & (curve.recall == best_recall))
    i = candidates[np.argmax(curve.thresholds[candidates])]
    threshold = float(curve.thresholds[i])
    return Threshold(threshold, float(curve.precision[i]), float(curve.recall[i]), int((scores >= threshold).sum()))


@dataclass
class Calibration:
    """A threshold on one acceptance rule for one model (see the module docstring)."""

    rule: str
    settings: dict
    threshold: float
    target_precision: float
    precision: float
    recall: float
    accepted: int
    num_queries: int
    method: str
    fingerprint: str
    sequence_length: int = 1
    measured_on: dict = field(default_factory=dict)
    created: str = ""
    fdnet_version: str = ""
    notes: list = field(default_factory=list)
    #: the probability that an accepted match is right, as a function of the score
    #: (:func:`fit_probability`): {"scores": [...], "p_correct": [...], "frames": N}; empty when
    #: the calibration data could not fit one
    probability: dict = field(default_factory=dict)
    #: what the threshold assumes: the quantiles of the scores it was measured on
    #: (:func:`score_distribution`): {"levels": [...], "quantiles": [...], "frames": N}
    score_distribution: dict = field(default_factory=dict)

    # ------------------------------------------------------------------ use
    @property
    def spec(self) -> AcceptanceSpec:
        """The rule expression with its stored settings."""
        items = [
            f"{name}:{key}={yaml_text(value)}"
            for name, values in self.settings.items()
            for key, value in values.items()
        ]
        return parse_acceptance(self.rule, items)

    def check(
        self,
        descriptor=None,
        method: str | None = None,
        fingerprint: str | None = None,
        sequence_length: int | None = None,
        source: str = "calibration",
    ) -> None:
        """Refuse to apply this calibration to another model or another sequence length."""
        if descriptor is not None:
            method, fingerprint = descriptor.name, descriptor.fingerprint()
        if fingerprint is not None and fingerprint != self.fingerprint:
            raise ConfigError(
                f"{source}: calibrated for method {self.method!r} with descriptor fingerprint "
                f"{self.fingerprint[:12]}, but this is {method or 'a model'!s} with fingerprint "
                f"{fingerprint[:12]}: another model (or other weights or settings); calibrate this "
                f"one with `fdnet calibrate`"
            )
        if sequence_length is not None and int(sequence_length) != int(self.sequence_length):
            raise ConfigError(
                f"{source}: calibrated with --sequence-length {self.sequence_length}, used with "
                f"{sequence_length}: sequence scores and single-image scores need their own thresholds"
            )

    def p_correct(self, scores) -> np.ndarray:
        """The fitted probability that a match with each score is right (NaN without a fit;
        0 for a rejected score, -inf)."""
        scores = np.asarray(scores, dtype=np.float64)
        fit = self.probability or {}
        if not fit.get("scores"):
            return np.full(scores.shape, np.nan)
        p = np.interp(scores, np.asarray(fit["scores"], np.float64), np.asarray(fit["p_correct"], np.float64))
        return np.where(np.isneginf(scores), 0.0, p)

    def decide(self, candidates: Candidates) -> tuple[Decision, np.ndarray]:
        """(the rule's decision, (Q,) accepted) for ranked candidates of this model."""
        decision = decide(self.spec, candidates)
        return decision, decision.accepted(self.threshold)

    # ------------------------------------------------------------------ storage
    def to_dict(self, json_safe: bool = False) -> dict:
        """The stored form (YAML keeps +inf as .inf); ``json_safe`` writes non-finite numbers as
        the strings "inf"/"nan", which :meth:`from_dict` reads back (JSON has no infinity)."""
        out = {"format": FORMAT, "version": FORMAT_VERSION, **asdict(self)}
        if json_safe:
            for key in ("threshold", "precision", "recall"):
                if not math.isfinite(out[key]):
                    out[key] = str(out[key])
        return out

    @classmethod
    def from_dict(cls, data, source: str = "calibration") -> "Calibration":
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise DataError(f"{source}: not an fdnet calibration (no 'format: {FORMAT}')")
        if data.get("version") != FORMAT_VERSION:
            raise DataError(
                f"{source}: calibration format version {data.get('version')!r}; this fdnet reads "
                f"version {FORMAT_VERSION}"
            )
        names = [f for f in cls.__dataclass_fields__]
        required = ["rule", "settings", "threshold", "target_precision", "method", "fingerprint"]
        missing = [k for k in required if k not in data]
        if missing:
            raise DataError(f"{source}: calibration lacks {', '.join(missing)}")
        values = {k: data[k] for k in names if k in data}
        try:
            for key in ("threshold", "target_precision", "precision", "recall"):
                if key in values:
                    if isinstance(values[key], bool):
                        raise TypeError(key)
                    values[key] = float(values[key])
        except (TypeError, ValueError) as exc:
            raise DataError(f"{source}: threshold, target_precision, precision and recall must be numbers") from exc
        check_target(values["target_precision"], f"{source}: target_precision")
        if math.isnan(values["threshold"]) or values["threshold"] == -math.inf:
            # -inf would accept the queries a gate rejected (their score is -inf): never stored
            raise DataError(
                f"{source}: threshold is {values['threshold']}; a threshold is a number or +inf " f"(accept nothing)"
            )
        for key in ("rule", "method", "fingerprint"):
            if not isinstance(values[key], str) or not values[key]:
                raise DataError(f"{source}: {key} must be text, got {values[key]!r}")
        if "sequence_length" in values and (
            isinstance(values["sequence_length"], bool)
            or not isinstance(values["sequence_length"], int)
            or values["sequence_length"] < 1
        ):
            raise DataError(
                f"{source}: sequence_length must be a whole number of frames, at least 1 (1 = single "
                f"images), got {values['sequence_length']!r}"
            )
        for key in ("accepted", "num_queries"):
            if key in values and (isinstance(values[key], bool) or not isinstance(values[key], int) or values[key] < 0):
                raise DataError(f"{source}: {key} must be a whole number >= 0, got {values[key]!r}")
        for key in ("probability", "score_distribution"):
            value = values.get(key, {}) or {}
            if not isinstance(value, dict) or not all(
                isinstance(value.get(k, []), list) and all(_is_real(x) for x in value.get(k, []))
                for k in ("scores", "p_correct", "levels", "quantiles")
            ):
                raise DataError(
                    f"{source}: {key} must map 'scores'/'p_correct' (or 'levels'/'quantiles') to lists " "of numbers"
                )
            values[key] = value
        fit = values.get("probability") or {}
        if len(fit.get("scores", [])) != len(fit.get("p_correct", [])) or any(
            not 0.0 <= p <= 1.0 for p in fit.get("p_correct", [])
        ):
            raise DataError(
                f"{source}: probability: 'scores' and 'p_correct' must be lists of one length, "
                "probabilities in [0, 1]"
            )
        if not isinstance(values.get("measured_on", {}), dict):
            raise DataError(f"{source}: measured_on must map names to values")
        notes = values.get("notes", [])
        if not isinstance(notes, list) or not all(isinstance(n, str) for n in notes):
            raise DataError(f"{source}: notes must be a list of text lines")
        for key in ("created", "fdnet_version"):
            if key in values and not isinstance(values[key], str):
                values[key] = str(values[key])  # YAML reads an unquoted date or version as a date/number
        settings = values["settings"]
        if not isinstance(settings, dict) or not all(isinstance(v, dict) for v in settings.values()):
            raise DataError(f"{source}: settings must map each rule to its settings")
        values.setdefault("precision", math.nan)
        values.setdefault("recall", math.nan)
        values.setdefault("accepted", 0)
        values.setdefault("num_queries", 0)
        calibration = cls(**values)
        try:
            calibration.spec  # the rule exists and its settings are valid here
        except ConfigError as exc:
            raise DataError(f"{source}: {exc}") from exc
        return calibration


def _is_real(value) -> bool:
    return not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)


#: the quantiles of a calibration's scores it stores (what its threshold assumes)
DISTRIBUTION_LEVELS = tuple(round(0.05 * i, 2) for i in range(1, 20))


def score_distribution(scores: np.ndarray, below: float = math.inf) -> dict:
    """The stored form of a score distribution: the :data:`DISTRIBUTION_LEVELS` quantiles of the
    finite ``scores`` under ``below`` (rejections, -inf, left out) and how many there were. A
    calibration stores those under its threshold: the frames it rejects are mostly places the
    robot had not seen, whose scores say how a route's wrong candidates stand out, and a run
    sees them from its first frame on (its revisits come later, in a proportion no calibration
    can know)."""
    scores = np.asarray(scores, dtype=np.float64)
    scores = scores[np.isfinite(scores) & (scores < below)]
    if not len(scores):
        return {}
    return {
        "levels": list(DISTRIBUTION_LEVELS),
        "quantiles": [float(q) for q in np.quantile(scores, DISTRIBUTION_LEVELS)],
        "frames": int(len(scores)),
    }


#: a loop calibration for precision 1.0 also keeps the expected number of wrong closures among this
#: many wrong-candidate frames under one (:func:`tail_threshold`)
EXTRAPOLATE_TO = 1000


def tail_threshold(wrong_scores: np.ndarray, frames: int = EXTRAPOLATE_TO) -> dict | None:
    """The score above which fewer than one of ``frames`` wrong candidates is expected, from an
    exponential fit of the upper tail of ``wrong_scores`` (the finite scores of frames whose
    candidate was wrong): the top k = max(10, n / 10) scores over the k-th, whose mean excess is
    the tail's scale beta; P(score > t) = (k / n) exp(-(t - u) / beta), so t = u + beta ln(frames
    k / n). Why: a threshold set just above the most confident wrong frame of a loop bounds the
    largest of that loop's n wrong frames, not of a longer route's (a 300-frame loop's threshold
    admitted a 2000-frame loop's stronger look-alikes, docs/loop-closure.md); this one is set for
    ``frames`` of them. None with fewer than 20 wrong scores (no tail to fit)."""
    wrong = np.sort(np.asarray(wrong_scores, dtype=np.float64)[np.isfinite(wrong_scores)])[::-1]
    if len(wrong) < 20:
        return None
    k = max(10, len(wrong) // 10)
    u = float(wrong[k])
    beta = float(np.mean(wrong[:k] - u))
    if beta <= 0:
        return None
    return {
        "threshold": u + beta * math.log(frames * k / len(wrong)),
        "u": u,
        "beta": beta,
        "k": k,
        "wrong": int(len(wrong)),
        "frames": int(frames),
    }


#: the upper levels of a stored distribution the drift check reads, and the z-score above which a
#: run's share of scores over them counts as departed (one-sided: a route whose wrong candidates
#: stand out less than the calibration loop's only costs recall)
TAIL_LEVELS = (0.8, 0.85, 0.9, 0.95)
TAIL_Z = 3.0


def tail_quantiles(distribution: dict) -> list[tuple[float, float]]:
    """(level, quantile) of a stored :func:`score_distribution` at each of :data:`TAIL_LEVELS`."""
    if not distribution:
        return []
    levels = np.asarray(distribution["levels"], np.float64)
    quantiles = np.asarray(distribution["quantiles"], np.float64)
    out = []
    for level in TAIL_LEVELS:
        at = np.flatnonzero(np.isclose(levels, level))
        if len(at):
            out.append((level, float(quantiles[at[0]])))
    return out


def tail_departure_of_counts(tails: list[tuple[float, float]], above, n: int) -> dict | None:
    """:func:`tail_departure` from counts: ``above[i]`` of ``n`` scores lie above the quantile of
    ``tails[i]`` (:func:`tail_quantiles`), so a run can count as it goes instead of keeping its
    scores."""
    if not tails or n <= 0:
        return None
    worst = None
    for (level, quantile), count in zip(tails, above):
        share = float(count) / n
        expected = 1.0 - level
        z = (share - expected) / math.sqrt(level * expected / n)
        if worst is None or z > worst["z"]:
            worst = {"level": level, "quantile": quantile, "share": share, "expected": expected, "z": z}
    return worst if worst is not None and worst["z"] > TAIL_Z else None


def tail_departure(distribution: dict, scores: np.ndarray) -> dict | None:
    """Whether ``scores`` reach into the upper tail of a stored :func:`score_distribution` more
    often than it did: for each of :data:`TAIL_LEVELS`, the share of ``scores`` above the stored
    quantile against the share expected (1 - level), as a binomial z-score. Returns the worst
    level's {level, quantile, share, expected, z} when its z exceeds :data:`TAIL_Z`, else None."""
    scores = np.asarray(scores, dtype=np.float64)
    scores = scores[np.isfinite(scores)]
    tails = tail_quantiles(distribution)
    return tail_departure_of_counts(tails, [int((scores > q).sum()) for _, q in tails], len(scores))


#: p_correct is the lower bound of this one-sided confidence level on each block's share right
P_CORRECT_CONFIDENCE = 0.95


def expected_wrong(tail: dict | None, low: float, high: float = math.inf) -> float:
    """How many wrong frames the exponential tail of a loop's wrong scores (:func:`tail_threshold`:
    u, beta, k) expects between scores ``low`` and ``high`` on that loop (0 without a tail; only
    the part above u, where the tail starts, counts)."""
    if not tail:
        return 0.0
    u, scale, k = float(tail["u"]), float(tail["beta"]), float(tail["k"])
    upper = 0.0 if math.isinf(high) else math.exp(-max(high - u, 0.0) / scale)
    return max(k * (math.exp(-max(low - u, 0.0) / scale) - upper), 0.0)


def fit_probability(scores: np.ndarray, correct: np.ndarray, wrong_tail: dict | None = None) -> dict:
    """The probability that a match is right as a non-decreasing function of its score: isotonic
    regression (scikit-learn) of ``correct`` on the finite ``scores``; each of its constant
    blocks (n frames, k right) then gets the Clopper-Pearson lower bound of its share right at
    :data:`P_CORRECT_CONFIDENCE` (scipy's beta quantile), not k / n. A block of a few right
    answers proves little: 20 of 20 gives 0.86, 68 of 68 gives 0.957, and 0.99 needs about 300
    right in a row. So p_correct errs low: on loops it was not fitted on, the frames it gives
    0.99 were right at least as often (docs/loop-closure.md). Stored as the block ends (scores,
    p_correct), read by linear interpolation (:meth:`Calibration.p_correct`).

    ``wrong_tail`` (:func:`tail_threshold` of the loop's wrong scores): a block counts at least
    as many wrong frames as that tail expects within its scores (:func:`expected_wrong`; the top
    block's reach to any higher score) on a route of :data:`EXTRAPOLATE_TO` wrong frames, the
    route the threshold is set for (a loop with fewer wrong frames has its expectation scaled
    up). A loop's few hundred wrong frames rarely reach its top scores, so the top blocks would
    count none by the luck of the draw; the tail that sets the threshold says how many a route
    should be expected to hold there."""
    from scipy.stats import beta
    from sklearn.isotonic import IsotonicRegression

    scores = np.asarray(scores, dtype=np.float64)
    correct = np.asarray(correct, dtype=np.float64)
    finite = np.isfinite(scores)
    scores, correct = scores[finite], correct[finite]
    if len(scores) < 2 or len(np.unique(scores)) < 2:
        return {}
    fitted = IsotonicRegression(out_of_bounds="clip").fit(scores, correct).predict(scores)
    per_route = max(1.0, EXTRAPOLATE_TO / float(wrong_tail["wrong"])) if wrong_tail and wrong_tail.get("wrong") else 1.0
    order = np.argsort(scores, kind="stable")
    scores, correct, fitted = scores[order], correct[order], fitted[order]
    xs, ps = [], []
    values = np.unique(fitted)
    for i, value in enumerate(values):
        block = fitted == value
        n, right = int(block.sum()), int(correct[block].sum())
        lo, hi = float(scores[block].min()), float(scores[block].max())
        expected = expected_wrong(wrong_tail, lo, hi if i < len(values) - 1 else math.inf) * per_route
        wrong = max(float(n - right), expected)
        p = float(beta.ppf(1.0 - P_CORRECT_CONFIDENCE, right, wrong + 1)) if right else 0.0
        xs += [lo, hi] if hi > lo else [lo]
        ps += [p, p] if hi > lo else [p]
    ps = list(np.maximum.accumulate(ps))  # a bound of a larger block may pass a smaller one's
    fit = {"scores": xs, "p_correct": [float(p) for p in ps], "frames": int(len(scores))}
    if wrong_tail:
        fit["wrong_score_tail"] = {key: float(wrong_tail[key]) for key in ("u", "beta", "k")}
    return fit


def yaml_text(value) -> str:
    import yaml

    return yaml.safe_dump(value, default_flow_style=True).strip().removesuffix("...").strip()


def save_calibration(calibration: Calibration, path: str | Path) -> Path:
    """Write ``calibration`` as YAML, atomically. A directory means ``DIR/calibration.yaml``."""
    import yaml

    from fdnet.io import atomic_write_text

    path = Path(path)
    if path.is_dir():
        path = path / CALIBRATION_FILE
    atomic_write_text(path, yaml.safe_dump(calibration.to_dict(), sort_keys=False))
    return path


def load_calibration(path: str | Path) -> Calibration:
    """A calibration YAML file, or ``DIR/calibration.yaml`` for a run directory."""
    from fdnet.config import read_yaml_file

    path = Path(path)
    if path.is_dir():
        path = path / CALIBRATION_FILE
        if not path.is_file():
            raise DataError(
                f"{path.parent}: no {CALIBRATION_FILE} in this folder (run `fdnet calibrate ... "
                f"--store-in-run` or give the calibration file)"
            )
    if not path.is_file():
        raise DataError(f"{path}: calibration file not found")
    try:
        data = read_yaml_file(path, "calibration file", DataError)
    except OSError as exc:
        raise DataError(f"{path}: cannot read the calibration file ({exc.strerror or exc})") from exc
    return Calibration.from_dict(data, source=str(path))


def stored_in_run(run_dir, names=(CALIBRATION_FILE,)) -> Path | None:
    """The calibration a run directory stores, by the one rule every deciding command follows
    (``match``, ``database query``, ``loop-closure``, when given no threshold or calibration and,
    for the database commands, none is stored in the database): the first of ``names`` found in
    ``RUN``, then ``RUN/best`` (a run directory means its best weights), or, given ``RUN/best``,
    in ``RUN``. None when there is none."""
    if run_dir is None:
        return None
    run_dir = Path(run_dir)
    folders = [run_dir, run_dir / "best"] + ([run_dir.parent] if run_dir.name == "best" else [])
    for name in names:
        for folder in folders:
            if (folder / name).is_file():
                return folder / name
    return None


def candidate_specs(spec: AcceptanceSpec, choose: dict[str, Sequence] | None) -> list[AcceptanceSpec]:
    """``spec`` with every combination of the values in ``choose`` (setting -> values, applied to
    each part of the expression that has the setting); ``[spec]`` when there is nothing to choose."""
    import itertools

    if not choose:
        return [spec]
    for key in choose:
        if not any(key in values for _, values in spec.parts):
            raise ConfigError(f"--choose {key}: rule {spec.name} has no setting {key!r}")
        if not choose[key]:
            raise ConfigError(f"--choose {key}: no values to choose from")
    out = []
    for combination in itertools.product(*choose.values()):
        items = [
            f"{name}:{key}={yaml_text(value)}"
            for name, values in spec.parts
            for key, value in values.items()
            if key not in choose
        ]
        items += [
            f"{name}:{key}={yaml_text(value)}"
            for name, values in spec.parts
            for key, value in zip(choose, combination)
            if key in values
        ]
        out.append(parse_acceptance(spec.name, items))
    return out


def apply_threshold(calibration: Calibration, scores: np.ndarray, correct: np.ndarray, has_match: np.ndarray) -> dict:
    """Precision and recall a calibration's threshold reaches on another split's acceptance scores
    (``correct``: whether each accepted match is right): how well it transfers."""
    scores = np.asarray(scores, dtype=np.float64)
    accepted = scores >= calibration.threshold
    tp = int((accepted & np.asarray(correct, bool)).sum())
    n = int(accepted.sum())
    positives = int(np.count_nonzero(has_match))
    return {
        "accepted": n,
        "true_positives": tp,
        "precision": tp / n if n else 1.0,
        "recall": tp / positives if positives else math.nan,
    }


def stored_calibration(database):
    """(the calibration ``fdnet calibrate --db`` stored in the database, where it came from), or
    (None, None) when the database (a PlaceDatabase or an existing file) holds none."""
    from fdnet.matching.database import MEMORY, PlaceDatabase

    if isinstance(database, PlaceDatabase):
        stored, path = database.get_metadata(DATABASE_KEY), database.path
    elif database is not None and str(database) != MEMORY and Path(database).is_file():
        with PlaceDatabase.open(database) as db:
            stored, path = db.get_metadata(DATABASE_KEY), db.path
    else:
        return None, None
    if stored is None:
        return None, None
    source = f"{path} (its stored calibration)"
    return Calibration.from_dict(stored, source=source), source


def checked_calibration(calibration, descriptor, sequence_length: int, source: str | None = None):
    """A :class:`~fdnet.decisions.calibration.Calibration` (or the path of its file, or a run
    directory holding one), refused when it was made for another model or sequence length."""
    source = source or "calibration"
    if not isinstance(calibration, Calibration):
        source = str(calibration)
        calibration = load_calibration(calibration)
    calibration.check(descriptor=descriptor, sequence_length=sequence_length, source=source)
    return calibration, source
