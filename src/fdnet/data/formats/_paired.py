"""Two traverses of one route plus a file of frame correspondences (Alderley, FAS).

The correspondence file pairs a frame of one traverse with the frame of the other taken at the
same place. A query matches the references within ``tolerance`` frames of its corresponding
frame. A split cuts the *query* traverse; the reference map is the stretch of the other traverse
that those queries correspond to (widened by the tolerance), so train and test never share
places.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from fdnet.data.dataset import RouteDataset, Traverse
from fdnet.data.formats._common import (
    Correspondences,
    DatasetFormat,
    SplitRule,
    check_correspondences_cover,
    describe,
    find_child,
    frame_numbers,
    ground_truth_from_correspondences,
    image_folder,
    read_correspondences,
    resolve_split,
)
from fdnet.data.images import list_images
from fdnet.data.split import EvaluationSplit
from fdnet.errors import ConfigError, DataError


def swap(corr: Correspondences) -> Correspondences:
    return Correspondences(corr.reference, corr.query, corr.path, corr.by_name)


def read_numbered(folder: Path, name: str) -> Traverse:
    """Frames named by number (Image00001.jpg): frame ids are those numbers. Names without one
    distinct number each (e.g. timestamps with a fraction) fall back to positions 0, 1, 2...; a
    correspondence file of file names works either way."""
    folder = image_folder(folder)
    paths = list_images(folder)
    try:
        ids = frame_numbers(paths, folder)
    except DataError:
        ids = np.arange(len(paths))
    return Traverse(name, paths, frame_ids=ids)


class PairedFormat(DatasetFormat):
    """Subclasses set: ``conditions`` (condition name -> folder name candidates), ``first`` and
    ``second`` (the conditions of the file's first and second column), ``default_reference``,
    ``default_query``, ``correspondence_names`` (file name candidates), ``split_rules``."""

    conditions: Mapping[str, Sequence[str]] = {}
    first: str = ""
    second: str = ""
    default_reference: str = ""
    default_query: str = ""
    correspondence_names: Sequence[str] = ()
    correspondence_globs: Sequence[str] = ()
    split_rules: Mapping[str, SplitRule] = {}

    # -- files ---------------------------------------------------------------------------------
    def folder(self, root: Path, condition: str) -> Path | None:
        return find_child(root, self.conditions[condition])

    def condition_name(self, root: Path, name: str) -> str:
        """Accept a condition name (``day``) or its folder name (``FRAMESB``)."""
        for condition, folders in self.conditions.items():
            if name.lower() == condition or name.lower() in (f.lower() for f in folders):
                return condition
        raise DataError(
            f"{root}: no condition {name!r} in the {self.name} layout; conditions: "
            + ", ".join(f"{c} ({'/'.join(f[:1])})" for c, f in self.conditions.items())
        )

    def correspondence_file(self, root: Path, given: str | None) -> Path:
        if given:
            path = Path(given)
            path = path if path.is_absolute() else root / path
            if not path.is_file():
                raise DataError(f"{path}: correspondence (ground-truth) file not found")
            return path
        found = find_child(root, self.correspondence_names, kind="file")
        if found is not None:
            return found
        for pattern in self.correspondence_globs:
            matches = sorted(p for p in root.glob(pattern) if p.is_file())
            if matches:
                return matches[0]
        raise DataError(
            f"{root}: missing the frame-correspondence file (looked for {', '.join(self.correspondence_names)}"
            f"{', ' + ', '.join(self.correspondence_globs) if self.correspondence_globs else ''}); "
            f"give its path with correspondences=FILE"
        )

    def read_condition(self, root: Path, condition: str) -> Traverse:
        folder = self.folder(root, condition)
        if folder is None:
            raise DataError(
                f"{root}: missing the {condition} image folder " f"(expected {' or '.join(self.conditions[condition])})"
            )
        return read_numbered(folder, condition)

    def detect(self, root: Path) -> bool:
        return all(self.folder(root, c) is not None for c in self.conditions)

    # -- protocol ------------------------------------------------------------------------------
    def _setup(self, root: Path, reference: str | None, query: str | None, options):
        reference = self.condition_name(root, reference) if reference else self.default_reference
        query = self.condition_name(root, query) if query else self.default_query
        if reference == query:
            raise DataError(f"{root}: reference and query are both {reference!r}")
        ref, qry = self.read_condition(root, reference), self.read_condition(root, query)
        numbering = getattr(options, "numbering", "names")
        if numbering in ("positions", "positions1"):
            first = 0 if numbering == "positions" else 1
            for t in (ref, qry):
                t.frame_ids = np.arange(first, first + len(t))
        elif numbering != "names":
            raise ConfigError(
                f"numbering {numbering!r}: expected names (the numbers in the image "
                f"names), positions (0-based) or positions1 (1-based)"
            )
        corr = read_correspondences(
            self.correspondence_file(root, options.correspondences), options.first_column, options.second_column
        )
        if query == self.second:
            corr = swap(corr)  # rows are (first, second); make them (query, reference)
        check_correspondences_cover(corr, qry, ref)
        return ref, qry, corr

    def _reference_span(self, corr: Correspondences, qry: Traverse, ref: Traverse, tolerance: int) -> tuple[int, int]:
        """Positions [lo, hi) of the reference frames that ``qry``'s frames correspond to."""
        if corr.by_name:
            q_keys = {p.stem for p in qry.paths}
            ref_pos = {p.stem: i for i, p in enumerate(ref.paths)}
        else:
            q_keys = set(int(f) for f in qry.frame_ids)
            ref_pos = {int(f): i for i, f in enumerate(ref.frame_ids)}
        hits = [ref_pos[r] for q, r in zip(corr.query, corr.reference) if q in q_keys and r in ref_pos]
        if not hits:
            raise DataError(
                f"{corr.path}: none of the selected {len(qry)} {qry.name} frames "
                f"({qry.paths[0].name}..{qry.paths[-1].name}) has a correspondence"
            )
        return max(min(hits) - tolerance, 0), min(max(hits) + tolerance + 1, len(ref))

    def evaluation_split(self, root, reference, query, split, options) -> EvaluationSplit:
        ref_full, qry_full, corr = self._setup(root, reference, query, options)
        start, end = resolve_split(split, self.split_rules, len(qry_full), str(root))
        qry = qry_full.frames(start, end)
        if (start, end) == (None, None):
            ref = ref_full
        else:
            lo, hi = self._reference_span(corr, qry, ref_full, options.tolerance)
            ref = ref_full.frames(lo, hi)
        gt = ground_truth_from_correspondences(corr, qry, ref, options.tolerance)
        return EvaluationSplit(ref, qry, gt, describe(root, qry, ref, gt, f"split {split or 'all'}"))

    def training_dataset(self, root, split, conditions, options) -> RouteDataset:
        """``train``: the train rule's query frames and every reference frame outside the test
        stretch; other splits cut the query traverse as in evaluation."""
        names = (
            [self.condition_name(root, c) for c in conditions]
            if conditions
            else [self.default_reference, self.default_query]
        )
        if len(names) != 2:
            raise DataError(f"{root}: the {self.name} layout has exactly two traverses")
        ref_full, qry_full, corr = self._setup(root, names[0], names[1], options)
        if split == "train" and "test" in self.split_rules:
            # queries: the train rule; references: every frame outside the test stretch
            start, end = resolve_split("train", self.split_rules, len(qry_full), str(root))
            t_start, t_end = resolve_split("test", self.split_rules, len(qry_full), str(root))
            qry = qry_full.frames(start, end)
            lo, hi = self._reference_span(corr, qry_full.frames(t_start, t_end), ref_full, options.tolerance)
            ref = ref_full.select(np.setdiff1d(np.arange(len(ref_full)), np.arange(lo, hi)))
        else:
            start, end = resolve_split(split, self.split_rules, len(qry_full), str(root))
            qry = qry_full.frames(start, end)
            if (start, end) == (None, None):
                ref = ref_full
            else:
                lo, hi = self._reference_span(corr, qry, ref_full, options.tolerance)
                ref = ref_full.frames(lo, hi)
        return RouteDataset(root, {names[0]: ref, names[1]: qry})
