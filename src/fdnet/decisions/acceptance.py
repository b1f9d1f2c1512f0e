"""Acceptance scores: named rules over each query's ranked candidates (pure numpy).

Input: :class:`Candidates` -- ``retrieved`` (Q, k) reference indices, best first, and their
``scores`` (Q, k), higher = more similar, as :func:`fdnet.matching.similarity.top_k`, a faiss
index, :func:`fdnet.matching.sequence.sequence_top_k` or a place database return them, plus what
some rules need about the map (reference timestamps or positions, the similarity's ceiling, the
image paths). Output: :class:`Decision` -- one acceptance score per query (higher = more
confident; ``-inf`` = rejected by a gate whatever the threshold) and the reference it vouches for.
A query is accepted when its score reaches a threshold (chosen by :mod:`fdnet.decisions.calibration`).

Rules (``rule_names()``; settings with ``--accept-set [RULE:]KEY=VALUE``):

``raw``
    the best candidate's similarity itself (the field's usual score).
``margin``
    the best similarity minus the best similarity *outside a neighbourhood* of the best
    candidate: how much the best place stands out from every other place. The neighbourhood is
    reference-index distance <= ``radius`` (frames of a traverse, places of a database by id),
    or, when set, time distance <= ``radius_s`` seconds (``Candidates.reference_times``) or
    Euclidean distance <= ``radius_m`` metres (``Candidates.reference_positions``);
    ``radius_m`` wins over ``radius_s``, which wins over ``radius``.
``ratio``
    Lowe's ratio test, made "higher = more confident": ``1 - d_best / d_outside`` with the
    distance ``d = ceiling - similarity``. ``ceiling`` is the largest value the method's
    similarity can take (``Descriptor.similarity_ceiling``: 1 for cosine, DBoW's L1 score and
    Landmarks' normalised score; 0 for SAD's negative mean absolute difference). For unit
    vectors ``1 - cos = |a - b|^2 / 2``, so the ratio is Lowe's ratio of squared Euclidean
    distances; for SAD it is the ratio of the SADs. Ranges from 0 (best and outside equally
    far) to 1 (best at distance 0). A score above the ceiling is an error, not a silent
    negative distance. ``outside`` is the same neighbourhood as for ``margin``.
``floor`` (gate)
    passes a query when its best candidate's similarity is at least ``min`` (which must be set).

**Composition** ``A+B+...``: ``A`` gives the score (and may choose the candidate, e.g. a
re-ranking verifier); each later part is a *gate* that passes or rejects that candidate, and a
rejected query scores ``-inf`` (never accepted). A rule may offer both roles (a verifier scores
by inlier count when first and gates by a minimum inlier count after ``+``).

**Retrieval depth.** The outside candidate must be among the k retrieved. With a frame radius r
the neighbourhood holds at most 2r + 1 references, so ``k >= 2r + 2`` guarantees an outside
candidate (when the map has that many references); :meth:`AcceptanceSpec.depth` says how many
candidates a rule needs and evaluation retrieves at least that many. With ``radius_s`` or
``radius_m`` no k guarantees it; the setting ``depth`` (default 50) is retrieved. When no
outside candidate is among the k, the k-th (last valid) score stands in for it: every outside
reference scores at most that, so the margin (and ratio) used is a lower bound, i.e. the
decision errs towards rejecting.

**Sequence-consistent rules** need nothing special: run them on the candidates of SeqSLAM
sequence matching (:func:`fdnet.matching.sequence.sequence_similarity` / ``sequence_top_k``,
causal: a query's row uses only itself and earlier queries), e.g. ``fdnet evaluate
--sequence-length 10 --accept margin``. The margin is then taken between sequence scores.

**Registering a rule** (how other modules add one, e.g. ``fdnet.decisions.verification``)::

    from fdnet.decisions.acceptance import Rule, register_rule

    def inlier_score(candidates, *, top=5, **_):      # -> scores (Q,) or (scores, match)
        ...
    def inlier_gate(candidates, match, *, min_inliers=15, **_):   # -> bool (Q,)
        ...
    register_rule(Rule(name="verified", description="...", defaults={"top": 5, "min_inliers": 15},
                       score=inlier_score, gate=inlier_gate, needs=frozenset({"images"})))

A score function is called ``score(candidates, **settings)`` and returns the (Q,) scores (the
match is then column 0 of ``retrieved``) or ``(scores, match)`` with ``match`` (Q,) reference
indices; a gate is called ``gate(candidates, match, **settings)`` and returns (Q,) bools. Both
receive every setting of the rule (defaults overridden by the user's). ``needs={"images"}``
makes :func:`decide` refuse candidates without ``query_paths``/``reference_paths``.
Modules listed in ``PLUGIN_MODULES`` are imported the first time the registry is read, so their
rules are available to every command without the caller importing them.
"""

from __future__ import annotations

import importlib
import importlib.util
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from fdnet.errors import ConfigError, DataError

#: the rule ``fdnet evaluate`` reports when ``--accept`` is not given (chosen from measurements
#: on validation pairs; docs/decisions.md)
DEFAULT_ACCEPTANCE = "margin"

#: modules that register rules when imported (imported lazily, only if they exist)
PLUGIN_MODULES = ("fdnet.decisions.verification",)

#: default neighbourhood radius in reference indices (frames), chosen on validation pairs
#: (docs/decisions.md)
DEFAULT_RADIUS = 3

#: candidates retrieved when the neighbourhood is in seconds or metres (no k guarantees an
#: outside candidate there)
DEFAULT_DEPTH = 50


@dataclass(frozen=True)
class Candidates:
    """Each query's ranked candidates and what rules may need to know about the map.

    ``retrieved`` (Q, k) reference indices best first (negative = no candidate, as faiss pads);
    ``scores`` (Q, k) their similarities, higher = more similar. ``similarity_ceiling``: the
    largest similarity the method can produce (``Descriptor.similarity_ceiling``).
    ``reference_times`` (R,) seconds and ``reference_positions`` (R, D) metres, indexed by
    reference index, for neighbourhoods in time or space. ``query_paths``/``reference_paths``
    for rules that look at the images (verification). ``query_indices`` (Q,): the queries'
    positions in their traverse, for rules that need them (None = 0..Q-1).
    """

    retrieved: np.ndarray
    scores: np.ndarray
    similarity_ceiling: float = 1.0
    reference_times: np.ndarray | None = None
    reference_positions: np.ndarray | None = None
    query_paths: Sequence[Path] | None = None
    reference_paths: Sequence[Path] | None = None
    query_indices: np.ndarray | None = None

    def __post_init__(self):
        retrieved = np.asarray(self.retrieved)
        scores = np.asarray(self.scores, dtype=np.float64)
        if retrieved.ndim == 1 and scores.ndim == 1:  # one candidate per query
            retrieved, scores = retrieved[:, None], scores[:, None]
        if retrieved.ndim != 2 or retrieved.shape != scores.shape:
            raise DataError(
                f"candidates: retrieved indices {retrieved.shape} and scores {scores.shape} must be "
                f"two (queries x k) arrays of one shape"
            )
        if retrieved.shape[1] < 1:
            raise DataError("candidates: every query needs at least one candidate (k >= 1)")
        if not np.issubdtype(retrieved.dtype, np.integer):
            raise DataError(f"candidates: retrieved indices must be integers, got {retrieved.dtype}")
        valid = retrieved >= 0
        if not np.isfinite(scores[valid]).all():
            raise DataError("candidates: scores contain NaN or infinite values")
        if not np.isfinite(self.similarity_ceiling):
            raise DataError(f"candidates: similarity ceiling must be finite, got {self.similarity_ceiling}")
        object.__setattr__(self, "retrieved", retrieved.astype(np.int64, copy=False))
        object.__setattr__(self, "scores", scores)
        for name in ("reference_times", "reference_positions"):
            value = getattr(self, name)
            if value is not None:
                value = np.asarray(value, dtype=np.float64)
                if name == "reference_positions" and value.ndim == 1:
                    value = value[:, None]
                if not np.isfinite(value).all():
                    raise DataError(f"candidates: {name} contain NaN or infinite values")
                object.__setattr__(self, name, value)

    @property
    def num_queries(self) -> int:
        return int(self.retrieved.shape[0])

    @property
    def k(self) -> int:
        return int(self.retrieved.shape[1])


@dataclass(frozen=True)
class Decision:
    """Per query: the acceptance ``score`` (higher = more confident; -inf = rejected by a gate)
    and the reference index ``match`` it vouches for, under ``rule`` (its expression)."""

    score: np.ndarray
    match: np.ndarray
    rule: str
    settings: Mapping[str, Mapping] = field(default_factory=dict)

    def accepted(self, threshold: float) -> np.ndarray:
        """(Q,) bool: queries whose score reaches ``threshold`` (a query with none is a new place)."""
        return self.score >= float(threshold)


ScoreFn = Callable[..., "np.ndarray | tuple[np.ndarray, np.ndarray]"]
GateFn = Callable[..., np.ndarray]


@dataclass(frozen=True)
class Rule:
    """A named acceptance rule: a ``score`` function, a ``gate`` function, or both (see the module
    docstring for their signatures). ``defaults`` lists every setting (None = must be set when it
    is used, or optional as the rule documents). ``depth(settings)`` says how many candidates per
    query the rule needs (None = one). ``validate(settings)`` raises ConfigError on a bad value.
    ``check_images(settings, query_paths, reference_paths)``, for rules that look at the images,
    raises DataError when they cannot be used (e.g. too small for local features), so evaluation
    stops before describing anything."""

    name: str
    description: str
    defaults: Mapping[str, object] = field(default_factory=dict)
    score: ScoreFn | None = None
    gate: GateFn | None = None
    depth: Callable[[Mapping[str, object]], int] | None = None
    validate: Callable[[Mapping[str, object]], None] | None = None
    needs: frozenset = frozenset()
    check_images: Callable[[Mapping[str, object], Sequence[Path], Sequence[Path]], None] | None = None


_RULES: dict[str, Rule] = {}
_plugins_loaded = False


def register_rule(rule: Rule, replace: bool = False) -> Rule:
    """Add ``rule`` to the registry (``replace=True`` to redefine a name, e.g. in tests)."""
    if not rule.name or not rule.name.replace("_", "").isalnum():
        raise ValueError(f"rule name {rule.name!r} must be letters, digits and underscores ('+' and ',' are syntax)")
    if rule.score is None and rule.gate is None:
        raise ValueError(f"rule {rule.name!r} needs a score function, a gate function or both")
    if rule.name in _RULES and not replace and _RULES[rule.name] is not rule:
        raise ValueError(f"an acceptance rule named {rule.name!r} is already registered")
    _RULES[rule.name] = rule
    return rule


def _load_plugins() -> None:
    global _plugins_loaded
    if _plugins_loaded:
        return
    _plugins_loaded = True
    for module in PLUGIN_MODULES:
        if importlib.util.find_spec(module) is not None:
            importlib.import_module(module)


def rule_names() -> list[str]:
    _load_plugins()
    return sorted(_RULES)


def get_rule(name: str) -> Rule:
    _load_plugins()
    try:
        return _RULES[name]
    except KeyError as exc:
        raise ConfigError(
            f"unknown acceptance rule {name!r}; choose from {', '.join(rule_names())} "
            f"(combine a score with gates as A+B)"
        ) from exc


# ---------------------------------------------------------------------------- parsing
@dataclass(frozen=True)
class AcceptanceSpec:
    """A parsed rule expression ``A`` or ``A+B+...`` with every part's full settings."""

    parts: tuple[tuple[str, Mapping[str, object]], ...]

    @property
    def name(self) -> str:
        return "+".join(name for name, _ in self.parts)

    @property
    def settings(self) -> dict[str, dict]:
        return {name: dict(values) for name, values in self.parts}

    @property
    def depth(self) -> int:
        """Candidates per query this expression needs (see the module docstring)."""
        need = 1
        for name, values in self.parts:
            rule = get_rule(name)
            if rule.depth is not None:
                need = max(need, int(rule.depth(values)))
        return need

    @property
    def needs(self) -> frozenset:
        out: set = set()
        for name, _ in self.parts:
            out |= set(get_rule(name).needs)
        return frozenset(out)

    def check_available(self, available, where: str) -> None:
        """ConfigError, before any work, when a part needs what ``where``'s candidates will not
        carry (``available``: a subset of "images", "reference_times", "reference_positions"):
        a rule's ``needs``, or the references' positions for ``radius_m`` / times for ``radius_s``."""
        for name, values in self.parts:
            if values.get("radius_m") is not None and "reference_positions" not in available:
                raise ConfigError(
                    f"--accept-set {name}:radius_m: {where} has no positions of the references (metres); "
                    f"use radius (frames) here"
                )
            if (
                values.get("radius_m") is None
                and values.get("radius_s") is not None
                and "reference_times" not in available
            ):
                raise ConfigError(
                    f"--accept-set {name}:radius_s: {where} has no timestamps of the references "
                    f"(seconds); use radius (frames) here"
                )
            if "images" in get_rule(name).needs and "images" not in available:
                raise ConfigError(f"acceptance rule {name!r} looks at the images, but {where} has no image paths")

    def check_images(self, query_paths: Sequence[Path], reference_paths: Sequence[Path]) -> None:
        """Each part's ``Rule.check_images`` (DataError when the images cannot be used)."""
        for name, values in self.parts:
            rule = get_rule(name)
            if rule.check_images is not None:
                rule.check_images(values, query_paths, reference_paths)

    def to_dict(self) -> dict:
        return {"rule": self.name, "settings": self.settings}


def setting_value(value):
    """A command-line setting value as YAML reads it (3 -> int, 2.5 -> float, null -> None)."""
    if not isinstance(value, str):
        return value
    import yaml

    try:
        return yaml.safe_load(value)
    except yaml.YAMLError:
        return value


def _split_settings(items: Sequence[str] | Mapping[str, object] | None) -> list[tuple[str | None, str, object]]:
    """``["radius=3", "margin:radius=2"]`` or a mapping -> [(rule or None, key, typed value)]."""
    if not items:
        return []
    if isinstance(items, Mapping):
        pairs = list(items.items())
    else:
        pairs = []
        for item in items:
            if "=" not in str(item):
                raise ConfigError(f"--accept-set {item!r}: expected [RULE:]KEY=VALUE")
            key, value = str(item).split("=", 1)
            pairs.append((key.strip(), value.strip()))
    out = []
    for key, value in pairs:
        target, sep, setting = str(key).partition(":")
        out.append((target if sep else None, setting if sep else target, setting_value(value)))
    return out


def parse_acceptance_list(
    text: str | Sequence[str], settings: Sequence[str] | Mapping[str, object] | None = None
) -> list[AcceptanceSpec]:
    """``"raw,margin+floor"`` (or a list of expressions) and ``--accept-set`` items -> one
    :class:`AcceptanceSpec` per expression. A setting ``RULE:KEY=VALUE`` goes to that rule, a
    bare ``KEY=VALUE`` to every listed rule that has KEY; a setting no listed rule has, or a
    rule not listed, is an error (a typo must not be silently ignored)."""
    expressions = [e.strip() for e in (text.split(",") if isinstance(text, str) else text) if str(e).strip()]
    if not expressions:
        raise ConfigError("--accept: no acceptance rule given")
    names_per_expr = []
    for expr in expressions:
        names = [n.strip() for n in expr.split("+")]
        if any(not n for n in names):
            raise ConfigError(f"--accept {expr!r}: empty rule name around '+'")
        rules = [get_rule(n) for n in names]
        if rules[0].score is None:
            raise ConfigError(
                f"--accept {expr!r}: {names[0]!r} is a gate and gives no score; put a score rule "
                f"first, e.g. margin+{names[0]}"
            )
        for n, r in zip(names[1:], rules[1:]):
            if r.gate is None:
                raise ConfigError(
                    f"--accept {expr!r}: {n!r} gives a score, not a gate; after '+' only gates "
                    f"(rules that pass or reject a match) can follow"
                )
        if len(set(names)) != len(names):
            raise ConfigError(f"--accept {expr!r}: a rule appears twice")
        names_per_expr.append(names)
    listed = {n for names in names_per_expr for n in names}
    overrides = _split_settings(settings)
    for target, key, _ in overrides:
        if target is not None and target not in listed:
            raise ConfigError(
                f"--accept-set {target}:{key}: rule {target!r} is not among the rules asked for "
                f"({', '.join(sorted(listed))})"
            )
        owners = [target] if target is not None else sorted(listed)
        if not any(key in get_rule(n).defaults for n in owners):
            known = sorted({k for n in owners for k in get_rule(n).defaults})
            raise ConfigError(
                f"--accept-set {key}: no setting {key!r} in rule {' or '.join(owners)} "
                f"(settings: {', '.join(known) or 'none'})"
            )
    specs = []
    for names in names_per_expr:
        parts = []
        for n in names:
            rule = get_rule(n)
            values = dict(rule.defaults)
            for target, key, value in overrides:
                if key in values and target in (None, n):
                    values[key] = value
            if rule.validate is not None:
                rule.validate(values)
            parts.append((n, values))
        specs.append(AcceptanceSpec(tuple(parts)))
    return specs


def parse_acceptance(text: str, settings: Sequence[str] | Mapping[str, object] | None = None) -> AcceptanceSpec:
    """One rule expression (``"margin"``, ``"margin+floor"``) with its settings."""
    if "," in text:
        raise ConfigError(f"acceptance rule {text!r}: one rule expression expected here, not a list")
    return parse_acceptance_list(text, settings)[0]


# ---------------------------------------------------------------------------- deciding
def decide(spec: AcceptanceSpec | str, candidates: Candidates) -> Decision:
    """Acceptance scores of ``candidates`` under ``spec`` (an expression, or its text)."""
    if isinstance(spec, str):
        spec = parse_acceptance(spec)
    if "images" in spec.needs and (candidates.query_paths is None or candidates.reference_paths is None):
        raise ConfigError(
            f"acceptance rule {spec.name!r} looks at the images, but these candidates come without "
            f"image paths (e.g. a precomputed similarity matrix)"
        )
    (first, first_settings), *gates = spec.parts
    out = get_rule(first).score(candidates, **first_settings)
    if isinstance(out, tuple):
        score, match = out
    else:
        score, match = out, candidates.retrieved[:, 0]
    score = np.asarray(score, dtype=np.float64).copy()
    match = np.asarray(match, dtype=np.int64)
    if score.shape != (candidates.num_queries,) or match.shape != (candidates.num_queries,):
        raise DataError(
            f"acceptance rule {first!r} returned {score.shape} scores and {match.shape} matches for "
            f"{candidates.num_queries} queries"
        )
    if np.isnan(score).any():
        raise DataError(f"acceptance rule {first!r} gave NaN scores")
    score[candidates.retrieved[:, 0] < 0] = -np.inf  # a query with no candidate at all accepts nothing
    for name, values in gates:
        passed = np.asarray(get_rule(name).gate(candidates, match, **values), dtype=bool)
        if passed.shape != (candidates.num_queries,):
            raise DataError(f"acceptance gate {name!r} returned {passed.shape} for {candidates.num_queries} queries")
        score[~passed] = -np.inf
    return Decision(score=score, match=match, rule=spec.name, settings=spec.settings)


# ---------------------------------------------------------------------------- built-in rules
def _raw(candidates: Candidates, **_) -> np.ndarray:
    return candidates.scores[:, 0].copy()


def _outside_scores(candidates: Candidates, radius, radius_s, radius_m) -> np.ndarray:
    """(Q,) the best score outside the neighbourhood of each query's best candidate; when none
    of the k candidates is outside, the last valid candidate's score (an upper bound on every
    outside score, since candidates are sorted best first)."""
    idx, scores = candidates.retrieved, candidates.scores
    valid = idx >= 0
    safe = np.where(valid, idx, 0)
    best = safe[:, :1]
    if radius_m is not None:
        pos = candidates.reference_positions
        if pos is None:
            raise ConfigError("acceptance setting radius_m needs the references' positions (metres); none were given")
        _check_indices(safe, len(pos), "reference_positions")
        inside = np.linalg.norm(pos[safe] - pos[best], axis=-1) <= float(radius_m)
    elif radius_s is not None:
        times = candidates.reference_times
        if times is None:
            raise ConfigError("acceptance setting radius_s needs the references' timestamps (seconds); none were given")
        _check_indices(safe, len(times), "reference_times")
        inside = np.abs(times[safe] - times[best]) <= float(radius_s)
    else:
        inside = np.abs(safe - best) <= int(radius)
    outside = valid & ~inside
    outside_best = np.where(outside, scores, -np.inf).max(axis=1)
    # No outside candidate among the k: the last valid score bounds every outside score from above.
    last_valid = np.where(valid, scores, np.inf).min(axis=1)
    return np.where(np.isfinite(outside_best), outside_best, last_valid)


def _check_indices(idx: np.ndarray, size: int, what: str) -> None:
    if idx.size and int(idx.max()) >= size:
        raise DataError(f"candidates: reference index {int(idx.max())} but {what} has only {size} entries")


def _margin(candidates: Candidates, *, radius, radius_s=None, radius_m=None, **_) -> np.ndarray:
    return candidates.scores[:, 0] - _outside_scores(candidates, radius, radius_s, radius_m)


def _ratio(candidates: Candidates, *, radius, radius_s=None, radius_m=None, ceiling=None, **_) -> np.ndarray:
    top = float(candidates.similarity_ceiling if ceiling is None else ceiling)
    best = candidates.scores[:, 0]
    # a little slack for float32 round-off of unit-vector dot products (1.0000001)
    if (best > top + 1e-5 * max(1.0, abs(top))).any():
        q = int(np.argmax(best))
        raise DataError(
            f"ratio: similarity {best[q]:.6g} (query {q}) is above the declared ceiling {top:g}, so "
            f"'ceiling - similarity' is no distance; set --accept-set ratio:ceiling=VALUE to the "
            f"similarity's largest possible value"
        )
    d_best = np.maximum(top - best, 0.0)
    d_out = np.maximum(top - _outside_scores(candidates, radius, radius_s, radius_m), 0.0)
    # d_out >= d_best always (the outside score is at most the best); both 0 = indistinguishable
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(d_out > 0, 1.0 - d_best / np.where(d_out > 0, d_out, 1.0), 0.0)


def _neighbourhood_depth(settings: Mapping[str, object]) -> int:
    if settings.get("radius_m") is not None or settings.get("radius_s") is not None:
        return int(settings.get("depth") or DEFAULT_DEPTH)
    return 2 * int(settings["radius"]) + 2


def _number(settings, key, rule, minimum=0.0, integer=False, optional=False):
    value = settings.get(key)
    if value is None and optional:
        return
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float))
        or (integer and not isinstance(value, int))
        or not math.isfinite(value)
        or value < minimum
    ):
        kind = "an integer" if integer else "a number"
        raise ConfigError(f"--accept-set {rule}:{key}={value!r}: must be {kind} >= {minimum:g}")


def _validate_neighbourhood(rule: str):
    def validate(settings):
        _number(settings, "radius", rule, integer=True)
        _number(settings, "radius_s", rule, optional=True)
        _number(settings, "radius_m", rule, optional=True)
        _number(settings, "depth", rule, minimum=2, integer=True, optional=True)
        if "ceiling" in settings:
            _number(settings, "ceiling", rule, minimum=-math.inf, optional=True)

    return validate


def _floor_gate(candidates: Candidates, match, *, min=None, **_) -> np.ndarray:
    # the raw similarity of the candidate the score vouches for (it may not be column 0)
    hit = candidates.retrieved == np.asarray(match)[:, None]
    similarity = np.where(hit, candidates.scores, -np.inf).max(axis=1)
    return similarity >= float(min)


def _validate_floor(settings):
    if settings.get("min") is None:
        raise ConfigError(
            "rule floor needs its threshold: --accept-set floor:min=VALUE (the lowest raw similarity "
            "a match may have)"
        )
    _number(settings, "min", "floor", minimum=-math.inf)


_NEIGHBOURHOOD = {"radius": DEFAULT_RADIUS, "radius_s": None, "radius_m": None, "depth": None}

register_rule(Rule(name="raw", description="the best candidate's similarity", score=_raw))
register_rule(
    Rule(
        name="margin",
        description="best similarity minus the best similarity outside the best candidate's neighbourhood "
        "(index distance <= radius, or radius_s seconds / radius_m metres)",
        defaults=dict(_NEIGHBOURHOOD),
        score=_margin,
        depth=_neighbourhood_depth,
        validate=_validate_neighbourhood("margin"),
    )
)
register_rule(
    Rule(
        name="ratio",
        description="1 - d_best / d_outside with d = ceiling - similarity (Lowe's ratio, higher = more confident); "
        "outside = as for margin",
        defaults={**_NEIGHBOURHOOD, "ceiling": None},
        score=_ratio,
        depth=_neighbourhood_depth,
        validate=_validate_neighbourhood("ratio"),
    )
)
register_rule(
    Rule(
        name="floor",
        description="gate: the match's raw similarity is at least min",
        defaults={"min": None},
        gate=_floor_gate,
        validate=_validate_floor,
    )
)
