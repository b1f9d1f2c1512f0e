"""Pieces every dataset adapter needs: frame numbers, named splits, size checks and
frame-correspondence files. The image order (``list_images``, ``natural_key``) belongs to
:mod:`fdnet.data.images` (re-exported here) and the
tunnel/stationary frame filter to :mod:`fdnet.data.filters` (``filter_frames``).

Kept in one place so that each adapter module reads as "where the files are, what the protocol
is", not as plumbing.
"""

from __future__ import annotations

import csv
import io
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Mapping, Sequence

import numpy as np

from fdnet.data.dataset import RouteDataset, Traverse, parse_frame_range
from fdnet.data.groundtruth import GroundTruth
from fdnet.data.images import has_images, image_size, list_images, natural_key  # noqa: F401 (re-exported)
from fdnet.errors import ConfigError, DataError

# ----------------------------------------------------------------------------- file order

_LAST_NUMBER = re.compile(r"(\d+)(?!.*\d)")


def frame_number(path: str | os.PathLike) -> int | None:
    """The last integer in a file's stem (``images-00010.png`` -> 10, ``Image00042.jpg`` -> 42)."""
    match = _LAST_NUMBER.search(Path(path).stem)
    return int(match.group(1)) if match else None


def frame_numbers(paths: Sequence[Path], where: Path) -> np.ndarray:
    """Frame numbers from file names; every file must carry one and they must be distinct."""
    numbers = [frame_number(p) for p in paths]
    missing = [p.name for p, n in zip(paths, numbers) if n is None]
    if missing:
        raise DataError(
            f"{where}: file name {missing[0]!r} carries no frame number; this layout "
            f"names frames by number (e.g. Image00001.jpg)"
        )
    arr = np.asarray(numbers, dtype=np.int64)
    if len(np.unique(arr)) != len(arr):
        values, counts = np.unique(arr, return_counts=True)
        dup = int(values[counts > 1][0])
        names = [p.name for p, n in zip(paths, numbers) if n == dup]
        raise DataError(f"{where}: frame number {dup} appears in several files ({', '.join(names[:3])})")
    return arr


def find_child(root: Path, names: Iterable[str], kind: str = "folder") -> Path | None:
    """The first child of ``root`` whose name matches one of ``names`` ignoring case and the
    ``-``/``_``/space spelling (``Localization-2`` = ``localization_2``)."""

    def norm(s: str) -> str:
        return re.sub(r"[-_ ]", "", s.lower())

    wanted = [norm(n) for n in names]
    if not root.is_dir():
        return None
    children = sorted(root.iterdir())
    for w in wanted:
        for child in children:
            if norm(child.name) == w and (child.is_dir() if kind == "folder" else child.is_file()):
                return child
    return None


def image_folder(folder: Path, subfolders: Sequence[str] = ("images", "frames", "img", "imgs")) -> Path:
    """``folder`` itself when it holds images, else its one conventional image sub-folder."""
    if has_images(folder):
        return folder
    for name in subfolders:
        child = find_child(folder, [name])
        if child is not None and has_images(child):
            return child
    raise DataError(f"{folder}: contains no images (also looked in sub-folders {', '.join(subfolders)})")


# ----------------------------------------------------------------------------- image sizes


def check_image_sizes(traverse: Traverse, where: Path | None = None) -> tuple[int, int]:
    """All images of one condition must share one size; returns (width, height).

    Reads only each file's header (Pillow decodes pixels lazily), so 30k frames take seconds.
    """
    first_size = None
    first_path = None
    for path in traverse.paths:
        size = image_size(path)
        if first_size is None:
            first_size, first_path = size, path
        elif size != first_size:
            raise DataError(
                f"{where or path.parent}: mixed image sizes in condition {traverse.name!r}: "
                f"{first_path.name} is {first_size[0]}x{first_size[1]} but {path.name} is "
                f"{size[0]}x{size[1]}; every image of a condition must have the same size"
            )
    return first_size or (0, 0)


# ----------------------------------------------------------------------------- splits

# A named split maps the number of frames to (start, end); END exclusive, None = open.
SplitRule = Callable[[int], tuple[int | None, int | None]]


def fixed(start: int | None, end: int | None) -> SplitRule:
    return lambda n: (start, end)


def resolve_split(
    split: str | None, rules: Mapping[str, SplitRule], length: int, where: str
) -> tuple[int | None, int | None]:
    """A split name (``train``, ``test``, ``all``) or ``START:END`` -> (start, end) over ``length``
    frames. A named split that would select nothing is an error naming the frame count."""
    if split is None or split == "" or split == "all":
        return None, None
    if ":" in split:
        return parse_frame_range(split)
    if split not in rules:
        names = ", ".join(["all", *rules])
        raise ConfigError(f"{where}: no split named {split!r}; named splits: {names}, or START:END")
    start, end = rules[split](length)
    selected = len(range(length)[slice(start, end)])
    if selected == 0:
        raise DataError(
            f"{where}: split {split!r} is frames {start or 0}:{'' if end is None else end} but this "
            f"copy has only {length} frames; give --split START:END instead"
        )
    return start, end


# ----------------------------------------------------------------------------- correspondences


@dataclass
class Correspondences:
    """Rows of (query frame, reference frame) from a dataset's ground-truth file.

    Values are frame *numbers* as they appear in the file (matched to the numbers in image file
    names) unless ``by_name``: then they are file names/stems.
    """

    query: list
    reference: list
    path: Path
    by_name: bool


def read_text_lines(path: Path, what: str, not_text: str, comments: tuple[str, ...] = ("#",)) -> list[tuple[int, str]]:
    """(line number, line) of the non-blank, non-comment lines of a text file; a missing or
    binary file is a DataError naming it (``what`` / ``not_text`` say what was expected)."""
    try:
        # utf-8-sig: spreadsheet programs (Excel's "CSV UTF-8") start the file with a byte-order
        # mark, which would otherwise be read as part of the first column's name
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError as exc:
        raise DataError(f"{path}: {what} not found") from exc
    except UnicodeDecodeError as exc:
        raise DataError(f"{path}: {not_text}") from exc
    return [
        (i + 1, line)
        for i, line in enumerate(text.splitlines())
        if line.strip() and not line.lstrip().startswith(comments)
    ]


def read_correspondences(path: Path, query_column: int = 0, reference_column: int = 1) -> Correspondences:
    """Read a two-(or more-)column correspondence file: CSV, TSV or whitespace separated, with or
    without a header line. Integer values are frame numbers; anything else is taken as file names.
    Errors name the file and line."""
    lines = read_text_lines(
        path,
        "correspondence (ground-truth) file",
        "not a text file; expected rows 'query_frame,reference_frame'",
        ("#", "%"),
    )
    if not lines:
        raise DataError(f"{path}: empty correspondence file")
    sample = lines[0][1]
    delimiter = "," if "," in sample else ("\t" if "\t" in sample else None)

    def split_line(line: str) -> list[str]:
        if delimiter is None:
            return line.split()
        return [c.strip() for c in next(csv.reader(io.StringIO(line), delimiter=delimiter))]

    rows = [(no, split_line(line)) for no, line in lines]
    need = max(query_column, reference_column) + 1

    def numeric(cell: str) -> bool:
        try:
            float(cell)
            return True
        except ValueError:
            return False

    # A first row that is not numeric while the next one is = header.
    if (
        len(rows) > 1
        and len(rows[0][1]) >= need
        and not numeric(rows[0][1][query_column])
        and len(rows[1][1]) >= need
        and numeric(rows[1][1][query_column])
    ):
        rows = rows[1:]
    by_name = not all(numeric(r[query_column]) and numeric(r[reference_column]) for _, r in rows if len(r) >= need)
    query, reference = [], []
    for no, cells in rows:
        if len(cells) < need:
            raise DataError(
                f"{path}, line {no}: expected at least {need} columns "
                f"(query frame, reference frame), got {len(cells)}: {cells!r}"
            )
        q, r = cells[query_column], cells[reference_column]
        if by_name:
            query.append(Path(q).stem)
            reference.append(Path(r).stem)
            continue
        try:
            qf, rf = float(q), float(r)
        except ValueError as exc:
            raise DataError(f"{path}, line {no}: non-numeric frame number in {cells!r}") from exc
        if not (qf.is_integer() and rf.is_integer()):
            raise DataError(f"{path}, line {no}: frame numbers must be integers, got {q!r}, {r!r}")
        query.append(int(qf))
        reference.append(int(rf))
    if not query:
        raise DataError(f"{path}: no correspondence rows")
    return Correspondences(query, reference, path, by_name)


def ground_truth_from_correspondences(
    corr: Correspondences, query: Traverse, reference: Traverse, tolerance: int
) -> GroundTruth:
    """Each query with a correspondence row matches the references whose frame number is within
    ``tolerance`` of its corresponding reference frame (union over rows; queries without a row have
    no match). Frame numbers are the traverses' ``frame_ids``; with file-name correspondences the
    names are first turned into those ids."""
    if tolerance < 0:
        raise DataError(f"frame tolerance must be >= 0, got {tolerance}")
    if corr.by_name:
        q_ids = {p.stem: int(f) for p, f in zip(query.paths, query.frame_ids)}
        r_ids = {p.stem: int(f) for p, f in zip(reference.paths, reference.frame_ids)}
        pairs = [(q_ids.get(q), r_ids.get(r)) for q, r in zip(corr.query, corr.reference)]
    else:
        pairs = list(zip(corr.query, corr.reference))
    target: dict[int, list[int]] = {}
    for q, r in pairs:
        if q is None or r is None:
            continue  # a row about a frame outside this split
        target.setdefault(int(q), []).append(int(r))
    ref_ids = reference.frame_ids
    order = np.argsort(ref_ids, kind="stable")
    sorted_ids = ref_ids[order]
    positives = []
    for qf in query.frame_ids:
        hits: list[np.ndarray] = []
        for r in target.get(int(qf), []):
            lo = np.searchsorted(sorted_ids, r - tolerance, side="left")
            hi = np.searchsorted(sorted_ids, r + tolerance, side="right")
            hits.append(order[lo:hi])
        positives.append(np.concatenate(hits) if hits else np.zeros(0, dtype=np.int64))
    return GroundTruth(
        positives, len(reference), f"correspondences from {corr.path.name}, tolerance {tolerance} frames"
    )


def check_correspondences_cover(corr: Correspondences, query: Traverse, reference: Traverse) -> None:
    """Fail when the correspondence file names frames none of which exist (wrong file, or frame
    numbering that does not match the image names)."""
    if corr.by_name:
        q_known = {p.stem for p in query.paths}
        r_known = {p.stem for p in reference.paths}
    else:
        q_known = set(int(f) for f in query.frame_ids)
        r_known = set(int(f) for f in reference.frame_ids)
    q_hit = sum(1 for q in corr.query if q in q_known)
    r_hit = sum(1 for r in corr.reference if r in r_known)
    if q_hit == 0 or r_hit == 0:
        side, sample = ("query", corr.query[0]) if q_hit == 0 else ("reference", corr.reference[0])
        folder = query.paths[0].parent if q_hit == 0 else reference.paths[0].parent
        raise DataError(
            f"{corr.path}: none of its {side} frames (e.g. {sample!r}) is an image in {folder}; "
            f"check the file and the column order (query_column/reference_column settings)"
        )


# ----------------------------------------------------------------------------- frame alignment


def common_frames(route: RouteDataset) -> RouteDataset:
    """Keep, in every condition, only the frame numbers all conditions have (order preserved)."""
    common = None
    for t in route.traverses.values():
        ids = set(int(f) for f in t.frame_ids)
        common = ids if common is None else common & ids
    common = common or set()
    out = {}
    for name, t in route.traverses.items():
        mask = np.fromiter((int(f) in common for f in t.frame_ids), dtype=bool, count=len(t))
        out[name] = t.select(np.flatnonzero(mask))
    return RouteDataset(route.root, out)


def describe(root: Path, query: Traverse, reference: Traverse, gt: GroundTruth, extra: str = "") -> str:
    text = f"{root.name}: {query.name} -> {reference.name}, {gt.description}"
    return f"{text}, {extra}" if extra else text


# ----------------------------------------------------------------------------- adapter base


class DatasetFormat:
    """One published dataset layout. Subclasses set the class attributes and implement
    :meth:`detect`, :meth:`evaluation_split` and :meth:`training_dataset`.

    ``Options`` is a dataclass of the protocol settings (tolerances, file names, columns...), so
    they can be given as ``key=value`` strings and saved with :mod:`fdnet.config`.
    """

    name: str = ""
    summary: str = ""
    Options: type = object
    splits: dict[str, str] = {}
    default_eval_split: str = "all"
    default_train_split: str = "all"

    def detect(self, root: Path) -> bool:  # pragma: no cover - interface
        raise NotImplementedError

    def evaluation_split(
        self, root: Path, reference: str | None, query: str | None, split: str | None, options
    ) -> "EvaluationSplit":  # noqa: F821
        raise NotImplementedError  # pragma: no cover - interface

    def training_dataset(
        self, root: Path, split: str | None, conditions: Sequence[str] | None, options
    ) -> RouteDataset:
        raise NotImplementedError  # pragma: no cover - interface

    def listed_evaluation_split(
        self, root: Path, reference: str | None, query: str | None, split: str | None, options, ground_truth: Path
    ) -> "EvaluationSplit":  # noqa: F821
        """The split's images with an explicit ground-truth CSV in place of the format's own
        (indices over the split's images). Formats whose own ground truth can fail where an
        explicit list would not (e.g. frame alignment of unequal folders) override this."""
        from fdnet.data.split import with_listed_ground_truth

        return with_listed_ground_truth(self.evaluation_split(root, reference, query, split, options), ground_truth)


def pick_conditions(available: Sequence[str], wanted: Sequence[str] | None, root: Path) -> list[str]:
    if not wanted:
        return list(available)
    missing = [c for c in wanted if c not in available]
    if missing:
        raise DataError(f"{root}: no condition {missing[0]!r}; available: {', '.join(available)}")
    return list(wanted)
