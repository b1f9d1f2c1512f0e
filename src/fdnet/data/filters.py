"""Frame filters the paper applies before training and testing: drop dark frames (the train is in
a tunnel) and near-duplicate consecutive frames (the train is standing still).

Qin et al. (FDNet paper, section 5.1.1) remove "frames where the train is in a tunnel or
stationary" from Nordland but do not say how; these are simple, configurable detectors:

* **dark**: the mean grey level (BT.601 luminance, images in [0, 1]) of a frame's thumbnail is
  below ``dark_threshold`` (default 0.1, about 25 of 255). On Nordland tunnel frames are
  nearly black (mean 0.02 to 0.07) and daylight frames are far above 0.1.
* **near-duplicate**: the mean absolute difference between a frame's grey thumbnail and the
  **last kept** frame's thumbnail is below ``duplicate_threshold`` (default 0.01). Comparing
  with the last kept frame, not the previous one, means a slow creep during a long stop is
  still removed until the view has really changed. On Nordland (16x32 thumbnails) moving
  frames differ by about 0.1 and stationary ones by under 0.002.

Both are thresholds on the measures loop closure's gates read too (:func:`fdnet.data.images.grey_levels`,
:func:`fdnet.data.images.thumbnail_difference`; :mod:`fdnet.decisions.loop_gates`). The
thresholds differ because the questions do: a training set drops a frame for good only when it
is nearly black or shows nothing new since the last frame kept (0.01), while a robot's still
frames are compared with the frame just before, online, and only stop deciding (0.04).

**Alignment rule.** Conditions of one route are filtered together, so frame-aligned ground
truth stays valid: a frame *position* is dropped from every condition when it is dark in
**any** condition, or a near-duplicate (of the last kept position) in **any** condition. The
kept traverses keep their ``frame_ids``, so ``GroundTruth.from_frames`` still pairs them.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fdnet.data.dataset import RouteDataset
from fdnet.data.images import grey_levels, load_images, thumbnail_difference, to_grey
from fdnet.errors import ConfigError, DataError


@dataclass
class FilterSettings:
    dark_threshold: float | None = 0.1  # None: keep dark frames
    duplicate_threshold: float | None = 0.01  # None: keep near-duplicates
    thumbnail_size: tuple[int, int] = (16, 32)  # (height, width) the detectors look at

    def __post_init__(self) -> None:
        for name in ("dark_threshold", "duplicate_threshold"):
            value = getattr(self, name)
            if value is not None and not (0.0 <= float(value) <= 1.0):
                raise ConfigError(f"frame filter: {name} must be in [0, 1] (images are in [0, 1]), got {value}")
        h, w = (int(v) for v in self.thumbnail_size)
        if h < 1 or w < 1:
            raise ConfigError(f"frame filter: thumbnail_size must be positive, got {self.thumbnail_size}")
        self.thumbnail_size = (h, w)


@dataclass
class FilterReport:
    """What was dropped and why (positions are indices into the unfiltered traverses)."""

    num_frames: int
    kept: np.ndarray  # positions kept, ascending
    dark: dict[str, np.ndarray] = field(default_factory=dict)  # per condition
    duplicate: dict[str, np.ndarray] = field(default_factory=dict)  # per condition
    settings: FilterSettings = field(default_factory=FilterSettings)

    @property
    def dropped_dark(self) -> np.ndarray:
        """Positions dropped because they are dark in at least one condition."""
        if not self.dark:
            return np.zeros(0, dtype=np.int64)
        return np.unique(np.concatenate(list(self.dark.values())))

    @property
    def dropped_duplicate(self) -> np.ndarray:
        """Positions dropped as near-duplicates (and not dark)."""
        if not self.duplicate:
            return np.zeros(0, dtype=np.int64)
        return np.setdiff1d(np.unique(np.concatenate(list(self.duplicate.values()))), self.dropped_dark)

    def to_dict(self) -> dict:
        return {
            "num_frames": int(self.num_frames),
            "num_kept": int(len(self.kept)),
            "num_dropped_dark": int(len(self.dropped_dark)),
            "num_dropped_duplicate": int(len(self.dropped_duplicate)),
            "dark_per_condition": {c: int(len(v)) for c, v in self.dark.items()},
            "duplicate_per_condition": {c: int(len(v)) for c, v in self.duplicate.items()},
            "settings": {
                "dark_threshold": self.settings.dark_threshold,
                "duplicate_threshold": self.settings.duplicate_threshold,
                "thumbnail_size": list(self.settings.thumbnail_size),
                "rule": "drop a frame position from every condition if dark or " "near-duplicate in any condition",
            },
        }

    def summary(self) -> str:
        d = self.to_dict()
        per = ", ".join(
            f"{c} {n} dark / {d['duplicate_per_condition'].get(c, 0)} still" for c, n in d["dark_per_condition"].items()
        )
        return (
            f"kept {d['num_kept']} of {d['num_frames']} frames: dropped {d['num_dropped_dark']} dark, "
            f"{d['num_dropped_duplicate']} near-duplicate" + (f" ({per})" if per else "")
        )


def dark_frames(grey: np.ndarray, threshold: float) -> np.ndarray:
    """(N, h, w) grey in [0, 1] -> (N,) bool: mean brightness below ``threshold``."""
    return grey_levels(grey)[:, 0] < threshold


def near_duplicates(thumbnails: np.ndarray, threshold: float, skip: np.ndarray | None = None) -> np.ndarray:
    """(C, N, h, w) grey thumbnails of C aligned conditions -> (C, N) bool: True where position
    j of condition c differs from the last kept position by less than ``threshold`` (mean
    absolute difference). A position is kept only when it is no duplicate in any condition;
    positions in ``skip`` (e.g. dark ones) are neither kept nor compared.

    Sequential by nature (what counts as "last kept" depends on earlier decisions), hence the
    Python loop over frames; each step is a vectorised comparison over all conditions.
    """
    c, n = thumbnails.shape[:2]
    skip = np.zeros(n, dtype=bool) if skip is None else np.asarray(skip, dtype=bool)
    out = np.zeros((c, n), dtype=bool)
    last = None
    for j in range(n):
        if skip[j]:
            continue
        if last is not None:
            diff = thumbnail_difference(thumbnails[:, j], thumbnails[:, last])
            out[:, j] = diff < threshold
            if out[:, j].any():
                continue
        last = j
    return out


def route_thumbnails(dataset: RouteDataset, size: tuple[int, int]) -> dict[str, np.ndarray]:
    """Grey thumbnails (N, h, w) of every condition, for the detectors."""
    return {name: to_grey(load_images(t.paths, size)) for name, t in dataset.traverses.items()}


def filter_route(
    dataset: RouteDataset,
    dark_threshold: float | None = 0.1,
    duplicate_threshold: float | None = 0.01,
    thumbnail_size: tuple[int, int] = (16, 32),
) -> tuple[RouteDataset, FilterReport]:
    """Drop dark and near-duplicate frame positions from every condition of a frame-aligned route.

    Returns the filtered dataset (same conditions; ``frame_ids`` of the kept frames preserved)
    and a :class:`FilterReport`. Pass ``None`` as a threshold to switch that filter off.
    """
    settings = FilterSettings(dark_threshold, duplicate_threshold, tuple(thumbnail_size))
    lengths = {name: len(t) for name, t in dataset.traverses.items()}
    if not lengths:
        raise DataError(f"{dataset.root}: no conditions to filter")
    if len(set(lengths.values())) != 1:
        listing = ", ".join(f"{dataset.root / k}: {v}" for k, v in lengths.items())
        raise DataError(
            f"frame filters keep conditions aligned, so every condition needs the same number of "
            f"frames, but the counts differ ({listing})"
        )
    n = next(iter(lengths.values()))
    thumbs = route_thumbnails(dataset, settings.thumbnail_size)
    names = list(thumbs)

    dark = {name: np.zeros(n, dtype=bool) for name in names}
    if settings.dark_threshold is not None:
        dark = {name: dark_frames(thumbs[name], settings.dark_threshold) for name in names}
    for name in names:
        if n >= 4 and dark[name].mean() > 0.5:
            # Half a traverse "in tunnels" is a night traverse, not tunnels: refuse rather than
            # silently drop it.
            raise ConfigError(
                f"{dataset.root / name}: {int(dark[name].sum())} of {n} frames are darker than dark_threshold "
                f"{settings.dark_threshold:g} (mean grey level); this looks like a night-time traverse, not "
                f"tunnels. Lower the dark threshold or switch the dark filter off for it"
            )
    any_dark = np.logical_or.reduce([dark[name] for name in names])

    dup = np.zeros((len(names), n), dtype=bool)
    if settings.duplicate_threshold is not None:
        dup = near_duplicates(np.stack([thumbs[name] for name in names]), settings.duplicate_threshold, skip=any_dark)
    keep = ~any_dark & ~dup.any(axis=0)
    kept = np.flatnonzero(keep)
    report = FilterReport(
        num_frames=n,
        kept=kept,
        dark={name: np.flatnonzero(dark[name]) for name in names},
        duplicate={name: np.flatnonzero(dup[i]) for i, name in enumerate(names)},
        settings=settings,
    )
    filtered = RouteDataset(dataset.root, {name: t.select(kept) for name, t in dataset.traverses.items()})
    return filtered, report


FILTER_RULE = "fdnet-filter-v2"  # change when the detectors change, so old cache entries are not reused


def default_cache_dir() -> Path:
    return Path(os.environ.get("FDNET_CACHE") or Path.home() / ".cache" / "fdnet") / "filters"


def _cache_file(dataset: RouteDataset, settings: FilterSettings, cache_dir: str | os.PathLike | None) -> Path:
    """Cache entry named by the settings and every file (path, size, modification time), so an
    edited, added or removed image means a new entry."""
    fingerprint = hashlib.sha1()
    fingerprint.update(
        json.dumps(
            {
                "rule": FILTER_RULE,
                "dark_threshold": settings.dark_threshold,
                "duplicate_threshold": settings.duplicate_threshold,
                "thumbnail_size": list(settings.thumbnail_size),
            },
            sort_keys=True,
        ).encode()
    )
    for name, traverse in sorted(dataset.traverses.items()):
        fingerprint.update(name.encode())
        for path in traverse.paths:
            st = path.stat()
            fingerprint.update(f"{path.resolve()}|{st.st_size}|{st.st_mtime_ns}".encode())
    base = Path(cache_dir) if cache_dir else default_cache_dir()
    return base / f"{fingerprint.hexdigest()}.json"


def _read_cache(cache_file: Path, num_frames: int) -> tuple[np.ndarray, str] | None:
    try:
        cached = json.loads(cache_file.read_text())
        kept = np.asarray(cached["kept_positions"], dtype=np.int64)
        summary = str(cached["summary"])
    except (OSError, ValueError, KeyError, TypeError):
        return None  # absent or unreadable: recompute
    if kept.ndim != 1 or (len(kept) and (kept.min() < 0 or kept.max() >= num_frames)):
        return None
    return kept, summary


def filter_frames(
    dataset: RouteDataset,
    dark_threshold: float | None = 0.1,
    duplicate_threshold: float | None = 0.01,
    thumbnail_size: tuple[int, int] = (16, 32),
    cache_dir: str | os.PathLike | None = None,
    use_cache: bool = True,
) -> tuple[RouteDataset, str]:
    """The paper's removal of tunnel (dark) and near-duplicate (stationary) frames from a
    frame-aligned route, as every command and adapter applies it: a position dropped in any
    condition is dropped from all (:func:`filter_route`).

    The kept positions are cached as JSON under ``cache_dir`` (default ``$FDNET_CACHE/filters``
    or ``~/.cache/fdnet/filters``), keyed by the settings and the files (paths, sizes,
    modification times); a cache that cannot be written is skipped, not an error. Returns the
    filtered route (``frame_ids`` kept) and a one-line summary of what was dropped.
    """
    settings = FilterSettings(dark_threshold, duplicate_threshold, tuple(thumbnail_size))
    num_frames = max((len(t) for t in dataset.traverses.values()), default=0)
    cache_file = _cache_file(dataset, settings, cache_dir) if use_cache else None
    cached = _read_cache(cache_file, num_frames) if cache_file is not None else None
    if cached is not None and all(len(t) == num_frames for t in dataset.traverses.values()):
        kept, summary = cached
    else:
        _, report = filter_route(
            dataset, settings.dark_threshold, settings.duplicate_threshold, settings.thumbnail_size
        )
        kept, summary = np.asarray(report.kept, dtype=np.int64), report.summary()
        if cache_file is not None:
            from fdnet.io import atomic_write_text

            try:
                atomic_write_text(
                    cache_file,
                    json.dumps({"kept_positions": kept.tolist(), "summary": summary, "report": report.to_dict()}),
                )
            except OSError:
                pass  # a read-only home or cache folder only costs the next run the detector pass
    filtered = RouteDataset(dataset.root, {name: t.select(kept) for name, t in dataset.traverses.items()})
    return filtered, summary
