"""An evaluation split: a reference traverse (the map), a query traverse, and their ground truth.

Every dataset adapter (folder per condition, VPR-Bench, Nordland, Oxford RobotCar...) produces
one of these, so evaluation never needs to know where the data came from.
"""

from __future__ import annotations

from dataclasses import dataclass

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


def aligned_split(dataset: RouteDataset, reference: str, query: str, tolerance: int,
                  start: int | None = None, end: int | None = None) -> EvaluationSplit:
    """Frame-aligned conditions of one route: frame i of ``query`` is frame i of ``reference``.

    ``start:end`` slices both traverses (e.g. the test part of a route). The traverses must have
    the same number of frames, otherwise frame alignment is meaningless.
    """
    ref_full, query_full = dataset[reference], dataset[query]
    if len(ref_full) != len(query_full):
        raise DataError(
            f"frame-aligned ground truth needs the same number of frames in every condition, but "
            f"{dataset.root / reference} has {len(ref_full)} images and {dataset.root / query} has "
            f"{len(query_full)}; give an explicit --ground-truth CSV instead"
        )
    ref, qry = ref_full.frames(start, end), query_full.frames(start, end)
    if len(ref) == 0:
        raise DataError(f"frame range {start}:{end} selects no images of {dataset.root / reference} "
                        f"({len(ref_full)} images)")
    gt = GroundTruth.from_frames(qry.frame_ids, ref.frame_ids, tolerance)
    return EvaluationSplit(ref, qry, gt, f"{dataset.root.name}: {query} -> {reference}, {gt.description}")
