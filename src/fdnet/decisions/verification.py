"""Geometric verification of ranked candidates with local features (OpenCV).

A descriptor ranks references for a query by global similarity; verification asks a different
question of its top-K candidates: do the two images share enough local features that move
consistently under one camera geometry? For each candidate pair:

1. each image is read once per run (grey, optional CLAHE, resized so its longer side is at most
   ``max_side``; never enlarged) and described by SIFT, ORB or AKAZE (``features``); keypoints and
   descriptors are cached by image (an LRU of ``cache_size`` images), so a reference that is a
   candidate of many queries is described once;
2. each query keypoint's two nearest reference descriptors (``cv2.batchDistance``, L2 for SIFT,
   Hamming for the binary ORB/AKAZE descriptors) are kept when they pass Lowe's ratio test
   (nearest < ``ratio`` x second nearest);
3. a fundamental matrix (any rigid scene, any viewpoint) or a homography (``model``) is fitted to
   the kept matches by ``cv2.findFundamentalMat`` / ``cv2.findHomography`` with a robust estimator
   (``estimator``, default ``cv2.USAC_MAGSAC``) and an inlier threshold in pixels of the resized
   image (``threshold``);
4. the inlier count is the pair's score. Fewer ratio-test matches than the model's minimal sample
   (8 for a fundamental matrix, 4 for a homography) score 0: there is nothing to verify.

:func:`verify_candidates` does this for every query's top-K (an evaluation), re-ranking them by
inliers (``rerank``) or keeping the descriptor's order and only scoring them; :class:`Verifier` is
the same per query for an online loop (paths or in-memory images, the cache kept between calls).

Images too small for local features (Nordland's 64x32 thumbnails: ORB and AKAZE find no keypoint
there, SIFT a dozen) raise :class:`~fdnet.errors.DataError` naming the image and the minimum size
(``min_side``, the shorter side after resizing), never a silent score of 0.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Hashable, Sequence, Union

import numpy as np

from fdnet.decisions.acceptance import Rule, register_rule
from fdnet.errors import ConfigError, DataError

logger = logging.getLogger(__name__)

FEATURES = ("sift", "orb", "akaze")
MODELS = ("fundamental", "homography")
#: minimal sample of each model: fewer ratio-test matches cannot be verified at all
MINIMAL_MATCHES = {"fundamental": 8, "homography": 4}
ESTIMATORS = ("magsac", "usac_accurate", "usac_default", "ransac")

ImageSource = Union[str, os.PathLike, np.ndarray]


@dataclass
class VerificationSettings:
    """How candidates are verified. Every field is a setting of the ``verified`` acceptance rule
    (``--accept-set verified:KEY=VALUE`` on the command line)."""

    #: local features: akaze or orb (binary descriptors, Hamming) or sift (float, L2). AKAZE by
    #: measurement (docs/decisions.md, "Geometric verification"): on Gardens Point it re-ranked best
    #: and cost least of the three
    features: str = "akaze"
    #: keypoints kept per image (the strongest responses)
    max_features: int = 2000
    #: images are shrunk so their longer side is at most this many pixels (never enlarged)
    max_side: int = 640
    #: the shorter side, after resizing, must be at least this many pixels (see module docstring)
    min_side: int = 80
    #: equalise contrast locally (CLAHE, clip limit ``clahe_clip``, 8x8 tiles) before detection
    clahe: bool = False
    clahe_clip: float = 2.0
    #: Lowe's ratio test: keep a match when nearest < ratio x second nearest descriptor distance
    ratio: float = 0.8
    #: geometric model fitted to the matches: fundamental (3-D scene) or homography (plane/far)
    model: str = "fundamental"
    #: robust estimator: magsac (cv2.USAC_MAGSAC), usac_accurate, usac_default, ransac
    estimator: str = "magsac"
    #: inlier threshold in pixels of the resized images
    threshold: float = 1.0
    confidence: float = 0.999
    max_iterations: int = 10000
    #: candidates verified per query (the first K of the descriptor's ranking)
    top_k: int = 5
    #: True: reorder the top-K by inlier count (ties keep the descriptor's order); False: score only
    rerank: bool = False
    #: images whose features are kept in memory (least recently used dropped first)
    cache_size: int = 4096

    def __post_init__(self) -> None:
        def bad(name: str, what: str) -> ConfigError:
            return ConfigError(f"verification setting {name}={getattr(self, name)!r}: {what}")

        if self.features not in FEATURES:
            raise bad("features", f"unknown local features; choose one of {', '.join(FEATURES)}")
        if self.model not in MODELS:
            raise bad("model", f"unknown geometric model; choose one of {', '.join(MODELS)}")
        if self.estimator not in ESTIMATORS:
            raise bad("estimator", f"unknown robust estimator; choose one of {', '.join(ESTIMATORS)}")
        for name in ("max_features", "max_side", "min_side", "max_iterations", "top_k", "cache_size"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise bad(name, "must be a whole number >= 1")
        if self.min_side > self.max_side:
            raise bad("min_side", f"is larger than max_side={self.max_side}, so no image could be verified")
        for name in ("clahe", "rerank"):
            if not isinstance(getattr(self, name), bool):
                raise bad(name, "must be true or false")
        if not 0.0 < _number(self.ratio) <= 1.0:
            raise bad("ratio", "must be in (0, 1] (Lowe uses 0.8)")
        if not 0.0 < _number(self.threshold):
            raise bad("threshold", "must be a positive number of pixels")
        if not 0.0 < _number(self.confidence) < 1.0:
            raise bad("confidence", "must be in (0, 1)")
        if not 0.0 < _number(self.clahe_clip):
            raise bad("clahe_clip", "must be positive")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _number(value) -> float:
    """A real number, or NaN (which fails every range check) for anything else."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return float("nan")
    return float(value)


def settings_from_overrides(
    overrides: dict[str, object] | Sequence[str] | None, base: VerificationSettings | None = None
) -> VerificationSettings:
    """:class:`VerificationSettings` with ``KEY=VALUE`` overrides (a dict or ``["k=v", ...]``),
    text values read as YAML scalars (``5`` a number, ``true`` a boolean); an unknown key or a bad
    value is a :class:`ConfigError` naming it."""
    import yaml

    from fdnet.config import parse_overrides

    if overrides is None:
        overrides = {}
    if not isinstance(overrides, dict):
        overrides = parse_overrides(list(overrides))
    values = (base or VerificationSettings()).to_dict()
    for key, value in overrides.items():
        if key not in values:
            raise ConfigError(f"verification setting {key!r} is unknown; valid: {', '.join(values)}")
        if isinstance(value, str):
            try:
                value = yaml.safe_load(value)
            except yaml.YAMLError:
                pass  # kept as text: the setting's check names it
        values[key] = value
    return VerificationSettings(**values)


@dataclass(frozen=True)
class ImageFeatures:
    """One image's local features at the size they were detected at."""

    points: np.ndarray  # (N, 2) float32 keypoint coordinates (x, y)
    descriptors: np.ndarray  # (N, D): float32 for SIFT, uint8 bytes for ORB/AKAZE; (0, D) when none
    size: tuple[int, int]  # (width, height) of the described (resized) image

    def __len__(self) -> int:
        return len(self.points)


def _akaze_factory():
    import cv2

    # OpenCV 4.x has cv2.AKAZE_create; 5.x moved AKAZE to the contrib module xfeatures2d.
    factory = getattr(cv2, "AKAZE_create", None)
    if factory is None and hasattr(cv2, "xfeatures2d"):
        factory = getattr(cv2.xfeatures2d, "AKAZE_create", None)
    if factory is None:
        raise ConfigError(
            "verification setting features='akaze': this OpenCV build has no AKAZE "
            "(install opencv-contrib-python-headless)"
        )
    return factory


class Verifier:
    """Verifies a query against candidate images; keeps each image's features (LRU cache).

    Images are given as paths (cached by resolved path) or arrays (H, W), (H, W, 3) or (H, W, 4),
    uint8 or float in [0, 1] (cached under ``key`` when one is given). Counters in :attr:`stats`
    (seconds describing and matching, images described, pairs verified) let callers report cost.
    """

    def __init__(self, settings: VerificationSettings | None = None):
        import cv2

        self.settings = settings or VerificationSettings()
        s = self.settings
        if s.features == "sift":
            self._detector = cv2.SIFT_create(nfeatures=s.max_features)
            self._norm = cv2.NORM_L2
        elif s.features == "orb":
            self._detector = cv2.ORB_create(nfeatures=s.max_features)
            self._norm = cv2.NORM_HAMMING
        else:
            self._detector = _akaze_factory()()
            self._norm = cv2.NORM_HAMMING
        self._clahe = cv2.createCLAHE(clipLimit=float(s.clahe_clip), tileGridSize=(8, 8)) if s.clahe else None
        self._estimator = {
            "magsac": cv2.USAC_MAGSAC,
            "usac_accurate": cv2.USAC_ACCURATE,
            "usac_default": cv2.USAC_DEFAULT,
            "ransac": cv2.RANSAC,
        }[s.estimator]
        self._cache: OrderedDict[Hashable, ImageFeatures] = OrderedDict()
        # inlier counts of pairs already verified, so a second rule over the same candidates
        # (``verified`` and ``margin+verified`` in one evaluation) verifies nothing twice
        self._pairs: OrderedDict[tuple, int] = OrderedDict()
        self.stats = {"seconds_describe": 0.0, "seconds_match": 0.0, "images_described": 0, "pairs_verified": 0}

    # ------------------------------------------------------------------ images and features
    def described_size(self, width: int, height: int) -> tuple[int, int]:
        """(width, height) an image of this size is described at (shrunk to ``max_side``)."""
        scale = min(1.0, self.settings.max_side / max(width, height))
        return max(1, round(width * scale)), max(1, round(height * scale))

    def check_size(self, width: int, height: int, name: str) -> None:
        """DataError when an image of ``width`` x ``height`` is too small to verify (``name`` in the message)."""
        w, h = self.described_size(width, height)
        if min(w, h) < self.settings.min_side:
            resized = f" (resized to {w}x{h} by max_side={self.settings.max_side})" if (w, h) != (width, height) else ""
            raise DataError(
                f"{name}: {width}x{height} pixels{resized} is too small for geometric verification: local "
                f"features ({self.settings.features}) need the shorter side to be at least "
                f"{self.settings.min_side} pixels (verification setting min_side). Verify larger images, "
                f"or use an acceptance rule without 'verified'"
            )

    def check_paths(self, paths: Sequence[str | os.PathLike]) -> None:
        """Check image sizes from the files' headers (no decoding) before any work; DataError at the
        first image too small (or unreadable)."""
        from fdnet.data.images import image_size

        for path in paths:
            width, height = image_size(path)
            self.check_size(width, height, str(path))

    def _grey(self, image: ImageSource, name: str) -> np.ndarray:
        import cv2

        if isinstance(image, np.ndarray):
            arr = image
            if arr.ndim == 3 and arr.shape[2] in (3, 4):
                arr = arr[..., :3]
            elif arr.ndim != 2:
                raise DataError(f"{name}: expected an image array (H, W) or (H, W, 3), got shape {arr.shape}")
            if arr.dtype != np.uint8:
                arr = np.clip(np.rint(np.asarray(arr, dtype=np.float32) * 255.0), 0, 255).astype(np.uint8)
            grey = cv2.cvtColor(np.ascontiguousarray(arr), cv2.COLOR_RGB2GRAY) if arr.ndim == 3 else arr
        else:
            from fdnet.data.images import load_image_uint8

            grey = cv2.cvtColor(load_image_uint8(image), cv2.COLOR_RGB2GRAY)
        height, width = grey.shape
        self.check_size(width, height, name)
        w, h = self.described_size(width, height)
        if (w, h) != (width, height):
            grey = cv2.resize(grey, (w, h), interpolation=cv2.INTER_AREA)
        if self._clahe is not None:
            grey = self._clahe.apply(grey)
        return np.ascontiguousarray(grey)

    def features(self, image: ImageSource, key: Hashable | None = None) -> ImageFeatures:
        """The local features of ``image`` (a path or an array), from the cache when described before.
        Paths are cached by their resolved path; arrays only when ``key`` is given."""
        key = self._key(image, key)
        if key is not None and key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        name = str(image) if not isinstance(image, np.ndarray) else (str(key) if key is not None else "image array")
        t0 = time.perf_counter()
        grey = self._grey(image, name)
        keypoints, descriptors = self._detector.detectAndCompute(grey, None)
        if descriptors is None or not keypoints:
            dim = self._detector.descriptorSize()
            dtype = np.float32 if self.settings.features == "sift" else np.uint8
            found = ImageFeatures(np.zeros((0, 2), np.float32), np.zeros((0, dim), dtype), grey.shape[::-1])
        else:
            points = np.array([kp.pt for kp in keypoints], dtype=np.float32)
            if len(keypoints) > self.settings.max_features:
                # AKAZE has no feature budget of its own: keep the strongest responses, as SIFT/ORB do
                strongest = np.argsort([-kp.response for kp in keypoints], kind="stable")[: self.settings.max_features]
                points, descriptors = points[strongest], descriptors[strongest]
            found = ImageFeatures(points, np.ascontiguousarray(descriptors), grey.shape[::-1])
        self.stats["seconds_describe"] += time.perf_counter() - t0
        self.stats["images_described"] += 1
        if key is not None:
            self._cache[key] = found
            while len(self._cache) > self.settings.cache_size:
                self._cache.popitem(last=False)
        return found

    # ------------------------------------------------------------------ pairs
    def matches(self, query: ImageFeatures, reference: ImageFeatures) -> tuple[np.ndarray, np.ndarray]:
        """Ratio-test matches: (M, 2) query points and the (M, 2) reference points they match."""
        import cv2

        if len(query) == 0 or len(reference) < 2:
            return np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32)
        distance_type = cv2.CV_32F if self._norm == cv2.NORM_L2 else cv2.CV_32S
        # batchDistance returns the two nearest as arrays: no per-match DMatch objects to unpack
        distances, nearest = cv2.batchDistance(
            query.descriptors, reference.descriptors, distance_type, normType=self._norm, K=2
        )
        keep = distances[:, 0] < self.settings.ratio * distances[:, 1]
        return query.points[keep], reference.points[nearest[keep, 0]]

    def inliers(self, query: ImageFeatures, reference: ImageFeatures) -> int:
        """Inliers of the geometric model fitted to the ratio-test matches of the two images."""
        import cv2

        t0 = time.perf_counter()
        q, r = self.matches(query, reference)
        s = self.settings
        count = 0
        if len(q) >= MINIMAL_MATCHES[s.model]:
            if s.model == "fundamental":
                _, mask = cv2.findFundamentalMat(
                    q, r, self._estimator, float(s.threshold), float(s.confidence), s.max_iterations
                )
            else:
                _, mask = cv2.findHomography(
                    q, r, self._estimator, float(s.threshold), maxIters=s.max_iterations, confidence=float(s.confidence)
                )
            count = 0 if mask is None else int(np.count_nonzero(mask))
        self.stats["seconds_match"] += time.perf_counter() - t0
        self.stats["pairs_verified"] += 1
        return count

    def verify(
        self,
        query: ImageSource,
        candidates: Sequence[ImageSource],
        query_key: Hashable | None = None,
        candidate_keys: Sequence[Hashable | None] | None = None,
    ) -> np.ndarray:
        """Inlier counts (len(candidates),) int of ``query`` against each candidate. Pairs of cached
        images (paths, or arrays with keys) verified before are not verified again."""
        keys = list(candidate_keys) if candidate_keys is not None else [None] * len(candidates)
        if len(keys) != len(candidates):
            raise ValueError("candidate_keys must have one key per candidate")
        query_key = self._key(query, query_key)
        q = None
        out = np.zeros(len(candidates), dtype=np.int64)
        for i, (candidate, key) in enumerate(zip(candidates, keys)):
            key = self._key(candidate, key)
            pair = (query_key, key)
            if query_key is not None and key is not None and pair in self._pairs:
                self._pairs.move_to_end(pair)
                out[i] = self._pairs[pair]
                continue
            q = q if q is not None else self.features(query, query_key)
            out[i] = self.inliers(q, self.features(candidate, key))
            if query_key is not None and key is not None:
                self._pairs[pair] = int(out[i])
                while len(self._pairs) > 8 * self.settings.cache_size:
                    self._pairs.popitem(last=False)
        return out

    @staticmethod
    def _key(image: ImageSource, key: Hashable | None) -> Hashable | None:
        if key is None and not isinstance(image, np.ndarray):
            return str(Path(image).resolve())
        return key


@dataclass
class VerificationResult:
    """Every query's verified top-K.

    ``retrieved``/``scores`` are the descriptor's candidates (all k columns), the first K reordered
    by inliers when ``reranked``; ``inliers`` (Q, K) are the inlier counts of those first K columns
    in that (output) order, so ``inliers[:, 0]`` is the best match's verification score.
    """

    retrieved: np.ndarray
    scores: np.ndarray
    inliers: np.ndarray
    reranked: bool
    timing: dict
    settings: dict


def verify_candidates(
    query_paths: Sequence[str | os.PathLike],
    reference_paths: Sequence[str | os.PathLike],
    retrieved: np.ndarray,
    scores: np.ndarray,
    settings: VerificationSettings | None = None,
    verifier: Verifier | None = None,
    log: Callable[[str], None] | None = None,
) -> VerificationResult:
    """Verify each query's first ``settings.top_k`` candidates (columns of ``retrieved``, reference
    indices best first, negative = no candidate; with their descriptor ``scores``), re-ranking them
    by inliers when ``settings.rerank``. ``verifier`` (default: a new one with ``settings``) keeps
    features and pairs between calls. The first query's and first reference's sizes are checked from
    their file headers, so a dataset of thumbnails stops before any image is described; every image
    is checked again when described. ``timing``: ``verification_ms_per_query`` (wall time of
    everything here over the queries) and the describe/match parts."""
    settings = settings or (verifier.settings if verifier is not None else VerificationSettings())
    verifier = verifier or Verifier(settings)
    retrieved = np.asarray(retrieved)
    scores = np.asarray(scores)
    if retrieved.ndim != 2 or retrieved.shape != scores.shape or retrieved.shape[0] != len(query_paths):
        raise DataError(
            f"verification: retrieved {retrieved.shape} and scores {scores.shape} must both be "
            f"(queries={len(query_paths)}, k)"
        )
    say = log or (lambda message: None)
    num_queries, k = retrieved.shape
    top = min(settings.top_k, k)
    t0 = time.perf_counter()
    before = dict(verifier.stats)
    verifier.check_paths(list(query_paths[:1]) + list(reference_paths[:1]))
    inliers = np.zeros((num_queries, top), dtype=np.int64)
    report_every = max(1, num_queries // 10)
    for i in range(num_queries):
        valid = retrieved[i, :top] >= 0
        candidates = [reference_paths[int(j)] for j in retrieved[i, :top][valid]]
        inliers[i, valid] = verifier.verify(query_paths[i], candidates)
        if (i + 1) % report_every == 0 or i + 1 == num_queries:
            say(
                f"verification: {i + 1}/{num_queries} queries, "
                f"{1000.0 * (time.perf_counter() - t0) / (i + 1):.0f} ms/query"
            )
    out_retrieved, out_scores = retrieved.copy(), scores.copy()
    reranked = bool(settings.rerank and top > 1)
    if reranked:
        # stable sort: equal inlier counts keep the descriptor's order; missing candidates go last
        key = np.where(retrieved[:, :top] >= 0, inliers, -1)
        order = np.argsort(-key, axis=1, kind="stable")
        out_retrieved[:, :top] = np.take_along_axis(retrieved[:, :top], order, axis=1)
        out_scores[:, :top] = np.take_along_axis(scores[:, :top], order, axis=1)
        inliers = np.take_along_axis(inliers, order, axis=1)
    seconds = time.perf_counter() - t0
    stats = {key: verifier.stats[key] - before[key] for key in verifier.stats}
    timing = {
        "verification_ms_per_query": 1000.0 * seconds / max(num_queries, 1),
        "verification_ms_per_image_described": 1000.0 * stats["seconds_describe"] / max(stats["images_described"], 1),
        "verification_ms_per_pair": 1000.0 * stats["seconds_match"] / max(stats["pairs_verified"], 1),
        "verification_images_described": int(stats["images_described"]),
        "verification_pairs": int(stats["pairs_verified"]),
    }
    return VerificationResult(out_retrieved, out_scores, inliers, reranked, timing, settings.to_dict())


# ---------------------------------------------------------------------------- acceptance rule
#: the rule's settings: every verification setting, and the gate's minimum inlier count
#: min_inliers 20: above every inlier count measured for wrong matches of unrelated places on
#: Gardens Point (at most 15 with AKAZE and a fundamental matrix; docs/decisions.md)
RULE_DEFAULTS = {**VerificationSettings().to_dict(), "min_inliers": 20}
#: settings that do not change an image's features or a pair's inlier count
_PER_CALL = ("top_k", "rerank", "cache_size")
_SHARED: OrderedDict[tuple, Verifier] = OrderedDict()
_MAX_SHARED = 4


def _rule_settings(values) -> tuple[VerificationSettings, int]:
    values = dict(values)
    min_inliers = values.pop("min_inliers", RULE_DEFAULTS["min_inliers"])
    if isinstance(min_inliers, bool) or not isinstance(min_inliers, int) or min_inliers < 0:
        raise ConfigError(f"verification setting min_inliers={min_inliers!r}: must be a whole number >= 0")
    try:
        return VerificationSettings(**values), min_inliers
    except TypeError as exc:  # a key that is no setting (the registry normally refuses it first)
        raise ConfigError(f"verification settings: {exc}") from exc


def shared_verifier(settings: VerificationSettings) -> Verifier:
    """The process's :class:`Verifier` for these settings, so every rule and every call in one run
    reuses the images already described and the pairs already verified (a few settings at most
    are kept; the least recently used is dropped)."""
    key = tuple((k, v) for k, v in settings.to_dict().items() if k not in _PER_CALL)
    verifier = _SHARED.get(key)
    if verifier is None:
        verifier = _SHARED[key] = Verifier(settings)
        while len(_SHARED) > _MAX_SHARED:
            _SHARED.popitem(last=False)
    _SHARED.move_to_end(key)
    return verifier


def _verified_score(candidates, **values):
    """``verified`` as a score: the inlier count of the best candidate (after re-ranking the
    top-K by inliers when ``rerank``), and that candidate as the match."""
    settings, _ = _rule_settings(values)
    result = verify_candidates(
        candidates.query_paths,
        candidates.reference_paths,
        candidates.retrieved,
        candidates.scores,
        settings,
        shared_verifier(settings),
        log=lambda message: logger.info(message),
    )
    return result.inliers[:, 0].astype(np.float64), result.retrieved[:, 0]


def _verified_gate(candidates, match, **values):
    """``verified`` after ``+``: passes a query when its match has at least ``min_inliers``."""
    settings, min_inliers = _rule_settings(values)
    verifier = shared_verifier(settings)
    match = np.asarray(match)
    verifier.check_paths(list(candidates.query_paths[:1]) + list(candidates.reference_paths[:1]))
    passed = np.zeros(len(match), dtype=bool)
    for i, j in enumerate(match):
        if j >= 0:
            inliers = verifier.verify(candidates.query_paths[i], [candidates.reference_paths[int(j)]])[0]
            passed[i] = inliers >= min_inliers
    return passed


def _check_images(values, query_paths, reference_paths) -> None:
    """Before any work: the first query and the first reference are large enough (file headers
    only); every image is checked again when it is described."""
    settings, _ = _rule_settings(values)
    shared_verifier(settings).check_paths(list(query_paths[:1]) + list(reference_paths[:1]))


def _validate_rule(values) -> None:
    _rule_settings(values)


def _depth(values) -> int:
    return int(values.get("top_k", RULE_DEFAULTS["top_k"]))


def _register() -> None:
    register_rule(
        Rule(
            name="verified",
            description="geometric verification: inlier count of the best candidate (local features, ratio test, "
            "fundamental matrix or homography by MAGSAC); as a gate after '+': at least min_inliers",
            defaults=dict(RULE_DEFAULTS),
            score=_verified_score,
            gate=_verified_gate,
            depth=_depth,
            validate=_validate_rule,
            needs=frozenset({"images"}),
            check_images=_check_images,
        )
    )


_register()
