"""Decoding the frames of videos and ROS bags (:mod:`fdnet.data.sources` lists them).

A frame path (``route/summer.mp4/frame_000025_1000ms``, ``run.bag/camera/image_raw/frame_...ns``)
is decoded by :func:`open_frame`, which :func:`fdnet.data.images.load_image` calls for any path
that is not an image file. Each process keeps its open videos and bags (at most a few), reading
forward from the last frame decoded, so a traverse decodes in one pass; a process that forks
(the DataLoader's decoding workers) closes them first.
"""

from __future__ import annotations

import contextlib
import io
import os
import threading
from pathlib import Path

import numpy as np

from fdnet.data.frame_records import locate
from fdnet.data.sources import (
    BAG_FRAME_NAME,
    RAW_ENCODINGS,
    READ_FORWARD,
    VIDEO_FRAME_NAME,
    bag_errors,
    bag_reader,
    open_capture,
)
from fdnet.errors import DataError


class _VideoReader:
    """One open video, read forward: the next wanted frame is grabbed up to, not sought."""

    def __init__(self, source: Path):
        self.source = source
        self.capture = open_capture(source)
        self.next = 0

    def read(self, index: int) -> np.ndarray:
        import cv2

        if index < self.next or index - self.next > READ_FORWARD:
            self.capture.set(cv2.CAP_PROP_POS_FRAMES, index)
            self.next = index
        while self.next < index:
            if not self.capture.grab():
                raise DataError(f"{self.source}: the video ends at frame {self.next}, before frame {index}")
            self.next += 1
        ok, frame = self.capture.read()
        if not ok:
            raise DataError(f"{self.source}: frame {index} cannot be decoded (the video ends or is damaged there)")
        self.next += 1
        if frame.ndim == 2:
            return frame
        return cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)

    def close(self) -> None:
        self.capture.release()


class _BagReader:
    """One open bag topic, read forward from the last message decoded."""

    def __init__(self, source: Path, topic: str):
        self.source, self.topic = source, topic
        with bag_errors(source, topic):
            self.reader = bag_reader(source)
        self.connections = [c for c in self.reader.connections if c.topic == topic]
        if not self.connections:
            raise DataError(f"{source}: has no topic {topic}")
        self.messages = None
        self.ordinal = -1  # ordinal of the last message taken from self.messages

    def read(self, ordinal: int, nanos: int, repeat: int):
        with bag_errors(self.source, self.topic):
            if self.messages is None or ordinal <= self.ordinal or ordinal - self.ordinal > READ_FORWARD:
                self.messages = self.reader.messages(connections=self.connections, start=nanos)
                self.ordinal = ordinal - repeat - 1
            for connection, timestamp, raw in self.messages:
                self.ordinal += 1
                if self.ordinal == ordinal:
                    if int(timestamp) != nanos:
                        raise DataError(
                            f"{self.source}, topic {self.topic}: message {ordinal} was recorded at "
                            f"{timestamp} ns, not {nanos} ns as when it was listed; has the bag changed?"
                        )
                    return decode_image_message(
                        self.reader.deserialize(raw, connection.msgtype),
                        connection.msgtype,
                        f"{self.source}, topic {self.topic}, " f"message {ordinal}",
                    )
        raise DataError(f"{self.source}, topic {self.topic}: message {ordinal} not found; has the bag changed?")

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.reader.close()


def decode_image_message(message, msgtype: str, where: str):
    """A sensor_msgs Image or CompressedImage as a PIL image (mode RGB, RGBA, L or I;16), which
    :func:`fdnet.data.images.load_image` resizes and converts as it does image files."""
    from PIL import Image, UnidentifiedImageError

    if msgtype.endswith("CompressedImage"):
        try:
            image = Image.open(io.BytesIO(bytes(message.data)))
            image.load()
        except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
            raise DataError(f"{where}: compressed image ({message.format!r}) cannot be decoded ({exc})") from exc
        return image
    encoding = message.encoding
    if encoding not in RAW_ENCODINGS:
        raise DataError(
            f"{where}: image encoding {encoding!r} cannot be decoded; fdnet reads " f"{', '.join(RAW_ENCODINGS)}"
        )
    height, width, step = int(message.height), int(message.width), int(message.step)
    sixteen = encoding == "mono16"
    channels = {"rgb8": 3, "bgr8": 3, "8UC3": 3, "rgba8": 4, "bgra8": 4}.get(encoding, 1)
    item = 2 if sixteen else 1
    data = np.frombuffer(bytes(message.data), dtype=np.uint8)
    if height <= 0 or width <= 0 or step < width * channels * item or len(data) < height * step:
        raise DataError(f"{where}: {encoding} image of {width}x{height} (step {step}) but {len(data)} bytes of data")
    rows = data[: height * step].reshape(height, step)[:, : width * channels * item]
    if sixteen:
        grey = rows.copy().view(">u2" if message.is_bigendian else "<u2").reshape(height, width)
        return Image.fromarray(grey.astype(np.uint16))
    pixels = np.ascontiguousarray(rows.reshape(height, width, channels) if channels > 1 else rows)
    if encoding.startswith("bayer_"):
        import cv2

        code = {
            "bayer_rggb8": cv2.COLOR_BayerRGGB2RGB,
            "bayer_bggr8": cv2.COLOR_BayerBGGR2RGB,
            "bayer_gbrg8": cv2.COLOR_BayerGBRG2RGB,
            "bayer_grbg8": cv2.COLOR_BayerGRBG2RGB,
        }[encoding]
        # OpenCV names Bayer patterns by the second row's pair; cv_bridge uses the same table
        return Image.fromarray(cv2.cvtColor(pixels, code))
    if encoding in ("bgr8", "8UC3"):
        pixels = pixels[..., ::-1]
    elif encoding == "bgra8":
        pixels = pixels[..., [2, 1, 0, 3]]
    return Image.fromarray(np.ascontiguousarray(pixels))


# open readers of this process (a decoding worker keeps its own), by source and topic, and under
# "pid" the process that opened them
_READERS: dict = {}
_READERS_LOCK = threading.Lock()
_MAX_READERS = 8


def open_frame(path: str | os.PathLike):
    """The frame a frame path names, as a PIL image; None when ``path`` is no frame of a source."""
    found = locate(path)
    if found is None:
        return None
    with _READERS_LOCK:  # one reader per source, read by one thread at a time (load_images uses threads)
        return _read_frame(*found)


def _read_frame(source: Path, topic: str | None, name: str):
    from PIL import Image

    if _READERS.get("pid") != os.getpid():
        # a forked decoding worker inherits its parent's readers, whose file offsets (and sqlite
        # connections) it must not share: it opens its own
        _READERS.clear()
        _READERS["pid"] = os.getpid()
    key = (str(source), topic)
    reader = _READERS.get(key)
    if reader is None:
        if len(_READERS) > _MAX_READERS:
            _READERS.pop(next(k for k in _READERS if k != "pid")).close()
        reader = _VideoReader(source) if topic is None else _BagReader(source, topic)
        _READERS[key] = reader
    if topic is None:
        index = int(VIDEO_FRAME_NAME.match(name).group(1))
        return Image.fromarray(reader.read(index))
    match = BAG_FRAME_NAME.match(name)
    return reader.read(int(match.group(1)), int(match.group(2)), int(match.group(3) or 0))


def close_readers() -> None:
    """Close every video and bag this process holds open."""
    with _READERS_LOCK:
        owner = _READERS.pop("pid", None)
        while _READERS:
            reader = _READERS.popitem()[1]
            if owner == os.getpid():
                reader.close()


# A process that forks (DataLoader's decoding workers) first closes its readers: a child forked
# while OpenCV's FFmpeg decoder threads run hangs in its own first VideoCapture (measured: a worker
# never returned), and a child must not share a parent's file offsets or sqlite connections.
if hasattr(os, "register_at_fork"):
    os.register_at_fork(before=close_readers)
