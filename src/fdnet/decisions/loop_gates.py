"""The gates a robot's loop closure needs beyond an acceptance rule: what a frame may match and
when a match is trusted.

Measured on real routes driven twice (docs/loop-closure.md), the most confident wrong closures
come from the traverse itself, not from look-alike places elsewhere:

* **uninformative frames** (:func:`informative_frames`): a tunnel's black frames, a covered lens,
  a blank wall look like each other wherever they are. A frame whose grey mean is below
  ``min_brightness`` or whose grey standard deviation is below ``min_contrast`` (measured on the
  pixels the descriptor sees) neither closes a loop nor serves as a place;
* **the robot's own recent past** (:class:`RecentPast`): besides the last ``exclude_last``
  frames, a robot that has stopped (a train in a station) sees the same view for minutes. The
  *current visual segment* (going back through consecutive frames whose grey thumbnails differ
  by less than ``still_difference``, or whose descriptor similarity is at least
  ``segment_similarity``), the last ``exclude_seconds`` seconds (frames with timestamps) and the
  last ``exclude_metres`` metres travelled (frames with positions) are excluded too. With
  sequences of L frames a candidate may not share frames with the query's own sequence either:
  the exclusion grows by L - 1 (the detector applies it);
* **a still robot's frames** make no decision (``decide_when_still``): they show nothing new, and
  the places of a stop all look alike;
* **incomplete sequences**: with sequences of L frames, a sequence that would run off the start
  of the map is scored over all L frames with the missing ones neutral (a mean over fewer frames
  is noisier and wins by chance; the detector applies it);
* **temporal consistency** (:class:`ConsistencyGate`): like ORB-SLAM3's and Kimera's three
  consecutive detections, a closure is accepted only when the last ``consistency`` frames each
  found a candidate, and consecutive candidates lie within ``consistency_window`` places of
  each other. The gated score is the smallest of those frames' scores,
  so "gated score >= threshold" is exactly "each of the k frames scored >= threshold and their
  matches agree", and a threshold can still be swept and calibrated.

All of it is causal: a frame's gates read only that frame and earlier ones.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Sequence

import numpy as np

from fdnet.data.images import grey_levels, thumbnail_difference, to_grey
from fdnet.errors import ConfigError


@dataclass(frozen=True)
class LoopGates:
    """The gates' settings (``None`` or 0 switches one off; see the module docstring).

    ``min_brightness`` / ``min_contrast``: grey mean / standard deviation in [0, 1] below which a
    frame is uninformative. ``still_difference``: consecutive frames whose grey thumbnails
    (:data:`THUMBNAIL`) differ by less than this (mean absolute difference) belong to one visual
    segment, which is excluded while the robot is in it; ``segment_similarity``: the same by the
    descriptor's similarity (consecutive frames at least this similar), for a descriptor whose
    scale is known. ``decide_when_still``: whether a frame taken while the robot is still (its
    thumbnail as above) makes a decision; by default it does not: it shows nothing its previous
    frame did not, and the places of a stop all look alike, so its match would be a guess among
    them (ORB-SLAM3 likewise closes loops only at keyframes). It is still added as a place.
    ``exclude_seconds`` / ``exclude_metres``: also exclude the frames of the last seconds /
    metres travelled (when frames carry timestamps / positions). ``similar_past``: also exclude
    the frames of the current segment the new frame still resembles more than unrelated places,
    found from its own similarities (:mod:`fdnet.decisions.loop_recency`; the default, which
    needs no frame count). ``consistency``: how many
    consecutive frames must agree (1 = off); ``consistency_window``: how far (in places) a
    frame's candidate may be from the previous frame's candidate.
    """

    min_brightness: float | None = 0.1
    min_contrast: float | None = 0.02
    still_difference: float | None = 0.04
    segment_similarity: float | None = None
    exclude_seconds: float | None = None
    exclude_metres: float | None = None
    decide_when_still: bool = False
    similar_past: bool = True
    consistency: int = 1
    consistency_window: int = 3

    def __post_init__(self) -> None:
        for name in ("min_brightness", "min_contrast", "still_difference"):
            value = getattr(self, name)
            if value is not None and not (_is_number(value) and 0.0 <= float(value) <= 1.0):
                raise ConfigError(f"loop gate {name} must be in [0, 1] (pixels are in [0, 1]), got {value!r}")
        if self.segment_similarity is not None and not (
            _is_number(self.segment_similarity) and math.isfinite(float(self.segment_similarity))
        ):
            raise ConfigError(f"loop gate segment_similarity must be a finite number, got {self.segment_similarity!r}")
        for name in ("exclude_seconds", "exclude_metres"):
            value = getattr(self, name)
            if value is not None and not (_is_number(value) and math.isfinite(float(value)) and float(value) >= 0):
                raise ConfigError(f"loop gate {name} must be a number of at least 0, got {value!r}")
        for name in ("decide_when_still", "similar_past"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"loop gate {name} must be true or false, got {getattr(self, name)!r}")
        if not _is_whole(self.consistency) or self.consistency < 1:
            raise ConfigError(
                f"loop gate consistency must be a whole number of at least 1 (1 = off), got " f"{self.consistency!r}"
            )
        if not _is_whole(self.consistency_window) or self.consistency_window < 0:
            raise ConfigError(
                f"loop gate consistency_window must be a whole number of at least 0, got "
                f"{self.consistency_window!r}"
            )

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict | None) -> "LoopGates":
        data = dict(data or {})
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ConfigError(f"unknown loop gate setting(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
        return cls(**data)

    def with_settings(self, items: Sequence[str]) -> "LoopGates":
        """These gates with ``KEY=VALUE`` settings applied (``none`` or ``off`` switches a gate off)."""
        data = self.to_dict()
        for item in items:
            key, sep, text = str(item).partition("=")
            key = key.strip().replace("-", "_")
            if not sep or not key:
                raise ConfigError(f"loop gate setting {item!r}: expected KEY=VALUE, e.g. consistency=3")
            if key not in data:
                raise ConfigError(f"unknown loop gate setting {key!r}; known: {', '.join(sorted(data))}")
            text = text.strip()
            if key in ("decide_when_still", "similar_past"):
                if text.lower() not in ("true", "false", "yes", "no", "1", "0"):
                    raise ConfigError(f"loop gate setting {key}={text!r}: give true or false")
                data[key] = text.lower() in ("true", "yes", "1")
                continue
            if text.lower() in ("none", "off"):
                if key in ("consistency", "consistency_window"):
                    data[key] = 1 if key == "consistency" else 0
                else:
                    data[key] = None
                continue
            try:
                value = float(text)
            except ValueError as exc:
                raise ConfigError(f"loop gate setting {key}={text!r}: not a number") from exc
            if key in ("consistency", "consistency_window"):
                # 1e9 is a number: say what is wrong with it (whole? in range?), not that it is none
                if not math.isfinite(value) or value != int(value):
                    raise ConfigError(f"loop gate setting {key}={text!r}: give a whole number of frames")
                value = int(value)
            data[key] = value
        return LoopGates.from_dict(data)


def _is_number(value) -> bool:
    return not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating))


def _is_whole(value) -> bool:
    return not isinstance(value, bool) and isinstance(value, (int, np.integer))


#: (height, width) of the grey thumbnails that tell a still robot's frames apart
THUMBNAIL = (16, 32)


@dataclass(frozen=True)
class FrameSignals:
    """What the gates read from a batch of frames' pixels: ``statistics`` (N, 2) grey mean and
    standard deviation in [0, 1], ``thumbnails`` (N, 16, 32) grey in [0, 1]."""

    statistics: np.ndarray
    thumbnails: np.ndarray

    def __len__(self) -> int:
        return len(self.statistics)

    def __getitem__(self, index: int) -> "FrameSignals":
        return FrameSignals(self.statistics[index : index + 1], self.thumbnails[index : index + 1])


def frame_signals(images: np.ndarray) -> FrameSignals:
    """(N, H, W, 3) images (uint8, or float in [0, 1], as the descriptors get them) -> their
    :class:`FrameSignals`."""
    import cv2

    array = np.asarray(images)
    if array.ndim != 4 or array.shape[-1] != 3:
        raise ConfigError(f"frame signals need (N, H, W, 3) images, got shape {array.shape}")
    scale = 1.0 / 255.0 if array.dtype == np.uint8 else 1.0
    grey = to_grey(array.astype(np.float32)) * scale
    statistics = grey_levels(grey)
    h, w = THUMBNAIL
    thumbnails = (
        np.stack([cv2.resize(g, (w, h), interpolation=cv2.INTER_AREA) for g in grey])
        if len(grey)
        else np.zeros((0, h, w), np.float32)
    )
    return FrameSignals(statistics, thumbnails.astype(np.float32))


def informative_frames(statistics: np.ndarray, gates: LoopGates) -> np.ndarray:
    """(N, 2) grey mean and std (:attr:`FrameSignals.statistics`) -> (N,) bool: frames bright
    and textured enough to be places under ``gates``."""
    stats = np.asarray(statistics, dtype=np.float64).reshape(-1, 2)
    keep = np.ones(len(stats), dtype=bool)
    if gates.min_brightness is not None:
        keep &= stats[:, 0] >= float(gates.min_brightness)
    if gates.min_contrast is not None:
        keep &= stats[:, 1] >= float(gates.min_contrast)
    return keep


def is_still(thumbnail: np.ndarray | None, previous: np.ndarray | None, gates: LoopGates) -> bool:
    """Whether a frame's grey thumbnail differs from the previous frame's by less than
    ``gates.still_difference`` (mean absolute difference): the robot has not moved."""
    if thumbnail is None or previous is None or gates.still_difference is None:
        return False
    return float(thumbnail_difference(thumbnail, previous)) < float(gates.still_difference)


class RecentPast:
    """The first frame of this traverse that is still the robot's recent past, for each new frame
    (frames from it on are never candidates): the oldest of the last ``exclude_last`` frames, the
    current visual segment's first frame, and the first frame within ``exclude_seconds`` /
    ``exclude_metres`` of the new one. Causal, O(1) amortised per frame."""

    def __init__(self, exclude_last: int, gates: LoopGates):
        self.exclude_last = int(exclude_last)
        self.gates = gates
        self._segment_start = 0
        self._times: list[float | None] = []
        self._travelled: list[float | None] = []  # metres along the path up to each frame
        self._last_position: tuple[float, ...] | None = None

    def first_excluded(
        self,
        frame: int,
        previous_similarity: float | None,
        still_pixels: bool,
        timestamp: float | None,
        position: Sequence[float] | None,
    ) -> int:
        """Record frame ``frame`` (its descriptor similarity to the previous frame, whether its
        pixels say it is still (:func:`is_still`), time, position) and return the first frame it
        may not match (``frame`` itself when nothing earlier is excluded)."""
        gates = self.gates
        still = bool(still_pixels) and gates.still_difference is not None
        if gates.segment_similarity is not None and previous_similarity is not None:
            still = still or previous_similarity >= gates.segment_similarity
        if frame == 0 or not still:
            self._segment_start = frame
        first = max(frame - self.exclude_last, 0) if self.exclude_last else frame
        first = min(first, self._segment_start)
        self._times.append(None if timestamp is None else float(timestamp))
        if gates.exclude_seconds is not None and timestamp is not None:
            first = min(first, self._first_within(self._times, float(timestamp) - float(gates.exclude_seconds)))
        if position is None:
            self._travelled.append(None)
        else:
            here = tuple(float(c) for c in position)
            last = self._travelled[-1] if self._travelled else None
            step = 0.0 if self._last_position is None else math.dist(here, self._last_position)
            self._travelled.append((last or 0.0) + step)
            self._last_position = here
            if gates.exclude_metres is not None:
                first = min(
                    first, self._first_within(self._travelled, self._travelled[-1] - float(gates.exclude_metres))
                )
        return first

    @staticmethod
    def _first_within(values: list[float | None], bound: float) -> int:
        """The first index from which every value (going back from the newest) is >= ``bound``;
        values are non-decreasing, an unknown value (None) ends the walk."""
        i = len(values) - 1
        while i > 0 and values[i - 1] is not None and values[i - 1] >= bound:
            i -= 1
        return i


class ConsistencyGate:
    """Accept only after ``k`` consecutive frames agree (see the module docstring). ``update``
    takes each frame's (match, score) in order, match -1 for a frame without a candidate, and
    returns the gated score: the smallest score of the last k frames when each consecutive pair
    of matches satisfies ``|m_t - m_{t-1}| <= window`` (place indices: a robot revisiting a
    route moves along it, forwards or backwards, about one place per frame), else -inf."""

    def __init__(self, k: int, window: int):
        self.k = int(k)
        self.window = int(window)
        self._history: list[tuple[int, float]] = []

    def update(self, match: int, score: float) -> float:
        self._history.append((int(match), float(score)))
        if len(self._history) > self.k:
            del self._history[0]
        if self.k <= 1:
            return float(score) if match >= 0 else -math.inf
        if len(self._history) < self.k or any(m < 0 or not math.isfinite(s) for m, s in self._history):
            return -math.inf
        for (previous, _), (current, _) in zip(self._history, self._history[1:]):
            if abs(current - previous) > self.window:
                return -math.inf
        return min(s for _, s in self._history)
