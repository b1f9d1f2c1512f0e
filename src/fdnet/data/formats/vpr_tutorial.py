"""VPR_Tutorial layout (Schubert, Neubert, Garg, Milford, Fischer, "Visual Place Recognition: A
Tutorial", IEEE RAM 2023; https://github.com/stschubert/VPR_Tutorial, ``datasets/load_dataset.py``).

The tutorial's downloads unpack to one folder per dataset holding two image folders and
``GT.npz`` with two boolean matrices of shape (number of database images, number of queries):

* ``GThard``: the places that must be found;
* ``GTsoft``: places that are also acceptable (the tutorial ignores them when counting false
  positives).

Known pairs (database -> reference, query): ``StLucia_small``: ``100909_0845`` and
``180809_1545``; ``SFU``: ``dry`` and ``jan``. Any other folder with ``GT.npz`` and two image
folders works when ``--reference``/``--query`` name them (or when exactly two exist: sorted order).
The tutorial's GardensPoint download has no GT.npz (its ground truth is the identity, soft +-8
frames); read it with the ``folders`` format (``tolerance=8`` reproduces GTsoft).

:class:`~fdnet.data.groundtruth.GroundTruth` has no "ignore" class: by default the positives are
GThard; ``use_soft=true`` makes them GTsoft (counting the soft matches as correct).
A ``START:END`` split selects queries; the database stays whole.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fdnet.data.arrays import load_npz_member
from fdnet.data.dataset import RouteDataset, Traverse
from fdnet.data.formats._common import (
    DatasetFormat,
    describe,
    has_images,
    pick_conditions,
    resolve_split,
)
from fdnet.data.groundtruth import GroundTruth
from fdnet.data.images import list_images
from fdnet.data.split import EvaluationSplit, read_listed_ground_truth
from fdnet.errors import ConfigError, DataError

KNOWN_PAIRS = {  # (reference = tutorial's database, query)
    frozenset({"100909_0845", "180809_1545"}): ("100909_0845", "180809_1545"),
    frozenset({"dry", "jan"}): ("dry", "jan"),
}


@dataclass
class VPRTutorialOptions:
    ground_truth: str = "GT.npz"
    use_soft: bool = False  # positives = GTsoft instead of GThard


def _image_folders(root: Path) -> list[str]:
    return sorted(p.name for p in root.iterdir() if p.is_dir() and has_images(p))


def load_gt_matrix(path: Path, key: str, num_references: int, num_queries: int) -> np.ndarray:
    """(num_references, num_queries) bool matrix from the tutorial's GT.npz."""
    if not path.is_file():
        raise DataError(f"{path}: ground-truth file not found (the VPR_Tutorial datasets ship GT.npz)")
    matrix = load_npz_member(path, key, ndim=2, what="ground-truth matrix")
    if matrix.shape == (num_references, num_queries):
        return matrix.astype(bool)
    if matrix.shape == (num_queries, num_references):
        return matrix.T.astype(bool)  # someone saved it queries-first
    raise DataError(
        f"{path}: {key} has shape {matrix.shape} but there are {num_references} database "
        f"and {num_queries} query images (expected ({num_references}, {num_queries}))"
    )


class VPRTutorialFormat(DatasetFormat):
    name = "vpr_tutorial"
    summary = "VPR_Tutorial: two image folders and GT.npz (GThard/GTsoft matrices)"
    Options = VPRTutorialOptions
    splits = {}

    def detect(self, root: Path) -> bool:
        return (root / "GT.npz").is_file() and len(_image_folders(root)) >= 2

    def _pair(self, root: Path, reference: str | None, query: str | None) -> tuple[str, str]:
        folders = _image_folders(root)
        if reference and query:
            pick_conditions(folders, [reference, query], root)
            return reference, query
        known = KNOWN_PAIRS.get(frozenset(folders))
        if known:
            return reference or known[0], query or known[1]
        if len(folders) == 2:
            return reference or folders[0], query or folders[1]
        raise ConfigError(
            f"{root}: image folders {', '.join(folders) or 'none'}; name the database "
            f"and query folders with --reference and --query"
        )

    def listed_evaluation_split(self, root, reference, query, split, options, ground_truth) -> EvaluationSplit:
        """The split's queries and the whole database with an explicit list over them; GT.npz is
        not needed."""
        reference, query = self._pair(root, reference, query)
        ref = Traverse(reference, list_images(root / reference))
        qry = Traverse(query, list_images(root / query))
        start, end = resolve_split(split, {}, len(qry), str(root))
        qry = qry.frames(start, end)
        gt = read_listed_ground_truth(ground_truth, ref, qry)
        return EvaluationSplit(ref, qry, gt, describe(root, qry, ref, gt))

    def evaluation_split(self, root, reference, query, split, options: VPRTutorialOptions) -> EvaluationSplit:
        reference, query = self._pair(root, reference, query)
        ref = Traverse(reference, list_images(root / reference))
        qry = Traverse(query, list_images(root / query))
        key = "GTsoft" if options.use_soft else "GThard"
        gt_path = Path(options.ground_truth)
        gt_path = gt_path if gt_path.is_absolute() else root / gt_path
        matrix = load_gt_matrix(gt_path, key, len(ref), len(qry))
        positives = [np.flatnonzero(matrix[:, j]) for j in range(len(qry))]
        gt = GroundTruth(positives, len(ref), f"{key} from {gt_path.name}")
        start, end = resolve_split(split, {}, len(qry), str(root))
        if (start, end) != (None, None):
            q_idx = np.arange(len(qry))[slice(start, end)]
            qry, gt = qry.select(q_idx), gt.subset(q_idx)
        return EvaluationSplit(ref, qry, gt, describe(root, qry, ref, gt))

    def training_dataset(self, root, split, conditions, options) -> RouteDataset:
        folders = pick_conditions(_image_folders(root), conditions, root)
        traverses = {c: Traverse(c, list_images(root / c)) for c in folders}
        start, end = resolve_split(split, {}, min(len(t) for t in traverses.values()), str(root))
        return RouteDataset(root, {c: t.frames(start, end) for c, t in traverses.items()})


FORMAT = VPRTutorialFormat()
