"""Ground truth: which references count as a correct match for each query.

Three ways to build it, one type to use it:

* frame-aligned (Nordland, Gardens Point, Alderley, FAS): query frame ``i`` matches reference
  frames within ``tolerance`` frames of ``i``;
* positions (Oxford RobotCar, St Lucia, own routes): references within ``tolerance_m`` metres;
* an explicit list per query (VPR-Bench style CSV ``query_index,reference_indices``).

Stored sparsely (one sorted index array per query) so 100k x 100k maps fit in memory.

Indices are positions in :func:`fdnet.data.images.list_images` order. A CSV written with image
names (``fdnet groundtruth`` writes ``query_index,reference_indices,query_name,reference_names``)
lets a reader check that its indices still mean the images being evaluated
(:meth:`GroundTruth.check_names`); the two-column VPR-Bench form has no names to check.
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

from fdnet.errors import DataError
from fdnet.io import atomic_write_text, from_spreadsheet_text, spreadsheet_text

# Separates the names in the reference_names column. A file name can contain spaces and commas
# but never "/" (on POSIX, and on Windows), so no name is ever split in two.
NAME_SEPARATOR = "/"
NAMED_HEADER = ["query_index", "reference_indices", "query_name", "reference_names"]


@dataclass
class NamedRow:
    """One row of a ground-truth CSV that carries names: its line, indices and the names the file
    says those indices stand for."""

    line: int
    query: int
    query_name: str
    references: list[int]
    reference_names: list[str]


@dataclass
class ListedNames:
    """The image names a ground-truth CSV was written for (see :meth:`GroundTruth.check_names`)."""

    path: Path
    rows: list[NamedRow]


@dataclass
class GroundTruth:
    positives: list[np.ndarray]
    num_references: int
    description: str = ""
    listed_names: ListedNames | None = None  # set by from_csv when the file has name columns

    def __post_init__(self) -> None:
        self.positives = [np.unique(np.asarray(p, dtype=np.int64)) for p in self.positives]

    # ------------------------------------------------------------------ queries
    @property
    def num_queries(self) -> int:
        return len(self.positives)

    @property
    def has_match(self) -> np.ndarray:
        """(Q,) bool: queries with at least one correct reference."""
        return np.array([len(p) > 0 for p in self.positives], dtype=bool)

    def is_correct(self, query: int, reference: int) -> bool:
        p = self.positives[query]
        i = np.searchsorted(p, reference)
        return bool(i < len(p) and p[i] == reference)

    def correct_mask(self, retrieved: np.ndarray) -> np.ndarray:
        """(Q, k) retrieved reference indices -> (Q, k) bool, True where correct."""
        retrieved = np.asarray(retrieved)
        if retrieved.ndim == 1:
            retrieved = retrieved[:, None]
        if retrieved.shape[0] != self.num_queries:
            raise DataError(f"ground truth has {self.num_queries} queries but {retrieved.shape[0]} were matched")
        out = np.zeros(retrieved.shape, dtype=bool)
        for q, p in enumerate(self.positives):
            if len(p):
                out[q] = np.isin(retrieved[q], p)
        return out

    def dense(self) -> np.ndarray:
        """(Q, R) bool matrix (for small sets and plots)."""
        m = np.zeros((self.num_queries, self.num_references), dtype=bool)
        for q, p in enumerate(self.positives):
            m[q, p] = True
        return m

    def subset(
        self, query_indices: Sequence[int] | None = None, reference_indices: Sequence[int] | None = None
    ) -> "GroundTruth":
        """Restrict to some queries and references, re-indexing the references. (The result
        carries no file names: check them with :meth:`check_names` before taking a subset.)"""
        q_idx = np.arange(self.num_queries) if query_indices is None else np.asarray(query_indices)
        if reference_indices is None:
            return GroundTruth([self.positives[q] for q in q_idx], self.num_references, self.description)
        r_idx = np.asarray(reference_indices)
        remap = np.full(self.num_references, -1, dtype=np.int64)
        remap[r_idx] = np.arange(len(r_idx))
        positives = []
        for q in q_idx:
            mapped = remap[self.positives[q]]
            positives.append(mapped[mapped >= 0])
        return GroundTruth(positives, len(r_idx), self.description)

    # ------------------------------------------------------------------ builders
    @classmethod
    def from_frames(
        cls, query_frames: Sequence[int] | np.ndarray, reference_frames: Sequence[int] | np.ndarray, tolerance: int
    ) -> "GroundTruth":
        """Frame-aligned: query with frame id f matches references with |frame id - f| <= tolerance.

        Frame ids (not list positions) are compared, so filtered or sliced traverses stay aligned.
        """
        if tolerance < 0:
            raise DataError(f"frame tolerance must be >= 0, got {tolerance}")
        qf = np.asarray(query_frames, dtype=np.int64)
        rf = np.asarray(reference_frames, dtype=np.int64)
        order = np.argsort(rf, kind="stable")
        sorted_rf = rf[order]
        lo = np.searchsorted(sorted_rf, qf - tolerance, side="left")
        hi = np.searchsorted(sorted_rf, qf + tolerance, side="right")
        positives = [np.sort(order[a:b]) for a, b in zip(lo, hi)]
        return cls(positives, len(rf), f"frame-aligned, tolerance {tolerance} frames")

    @classmethod
    def aligned(cls, num_queries: int, num_references: int, tolerance: int) -> "GroundTruth":
        """Frame-aligned traverses of the given lengths, frame i <-> frame i."""
        return cls.from_frames(np.arange(num_queries), np.arange(num_references), tolerance)

    @classmethod
    def from_positions(cls, query_xy: np.ndarray, reference_xy: np.ndarray, tolerance_m: float) -> "GroundTruth":
        """References within ``tolerance_m`` metres (Euclidean, planar metres) of each query."""
        from scipy.spatial import cKDTree

        if (
            isinstance(tolerance_m, bool)
            or not isinstance(tolerance_m, (int, float, np.integer, np.floating))
            or not np.isfinite(tolerance_m)
            or tolerance_m < 0
        ):
            # one place for every caller (fdnet groundtruth, the formats with GPS): NaN would match nothing
            raise DataError(f"a position tolerance must be a finite number of metres >= 0, got {tolerance_m!r}")
        q = np.asarray(query_xy, dtype=np.float64)
        r = np.asarray(reference_xy, dtype=np.float64)
        if q.ndim != 2 or r.ndim != 2 or q.shape[1] != r.shape[1]:
            raise DataError(f"positions must be (N, 2) arrays, got {q.shape} and {r.shape}")
        tree = cKDTree(r)
        positives = [np.asarray(p, dtype=np.int64) for p in tree.query_ball_point(q, r=tolerance_m)]
        return cls(positives, len(r), f"positions, tolerance {tolerance_m:g} m")

    # ------------------------------------------------------------------ CSV
    @classmethod
    def from_csv(
        cls, path: str | os.PathLike, num_references: int | None = None, num_queries: int | None = None
    ) -> "GroundTruth":
        """Read ``query_index,reference_indices`` (space-separated list; empty = no match), with
        or without a header; or, with a header naming them, also ``query_name,reference_names``
        (the reference names separated by ``/``, in the order of the indices).

        Queries missing from a two-column file have no match. Indices are checked against
        ``num_references``/``num_queries`` when given. Name columns are kept in
        ``listed_names``; :meth:`check_names` compares them with the images.
        """
        path = Path(path)
        try:
            # utf-8-sig: spreadsheet programs start CSV files with a byte-order mark.
            text = path.read_text(encoding="utf-8-sig")
        except FileNotFoundError as exc:
            raise DataError(f"{path}: ground-truth file not found") from exc
        except IsADirectoryError as exc:
            raise DataError(f"{path}: is a folder; expected a ground-truth CSV file") from exc
        except UnicodeDecodeError as exc:
            raise DataError(f"{path}: not a text CSV file") from exc
        reader = csv.reader(io.StringIO(text))
        rows = [(reader.line_num, row) for row in reader]
        if not rows:
            raise DataError(f"{path}: empty ground-truth file")
        header = [h.strip().lower() for h in rows[0][1]]
        named = header[:4] == NAMED_HEADER
        if named or (header and header[0] in ("query_index", "query", "query_idx")):
            rows = rows[1:]
        entries: dict[int, np.ndarray] = {}
        named_rows: list[NamedRow] = []
        for line_no, row in rows:
            if not row or all(not c.strip() for c in row):
                continue
            if named and len(row) != 4:
                raise DataError(
                    f"{path}, line {line_no}: expected 4 columns ({','.join(NAMED_HEADER)}), "
                    f"got {len(row)}: {row!r}"
                )
            if not named and len(row) > 2:
                raise DataError(f"{path}, line {line_no}: expected 'query_index,reference_indices', got {row!r}")
            try:
                q = int(row[0].strip())
                refs = [int(v) for v in (row[1].split() if len(row) > 1 else [])]
            except ValueError as exc:
                raise DataError(f"{path}, line {line_no}: non-integer value in {','.join(row)!r}") from exc
            if q < 0 or (num_queries is not None and q >= num_queries):
                raise DataError(
                    f"{path}, line {line_no}: query index {q} out of range"
                    + (f" (0..{num_queries - 1})" if num_queries is not None else "")
                )
            bad = [r for r in refs if r < 0 or (num_references is not None and r >= num_references)]
            if bad:
                raise DataError(
                    f"{path}, line {line_no}: reference index {bad[0]} out of range"
                    + (f" (0..{num_references - 1})" if num_references is not None else "")
                )
            if q in entries:
                raise DataError(f"{path}, line {line_no}: query {q} listed twice")
            entries[q] = np.asarray(refs, dtype=np.int64)
            if named:
                # names as written by to_csv, quoted against spreadsheet formulas
                ref_names = from_spreadsheet_text(row[3]).split(NAME_SEPARATOR) if row[3] else []
                if len(ref_names) != len(refs):
                    raise DataError(
                        f"{path}, line {line_no}: {len(refs)} reference indices but "
                        f"{len(ref_names)} reference names; the two lists go together"
                    )
                named_rows.append(NamedRow(line_no, q, from_spreadsheet_text(row[2]), refs, ref_names))
        if not entries:
            raise DataError(f"{path}: no ground-truth rows")
        n_q = num_queries if num_queries is not None else max(entries) + 1
        n_r = num_references
        if n_r is None:
            n_r = 1 + max((int(p.max()) for p in entries.values() if len(p)), default=-1)
        positives = [entries.get(q, np.zeros(0, dtype=np.int64)) for q in range(n_q)]
        return cls(positives, n_r, f"explicit list from {path.name}", ListedNames(path, named_rows) if named else None)

    def check_names(
        self, query_paths: Sequence[str | os.PathLike], reference_paths: Sequence[str | os.PathLike]
    ) -> None:
        """When the CSV this was read from names its images, check that they are the images
        being evaluated, in the same order; a mismatch is a DataError naming the file, the first
        mismatching row and both names. Nothing to check for a file without names."""
        named = self.listed_names
        if named is None:
            return
        query_names = [Path(p).name for p in query_paths]
        reference_names = [Path(p).name for p in reference_paths]
        query_folder = _folder_of(query_paths)
        reference_folder = _folder_of(reference_paths)
        hint = (
            "the ground truth was written for other images, or in another order; write it again "
            "with `fdnet groundtruth` for these folders"
        )
        for row in named.rows:
            if row.query >= len(query_names) or row.query_name != query_names[row.query]:
                actual = query_names[row.query] if row.query < len(query_names) else "no image"
                raise DataError(
                    f"{named.path}, line {row.line}: query {row.query} is {row.query_name!r} in the "
                    f"ground truth but {actual!r} in {query_folder}; {hint}"
                )
            for index, name in zip(row.references, row.reference_names):
                actual = reference_names[index] if index < len(reference_names) else "no image"
                if name != actual:
                    raise DataError(
                        f"{named.path}, line {row.line}: reference {index} is {name!r} in the "
                        f"ground truth but {actual!r} in {reference_folder}; {hint}"
                    )
        if len(named.rows) != len(query_names):
            raise DataError(
                f"{named.path}: has rows for {len(named.rows)} queries but {query_folder} has "
                f"{len(query_names)} query images; {hint}"
            )

    def to_csv(
        self,
        path: str | os.PathLike,
        query_names: Sequence[str] | None = None,
        reference_names: Sequence[str] | None = None,
    ) -> None:
        """Write ``query_index,reference_indices`` (one row per query); with ``query_names`` and
        ``reference_names`` (file names, one per query and per reference, in index order) also
        ``query_name,reference_names``, so a reader can check the indices still mean those
        images."""
        if (query_names is None) != (reference_names is None):
            raise ValueError("give both query_names and reference_names, or neither")
        buffer = io.StringIO()
        writer = csv.writer(buffer, lineterminator="\n")
        if query_names is None:
            writer.writerow(NAMED_HEADER[:2])
            for q, p in enumerate(self.positives):
                writer.writerow([q, " ".join(str(int(r)) for r in p)])
        else:
            query_names = [str(n) for n in query_names]
            reference_names = [str(n) for n in reference_names]
            if len(query_names) != self.num_queries or len(reference_names) != self.num_references:
                raise DataError(
                    f"{path}: ground truth is for {self.num_queries} queries x {self.num_references} "
                    f"references but {len(query_names)} query and {len(reference_names)} "
                    f"reference names were given"
                )
            slashed = next((n for n in [*query_names, *reference_names] if NAME_SEPARATOR in n), None)
            if slashed is not None:
                raise DataError(
                    f"{path}: image name {slashed!r} contains {NAME_SEPARATOR!r}; names are "
                    f"file names, without their folder"
                )
            writer.writerow(NAMED_HEADER)
            for q, p in enumerate(self.positives):
                writer.writerow(
                    [
                        q,
                        " ".join(str(int(r)) for r in p),
                        spreadsheet_text(query_names[q]),
                        spreadsheet_text(NAME_SEPARATOR.join(reference_names[int(r)] for r in p)),
                    ]
                )
        atomic_write_text(path, buffer.getvalue())

    def summary(self) -> dict:
        counts = np.array([len(p) for p in self.positives])
        return {
            "num_queries": self.num_queries,
            "num_references": self.num_references,
            "queries_with_match": int((counts > 0).sum()),
            "mean_matches_per_query": float(counts.mean()) if len(counts) else 0.0,
        }


def _folder_of(paths: Sequence[str | os.PathLike]) -> str:
    """The folder a list of images lives in, for messages ("the images" when they span several)."""
    parents = {str(Path(p).parent) for p in paths}
    return parents.pop() if len(parents) == 1 else "the images"


def latlon_to_metres(lat: np.ndarray, lon: np.ndarray, origin: tuple[float, float] | None = None) -> np.ndarray:
    """Degrees -> local planar metres (equirectangular about ``origin``, default the mean).

    Accurate to well under 0.1 % over the few kilometres of a VPR route, which is far below
    any matching tolerance; a full UTM projection would need pyproj for no practical gain.
    """
    lat = np.asarray(lat, dtype=np.float64)
    lon = np.asarray(lon, dtype=np.float64)
    lat0, lon0 = origin if origin is not None else (float(lat.mean()), float(lon.mean()))
    earth_radius = 6_371_008.8
    x = np.radians(lon - lon0) * earth_radius * math.cos(math.radians(lat0))
    y = np.radians(lat - lat0) * earth_radius
    return np.stack([x, y], axis=1)
