"""Dataset adapters: point fdnet at a dataset folder as it unpacks and get the paper's protocol.

``open_split(root)`` returns an :class:`~fdnet.data.split.EvaluationSplit` (reference map,
queries, ground truth); ``open_training(root)`` the :class:`~fdnet.data.dataset.RouteDataset` to
train on. The format is detected from characteristic files and folders (``detect_format``) or
named (``dataset_format=``/``--dataset-format``); each format's protocol settings (tolerances,
file names, columns) have the paper's values as defaults and can be overridden by keyword
(``tolerance=3``), strings are converted to the setting's type. Splits are named (``train``,
``test``, ``all``; see ``describe_formats()``) or ``START:END``.

One module per layout: ``nordland``, ``alderley``, ``oxford_robotcar``, ``st_lucia``, ``fas``,
``vprbench``, ``vpr_tutorial``, ``vg_benchmark`` (UTM in file names), ``folders`` (one sub-folder
per condition).
"""

from __future__ import annotations

import importlib
import os
from pathlib import Path
from typing import Sequence

from fdnet.config import from_dict, to_dict
from fdnet.data.dataset import RouteDataset
from fdnet.data.formats._common import DatasetFormat, check_image_sizes
from fdnet.data.split import EvaluationSplit
from fdnet.errors import ConfigError, DataError

# Detection order: most specific layouts first, the plain one-folder-per-condition layout last.
FORMAT_MODULES = {
    "vprbench": "fdnet.data.formats.vprbench",
    "vpr_tutorial": "fdnet.data.formats.vpr_tutorial",
    "vg_benchmark": "fdnet.data.formats.vg_benchmark",
    "oxford_robotcar": "fdnet.data.formats.oxford_robotcar",
    "alderley": "fdnet.data.formats.alderley",
    "fas": "fdnet.data.formats.fas",
    "st_lucia": "fdnet.data.formats.st_lucia",
    "nordland": "fdnet.data.formats.nordland",
    "folders": "fdnet.data.formats.folders",
}
ALIASES = {
    "robotcar": "oxford_robotcar",
    "oxford": "oxford_robotcar",
    "stlucia": "st_lucia",
    "vpr-bench": "vprbench",
    "vpr_bench": "vprbench",
    "vpr-tutorial": "vpr_tutorial",
    "freiburg": "fas",
    "folder": "folders",
    "plain": "folders",
    "gsv": "vg_benchmark",
    "vg-benchmark": "vg_benchmark",
}


def format_names() -> list[str]:
    return list(FORMAT_MODULES)


def get_format(name: str) -> DatasetFormat:
    key = ALIASES.get(name.lower(), name.lower())
    if key not in FORMAT_MODULES:
        raise ConfigError(f"unknown dataset format {name!r}; available: {', '.join(FORMAT_MODULES)}")
    return importlib.import_module(FORMAT_MODULES[key]).FORMAT


def detect_format(root: str | os.PathLike) -> str:
    """The name of the first format whose characteristic files/folders are in ``root``."""
    root = Path(root)
    if not root.is_dir():
        raise DataError(f"{root}: dataset folder not found")
    for name in FORMAT_MODULES:
        if get_format(name).detect(root):
            return name
    raise DataError(
        f"{root}: not a dataset layout fdnet recognises (looked for {', '.join(FORMAT_MODULES)}); "
        f"expected e.g. one sub-folder of images per condition, or query/ and ref/ with a ground truth; "
        f"name the layout with --dataset-format"
    )


def describe_formats() -> dict[str, dict]:
    """name -> {summary, splits, defaults} for help texts and docs."""
    out = {}
    for name in FORMAT_MODULES:
        fmt = get_format(name)
        out[name] = {"summary": fmt.summary, "splits": dict(fmt.splits), "defaults": to_dict(fmt.Options())}
    return out


def _options(fmt: DatasetFormat, protocol_options: dict):
    options = {k: v for k, v in protocol_options.items() if v is not None}
    return from_dict(fmt.Options, options, where=f"dataset format {fmt.name!r} settings")


def _resolve(root, dataset_format) -> tuple[Path, DatasetFormat]:
    root = Path(root)
    if not root.is_dir():
        raise DataError(f"{root}: dataset folder not found")
    return root, get_format(dataset_format or detect_format(root))


def open_split(
    root: str | os.PathLike,
    reference: str | None = None,
    query: str | None = None,
    dataset_format: str | None = None,
    split: str | None = None,
    check_sizes: bool = True,
    listed_ground_truth: str | os.PathLike | None = None,
    **protocol_options,
) -> EvaluationSplit:
    """Reference map, queries and ground truth of a dataset folder under its paper protocol.

    ``split``: a named split (``test`` is the default where the paper has one) or ``START:END``.
    ``check_sizes``: fail early when a condition mixes image sizes (reads only file headers).
    ``listed_ground_truth``: an explicit ground-truth CSV that replaces the format's ground truth
    for the chosen split: its indices are positions in the split's query and reference images
    (what ``fdnet groundtruth --data ROOT --split S`` writes); size and names are checked.
    (Not to be confused with the ``ground_truth`` setting of some formats, which names the
    dataset's own ground-truth file.)
    """
    root, fmt = _resolve(root, dataset_format)
    options = _options(fmt, protocol_options)
    split = split or fmt.default_eval_split
    if listed_ground_truth is not None:
        result = fmt.listed_evaluation_split(root, reference, query, split, options, Path(listed_ground_truth))
    else:
        result = fmt.evaluation_split(root, reference, query, split, options)
    if check_sizes:
        for traverse in (result.reference, result.query):
            check_image_sizes(traverse)
    return result


def open_training(
    root: str | os.PathLike,
    dataset_format: str | None = None,
    split: str | None = None,
    conditions: Sequence[str] | None = None,
    check_sizes: bool = True,
    **protocol_options,
) -> RouteDataset:
    """The conditions to train on (default: all of the layout's), cut to ``split`` (default
    ``train`` where the paper has one)."""
    root, fmt = _resolve(root, dataset_format)
    options = _options(fmt, protocol_options)
    route = fmt.training_dataset(root, split or fmt.default_train_split, conditions, options)
    if check_sizes:
        for traverse in route.traverses.values():
            check_image_sizes(traverse)
    return route


__all__ = [
    "open_split",
    "open_training",
    "detect_format",
    "get_format",
    "format_names",
    "describe_formats",
    "DatasetFormat",
]
