"""VPR-Bench layout (Zaffar et al., "VPR-Bench: An Open-Source Visual Place Recognition Evaluation
Framework with Quantifiable Viewpoint and Appearance Change", IJCV 2021;
https://github.com/MubarizZaffar/VPR-Bench).

Each dataset as VPR-Bench ships it::

    <dataset>/query/   0000000.jpg ...
    <dataset>/ref/     0000000.jpg ...
    <dataset>/ground_truth_new.npy   object array, one row per query: [query_index, [ref indices]]

The .npy holds Python objects (numpy pickles them); it is read here with an unpickler that only
accepts numpy arrays, dtypes and scalars, so a tampered file cannot run code. ``ground_truth.csv``
(``query_index,reference_indices``, as in ``../shared/data/corridor``) is read when present and
preferred. Images are ordered by natural sort of their names, which equals VPR-Bench's order for
its zero-padded names. A ``START:END`` split selects queries; the reference map stays whole.
"""

from __future__ import annotations

import os
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fdnet.data.dataset import RouteDataset, Traverse
from fdnet.data.formats._common import DatasetFormat, describe, has_images, resolve_split
from fdnet.data.groundtruth import GroundTruth
from fdnet.data.images import list_images
from fdnet.data.split import EvaluationSplit, read_listed_ground_truth
from fdnet.errors import DataError

GT_FILES = ("ground_truth.csv", "ground_truth_new.npy", "ground_truth.npy")


@dataclass
class VPRBenchOptions:
    ground_truth: str | None = None  # file name in the dataset folder (default: the first of GT_FILES)


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Rebuilds numpy object arrays and nothing else (no arbitrary callables)."""

    ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy.core.multiarray", "scalar"),
        ("numpy._core.multiarray", "scalar"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
    }

    def find_class(self, module, name):
        if (module, name) in self.ALLOWED:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name}")


def load_object_npy(path: Path) -> np.ndarray:
    """``np.load(path, allow_pickle=True)`` without running code from the file; the header is
    checked first (:mod:`fdnet.data.arrays`), so a forged shape allocates nothing."""
    from fdnet.data.arrays import check_npy_claim, load_npy, physical_memory_bytes, read_npy_header

    try:
        with open(path, "rb") as f:
            shape, _, dtype = read_npy_header(f, str(path))
            if not dtype.hasobject:
                return load_npy(path, what="ground-truth")
            check_npy_claim(
                shape,
                dtype,
                str(path),
                os.fstat(f.fileno()).st_size - f.tell(),
                physical_memory_bytes(),
                what="ground-truth array",
            )
            array = _NumpyOnlyUnpickler(f, encoding="latin1").load()
    except FileNotFoundError as exc:
        raise DataError(f"{path}: ground-truth file not found") from exc
    except (ValueError, OSError, EOFError, pickle.UnpicklingError) as exc:
        raise DataError(f"{path}: not a readable VPR-Bench ground-truth .npy ({exc})") from exc
    try:
        return np.asarray(array, dtype=object).reshape(shape)
    except ValueError as exc:
        raise DataError(f"{path}: the pickled rows do not have the shape {shape} its header claims") from exc


def ground_truth_from_npy(path: Path, num_queries: int, num_references: int) -> GroundTruth:
    """Rows ``[query_index, refs]`` (refs: a list/array of indices or one index)."""
    rows = load_object_npy(path)
    if rows.ndim == 1 and rows.dtype != object:
        raise DataError(f"{path}: expected rows [query_index, [reference indices]], got a flat array")
    entries: dict[int, np.ndarray] = {}
    for i, row in enumerate(rows):
        try:
            q = int(row[0])
            refs = np.atleast_1d(np.asarray(row[1])).astype(np.int64).ravel()
        except (TypeError, ValueError, IndexError) as exc:
            raise DataError(f"{path}: row {i} is not [query_index, [reference indices]]: {row!r}") from exc
        if not 0 <= q < num_queries:
            raise DataError(f"{path}: row {i}: query index {q} out of range (0..{num_queries - 1})")
        bad = refs[(refs < 0) | (refs >= num_references)]
        if len(bad):
            raise DataError(
                f"{path}: row {i}: reference index {int(bad[0])} out of range " f"(0..{num_references - 1})"
            )
        entries[q] = np.union1d(entries.get(q, np.zeros(0, np.int64)), refs)
    positives = [entries.get(q, np.zeros(0, np.int64)) for q in range(num_queries)]
    return GroundTruth(positives, num_references, f"explicit list from {path.name}")


class VPRBenchFormat(DatasetFormat):
    name = "vprbench"
    summary = "VPR-Bench: query/ and ref/ folders with ground_truth_new.npy or ground_truth.csv"
    Options = VPRBenchOptions
    splits = {}

    def detect(self, root: Path) -> bool:
        return has_images(root / "query") and has_images(root / "ref") and any((root / f).is_file() for f in GT_FILES)

    def _gt_path(self, root: Path, options: VPRBenchOptions) -> Path:
        if options.ground_truth:
            path = Path(options.ground_truth)
            return path if path.is_absolute() else root / path
        for name in GT_FILES:
            if (root / name).is_file():
                return root / name
        raise DataError(
            f"{root}: no ground-truth file; VPR-Bench datasets ship ground_truth_new.npy "
            f"(or give ground_truth.csv: query_index,reference_indices)"
        )

    def _traverses(self, root: Path) -> tuple[Traverse, Traverse]:
        for sub in ("ref", "query"):
            if not (root / sub).is_dir():
                raise DataError(f"{root / sub}: folder not found; the VPR-Bench layout has query/ and ref/")
        return (Traverse("ref", list_images(root / "ref")), Traverse("query", list_images(root / "query")))

    def evaluation_split(self, root, reference, query, split, options) -> EvaluationSplit:
        ref, qry = self._traverses(root)
        gt_path = self._gt_path(root, options)
        if gt_path.suffix.lower() == ".npy":
            gt = ground_truth_from_npy(gt_path, len(qry), len(ref))
        else:
            gt = read_listed_ground_truth(gt_path, ref, qry)
        start, end = resolve_split(split, {}, len(qry), str(root))
        if (start, end) != (None, None):
            q_idx = np.arange(len(qry))[slice(start, end)]
            qry, gt = qry.select(q_idx), gt.subset(q_idx)
        return EvaluationSplit(ref, qry, gt, describe(root, qry, ref, gt))

    def listed_evaluation_split(self, root, reference, query, split, options, ground_truth) -> EvaluationSplit:
        """The split's queries and the whole map with an explicit list over them; the dataset's
        own ground-truth file is not needed."""
        ref, qry = self._traverses(root)
        start, end = resolve_split(split, {}, len(qry), str(root))
        qry = qry.frames(start, end)
        gt = read_listed_ground_truth(ground_truth, ref, qry)
        return EvaluationSplit(ref, qry, gt, describe(root, qry, ref, gt))

    def training_dataset(self, root, split, conditions, options) -> RouteDataset:
        ref, qry = self._traverses(root)
        start, end = resolve_split(split, {}, min(len(ref), len(qry)), str(root))
        traverses = {"ref": ref.frames(start, end), "query": qry.frames(start, end)}
        if conditions:
            traverses = {c: traverses[c] for c in conditions if c in traverses}
        return RouteDataset(root, traverses)


FORMAT = VPRBenchFormat()
