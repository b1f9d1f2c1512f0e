"""Where each frame came from: its source, its time and its position (:class:`FrameRecord`), for
the frames :mod:`fdnet.data.sources` lists (a video's, a bag's) and for image files alike, and
positions in planar metres (:func:`positions_in_metres`). Read by every command that uses times
or positions (matching's neighbourhoods, loop closure, databases, extraction, ground truth)."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from fdnet.data.sources import BAG_FRAME_NAME, FRAME_OWNER, VIDEO_FRAME_NAME, SourceListing, kind_of


@dataclass(frozen=True)
class FrameRecord:
    """Where a frame came from: its source (video or bag; the folder for an image file), its time in
    seconds (None for image files) and its position (None where unknown)."""

    source: str
    timestamp: float | None = None
    position: tuple[float, float] | None = None
    position_kind: str | None = None
    topic: str | None = None


def locate(path: str | os.PathLike) -> tuple[Path, str | None, str] | None:
    """(source, topic, frame name) of a frame path, or None when ``path`` is no frame of a source."""
    path = Path(path)
    name = path.name
    video = VIDEO_FRAME_NAME.match(name)
    bag = BAG_FRAME_NAME.match(name)
    if not (video or bag):
        return None
    if video and path.parent.is_file() and kind_of(path.parent) == "video":
        return path.parent, None, name
    if bag:
        parent = path.parent
        topic_parts: list[str] = []
        while parent != parent.parent and not parent.exists():
            topic_parts.insert(0, parent.name)
            parent = parent.parent
        if topic_parts and kind_of(parent) == "bag":
            return parent, "/" + "/".join(topic_parts), name
    return None


def frame_records(paths: Sequence[str | os.PathLike]) -> list[FrameRecord]:
    """A :class:`FrameRecord` per path: a frame of a listed source gets its time and position; an
    image file gets its folder as source and no time."""
    out = []
    for p in paths:
        listing = FRAME_OWNER.get(str(p))
        if listing is None:
            found = locate(p)
            if found is not None:  # a frame path listed in another process: its name has its time
                source, topic, name = found
                match = (VIDEO_FRAME_NAME if topic is None else BAG_FRAME_NAME).match(name)
                scale = 1e3 if topic is None else 1e9
                out.append(FrameRecord(str(source), int(match.group(2)) / scale, topic=topic))
            else:
                out.append(FrameRecord(str(Path(p).parent)))
            continue
        i = listing.paths.index(Path(p)) if len(listing.paths) < 64 else _position_in(listing, p)
        position = None
        if listing.positions is not None and np.isfinite(listing.positions[i]).all():
            position = (float(listing.positions[i, 0]), float(listing.positions[i, 1]))
        out.append(
            FrameRecord(str(listing.source), float(listing.times[i]), position, listing.position_kind, listing.topic)
        )
    return out


def _position_in(listing: SourceListing, path) -> int:
    index = getattr(listing, "_index", None)
    if index is None:
        index = {str(q): k for k, q in enumerate(listing.paths)}
        listing._index = index  # type: ignore[attr-defined]
    return index[str(path)]


def positions_in_metres(records: Sequence[FrameRecord]) -> list[tuple[float, float] | None]:
    """Each record's position in planar metres, or None. Degrees are projected equirectangularly
    about the centre of the 1-degree cell of the first fix (so every traverse of one area gets the
    same origin without one being stored; the scale error stays under 1 % of a distance within
    the cell); metres (odometry) are kept."""
    from fdnet.data.groundtruth import latlon_to_metres

    origin = None
    out: list[tuple[float, float] | None] = []
    for record in records:
        if record.position is None:
            out.append(None)
        elif record.position_kind == "degrees":
            if origin is None:
                origin = (math.floor(record.position[0]) + 0.5, math.floor(record.position[1]) + 0.5)
            xy = latlon_to_metres(np.array([record.position[0]]), np.array([record.position[1]]), origin)[0]
            out.append((float(xy[0]), float(xy[1])))
        else:
            out.append(record.position)
    return out
