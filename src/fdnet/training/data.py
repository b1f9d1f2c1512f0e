"""Training data for every trained method: the route a run's ``DataConfig`` names, its images as
uint8 tensors held in memory, and the validation pair.

One function (:func:`training_route`) turns a ``DataConfig`` into the route to train on, for plain
condition folders (``--frames``) and published layouts (``--dataset-format/--split``) alike, so
FDNet, CALC and NetVLAD read their images the same way and ``--resume`` reads the same ones.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from fdnet.data.dataset import RouteDataset, parse_frame_range
from fdnet.data.groundtruth import GroundTruth
from fdnet.data.images import load_images
from fdnet.data.split import aligned_split
from fdnet.errors import ConfigError, DataError


def training_route(data) -> RouteDataset:
    """The conditions and frames a :class:`fdnet.methods.settings.DataConfig` names."""
    if not data.root:
        raise ConfigError("no training data given (--data DIR, a folder with one sub-folder per condition)")
    conditions = list(data.conditions) or None
    if data.dataset_format:
        from fdnet.data.formats import open_training

        if data.frames:
            raise ConfigError("with --dataset-format, choose frames with --split (a name or START:END), not --frames")
        fmt = data.dataset_format
        route = open_training(data.root, None if fmt == "auto" else fmt, data.split or None, conditions)
    else:
        if data.split:
            raise ConfigError("--split needs --dataset-format; for plain condition folders use --frames START:END")
        route = RouteDataset.from_folder(data.root, conditions)
        start, end = parse_frame_range(data.frames or None)
        route = route.frames(start, end)
    for name, traverse in route.traverses.items():
        if len(traverse) == 0:
            raise DataError(
                f"{Path(data.root) / name}: frame range {data.frames or data.split or 'all'!r} " "selects no images"
            )
    return route


def to_uint8_tensor(images: np.ndarray) -> torch.Tensor:
    """(N, H, W, 3) float [0, 1] -> (N, 3, H, W) uint8 (a quarter of float32's memory)."""
    return torch.from_numpy(np.clip(np.rint(images * 255.0), 0, 255).astype(np.uint8)).permute(0, 3, 1, 2).contiguous()


def load_uint8(paths, size, chunk: int = 256) -> torch.Tensor:
    """Images at ``size`` as one uint8 (N, 3, H, W) tensor, decoded chunk by chunk so the float
    copy never holds more than ``chunk`` images."""
    from fdnet.progress import progress_bar

    parts = []
    # minutes for a large route on a small machine: a bar with the time left (fdnet.progress)
    with progress_bar(total=len(paths), desc="reading training images", unit="img", leave=False) as bar:
        for i in range(0, len(paths), chunk):
            parts.append(to_uint8_tensor(load_images(paths[i : i + chunk], size)))
            bar.update(len(paths[i : i + chunk]))
    if not parts:
        return torch.zeros((0, 3, int(size[0]), int(size[1])), dtype=torch.uint8)
    return torch.cat(parts)


@dataclass
class TrainingImages:
    """Training images held in memory as uint8 (N, 3, H, W) per condition: decoding image files
    every step would cost more than the network on a 2-core CPU. ``frame_ids`` keep each image's
    place in its traversal (NetVLAD's positives)."""

    names: list[str]
    images: list[torch.Tensor]
    frame_ids: list[np.ndarray]


def route_images(
    route: RouteDataset, size, min_per_condition: int = 1, min_conditions: int = 1, why: str = ""
) -> TrainingImages:
    """Every condition of ``route`` at ``size`` (counts checked before anything is decoded)."""
    if len(route.conditions) < min_conditions:
        raise DataError(
            f"{route.root}: {why or 'this method'} needs at least {min_conditions} conditions "
            f"(sub-folders) to train on; found {', '.join(route.conditions) or 'none'}"
        )
    for name in route.conditions:
        if len(route[name]) < min_per_condition:
            raise DataError(
                f"{Path(route.root) / name}: {len(route[name])} training images, fewer than "
                f"the {min_per_condition} one mini-batch needs ({why})"
            )
    return TrainingImages(
        list(route.conditions),
        [load_uint8(route[c].paths, size) for c in route.conditions],
        [np.asarray(route[c].frame_ids) for c in route.conditions],
    )


@dataclass
class ValidationImages:
    reference: torch.Tensor
    query: torch.Tensor
    ground_truth: GroundTruth
    description: str


def load_validation_images(root: str | Path, validation, size) -> ValidationImages | None:
    """The validation pair a :class:`fdnet.methods.settings.ValidationConfig` names, at ``size``
    (None when validation is off)."""
    v = validation
    if not v.reference:
        return None
    # the one frame-aligned split (fdnet evaluate --data uses it too): equal frame counts,
    # a frame range that selects images, ground truth from frame ids
    start, end = parse_frame_range(v.frames)
    try:
        split = aligned_split(
            RouteDataset.from_folder(root, [v.reference, v.query]), v.reference, v.query, v.tolerance, start, end
        )
    except DataError as exc:
        raise DataError(f"validation {v.query}->{v.reference}: {exc}") from exc
    ref, query, gt = split.reference, split.query, split.ground_truth
    if not gt.has_match.any():
        raise DataError(f"validation {v.query}->{v.reference} frames {v.frames or 'all'}: no query has a match")
    return ValidationImages(
        load_uint8(ref.paths, size),
        load_uint8(query.paths, size),
        gt,
        f"{v.query}->{v.reference} frames {v.frames or 'all'} tolerance {v.tolerance}",
    )
