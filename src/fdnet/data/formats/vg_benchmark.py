"""Deep Visual Geo-localization Benchmark layout (Berton, Mereu, Trivigno, Masone, Csurka, Sattler,
Caputo, CVPR 2022; https://github.com/gmberton/VPR-datasets-downloader), in which St Lucia,
Pittsburgh, Tokyo 24/7, SF-XL... are commonly distributed::

    st_lucia/images/test/database/@0551583.12@5069506.43@55@J@...@.jpg
    st_lucia/images/test/queries/@...@.jpg
    (also images/train/, images/val/)

Each file name carries its UTM position: the fields after the first and second ``@`` are easting
and northing in metres (the toolkits' comment: "path/to/file/@utm_easting@utm_northing@...@.jpg").
Positives are the database images within ``tolerance_m`` (25 m, the benchmark's default) of a
query. Images are found recursively and listed in fdnet's one image order (natural order of the
path below the folder, :func:`fdnet.data.images.list_images`). Where every numeric field of the
names has the same width (zero-padded, as in the example above) that is the benchmark's own
``sorted(glob(...))`` order; otherwise a similarity matrix computed by the benchmark's code may
have its rows in another order (compare with ``fdnet evaluate --similarity`` only after checking).
The named splits are the folders under ``images/`` (``test`` by default, ``val``, ``train``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fdnet.data.dataset import RouteDataset, Traverse, parse_frame_range
from fdnet.data.formats._common import DatasetFormat, describe
from fdnet.data.groundtruth import GroundTruth
from fdnet.data.images import list_images
from fdnet.data.split import EvaluationSplit
from fdnet.errors import DataError

PARTS = ("test", "val", "train")


@dataclass
class VGBenchmarkOptions:
    tolerance_m: float = 25.0
    database: str = "database"
    queries: str = "queries"  # e.g. queries_night for SVOX


def _split_folder(root: Path, split: str) -> Path:
    """``root/images/<split>``, or ``root`` itself when it already holds database/ and queries/."""
    if (root / "database").is_dir():
        return root
    folder = root / "images" / split
    if not folder.is_dir():
        available = [p for p in PARTS if (root / "images" / p).is_dir()]
        raise DataError(f"{folder}: folder not found; splits here: {', '.join(available) or 'none'}")
    return folder


def read_utm_folder(folder: Path, name: str) -> Traverse:
    if not folder.is_dir():
        raise DataError(f"{folder}: folder not found (the geo-localization layout has database/ and queries/)")
    paths = list_images(folder, recursive=True)
    xy = np.empty((len(paths), 2), dtype=np.float64)
    for i, p in enumerate(paths):
        fields = p.name.split("@")
        try:
            xy[i] = float(fields[1]), float(fields[2])
        except (IndexError, ValueError) as exc:
            raise DataError(
                f"{p}: file name does not carry its position; expected " f"@utm_easting@utm_northing@...@{p.suffix}"
            ) from exc
    return Traverse(name, paths, positions=xy)


class VGBenchmarkFormat(DatasetFormat):
    name = "vg_benchmark"
    summary = "geo-localization benchmark: images/<split>/database|queries with @easting@northing@ names"
    Options = VGBenchmarkOptions
    splits = {"test": "images/test", "val": "images/val", "train": "images/train"}
    default_eval_split = "test"
    default_train_split = "train"

    def detect(self, root: Path) -> bool:
        for folder in [root, *(root / "images" / p for p in PARTS)]:
            db = folder / "database"
            if db.is_dir() and (folder / "queries").is_dir():
                return next(db.rglob("@*"), None) is not None  # stops at the first hit
        return False

    def _part_and_range(self, split: str | None, default: str):
        if split in PARTS:
            return split, (None, None)
        if split in (None, "", "all"):
            return default, (None, None)
        if ":" in split:
            return default, parse_frame_range(split)
        raise DataError(f"no split named {split!r}; named splits: {', '.join(PARTS)}, or START:END (queries)")

    def evaluation_split(self, root, reference, query, split, options: VGBenchmarkOptions) -> EvaluationSplit:
        part, (start, end) = self._part_and_range(split, "test")
        folder = _split_folder(root, part)
        ref = read_utm_folder(folder / (reference or options.database), reference or options.database)
        qry = read_utm_folder(folder / (query or options.queries), query or options.queries).frames(start, end)
        gt = GroundTruth.from_positions(qry.positions, ref.positions, options.tolerance_m)
        return EvaluationSplit(ref, qry, gt, describe(root, qry, ref, gt, f"split {part}"))

    def training_dataset(self, root, split, conditions, options: VGBenchmarkOptions) -> RouteDataset:
        part, (start, end) = self._part_and_range(split, "train")
        folder = _split_folder(root, part)
        names = list(conditions) if conditions else [options.database, options.queries]
        return RouteDataset(root, {n: read_utm_folder(folder / n, n).frames(start, end) for n in names})


FORMAT = VGBenchmarkFormat()
