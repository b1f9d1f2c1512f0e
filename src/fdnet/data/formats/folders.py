"""The plain layout: one sub-folder per condition, file names in traversal order.

``root/<condition>/*.jpg|png...``, images in :func:`fdnet.data.images.list_images` order; the
same position in two conditions is the same place (frame-aligned ground truth with a tolerance in
frames, :func:`fdnet.data.split.aligned_split`), unless an explicit ground-truth CSV
(``query_index,reference_indices`` over all images of the two folders, then cut to the split:
:func:`fdnet.data.split.listed_split`) is given. This is how ``../shared/data/nordland_trimmed``
and ``gardens_point`` are laid out, and how a user's own multi-condition route usually is.

Gardens Point Walking (Glover 2014) is recognised by its condition names (``day_left``,
``day_right``, ``night_right``): its default tolerance is +-2 frames and its default pair
``night_right`` -> ``day_right``, as VPR-Bench (Zaffar et al., IJCV 2021) evaluates it. Any other
folder defaults to tolerance 0 (exact position).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from fdnet.data.dataset import RouteDataset, Traverse
from fdnet.data.formats._common import DatasetFormat, describe, pick_conditions, resolve_split
from fdnet.data.images import has_images, list_images
from fdnet.data.split import EvaluationSplit, aligned_split, listed_split, read_listed_ground_truth
from fdnet.errors import ConfigError, DataError

GARDENS_POINT = {"day_left", "day_right", "night_right"}


@dataclass
class FoldersOptions:
    tolerance: int | None = None  # frames; None = 2 for Gardens Point, else 0
    ground_truth: str | None = None  # explicit CSV (relative to the dataset folder or absolute)


def condition_folders(root: Path) -> list[str]:
    if not root.is_dir():
        raise DataError(f"{root}: dataset folder not found")
    from fdnet.data.sources import is_source

    return sorted(
        p.name
        for p in root.iterdir()
        if not p.name.startswith(".") and (is_source(p) or (p.is_dir() and has_images(p)))
    )


def read_traverse(folder: Path, name: str | None = None) -> Traverse:
    """A condition folder (or video or ROS bag, :mod:`fdnet.data.sources`; ``summer`` finds
    ``summer.mp4``) in the one image order; frame ids are positions (position = place)."""
    from fdnet.data.sources import condition_path

    found = condition_path(folder.parent, folder.name)
    return Traverse(name=name or folder.name, paths=list_images(found if found is not None else folder))


def is_gardens_point(conditions: Sequence[str]) -> bool:
    return len(conditions) >= 2 and set(conditions) <= GARDENS_POINT


def default_pair(root: Path, conditions: list[str], reference: str | None, query: str | None) -> tuple[str, str]:
    if reference and query:
        return reference, query
    if is_gardens_point(conditions) and {"day_right", "night_right"} <= set(conditions):
        return reference or "day_right", query or "night_right"
    others = [c for c in conditions if c not in (reference, query)]
    if len(conditions) == 2:
        reference = reference or next(c for c in conditions if c != query)
        query = query or next(c for c in conditions if c != reference)
        return reference, query
    raise ConfigError(
        f"{root}: has {len(conditions)} conditions ({', '.join(conditions)}); name the "
        f"pair with --reference and --query" + (f" (e.g. {others[0]})" if others else "")
    )


class FoldersFormat(DatasetFormat):
    name = "folders"
    summary = "one sub-folder per condition, frame-aligned by position (or an explicit ground-truth CSV)"
    Options = FoldersOptions
    splits = {}

    def detect(self, root: Path) -> bool:
        try:
            return len(condition_folders(root)) >= 2
        except DataError:
            return False

    def _tolerance(self, conditions: list[str], options: FoldersOptions) -> int:
        if options.tolerance is not None:
            return int(options.tolerance)
        return 2 if is_gardens_point(conditions) else 0

    def _route(self, root: Path, reference, query) -> tuple[list[str], RouteDataset, str, str]:
        conditions = condition_folders(root)
        if len(conditions) < 2 and not (reference and query):
            raise DataError(
                f"{root}: needs at least two condition sub-folders with images, found "
                f"{len(conditions)} ({', '.join(conditions) or 'none'})"
            )
        reference, query = default_pair(root, conditions, reference, query)
        pick_conditions(conditions, [reference, query], root)
        route = RouteDataset(root, {name: read_traverse(root / name) for name in (reference, query)})
        return conditions, route, reference, query

    def listed_evaluation_split(
        self, root, reference, query, split, options: FoldersOptions, ground_truth: Path
    ) -> EvaluationSplit:
        """Both folders cut to ``split``, with an explicit list over the cut images (no frame
        alignment is computed, so the folders may hold different numbers of images)."""
        if options.ground_truth:
            raise ConfigError(
                f"two explicit ground truths: the ground_truth={options.ground_truth} setting "
                f"and {ground_truth}; give one"
            )
        _, route, reference, query = self._route(root, reference, query)
        start, end = resolve_split(split, {}, len(route[query]), str(root))
        ref, qry = route[reference].frames(start, end), route[query].frames(start, end)
        if len(ref) == 0 or len(qry) == 0:
            raise DataError(f"{root}: split {split!r} selects no images of {reference} or {query}")
        gt = read_listed_ground_truth(ground_truth, ref, qry)
        return EvaluationSplit(ref, qry, gt, describe(root, qry, ref, gt))

    def evaluation_split(self, root, reference, query, split, options: FoldersOptions) -> EvaluationSplit:
        conditions, route, reference, query = self._route(root, reference, query)
        if options.ground_truth:
            gt_path = Path(options.ground_truth)
            gt_path = gt_path if gt_path.is_absolute() else root / gt_path
            start, end = resolve_split(split, {}, len(route[query]), str(root))
            return listed_split(route, reference, query, gt_path, start, end)
        start, end = resolve_split(split, {}, len(route[reference]), str(root))
        return aligned_split(route, reference, query, self._tolerance(conditions, options), start, end)

    def training_dataset(self, root, split, conditions, options) -> RouteDataset:
        available = condition_folders(root)
        chosen = pick_conditions(available, conditions, root)
        traverses = {c: read_traverse(root / c) for c in chosen}
        length = min(len(t) for t in traverses.values())
        start, end = resolve_split(split, {}, length, str(root))
        return RouteDataset(root, {c: t.frames(start, end) for c, t in traverses.items()})


FORMAT = FoldersFormat()
