"""Nordland (NRK "Nordlandsbanen: minute by minute, season by season", 2012; dataset by S. Skrede,
CC BY 3.0; Sünderhauf, Neubert, Protzel, "Are we there yet? Challenging SeqSLAM on a 3000 km
journey across all four seasons", ICRA workshop 2013).

Two published layouts are read:

* **per season** (the 1 fps frame release and its downsampled/trimmed copies such as
  ``../shared/data/nordland_trimmed``): ``root/<season>/`` with ``<season>`` one of spring,
  summer, fall (or autumn), winter, possibly decorated (``summer_images``, ``nordland_winter``...),
  images directly inside or in an ``images``/``frames``/``image_rgb`` sub-folder. Frames are
  aligned across seasons by the number in their file name (``images-00010.png`` -> frame 10 of
  the 1 fps sequence), so a trimmed copy that keeps every 10th frame stays correctly aligned.
* **partitioned** (Olid, Fácil, Civera, "Single-View Place Recognition under Seasonal Changes",
  PPNIV @ IROS 2018): ``root/{train,test}/<season>_images_{train,test}/section<k>/<n>.png``,
  tunnels and stops already removed; the named splits are its two partitions.

Protocol (Qin et al., section 5.2.1 and Table 1): one frame per second, tunnel and stationary
frames removed, tolerance 5 frames. The paper trains on 27000 frames and tests on 1000 but does
not say which; here ``test`` is the last 1000 frames left after filtering and ``train`` everything
before them (for the full 28k-frame release that is exactly 27000 + 1000). On the partitioned
release ``START:END`` slices the test (evaluation) or train (training) partition.

Not confirmed: whether the partitioned release numbers files uniquely across sections; if it does
not, each section's numbers are offset by 1,000,000 so frames of different sections never match.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fdnet.data.dataset import RouteDataset, Traverse
from fdnet.data.filters import filter_frames
from fdnet.data.formats._common import (
    DatasetFormat,
    common_frames,
    describe,
    frame_numbers,
    image_folder,
    pick_conditions,
    resolve_split,
)
from fdnet.data.groundtruth import GroundTruth
from fdnet.data.images import list_images, natural_key
from fdnet.data.split import EvaluationSplit
from fdnet.errors import DataError

SEASONS = ("spring", "summer", "fall", "winter")
_SEASON_WORDS = {"spring": "spring", "summer": "summer", "fall": "fall", "autumn": "fall", "winter": "winter"}
TEST_FRAMES = 1000
SPLITS = {
    "test": lambda n: (max(n - TEST_FRAMES, 0), None),
    "train": lambda n: (0, max(n - TEST_FRAMES, 0)),
}
SECTION_OFFSET = 1_000_000


@dataclass
class NordlandOptions:
    tolerance: int = 5  # frames of the 1 fps sequence (Table 1)
    filter_frames: bool | None = None  # drop tunnel/stationary frames; None = yes unless partitioned
    filter_cache: str | None = None  # where kept frame numbers are cached (default $FDNET_CACHE/filters)


def season_of(name: str) -> str | None:
    words = re.split(r"[^a-z]+", name.lower())
    found = {_SEASON_WORDS[w] for w in words if w in _SEASON_WORDS}
    return found.pop() if len(found) == 1 else None


def season_folders(root: Path) -> dict[str, Path]:
    """season -> image folder, for the per-season layout."""
    out: dict[str, Path] = {}
    if not root.is_dir():
        return out
    for child in sorted(root.iterdir()):
        season = season_of(child.name) if child.is_dir() else None
        if season is None or season in out:
            continue
        try:
            out[season] = image_folder(child, ("images", "frames", "image_rgb", "img"))
        except DataError:
            continue
    return out


def is_partitioned(root: Path) -> bool:
    return any(_partition_folders(root, part) for part in ("train", "test"))


def _partition_folders(root: Path, partition: str) -> dict[str, Path]:
    base = root / partition
    out: dict[str, Path] = {}
    if not base.is_dir():
        return out
    for child in sorted(base.iterdir()):
        if (
            child.is_dir()
            and f"_images_{partition}" in child.name.lower()
            and not child.name.endswith(("_illumination", "_viewpoint"))
        ):
            season = season_of(child.name.lower().split("_images_")[0])
            if season and season not in out:
                out[season] = child
    return out


def read_season(folder: Path, season: str) -> Traverse:
    paths = list_images(folder)
    return Traverse(season, paths, frame_ids=frame_numbers(paths, folder))


def read_partition_season(folder: Path, season: str) -> Traverse:
    """Sections in natural order, frames by number inside each section."""
    sections = sorted((p for p in folder.iterdir() if p.is_dir()), key=lambda p: natural_key(p.name))
    if not sections:  # some copies flatten the sections
        return read_season(folder, season)
    paths: list[Path] = []
    ids: list[np.ndarray] = []
    for k, section in enumerate(sections):
        section_paths = list_images(section)
        paths += section_paths
        ids.append(frame_numbers(section_paths, section) + k * SECTION_OFFSET)
    all_ids = np.concatenate(ids)
    plain = all_ids % SECTION_OFFSET
    if len(np.unique(plain)) == len(plain):
        all_ids = plain  # numbers are unique across sections: keep the published numbering
    return Traverse(season, paths, frame_ids=all_ids)


class NordlandFormat(DatasetFormat):
    name = "nordland"
    summary = "Nordland four seasons: per-season folders (1 fps, trimmed) or the Olid et al. partition"
    Options = NordlandOptions
    splits = {
        "test": f"last {TEST_FRAMES} frames after filtering (partitioned: test/)",
        "train": "all frames before the test ones (partitioned: train/)",
    }
    default_eval_split = "test"
    default_train_split = "train"

    def detect(self, root: Path) -> bool:
        return len(season_folders(root)) >= 2 or is_partitioned(root)

    # -- reading -----------------------------------------------------------------------------
    def _route(
        self, root: Path, conditions, split: str | None, options: NordlandOptions, partition_for_ranges: str
    ) -> tuple[RouteDataset, str]:
        """The chosen seasons, filtered, then cut to ``split``; plus a note on the filtering.

        The filter looks at every season present (a frame dark in any season is dropped from all),
        so the frames of, say, the test split are the same whichever pair is evaluated.
        """
        if is_partitioned(root):
            partition = split if split in ("train", "test") else partition_for_ranges
            folders = _partition_folders(root, partition)
            if not folders:
                raise DataError(
                    f"{root / partition}: no <season>_images_{partition} folders " f"(partitioned Nordland layout)"
                )
            available = [s for s in SEASONS if s in folders]
            chosen = pick_conditions(available, conditions, root / partition)
            route = RouteDataset(root, {s: read_partition_season(folders[s], s) for s in available})
            filter_on = bool(options.filter_frames)  # the partition is already filtered
            rules: dict = {}
        else:
            folders = season_folders(root)
            if not folders:
                raise DataError(
                    f"{root}: no season folders (expected spring/, summer/, fall/, winter/ "
                    f"or {root}/train|test/<season>_images_*)"
                )
            available = [s for s in SEASONS if s in folders]
            chosen = pick_conditions(available, conditions, root)
            route = RouteDataset(root, {s: read_season(folders[s], s) for s in available})
            filter_on = options.filter_frames is None or bool(options.filter_frames)
            rules = SPLITS
        route = common_frames(route)
        note = ""
        if filter_on:
            route, note = filter_frames(route, cache_dir=options.filter_cache)
        route = RouteDataset(root, {s: route[s] for s in chosen})
        if is_partitioned(root) and split in ("train", "test"):
            return route, note
        return self._cut(route, split, rules, root), note

    @staticmethod
    def _cut(route: RouteDataset, split, rules, root: Path) -> RouteDataset:
        """Apply a split to the (common, aligned) frames of every season."""
        length = min(len(t) for t in route.traverses.values())
        start, end = resolve_split(split, rules, length, str(root))
        return route.frames(start, end)

    # -- protocol ----------------------------------------------------------------------------
    def evaluation_split(self, root, reference, query, split, options: NordlandOptions) -> EvaluationSplit:
        reference = reference or "summer"
        query = query or "winter"
        route, note = self._route(root, [reference, query], split, options, partition_for_ranges="test")
        ref, qry = route[reference], route[query]
        if len(ref) == 0 or len(qry) == 0:
            raise DataError(f"{root}: split {split!r} leaves no frames of {reference} or {query}")
        gt = GroundTruth.from_frames(qry.frame_ids, ref.frame_ids, options.tolerance)
        step = int(np.median(np.diff(np.sort(ref.frame_ids)))) if len(ref) > 1 else 1
        if step > 1:  # a trimmed copy (every 10th frame): say what the 1 fps tolerance means here
            gt.description = (
                f"frame-aligned, tolerance {options.tolerance} frames of the 1 fps sequence = "
                f"{options.tolerance // step} of these files ({step} frames apart)"
            )
        extra = f"split {split or 'all'}" + (f", frame filter: {note}" if note else "")
        return EvaluationSplit(ref, qry, gt, describe(root, qry, ref, gt, extra))

    def training_dataset(self, root, split, conditions, options) -> RouteDataset:
        return self._route(root, conditions, split, options, partition_for_ranges="train")[0]


FORMAT = NordlandFormat()
