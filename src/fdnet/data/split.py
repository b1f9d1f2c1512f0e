"""An evaluation split: a reference traverse (the map), a query traverse, and their ground truth.

Every dataset adapter (folder per condition, VPR-Bench, Nordland, Oxford RobotCar...) produces
one of these, so evaluation never needs to know where the data came from.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from fdnet.data.dataset import RouteDataset, Traverse
from fdnet.data.groundtruth import GroundTruth
from fdnet.errors import DataError


@dataclass
class EvaluationSplit:
    reference: Traverse
    query: Traverse
    ground_truth: GroundTruth
    description: str = ""

    def __post_init__(self) -> None:
        gt = self.ground_truth
        if gt.num_queries != len(self.query) or gt.num_references != len(self.reference):
            raise DataError(
                f"ground truth is for {gt.num_queries} queries x {gt.num_references} references, but the "
                f"split has {len(self.query)} query images ({self.query.name}) and "
                f"{len(self.reference)} reference images ({self.reference.name})"
            )


def aligned_split(
    dataset: RouteDataset, reference: str, query: str, tolerance: int, start: int | None = None, end: int | None = None
) -> EvaluationSplit:
    """Frame-aligned conditions of one route: frame i of ``query`` is frame i of ``reference``
    (frames compared by ``frame_ids``, so filtered traverses stay paired), within ``tolerance``.

    ``start:end`` slices both traverses (e.g. the test part of a route). The traverses must have
    the same number of frames, otherwise frame alignment is meaningless. The one frame-aligned
    split: ``fdnet evaluate --data`` and the ``folders`` dataset format both use it.
    """
    ref_full, query_full = dataset[reference], dataset[query]
    if len(ref_full) != len(query_full):
        raise DataError(
            f"frame-aligned ground truth needs the same number of frames in every condition, but "
            f"{dataset.root / reference} has {len(ref_full)} images and {dataset.root / query} has "
            f"{len(query_full)}; give an explicit ground-truth CSV (--ground-truth) instead"
        )
    ref, qry = ref_full.frames(start, end), query_full.frames(start, end)
    if len(ref) == 0:
        raise DataError(
            f"frame range {_range(start, end)} selects no images of {dataset.root / reference} "
            f"({len(ref_full)} images)"
        )
    gt = GroundTruth.from_frames(qry.frame_ids, ref.frame_ids, tolerance)
    return EvaluationSplit(ref, qry, gt, f"{dataset.root.name}: {query} -> {reference}, {gt.description}")


def read_listed_ground_truth(path: str | os.PathLike, reference: Traverse, query: Traverse) -> GroundTruth:
    """An explicit ground-truth CSV whose indices are positions in ``query`` and ``reference``:
    sizes checked against them and, when the file names its images, the names too."""
    gt = GroundTruth.from_csv(path, num_references=len(reference), num_queries=len(query))
    gt.check_names(query.paths, reference.paths)
    return gt


def listed_split(
    dataset: RouteDataset,
    reference: str,
    query: str,
    ground_truth: str | os.PathLike,
    start: int | None = None,
    end: int | None = None,
) -> EvaluationSplit:
    """Two conditions of one route with an explicit ground-truth CSV over all their images
    (``query_index,reference_indices``, indices in :func:`fdnet.data.images.list_images` order),
    then the same ``start:end`` slice of both. Used by ``fdnet evaluate --data ... --ground-truth``
    and the ``folders`` format's ``ground_truth`` setting."""
    ref_full, query_full = dataset[reference], dataset[query]
    gt = read_listed_ground_truth(ground_truth, ref_full, query_full)
    ref, qry = ref_full.frames(start, end), query_full.frames(start, end)
    if len(ref) == 0 or len(qry) == 0:
        raise DataError(
            f"frame range {_range(start, end)} selects no images of {dataset.root} "
            f"({len(ref_full)} reference, {len(query_full)} query images)"
        )
    gt = gt.subset(np.arange(len(query_full))[slice(start, end)], np.arange(len(ref_full))[slice(start, end)])
    return EvaluationSplit(ref, qry, gt, f"{dataset.root.name}: {query} -> {reference}, {gt.description}")


def with_listed_ground_truth(split: EvaluationSplit, ground_truth: str | os.PathLike) -> EvaluationSplit:
    """``split`` with its ground truth replaced by an explicit CSV whose indices are positions in
    the split's own query and reference images (what ``fdnet groundtruth --data ROOT --split S``
    writes); its size (and names, when it has them) are checked against the split."""
    gt = read_listed_ground_truth(ground_truth, split.reference, split.query)
    return EvaluationSplit(
        split.reference, split.query, gt, f"{split.description}; ground truth replaced by the {gt.description}"
    )


def _range(start: int | None, end: int | None) -> str:
    return f"{'' if start is None else start}:{'' if end is None else end}"
