"""Image sources that are not folders: video files and ROS 1 / ROS 2 bags, in the one image order.

A *source* is a video file (anything OpenCV's ``VideoCapture`` opens, recognised by its extension:
:data:`VIDEO_EXTENSIONS`) or a ROS bag read with the pure-Python ``rosbags`` package (a ROS 1
``.bag``, a ROS 2 ``.db3`` or ``.mcap`` file, or a ROS 2 bag folder holding ``metadata.yaml``),
optionally with its image topic as ``BAG:TOPIC``. :func:`fdnet.data.images.list_images` hands a
source to :func:`list_frames`, so every command that accepts a folder of images accepts a source.

**Frames are paths.** Each frame is named by a path below its source that does not exist on disk:
``route/summer.mp4/frame_000025_1000ms`` (source frame 25, 1000 ms after the first frame) or
``run.bag/camera/image_raw/frame_000012_1700000000123456789ns`` (message 12 of topic
``/camera/image_raw``, recorded at that time in nanoseconds since the epoch). Their names carry
the frame's index and timestamp and sort in the one image order (:func:`natural_key`), they
travel to decoding worker processes as plain paths, and :func:`fdnet.data.images.load_image`
decodes them through :func:`fdnet.data.frames.open_frame` (each process keeps its open videos and bags, reading
forward, so a traverse is decoded in one pass). So no command needs a special case.

**Sampling** (:class:`SourceOptions`, the ``--fps``, ``--every``, ``--window``, ``--topic`` and
``--position-topic`` flags of every command): a time window in seconds from the first frame, then
every k-th frame or the first frame of each 1/N-second slot. Frame names keep the source's own
index, so a sampled frame is named as it would be unsampled.

**Timestamps and positions** (:func:`fdnet.data.frame_records.frame_records`): a video frame's time
is its index divided by the container's frame rate (seconds from the first frame); a bag frame's
time is the time the bag recorded the message (seconds since the epoch; header stamps are not read,
so the images and the positions use one clock). Positions come from a ``sensor_msgs/NavSatFix``
(latitude, longitude; messages without a fix are skipped) or ``nav_msgs/Odometry`` topic (x, y in
metres), linearly interpolated to the image times; frames outside the position messages' time span
have none.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterator

import numpy as np

from fdnet.errors import ConfigError, DataError

log = logging.getLogger(__name__)

VIDEO_EXTENSIONS = (
    ".mp4",
    ".avi",
    ".mkv",
    ".mov",
    ".m4v",
    ".webm",
    ".mpg",
    ".mpeg",
    ".wmv",
    ".flv",
    ".ts",
    ".mts",
    ".m2ts",
    ".ogv",
    ".3gp",
    ".y4m",
)
BAG_EXTENSIONS = (".bag", ".db3", ".mcap")

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
ODOMETRY = "nav_msgs/msg/Odometry"

#: raw sensor_msgs/Image encodings fdnet decodes; others (16UC1 depth, 32FC1, ...) are refused
RAW_ENCODINGS = (
    "rgb8",
    "bgr8",
    "rgba8",
    "bgra8",
    "mono8",
    "8UC1",
    "8UC3",
    "mono16",
    "bayer_rggb8",
    "bayer_bggr8",
    "bayer_gbrg8",
    "bayer_grbg8",
)

VIDEO_FRAME_NAME = re.compile(r"^frame_([0-9]+)_([0-9]+)ms$")
BAG_FRAME_NAME = re.compile(r"^frame_([0-9]+)_([0-9]+)ns(?:_([0-9]+))?$")

#: frames a reader grabs forward before it seeks instead (seeking costs a key-frame decode)
READ_FORWARD = 256


@dataclass(frozen=True)
class SourceOptions:
    """How frames are taken from a video or bag (folders ignore these)."""

    fps: float | None = None  # at most this many frames per second (the first frame of each 1/fps slot)
    every: int | None = None  # every k-th frame
    window: tuple[float | None, float | None] = (None, None)  # seconds from the first frame, [start, end)
    topic: str | None = None  # a bag's image topic (needed when it has several)
    position_topic: str | None = None  # a bag's NavSatFix/Odometry topic (default: the only one)

    def check(self) -> "SourceOptions":
        if self.fps is not None and (not math.isfinite(self.fps) or self.fps <= 0):
            raise ConfigError(f"--fps must be a positive number of frames per second, got {self.fps}")
        if self.every is not None and self.every < 1:
            raise ConfigError(f"--every must be a whole number of at least 1, got {self.every}")
        if self.fps is not None and self.every is not None:
            raise ConfigError("give --fps or --every, not both")
        start, end = self.window
        for value in (start, end):
            if value is not None and (not math.isfinite(value) or value < 0):
                raise ConfigError(f"--window {_window_text(self.window)}: times must be seconds >= 0")
        if start is not None and end is not None and end <= start:
            raise ConfigError(f"--window {_window_text(self.window)}: END must be after START")
        return self


def _window_text(window) -> str:
    return ":".join("" if v is None else f"{v:g}" for v in window)


def parse_window(text: str | None) -> tuple[float | None, float | None]:
    """``"START:END"`` seconds (either side may be empty) -> (start, end)."""
    if not text:
        return None, None
    if ":" not in text:
        raise ConfigError(f"--window {text!r}: expected START:END in seconds from the first frame, e.g. 10:70")
    parts = text.split(":", 1)
    try:
        return tuple(float(p) if p.strip() else None for p in parts)  # type: ignore[return-value]
    except ValueError as exc:
        raise ConfigError(f"--window {text!r}: START and END must be numbers of seconds") from exc


_default = SourceOptions()


def default_options() -> SourceOptions:
    """The options used when a caller gives none (the CLI sets them from its flags)."""
    return _default


def set_default_options(options: SourceOptions) -> None:
    global _default
    _default = options.check()


@contextlib.contextmanager
def using_options(options: SourceOptions) -> Iterator[None]:
    """Make ``options`` the default inside the block (the CLI wraps a command in it)."""
    global _default
    previous = _default
    set_default_options(options)
    try:
        yield
    finally:
        _default = previous


# ----------------------------------------------------------------------------- what a path is


def _bag_folder(path: Path) -> bool:
    return path.is_dir() and (path / "metadata.yaml").is_file()


def kind_of(path: str | os.PathLike) -> str | None:
    """``"video"``, ``"bag"`` or None (a folder, an image, anything else), from the path alone."""
    path = Path(path)
    if path.is_file():
        suffix = path.suffix.lower()
        if suffix in VIDEO_EXTENSIONS:
            return "video"
        if suffix in BAG_EXTENSIONS:
            return "bag"
        return None
    return "bag" if _bag_folder(path) else None


def split_topic(path: str | os.PathLike) -> tuple[Path, str | None]:
    """``BAG:TOPIC`` -> (bag, topic); anything else -> (path, None)."""
    text = os.fspath(path)
    if not Path(text).exists() and ":" in text:
        head, _, topic = text.rpartition(":")
        if head and kind_of(head) == "bag":
            return Path(head), (topic if topic.startswith("/") else "/" + topic) if topic else None
    return Path(text), None


def is_source(path: str | os.PathLike) -> bool:
    """Whether :func:`list_frames` reads ``path`` (a video, a bag, or ``BAG:TOPIC``)."""
    bag, _ = split_topic(path)
    return kind_of(bag) is not None


def condition_path(root: str | os.PathLike, name: str) -> Path | None:
    """The condition ``name`` of a dataset folder: the sub-folder ``root/name``, the video or bag
    ``root/name`` (``summer.mp4``, ``run.bag:/camera``), or the one video or bag whose name
    without its extension is ``name`` (``summer`` for ``summer.mp4``); None when there is none.
    Two sources of that stem are refused (which one was meant?)."""
    root = Path(root)
    path = root / name
    if path.is_dir() or is_source(path):
        return path
    if not root.is_dir() or os.sep in name or "/" in name:
        return None
    found = sorted(p for p in root.iterdir() if p.stem == name and kind_of(p) is not None)
    if len(found) > 1:
        raise DataError(
            f"{root}: condition {name!r} could be {' or '.join(p.name for p in found)}; name it with " f"its extension"
        )
    return found[0] if found else None


# ----------------------------------------------------------------------------- listing


@dataclass
class SourceListing:
    """The frames :func:`list_frames` takes from one source, in order."""

    source: Path
    kind: str  # "video" or "bag"
    paths: list[Path]
    times: np.ndarray  # (N,) seconds: from the first frame (video) or since the epoch (bag)
    topic: str | None = None
    positions: np.ndarray | None = None  # (N, 2): degrees (lat, lon) or metres (x, y); NaN where unknown
    position_kind: str | None = None  # "degrees" or "metres"
    position_topic: str | None = None
    notes: list[str] = field(default_factory=list)


# Listings made in this process, by each frame path's text: frame_records.frame_records() finds a frame's time
# and position here without opening its source again.
_LISTINGS: dict[tuple, SourceListing] = {}
#: the listing each listed frame path belongs to (read by :mod:`fdnet.data.frame_records`)
FRAME_OWNER: dict[str, SourceListing] = {}


def list_frames(path: str | os.PathLike, options: SourceOptions | None = None) -> list[Path]:
    """The frames of a video or bag as frame paths (see the module docstring), in order."""
    return open_source(path, options).paths


def open_source(path: str | os.PathLike, options: SourceOptions | None = None) -> SourceListing:
    """List a video's or bag's frames (cached per source and options in this process)."""
    options = (options or default_options()).check()
    source, topic = split_topic(path)
    kind = kind_of(source)
    if kind is None:
        raise DataError(
            f"{source}: not a video ({', '.join(VIDEO_EXTENSIONS[:4])}, ...) or a ROS bag "
            f"({', '.join(BAG_EXTENSIONS)}, or a ROS 2 bag folder with metadata.yaml)"
        )
    if topic is not None:
        if options.topic is not None and options.topic.strip("/") != topic.strip("/"):
            raise ConfigError(f"{path}: names topic {topic} but --topic is {options.topic}; give one")
        options = replace(options, topic=topic)
    key = (str(source.resolve()), kind, options)
    listing = _LISTINGS.get(key)
    if listing is None:
        listing = _list_video(source, options) if kind == "video" else _list_bag(source, options)
        _LISTINGS[key] = listing
        for p in listing.paths:
            FRAME_OWNER[str(p)] = listing
    return listing


def sample(times: np.ndarray, options: SourceOptions) -> np.ndarray:
    """Indices of the frames kept: inside the window (seconds from the first frame), then every
    k-th, or the first frame of each 1/fps-second slot counted from the window's start."""
    times = np.asarray(times, dtype=np.float64)
    if len(times) == 0:
        return np.zeros(0, dtype=np.int64)
    relative = times - times[0]
    start, end = options.window
    keep = np.ones(len(times), dtype=bool)
    # a microsecond of slack: frame times are index / rate, computed in floating point
    if start is not None:
        keep &= relative >= start - 1e-6
    if end is not None:
        keep &= relative < end - 1e-6
    chosen = np.flatnonzero(keep)
    if options.every is not None:
        chosen = chosen[:: options.every]
    elif options.fps is not None and len(chosen):
        origin = relative[chosen[0]] if start is None else start
        slots = np.floor((relative[chosen] - origin) * options.fps + 1e-6).astype(np.int64)
        first = np.ones(len(chosen), dtype=bool)
        first[1:] = slots[1:] != slots[:-1]
        chosen = chosen[first]
    return chosen


def _no_frames(source: Path, options: SourceOptions, total: int, what: str = "frames") -> DataError:
    return DataError(
        f"{source}: the sampling (--window {_window_text(options.window) or ':'}) keeps none of its " f"{total} {what}"
    )


def open_capture(source: Path):
    # FFmpeg's own messages ("EBML header parsing failed") would precede fdnet's one-line error;
    # read when OpenCV first opens a video, so set before (a user's own setting wins)
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    import cv2

    capture = cv2.VideoCapture(str(source))
    if not capture.isOpened():
        capture.release()
        raise DataError(
            f"{source}: cannot be opened as a video (OpenCV's VideoCapture cannot read it; " f"is it a video file?)"
        )
    return capture


def _list_video(source: Path, options: SourceOptions) -> SourceListing:
    import cv2

    capture = open_capture(source)
    try:
        rate = float(capture.get(cv2.CAP_PROP_FPS) or 0.0)
        count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        if count <= 0:
            # containers without a frame count (raw streams): count by reading through once
            while capture.grab():
                count += 1
        if count > 0:
            capture.set(cv2.CAP_PROP_POS_FRAMES, 0)
            decodable = capture.grab()
        else:
            decodable = False
    finally:
        capture.release()
    if not decodable:
        raise DataError(f"{source}: holds no video frames OpenCV can decode")
    if not math.isfinite(rate) or rate <= 0:
        raise DataError(f"{source}: the video states no frame rate, so its frames have no timestamps")
    times = np.arange(count, dtype=np.float64) / rate
    chosen = sample(times, options)
    if len(chosen) == 0:
        raise _no_frames(source, options, count)
    paths = [source / f"frame_{i:06d}_{int(round(times[i] * 1000))}ms" for i in chosen]
    return SourceListing(source, "video", paths, times[chosen])


# ----------------------------------------------------------------------------- bags


def bag_errors(source: Path, topic: str | None = None):
    """rosbags raises many kinds of exception for a damaged or truncated bag (its own reader
    errors, sqlite/apsw errors, struct and EOF errors from the ROS 1 parser, KeyError for a
    missing index); all become one DataError naming the bag (and topic)."""

    @contextlib.contextmanager
    def guard():
        try:
            yield
        except (DataError, ConfigError):
            raise
        except Exception as exc:  # noqa: BLE001 (see the docstring)
            where = f"{source}" + (f", topic {topic}" if topic else "")
            raise DataError(
                f"{where}: cannot read the bag ({exc.__class__.__name__}: {exc}); is it truncated or "
                f"damaged? (ROS 1: `rosbag reindex`; ROS 2: `ros2 bag reindex`)"
            ) from exc

    return guard()


def bag_reader(source: Path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    ros1 = source.suffix.lower() == ".bag"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    reader = AnyReader([source], default_typestore=store)
    reader.open()
    return reader


def _describe_topics(topics: dict) -> str:
    return ", ".join(f"{name} ({info.msgtype})" for name, info in sorted(topics.items())) or "none"


def _image_topic(source: Path, topics: dict, wanted: str | None) -> str:
    images = sorted(name for name, info in topics.items() if info.msgtype in IMAGE_TYPES)
    if wanted is not None:
        wanted = wanted if wanted.startswith("/") else "/" + wanted
        if wanted not in topics:
            raise DataError(
                f"{source}: has no topic {wanted}; its image topics: {', '.join(images) or 'none'} "
                f"(all topics: {_describe_topics(topics)})"
            )
        if topics[wanted].msgtype not in IMAGE_TYPES:
            raise DataError(
                f"{source}, topic {wanted}: is {topics[wanted].msgtype}, not an image topic "
                f"(sensor_msgs/Image or CompressedImage); its image topics: {', '.join(images) or 'none'}"
            )
        return wanted
    if not images:
        raise DataError(
            f"{source}: has no image topics (sensor_msgs/Image or sensor_msgs/CompressedImage); "
            f"its topics: {_describe_topics(topics)}"
        )
    if len(images) > 1:
        raise ConfigError(
            f"{source}: has {len(images)} image topics ({', '.join(images)}); choose one with "
            f"--topic TOPIC or {source}:TOPIC"
        )
    return images[0]


def _position_topic(source: Path, topics: dict, wanted: str | None) -> str | None:
    kinds = (NAVSATFIX, ODOMETRY)
    if wanted is not None:
        wanted = wanted if wanted.startswith("/") else "/" + wanted
        if wanted not in topics or topics[wanted].msgtype not in kinds:
            found = sorted(n for n, i in topics.items() if i.msgtype in kinds)
            raise DataError(
                f"{source}: has no NavSatFix or Odometry topic {wanted}; its position topics: "
                f"{', '.join(found) or 'none'}"
            )
        return wanted
    for kind in kinds:  # GPS first, then odometry; only when it is the one topic of its kind
        found = sorted(n for n, i in topics.items() if i.msgtype == kind)
        if len(found) == 1:
            return found[0]
        if len(found) > 1:
            log.warning(
                "%s: has %d %s topics (%s); its frames get no positions unless --position-topic " "names one",
                source,
                len(found),
                kind,
                ", ".join(found),
            )
            return None
    return None


def _check_image_message(source: Path, topic: str, message, msgtype: str) -> None:
    """Refuse a topic whose images fdnet cannot decode before anything is described."""
    if msgtype.endswith("CompressedImage"):
        if "compresseddepth" in message.format.lower().replace(" ", ""):
            raise DataError(
                f"{source}, topic {topic}: compressed depth images ({message.format!r}) are not "
                f"camera images; fdnet reads colour or grey images"
            )
        return
    if message.encoding not in RAW_ENCODINGS:
        raise DataError(
            f"{source}, topic {topic}: image encoding {message.encoding!r} cannot be decoded "
            f"(a depth or other non-camera image?); fdnet reads {', '.join(RAW_ENCODINGS)}"
        )


def _list_bag(source: Path, options: SourceOptions) -> SourceListing:
    with bag_errors(source):
        reader = bag_reader(source)
    try:
        with bag_errors(source):
            topics = reader.topics
        topic = _image_topic(source, topics, options.topic)
        position_topic = _position_topic(source, topics, options.position_topic)
        connections = [c for c in reader.connections if c.topic == topic]
        stamps: list[int] = []
        with bag_errors(source, topic):
            for connection, timestamp, raw in reader.messages(connections=connections):
                if not stamps:
                    _check_image_message(source, topic, reader.deserialize(raw, connection.msgtype), connection.msgtype)
                stamps.append(int(timestamp))
        if not stamps:
            raise DataError(f"{source}, topic {topic}: holds no messages")
        nanos = np.asarray(stamps, dtype=np.int64)
        seconds = nanos.astype(np.float64) / 1e9
        chosen = sample(seconds, options)
        if len(chosen) == 0:
            raise _no_frames(source, options, len(stamps), f"messages on {topic}")
        paths, repeat, previous, keep = [], 0, None, set(chosen.tolist())
        prefix = source.joinpath(*[part for part in topic.split("/") if part])
        for i in range(len(nanos)):
            # messages recorded at the same nanosecond: a counter tells them apart
            repeat = repeat + 1 if nanos[i] == previous else 0
            previous = nanos[i]
            if i in keep:
                paths.append(prefix / (f"frame_{i:06d}_{nanos[i]}ns" + (f"_{repeat}" if repeat else "")))
        listing = SourceListing(source, "bag", paths, seconds[chosen], topic=topic)
        if position_topic is not None:
            with bag_errors(source, position_topic):
                _add_positions(reader, listing, position_topic)
        return listing
    finally:
        with contextlib.suppress(Exception):
            reader.close()


def _add_positions(reader, listing: SourceListing, topic: str) -> None:
    connections = [c for c in reader.connections if c.topic == topic]
    times, values, kind = [], [], None
    for connection, timestamp, raw in reader.messages(connections=connections):
        message = reader.deserialize(raw, connection.msgtype)
        if connection.msgtype == NAVSATFIX:
            kind = "degrees"
            if message.status.status < 0:  # STATUS_NO_FIX
                continue
            value = (float(message.latitude), float(message.longitude))
        else:
            kind = "metres"
            point = message.pose.pose.position
            value = (float(point.x), float(point.y))
        if all(math.isfinite(v) for v in value):
            times.append(int(timestamp) / 1e9)
            values.append(value)
    listing.position_topic, listing.position_kind = topic, kind
    positions = np.full((len(listing.times), 2), np.nan)
    if len(times) >= 1:
        t = np.asarray(times)
        order = np.argsort(t, kind="stable")
        t, v = t[order], np.asarray(values)[order]
        inside = (listing.times >= t[0]) & (listing.times <= t[-1])
        for axis in range(2):
            positions[inside, axis] = np.interp(listing.times[inside], t, v[:, axis])
        outside = int((~inside).sum())
        if outside:
            listing.notes.append(
                f"{outside} of {len(inside)} frames lie outside the time span of {topic}'s " f"positions and have none"
            )
    else:
        listing.notes.append(f"{topic} holds no usable positions (no message with a fix)")
    listing.positions = positions
    for note in listing.notes:
        log.warning("%s, topic %s: %s", listing.source, listing.topic, note)
