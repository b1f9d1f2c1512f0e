"""Small video files and ROS bags made from arrays, for the tests of ``fdnet.data.sources`` and the
example in docs/sources.md.

``python tests/data/source_files.py OUT`` writes the docs' example: ``OUT/route/{summer,winter}.avi``
(a synthetic route, lossless FFV1) and ``OUT/traverse.bag`` (ROS 1) and ``OUT/traverse_ros2/``
(ROS 2, sqlite) with a raw camera topic, a compressed one and a NavSatFix topic.
"""

from __future__ import annotations

import io
import sys
from pathlib import Path

import numpy as np

#: the first image's recording time in the made bags (nanoseconds since the epoch)
T0_NS = 1_700_000_000_000_000_000


def write_video(path, frames, fps: float = 25.0, fourcc: str = "FFV1") -> Path:
    """``frames`` (N, H, W, 3) uint8 RGB as a video; FFV1 in .avi/.mkv is lossless in OpenCV 5."""
    import cv2

    path = Path(path)
    frames = np.asarray(frames, dtype=np.uint8)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), float(fps), (frames.shape[2], frames.shape[1]))
    assert writer.isOpened(), f"OpenCV cannot write {fourcc} to {path}"
    for frame in frames:
        writer.write(np.ascontiguousarray(frame[..., ::-1]))
    writer.release()
    return path


def _store(ros1: bool):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)


def _header(store, ros1: bool, nanos: int, seq: int = 0):
    Time = store.types["builtin_interfaces/msg/Time"]
    Header = store.types["std_msgs/msg/Header"]
    stamp = Time(sec=nanos // 10**9, nanosec=nanos % 10**9)
    return Header(seq=seq, stamp=stamp, frame_id="camera") if ros1 else Header(stamp=stamp, frame_id="camera")


def image_message(store, ros1: bool, nanos: int, pixels: np.ndarray, encoding: str = "rgb8"):
    """sensor_msgs/Image of ``pixels`` (H, W, 3) uint8 RGB in ``encoding`` (rgb8, bgr8, mono8), or
    (H, W) uint16 for 16UC1/mono16."""
    Image = store.types["sensor_msgs/msg/Image"]
    if encoding == "bgr8":
        pixels = pixels[..., ::-1]
    pixels = np.ascontiguousarray(pixels)
    height, width = pixels.shape[:2]
    data = pixels.reshape(-1).view(np.uint8)
    return Image(
        header=_header(store, ros1, nanos),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=len(data) // height,
        data=data,
    )


def compressed_message(store, ros1: bool, nanos: int, pixels: np.ndarray, fmt: str = "png"):
    from PIL import Image as PILImage

    CompressedImage = store.types["sensor_msgs/msg/CompressedImage"]
    buffer = io.BytesIO()
    PILImage.fromarray(pixels).save(buffer, format="PNG" if fmt == "png" else "JPEG")
    return CompressedImage(
        header=_header(store, ros1, nanos), format=fmt, data=np.frombuffer(buffer.getvalue(), dtype=np.uint8)
    )


def navsatfix_message(store, ros1: bool, nanos: int, lat: float, lon: float, status: int = 0):
    NavSatFix = store.types["sensor_msgs/msg/NavSatFix"]
    NavSatStatus = store.types["sensor_msgs/msg/NavSatStatus"]
    return NavSatFix(
        header=_header(store, ros1, nanos),
        status=NavSatStatus(status=status, service=1),
        latitude=lat,
        longitude=lon,
        altitude=10.0,
        position_covariance=np.zeros(9),
        position_covariance_type=0,
    )


def write_bag(path, topics: dict, ros1: bool | None = None) -> Path:
    """A bag at ``path`` (``.bag``: ROS 1; otherwise a ROS 2 folder, sqlite3, or ``.mcap`` storage
    when the name ends in ``_mcap``). ``topics``: topic -> (msgtype, [(nanos, message), ...])."""
    path = Path(path)
    ros1 = path.suffix == ".bag" if ros1 is None else ros1
    store = _store(ros1)
    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if path.name.endswith("_mcap") else StoragePlugin.SQLITE3
        writer = Writer(path, version=9, storage_plugin=plugin)
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    with writer:
        connections = {
            topic: writer.add_connection(topic, msgtype, typestore=store) for topic, (msgtype, _) in topics.items()
        }
        records = sorted(
            ((nanos, topic, message) for topic, (_, messages) in topics.items() for nanos, message in messages),
            key=lambda r: r[0],
        )
        for nanos, topic, message in records:
            writer.write(connections[topic], nanos, serialize(message, topics[topic][0]))
    return path


def route_frames(count: int, seed: int = 0, size: tuple[int, int] = (32, 48)) -> np.ndarray:
    """(count, H, W, 3) uint8 random but smooth images, distinct per frame."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    noise = rng.random((count, size[0], size[1], 3))
    smooth = gaussian_filter(noise, sigma=(0, 2, 2, 0))
    smooth = (smooth - smooth.min()) / (np.ptp(smooth) + 1e-9)
    return np.rint(smooth * 255).astype(np.uint8)


def camera_bag(
    path,
    frames: np.ndarray,
    period_ns: int = 100_000_000,
    fixes: int | None = None,
    start_lat: float = 51.5,
    step_deg: float = 1e-5,
) -> Path:
    """A bag with ``/camera/image_raw`` (rgb8), ``/camera/image/compressed`` (PNG, the same images),
    and ``/gps/fix`` (NavSatFix) at half the image period from T0, moving north ``step_deg`` per fix."""
    path = Path(path)
    ros1 = path.suffix == ".bag"
    store = _store(ros1)
    raw = [(T0_NS + i * period_ns, image_message(store, ros1, T0_NS + i * period_ns, f)) for i, f in enumerate(frames)]
    packed = [
        (T0_NS + i * period_ns + 1, compressed_message(store, ros1, T0_NS + i * period_ns + 1, f))
        for i, f in enumerate(frames)
    ]
    fixes = 2 * len(frames) if fixes is None else fixes
    gps = [
        (
            T0_NS + k * period_ns // 2,
            navsatfix_message(store, ros1, T0_NS + k * period_ns // 2, start_lat + k * step_deg, -0.1),
        )
        for k in range(fixes)
    ]
    return write_bag(
        path,
        {
            "/camera/image_raw": ("sensor_msgs/msg/Image", raw),
            "/camera/image/compressed": ("sensor_msgs/msg/CompressedImage", packed),
            "/gps/fix": ("sensor_msgs/msg/NavSatFix", gps),
        },
    )


def write_example(out) -> None:
    """The example of docs/sources.md: a two-condition route as videos, and one traverse as bags."""
    from fdnet.data.synthetic import render_route

    out = Path(out)
    (out / "route").mkdir(parents=True, exist_ok=True)
    route = {
        name: np.rint(images * 255).astype(np.uint8)
        for name, images in render_route(frames=60, conditions=("summer", "winter"), seed=0, size=(64, 128)).items()
    }
    for condition, images in route.items():
        write_video(out / "route" / f"{condition}.avi", images, fps=10.0)
    camera_bag(out / "traverse.bag", route["summer"])
    camera_bag(out / "traverse_ros2", route["summer"])


if __name__ == "__main__":
    write_example(sys.argv[1] if len(sys.argv) > 1 else "sources-example")
    print(f"wrote {sys.argv[1] if len(sys.argv) > 1 else 'sources-example'}")
