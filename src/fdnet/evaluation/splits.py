"""The reference/query split and the precomputed similarity matrix that ``fdnet evaluate`` and
``fdnet calibrate`` score: condition folders aligned frame by frame (or with an explicit
ground-truth CSV), or a published dataset layout through its adapter.

The keyword names are the commands' flags (``--data``, ``--reference``, ``--query``,
``--dataset-format``, ``--split``, ``--format-set``, ``--frames``, ``--tolerance``,
``--filter-frames``, ``--ground-truth``), and error messages name those flags.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path

from fdnet.errors import ConfigError, DataError

logger = logging.getLogger(__name__)


def ground_truth_path(ground_truth) -> Path | None:
    """``--ground-truth`` as a path (relative to where the command runs), or None. A file that is
    not there is an error naming it, whatever else was given."""
    if ground_truth is None:
        return None
    path = Path(ground_truth)
    if not path.is_file():
        raise DataError(
            f"{path}: ground-truth file not found"
            if not path.exists()
            else f"{path}: is not a file; expected a ground-truth CSV"
        )
    return path  # as typed, so errors name the file the way the user wrote it


@dataclass(frozen=True)
class SplitSpec:
    """Which reference and query images a command evaluates or calibrates on, as the data flags
    give them: ``data`` (a folder of condition sub-folders, or a published layout with
    ``dataset_format``), ``reference`` and ``query`` conditions, a named ``split`` or a ``frames``
    range, the format's ``format_set`` (KEY=VALUE), the frame ``tolerance``, ``filter_frames``,
    and a ``ground_truth`` CSV replacing the frame alignment."""

    data: str
    reference: str | None = None
    query: str | None = None
    dataset_format: str | None = None
    split: str | None = None
    format_set: tuple = ()
    frames: str | None = None
    tolerance: int | None = None
    filter_frames: bool = False
    ground_truth: str | None = None


def _format_split(spec: SplitSpec, ground_truth):
    """``--dataset-format``: the adapter's split; ``--ground-truth`` replaces its ground truth for
    the chosen split (indices over the split's images, as ``fdnet groundtruth --data`` writes)."""
    from fdnet.config import parse_overrides
    from fdnet.data.formats import detect_format, get_format, open_split

    data, tolerance, filter_frames = spec.data, spec.tolerance, spec.filter_frames
    if spec.frames and spec.split:
        raise ConfigError("give --split or --frames, not both")
    name = detect_format(data) if spec.dataset_format == "auto" else spec.dataset_format
    fields = {f.name for f in dataclasses.fields(get_format(name).Options)}
    options = parse_overrides(list(spec.format_set))
    if tolerance is not None:
        options["tolerance"] = tolerance
    if filter_frames:
        if "filter_frames" not in fields:
            raise ConfigError(
                f"--filter-frames: the {name} format has no frame filter (formats with one: "
                f"nordland); without --dataset-format it applies to plain condition folders"
            )
        options["filter_frames"] = "true"
    if ground_truth is not None and options.get("ground_truth"):
        raise ConfigError(
            f"two explicit ground truths: --ground-truth {ground_truth} and "
            f"--format-set ground_truth={options['ground_truth']}; give one"
        )
    return open_split(
        data,
        spec.reference,
        spec.query,
        dataset_format=name,
        split=spec.split or spec.frames,
        listed_ground_truth=ground_truth,
        **options,
    )


def build_split(spec: SplitSpec):
    """:func:`_build_split`. Its ``description`` names the ground truth and the tolerance in use
    (Gardens Point's protocol tolerance is said there too), and every command that evaluates or
    calibrates on a split prints it."""
    if not isinstance(spec, SplitSpec):
        raise ConfigError(f"build_split needs a SplitSpec, got {type(spec).__name__}")
    return _build_split(spec)


def _build_split(spec: SplitSpec):
    """The :class:`~fdnet.data.split.EvaluationSplit` these settings describe. Without
    ``dataset_format``: ``data/reference/query`` frame-aligned (:func:`fdnet.data.split.aligned_split`,
    after the frame filter with ``filter_frames``) or with ``ground_truth`` over all images of the
    two folders (:func:`fdnet.data.split.listed_split`), sliced by ``frames``. With it: the
    dataset adapter's split, its ground truth replaced by ``ground_truth`` when given."""
    from fdnet.data.dataset import RouteDataset, parse_frame_range
    from fdnet.data.split import aligned_split, listed_split

    ground_truth = ground_truth_path(spec.ground_truth)
    if spec.dataset_format:
        return _format_split(spec, ground_truth)
    data, reference, query, frames = spec.data, spec.reference, spec.query, spec.frames
    tolerance, filter_frames = spec.tolerance, spec.filter_frames
    if spec.split or spec.format_set:
        raise ConfigError("--split and --format-set need --dataset-format")
    if not (reference and query):
        raise ConfigError("--data needs --reference COND and --query COND (sub-folders of --data)")
    start, end = parse_frame_range(frames)
    dataset = RouteDataset.from_folder(data, [reference, query] if reference != query else [reference])
    _check_frames_inside(frames, start, end, dataset)
    if ground_truth is not None:
        if filter_frames:
            raise ConfigError(
                "--filter-frames applies to frame-aligned folders; with --ground-truth CSV, filter "
                "the images before writing the ground truth"
            )
        return listed_split(dataset, reference, query, ground_truth, start, end)
    protocol_tolerance = False
    if tolerance is None:  # the layout is looked at once (it may refuse a published format)
        tolerance = default_folder_tolerance(data, dataset.conditions)
        protocol_tolerance = tolerance > 0
    if filter_frames:
        from fdnet.data.filters import filter_frames as drop_frames

        dataset, summary = drop_frames(dataset.frames(start, end))
        logger.info(f"frame filter: {summary}")
        start = end = None
    split = aligned_split(dataset, reference, query, tolerance, start, end)
    if protocol_tolerance:  # say where the tolerance came from
        split = dataclasses.replace(
            split,
            description=f"{split.description} (Gardens Point's protocol, as VPR-Bench; " "--tolerance changes it)",
        )
    return split


#: layouts that are frame-aligned condition folders, whose ground truth is the frame order itself
_FRAME_ALIGNED_FORMATS = ("folders", "nordland")


def default_folder_tolerance(data, conditions) -> int:
    """The frame tolerance of plain folders when none is given: 2 for Gardens Point (its
    protocol, as VPR-Bench uses), else 0. A folder laid out as a published dataset that carries
    its own ground truth (VPR-Bench's ground_truth.csv, GPS, a correspondence file) is refused:
    read as plain folders, query i would silently match only reference i."""
    from fdnet.data.formats import detect_format
    from fdnet.data.formats.folders import is_gardens_point

    try:
        layout = detect_format(data)
    except DataError:
        layout = None
    if layout is not None and layout not in _FRAME_ALIGNED_FORMATS:
        raise ConfigError(
            f"{data}: is laid out as the {layout!r} dataset format, which carries its own ground truth; "
            "read as plain folders, query i would match only reference i. Give --dataset-format "
            f"{layout} (or auto) to use its ground truth, --ground-truth FILE, or --tolerance N to align "
            "the folders frame by frame on purpose"
        )
    return 2 if is_gardens_point(list(conditions)) else 0


def _check_frames_inside(text, start, end, dataset) -> None:
    """A --frames range reaching past the folders' end would silently evaluate fewer frames than
    asked (50:500 of 60 images gave 10)."""
    counts = {name: len(traverse) for name, traverse in dataset.traverses.items()}
    frames = min(counts.values())
    listed = ", ".join(f"{name} {count}" for name, count in counts.items())
    if (end is not None and end > frames) or (start is not None and start >= frames):
        raise ConfigError(
            f"--frames {text}: past the end of the folders ({listed} images); give a range within "
            f"0:{frames}, or leave END out ({start or 0}:) for the rest"
        )


def load_similarity(path, distance: bool = False):
    """A plain numeric 2-D .npy matrix, finite everywhere; never unpickles, and refuses a header
    claiming more data than the file holds before allocating anything. Distances are negated."""
    import numpy as np

    from fdnet.data.arrays import load_npy

    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: similarity file not found")
    matrix = load_npy(path, ndim=2, what="similarity matrix (queries x references)")
    if not (np.issubdtype(matrix.dtype, np.floating) or np.issubdtype(matrix.dtype, np.integer)):
        raise DataError(f"{path}: expected a numeric (float or integer) matrix, got dtype {matrix.dtype}")
    if matrix.size == 0:
        raise DataError(f"{path}: the matrix is empty (shape {matrix.shape})")
    bad = ~np.isfinite(matrix) if np.issubdtype(matrix.dtype, np.floating) else None
    if bad is not None and bad.any():
        q, r = np.argwhere(bad)[0]
        raise DataError(
            f"{path}: {int(bad.sum())} NaN or infinite entries (first at query {q}, "
            f"reference {r}); every query-reference pair needs a score"
        )
    matrix = matrix.astype(np.float64)
    return -matrix if distance else matrix


def evaluate_similarity_file(
    path,
    *,
    split=None,
    ground_truth=None,
    distance: bool = False,
    name: str | None = None,
    protocols=("recall-over-queries",),
    thresholds: int | None = None,
    acceptance=None,
):
    """A precomputed (queries x references) matrix in the .npy file ``path`` scored against the
    ground truth of ``split`` (which also gives the images, for plots) or of the CSV
    ``ground_truth`` (whose indices are the matrix's: no images to check its names against).
    ``distance``: the file holds distances (negated here). ``name`` defaults to the file's name
    without ``_similarity``."""
    import re

    from fdnet.data.groundtruth import GroundTruth
    from fdnet.evaluation.experiment import ScoringSettings, evaluate_matrix

    matrix = load_similarity(path, distance)
    if split is not None:
        gt = split.ground_truth
    elif ground_truth:
        gt = GroundTruth.from_csv(ground_truth, num_references=matrix.shape[1], num_queries=matrix.shape[0])
    else:
        raise ConfigError(
            "--similarity needs ground truth: --ground-truth CSV, or --data with "
            "--reference/--query (frame-aligned, --tolerance)"
        )
    if matrix.shape != (gt.num_queries, gt.num_references):
        raise DataError(
            f"{path}: matrix is {matrix.shape[0]} x {matrix.shape[1]} but the ground "
            f"truth is for {gt.num_queries} queries x {gt.num_references} references"
        )
    return evaluate_matrix(
        matrix,
        gt,
        name or re.sub(r"_similarity$", "", Path(path).stem),
        ScoringSettings(protocols=protocols, thresholds=thresholds, acceptance=acceptance),
        dataset=split.description if split else f"{Path(path).name} vs {gt.description}",
        query_paths=split.query.paths if split else None,
        reference_paths=split.reference.paths if split else None,
        # a distance matrix was negated: its largest possible similarity is 0
        similarity_ceiling=0.0 if distance else 1.0,
    )


def check_descriptors_held_out(
    descriptors, data, conditions, frames=None, dataset_format=None, split=None, allow: bool = False
) -> None:
    """:func:`fdnet.runs.held_out.check_held_out` for every trained method among ``descriptors``
    (those that carry their run directory): one check for evaluate, calibrate and loop-closure."""
    from fdnet.descriptors.registry import trained_methods
    from fdnet.runs.held_out import check_held_out

    trained = set(trained_methods())
    for descriptor in descriptors:
        run_dir = descriptor.run_dir
        if descriptor.name in trained and run_dir is not None:
            check_held_out(descriptor.name, run_dir, data, conditions, frames, dataset_format, split, allow)
