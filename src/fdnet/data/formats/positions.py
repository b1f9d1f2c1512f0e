"""Position files: one row per image in traversal order, with a header naming the columns.

Accepted columns (case-insensitive, first match wins):

* image: ``image``, ``image_name``, ``filename``, ``file``, ``name``, ``path``, ``img`` (optional:
  without it rows are the images in order);
* degrees: ``lat``/``latitude`` and ``lon``/``lng``/``long``/``longitude``;
* metres: ``easting``/``east``/``utm_easting``/``x`` and ``northing``/``north``/``utm_northing``/``y``.

Degrees are projected to local planar metres about one origin shared by the reference and the
query (:func:`fdnet.data.groundtruth.latlon_to_metres`). Files with no header (e.g. a GPS log)
are read by giving ``columns``: the meaning of each column in order, ``-`` for one to skip
(``"-,lat,lon"``). Errors name the file and line.
"""

from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from fdnet.data.formats._common import read_text_lines
from fdnet.data.groundtruth import GroundTruth, latlon_to_metres
from fdnet.errors import DataError

IMAGE_COLUMNS = ("image", "image_name", "imagename", "filename", "file", "file_name", "name", "path", "img")
LAT_COLUMNS = ("lat", "latitude")
LON_COLUMNS = ("lon", "lng", "long", "longitude")
EAST_COLUMNS = ("easting", "east", "utm_easting", "utm_east", "x")
NORTH_COLUMNS = ("northing", "north", "utm_northing", "utm_north", "y")
TIME_COLUMNS = ("timestamp", "time", "t", "stamp")


@dataclass
class PositionTable:
    """Positions read from one file. ``values`` are (lat, lon) degrees or (easting, northing) metres."""

    path: Path
    kind: str  # "degrees" or "metres"
    values: np.ndarray  # (N, 2) float64
    images: list[str] | None = None
    timestamps: np.ndarray | None = None
    lines: list[int] | None = None  # file line of each row, for error messages

    def __len__(self) -> int:
        return len(self.values)


def _find(header: list[str], names: Sequence[str]) -> int | None:
    for name in names:
        if name in header:
            return header.index(name)
    return None


def _sniff_delimiter(line: str) -> str | None:
    for d in (",", "\t", ";"):
        if d in line:
            return d
    return None  # whitespace


def read_positions(
    path: str | os.PathLike, image_column: str | None = None, columns: Sequence[str] | str | None = None
) -> PositionTable:
    """Read a position file (see the module docstring for the accepted columns)."""
    path = Path(path)
    lines = read_text_lines(path, "position file", "not a text (CSV) file")
    if not lines:
        raise DataError(f"{path}: empty position file")
    delimiter = _sniff_delimiter(lines[0][1])

    def cells(line: str) -> list[str]:
        if delimiter is None:
            return line.split()
        return [c.strip() for c in next(csv.reader(io.StringIO(line), delimiter=delimiter))]

    if columns is not None:
        header = [c.strip().lower() for c in (columns.split(",") if isinstance(columns, str) else columns)]
        rows = lines
        # a header line present anyway (no cell of it is a number) is skipped
        if not any(_is_number(c) for c in cells(rows[0][1])):
            rows = rows[1:]
    else:
        header = [c.strip().lower() for c in cells(lines[0][1])]
        rows = lines[1:]
        if header and all(_is_number(c) for c in header):
            raise DataError(
                f"{path}, line {lines[0][0]}: no header; the first line must name the columns "
                f"(an image column and lat,lon or easting,northing), or give the column meanings"
            )
    if image_column is not None:
        img_idx = _find(header, [image_column.lower()])
        if img_idx is None:
            raise DataError(f"{path}: no column {image_column!r}; columns: {', '.join(header)}")
    else:
        img_idx = _find(header, IMAGE_COLUMNS)
    lat_idx, lon_idx = _find(header, LAT_COLUMNS), _find(header, LON_COLUMNS)
    east_idx, north_idx = _find(header, EAST_COLUMNS), _find(header, NORTH_COLUMNS)
    time_idx = _find(header, TIME_COLUMNS)
    if lat_idx is not None and lon_idx is not None:
        kind, a_idx, b_idx = "degrees", lat_idx, lon_idx
    elif east_idx is not None and north_idx is not None:
        kind, a_idx, b_idx = "metres", east_idx, north_idx
    else:
        raise DataError(
            f"{path}: missing position columns; need lat,lon (degrees) or easting,northing (metres), "
            f"found: {', '.join(h for h in header if h) or 'none'}"
        )
    if not rows:
        raise DataError(f"{path}: has a header but no position rows")

    values = np.empty((len(rows), 2), dtype=np.float64)
    images: list[str] = []
    stamps = np.empty(len(rows), dtype=np.float64) if time_idx is not None else None
    needed = max(i for i in (a_idx, b_idx, img_idx, time_idx) if i is not None) + 1
    for k, (line_no, line) in enumerate(rows):
        row = cells(line)
        if len(row) < needed:
            raise DataError(
                f"{path}, line {line_no}: expected {len(header)} columns " f"({', '.join(header)}), got {len(row)}"
            )
        for j, idx in enumerate((a_idx, b_idx)):
            try:
                v = float(row[idx])
            except ValueError as exc:
                raise DataError(f"{path}, line {line_no}: {header[idx]} is not a number: {row[idx]!r}") from exc
            if not math.isfinite(v):
                raise DataError(f"{path}, line {line_no}: {header[idx]} is not a finite number: {row[idx]!r}")
            values[k, j] = v
        if stamps is not None:
            try:
                stamps[k] = float(row[time_idx])
            except ValueError as exc:
                raise DataError(
                    f"{path}, line {line_no}: {header[time_idx]} is not a number: " f"{row[time_idx]!r}"
                ) from exc
        if img_idx is not None:
            images.append(row[img_idx])
        if kind == "degrees" and not (-90 <= values[k, 0] <= 90 and -180 <= values[k, 1] <= 180):
            raise DataError(
                f"{path}, line {line_no}: latitude {values[k, 0]:g}, longitude {values[k, 1]:g} "
                f"out of range (degrees expected)"
            )
    return PositionTable(path, kind, values, images if img_idx is not None else None, stamps, [no for no, _ in rows])


def _is_number(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def to_metres(reference: PositionTable, *others: PositionTable) -> list[np.ndarray]:
    """Planar metres for several tables on one common origin (the reference's mean)."""
    tables = (reference, *others)
    kinds = {t.kind for t in tables}
    if len(kinds) > 1:
        raise DataError(
            f"{reference.path} and {others[0].path}: one has lat,lon degrees and the other "
            f"easting,northing metres; give both in the same units"
        )
    if kinds == {"metres"}:
        return [t.values.copy() for t in tables]
    origin = (float(reference.values[:, 0].mean()), float(reference.values[:, 1].mean()))
    return [latlon_to_metres(t.values[:, 0], t.values[:, 1], origin) for t in tables]


def positions_ground_truth(reference: PositionTable, query: PositionTable, tolerance_m: float) -> GroundTruth:
    """References within ``tolerance_m`` metres of each query (rows = the query file's images)."""
    ref_xy, qry_xy = to_metres(reference, query)
    gt = GroundTruth.from_positions(qry_xy, ref_xy, tolerance_m)
    gt.description = f"positions ({reference.path.name}, {query.path.name}), tolerance {tolerance_m:g} m"
    return gt


def align_to_images(table: PositionTable, image_paths: Sequence[Path], where: Path) -> np.ndarray:
    """Row of ``table`` for each image: by the image column (file name or stem) when present, else
    row i = image i (then the counts must agree). Returns (N,) row indices."""
    if table.images is None:
        if len(table) != len(image_paths):
            raise DataError(
                f"{table.path}: has {len(table)} position rows but {where} has "
                f"{len(image_paths)} images; rows must be one per image in order "
                f"(or add an image column)"
            )
        return np.arange(len(image_paths))
    index: dict[str, int] = {}
    for k, name in enumerate(table.images):
        index.setdefault(Path(name).name, k)
        index.setdefault(Path(name).stem, k)
    rows = []
    for p in image_paths:
        k = index.get(p.name, index.get(p.stem))
        if k is None:
            raise DataError(f"{table.path}: no position row for image {p.name} of {where}")
        rows.append(k)
    return np.asarray(rows, dtype=np.int64)


def source_positions(path: str | os.PathLike, options=None) -> PositionTable:
    """A ROS bag's frames with their positions interpolated from its NavSatFix or Odometry topic
    (:func:`fdnet.data.sources.open_source`) as a :class:`PositionTable`, what a position CSV gives:
    one row per frame, named by the frame. Every frame needs a position."""
    from fdnet.data.sources import open_source

    listing = open_source(path, options)
    where = f"{listing.source}" + (f", topic {listing.topic}" if listing.topic else "")
    if listing.positions is None:
        raise DataError(
            f"{where}: no positions for its frames: "
            + (
                "a video has none"
                if listing.kind == "video"
                else "the bag has no single NavSatFix or Odometry topic; name one with --position-topic"
            )
        )
    missing = np.flatnonzero(~np.isfinite(listing.positions).all(axis=1))
    if len(missing):
        first = listing.paths[missing[0]].name
        raise DataError(
            f"{where}: {len(missing)} of {len(listing.paths)} frames (e.g. {first}) lie outside the "
            f"time span of the positions on {listing.position_topic}; narrow the frames with --window"
        )
    return PositionTable(
        Path(os.fspath(path)),
        listing.position_kind,
        listing.positions.copy(),
        images=[p.name for p in listing.paths],
        timestamps=listing.times.copy(),
        lines=[i + 1 for i in range(len(listing.paths))],
    )
