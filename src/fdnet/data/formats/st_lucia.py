"""St Lucia multiple times of day (Glover, Maddern, Milford, Wyeth, "FAB-MAP + RatSLAM: Appearance-based
SLAM for multiple times of day", ICRA 2010).

A car with a forward-facing roof camera drove the same route through the suburb of St Lucia,
Brisbane, at several times of day; each run is named by date and time (``DDMMYY_HHMM``) and
comes with GPS. Expected folder::

    st_lucia/190809_0845/<frames>  + a GPS file      early morning
    st_lucia/180809_1545/<frames>  + a GPS file      late afternoon
    (frames directly inside the run folder, or in images/ or frames/)

Protocol (Qin et al. 5.2.1, Table 1): 190809_0845 (reference) against 180809_1545 (query),
images extracted from the 15 fps videos, the first 3500 for training and the next 500 for
evaluation, tolerance 30 m from the provided GPS.

Not confirmed from public sources here, hence settings: the GPS file's name (looked up as
``fGPS.txt``, ``gps.csv``, ``gps.txt``, ``*gps*``; ``gps_file=NAME``) and its columns. It is read
with :mod:`fdnet.data.formats.positions`: a header naming lat,lon or easting,northing (and
optionally an image column), or ``gps_columns="-,lat,lon"`` for a headerless log. Without an image
column, row i is frame i. Frames must already be extracted from the videos (e.g.
``ffmpeg -i video.avi <run>/frames/%05d.png``); this adapter does not decode video.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from fdnet.data.dataset import RouteDataset, Traverse
from fdnet.data.formats._common import (
    DatasetFormat,
    describe,
    find_child,
    fixed,
    image_folder,
    pick_conditions,
    resolve_split,
)
from fdnet.data.formats.positions import PositionTable, align_to_images, read_positions, to_metres
from fdnet.data.groundtruth import GroundTruth
from fdnet.data.images import list_images
from fdnet.data.split import EvaluationSplit
from fdnet.errors import ConfigError, DataError

RUN_NAME = re.compile(r"^\d{6}_\d{4}$")
TRAIN_FRAMES, TEST_FRAMES = 3500, 500
GPS_NAMES = ("fGPS.txt", "gps.csv", "GPS.csv", "gps.txt", "GPS.txt")
GPS_GLOBS = ("*gps*.csv", "*GPS*.csv", "*gps*.txt", "*GPS*.txt")


@dataclass
class StLuciaOptions:
    tolerance_m: float = 30.0
    gps_file: str | None = None  # file name inside each run folder
    gps_columns: str | None = None  # column meanings for a headerless file, e.g. "-,lat,lon"
    image_column: str | None = None


def run_folders(root: Path) -> list[str]:
    if not root.is_dir():
        return []
    return sorted(p.name for p in root.iterdir() if p.is_dir() and RUN_NAME.match(p.name))


def gps_file(run: Path, given: str | None) -> Path:
    if given:
        path = run / given
        if not path.is_file():
            raise DataError(f"{path}: GPS file not found")
        return path
    found = find_child(run, GPS_NAMES, kind="file")
    if found:
        return found
    for pattern in GPS_GLOBS:
        matches = sorted(run.glob(pattern))
        if matches:
            return matches[0]
    raise DataError(
        f"{run}: missing the GPS file (looked for {', '.join(GPS_NAMES)}); " f"give its name with gps_file=NAME"
    )


class StLuciaFormat(DatasetFormat):
    name = "st_lucia"
    summary = "St Lucia times of day: run folders (DDMMYY_HHMM) of frames with their GPS fixes"
    Options = StLuciaOptions
    splits = {"train": f"frames 0:{TRAIN_FRAMES}", "test": f"frames {TRAIN_FRAMES}:{TRAIN_FRAMES + TEST_FRAMES}"}
    split_rules = {"train": fixed(0, TRAIN_FRAMES), "test": fixed(TRAIN_FRAMES, TRAIN_FRAMES + TEST_FRAMES)}
    default_eval_split = "test"
    default_train_split = "train"

    def detect(self, root: Path) -> bool:
        return len(run_folders(root)) >= 2

    def read_run(self, root: Path, name: str, options: StLuciaOptions) -> tuple[Traverse, PositionTable]:
        """One run's frames and the GPS row of each frame (still in the file's units)."""
        run = root / name
        if not run.is_dir():
            raise DataError(f"{run}: run folder not found; runs here: {', '.join(run_folders(root)) or 'none'}")
        folder = image_folder(run)
        paths = list_images(folder)
        table = read_positions(gps_file(run, options.gps_file), options.image_column, options.gps_columns)
        rows = align_to_images(table, paths, folder)
        return Traverse(name, paths), PositionTable(table.path, table.kind, table.values[rows])

    def _pair(self, root: Path, reference, query) -> tuple[str, str]:
        runs = run_folders(root)
        if reference and query:
            return reference, query
        if {"190809_0845", "180809_1545"} <= set(runs):
            return reference or "190809_0845", query or "180809_1545"
        if len(runs) == 2:
            return reference or runs[0], query or runs[1]
        raise ConfigError(f"{root}: runs {', '.join(runs)}; name the pair with --reference and --query")

    @staticmethod
    def _planar(runs: list[tuple[Traverse, PositionTable]]) -> list[Traverse]:
        """Set every traverse's positions in metres on one shared origin."""
        for (traverse, _), xy in zip(runs, to_metres(*[table for _, table in runs])):
            traverse.positions = xy
        return [traverse for traverse, _ in runs]

    def evaluation_split(self, root, reference, query, split, options: StLuciaOptions) -> EvaluationSplit:
        reference, query = self._pair(root, reference, query)
        ref_full, qry_full = self._planar(
            [self.read_run(root, reference, options), self.read_run(root, query, options)]
        )
        start, end = resolve_split(split, self.split_rules, min(len(ref_full), len(qry_full)), str(root))
        ref, qry = ref_full.frames(start, end), qry_full.frames(start, end)
        gt = GroundTruth.from_positions(qry.positions, ref.positions, options.tolerance_m)
        return EvaluationSplit(ref, qry, gt, describe(root, qry, ref, gt, f"split {split or 'all'}"))

    def training_dataset(self, root, split, conditions, options) -> RouteDataset:
        runs = pick_conditions(run_folders(root), conditions, root)
        traverses = self._planar([self.read_run(root, r, options) for r in runs])
        start, end = resolve_split(split, self.split_rules, min(len(t) for t in traverses), str(root))
        return RouteDataset(root, {t.name: t.frames(start, end) for t in traverses})


FORMAT = StLuciaFormat()
