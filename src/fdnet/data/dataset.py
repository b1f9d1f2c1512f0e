"""Datasets: a route traversed under several conditions.

On disk the common layout is one sub-folder per condition (``summer/``, ``winter/``...), whose
file names sort in traversal order (the natural order of :func:`fdnet.data.images.list_images`).
A :class:`Traverse` is one condition's ordered images; a :class:`RouteDataset` is the set of
traverses of one route.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from fdnet.data.images import has_images, list_images
from fdnet.errors import DataError


@dataclass
class Traverse:
    """One condition's images in traversal order.

    ``frame_ids`` are the original positions of the images in the full traverse; they survive
    slicing and filtering so frame-aligned ground truth stays correct.
    ``positions`` (optional, (N, 2) metres) and ``timestamps`` (optional) come from adapters.
    """

    name: str
    paths: list[Path]
    frame_ids: np.ndarray | None = None
    positions: np.ndarray | None = None
    timestamps: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.paths = [Path(p) for p in self.paths]
        if self.frame_ids is None:
            self.frame_ids = np.arange(len(self.paths))
        self.frame_ids = np.asarray(self.frame_ids, dtype=np.int64)
        if len(self.frame_ids) != len(self.paths):
            raise ValueError("frame_ids must have one entry per path")

    def __len__(self) -> int:
        return len(self.paths)

    def select(self, indices: Sequence[int] | np.ndarray) -> "Traverse":
        """A new traverse holding only ``indices`` (in that order)."""
        idx = np.asarray(indices, dtype=np.int64)
        return Traverse(
            name=self.name,
            paths=[self.paths[i] for i in idx],
            frame_ids=self.frame_ids[idx],
            positions=None if self.positions is None else self.positions[idx],
            timestamps=None if self.timestamps is None else self.timestamps[idx],
        )

    def frames(self, start: int | None, end: int | None) -> "Traverse":
        """Images whose position in this traverse is in [start, end) (Python slice semantics)."""
        return self.select(np.arange(len(self))[slice(start, end)])

    @classmethod
    def from_folder(cls, folder: str | os.PathLike, name: str | None = None) -> "Traverse":
        """A folder of images, or a video or ROS bag (:mod:`fdnet.data.sources`, whose frames
        bring their timestamps and, from a bag's position topic, positions)."""
        from fdnet.data import sources
        from fdnet.data.frame_records import frame_records

        paths = list_images(folder)
        folder = Path(folder)
        if not sources.is_source(folder):
            return cls(name=name or folder.name, paths=paths)
        records = frame_records(paths)
        return cls(
            name=name or folder.name, paths=paths, timestamps=np.array([r.timestamp for r in records], dtype=np.float64)
        )


@dataclass
class RouteDataset:
    """A route seen under several conditions: condition name -> :class:`Traverse`."""

    root: Path
    traverses: dict[str, Traverse] = field(default_factory=dict)

    @property
    def conditions(self) -> list[str]:
        return list(self.traverses)

    def __getitem__(self, condition: str) -> Traverse:
        try:
            return self.traverses[condition]
        except KeyError as exc:
            raise DataError(
                f"{self.root}: no condition {condition!r}; available: {', '.join(self.conditions) or 'none'}"
            ) from exc

    @classmethod
    def from_folder(cls, root: str | os.PathLike, conditions: Sequence[str] | None = None) -> "RouteDataset":
        """Read ``root/<condition>/*.png|jpg...`` (or ``root/<condition>.mp4``, a bag: a condition may be a
        video or ROS bag, named with or without its extension); ``conditions`` picks and orders them."""
        root = Path(root)
        if not root.is_dir():
            raise DataError(f"{root}: dataset folder not found")
        from fdnet.data.sources import condition_path, is_source

        if conditions is None:
            conditions = sorted(
                p.name for p in root.iterdir() if not p.name.startswith(".") and (is_source(p) or has_images(p))
            )
            if not conditions:
                raise DataError(
                    f"{root}: no condition sub-folders with images, videos or bags (expected "
                    f"root/<condition>/*.png or root/<condition>.mp4)"
                )
        traverses = {}
        for name in conditions:
            folder = condition_path(root, name)
            if folder is None:
                available = sorted(p.name for p in root.iterdir() if p.is_dir() or is_source(p))
                raise DataError(
                    f"{root / name}: condition folder not found; available: "
                    f"{', '.join(available) or 'none'} (a condition may be a folder, video or ROS bag)"
                )
            traverses[name] = Traverse.from_folder(folder, name)
        return cls(root=root, traverses=traverses)

    def frames(self, start: int | None, end: int | None) -> "RouteDataset":
        """The same slice of every condition (e.g. to split a route into train and test)."""
        return RouteDataset(self.root, {k: t.frames(start, end) for k, t in self.traverses.items()})


def parse_frame_range(text: str | None) -> tuple[int | None, int | None]:
    """``"START:END"`` -> (start, end), END exclusive; either side may be empty."""
    if text is None or text == "":
        return None, None
    if ":" not in text:
        raise DataError(f"frame range {text!r}: expected START:END (END exclusive), e.g. 0:1576")
    start_s, end_s = text.split(":", 1)
    try:
        start = int(start_s) if start_s.strip() else None
        end = int(end_s) if end_s.strip() else None
    except ValueError as exc:
        raise DataError(f"frame range {text!r}: START and END must be integers") from exc
    if start is not None and end is not None and end <= start:
        raise DataError(f"frame range {text!r}: END must be greater than START")
    return start, end


def frame_ranges_overlap(a: str | None, b: str | None) -> bool:
    """Whether two ``START:END`` frame ranges (None or empty: every frame) share a frame: the one
    test for "trained on the frames it is measured on" (reproduce's lengths study, the held-out
    check of evaluate, calibrate and loop-closure)."""
    (a0, a1), (b0, b1) = parse_frame_range(a), parse_frame_range(b)
    inf = float("inf")
    return max(a0 or 0, b0 or 0) < min(inf if a1 is None else a1, inf if b1 is None else b1)


def check_training_frames(train_frames: str | None, evaluated: str | None, train_flag: str, by: str) -> None:
    """Refuse an experiment that trains (``by``, e.g. ``--length-preset``) without training
    frames (``train_flag``), or on frames that overlap the ``evaluated`` ones (``--frames``)."""
    from fdnet.errors import ConfigError

    if not train_frames:
        raise ConfigError(f"{by} needs {train_flag} START:END (frames to train on, outside the evaluated --frames)")
    if frame_ranges_overlap(train_frames, evaluated):
        raise ConfigError(
            f"{train_flag} {train_frames} overlaps the evaluated frames --frames {evaluated or 'all'}: "
            "train and test on different frames"
        )
