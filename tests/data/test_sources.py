"""Videos and ROS bags as image sources (fdnet.data.sources), made by the tests with OpenCV and
rosbags: frames in order with the right count, times and positions, the same descriptors as the
frames in folders, and one-line errors naming the file and topic."""

from __future__ import annotations

import csv
import json
import re
import sqlite3

import numpy as np
import pytest
from PIL import Image

from fdnet.cli import main
from fdnet.data import sources
from fdnet.data.dataset import RouteDataset
from fdnet.data.formats.positions import source_positions
from fdnet.data.frame_records import frame_records, positions_in_metres
from fdnet.data.images import list_images, load_image, load_image_uint8
from fdnet.errors import ConfigError, DataError
from tests.data.source_files import (
    T0_NS,
    _store,
    camera_bag,
    image_message,
    route_frames,
    write_bag,
    write_video,
)


def frame_index(path) -> int:
    return int(path.name.split("_")[1])


# ----------------------------------------------------------------------------- videos


@pytest.fixture
def video(tmp_path):
    frames = route_frames(50, seed=1)
    return write_video(tmp_path / "route.avi", frames, fps=25.0), frames


def test_video_frames_come_back_in_order_exactly(video):
    path, frames = video
    paths = list_images(path)
    assert len(paths) == 50
    assert [frame_index(p) for p in paths] == list(range(50))
    assert paths[0].name == "frame_000000_0ms" and paths[25].name == "frame_000025_1000ms"
    # FFV1 is lossless: the decoded frames are the written ones, whichever order they are asked in
    for p in [paths[7], paths[3], paths[49], paths[0]]:
        assert np.array_equal(load_image_uint8(p), frames[frame_index(p)])
    assert np.allclose(load_image(paths[10]), frames[10] / 255.0)


@pytest.mark.parametrize(
    "options, expected",
    [
        (sources.SourceOptions(fps=5), list(range(0, 50, 5))),  # 25 fps video at 5 fps: every 5th frame
        (sources.SourceOptions(fps=2), [0, 13, 25, 38]),  # the first frame of each 0.5 s slot
        (sources.SourceOptions(every=7), list(range(0, 50, 7))),
        (sources.SourceOptions(window=(1.0, 1.5)), list(range(25, 38))),  # [1.0 s, 1.5 s)
        (
            sources.SourceOptions(fps=10, window=(0.5, None)),
            [13, 15, 18, 20, 23, 25, 28, 30, 33, 35, 38, 40, 43, 45, 48],
        ),
    ],
)
def test_video_sampling_by_rate_step_and_window(video, options, expected):
    path, frames = video
    with sources.using_options(options):
        paths = list_images(path)
    assert [frame_index(p) for p in paths] == expected
    records = frame_records(paths)
    assert [r.timestamp for r in records] == pytest.approx([i / 25.0 for i in expected])
    assert all(r.source == str(path) and r.position is None for r in records)
    for p in paths[::3]:
        assert np.array_equal(load_image_uint8(p), frames[frame_index(p)])


def test_video_frames_stream_through_worker_processes(video):
    from fdnet.descriptors.pipeline import iter_image_batches

    path, frames = video
    paths = list_images(path)
    load_image_uint8(paths[5])  # this process holds the video open when the workers start (which must not hang them)
    batches = list(iter_image_batches(paths, (32, 48), batch_size=8, uint8=True, workers=2))
    assert [start for start, _ in batches] == list(range(0, 50, 8))
    assert np.array_equal(np.concatenate([b for _, b in batches]), frames)


def test_video_frames_read_by_threads(video):
    from fdnet.data.images import load_images

    path, frames = video
    images = load_images(list_images(path), (32, 48), workers=4)  # threads share one open video
    assert np.array_equal(np.rint(images * 255).astype(np.uint8), frames)


def test_a_condition_of_a_dataset_may_be_a_video(tmp_path):
    route = tmp_path / "route"
    route.mkdir()
    write_video(route / "summer.avi", route_frames(6, seed=2), fps=10)
    write_video(route / "winter.mkv", route_frames(6, seed=3), fps=10)
    dataset = RouteDataset.from_folder(route, ["summer", "winter.mkv"])
    assert [len(t) for t in dataset.traverses.values()] == [6, 6]
    assert dataset["summer"].timestamps == pytest.approx(np.arange(6) / 10)
    assert sorted(RouteDataset.from_folder(route).conditions) == ["summer.avi", "winter.mkv"]
    with pytest.raises(DataError, match="autumn: condition folder not found; available: summer.avi, winter.mkv"):
        RouteDataset.from_folder(route, ["autumn"])


def save_folder(folder, frames):
    folder.mkdir(parents=True)
    for i, frame in enumerate(frames):
        Image.fromarray(frame).save(folder / f"{i:03d}.png")


def test_evaluate_on_videos_matches_evaluate_on_the_frames_as_folders(tmp_path):
    day = route_frames(24, seed=4)
    night = np.clip(day.astype(np.float32) * 0.6 + np.random.default_rng(5).normal(0, 6, day.shape), 0, 255)
    night = night.astype(np.uint8)
    videos, folders = tmp_path / "videos", tmp_path / "folders"
    videos.mkdir()
    write_video(videos / "day.avi", day, fps=10)
    write_video(videos / "night.avi", night, fps=10)
    save_folder(folders / "day", day)
    save_folder(folders / "night", night)
    results = {}
    for name, root in (("videos", videos), ("folders", folders)):
        out = tmp_path / f"{name}.json"
        assert (
            main(
                [
                    "evaluate",
                    "--data",
                    str(root),
                    "--reference",
                    "day",
                    "--query",
                    "night",
                    "--method",
                    "sad,hog",
                    "--tolerance",
                    "1",
                    "--json",
                    str(out),
                    "--workers",
                    "0",
                ]
            )
            == 0
        )
        results[name] = json.loads(out.read_text())
    # every metric of every method is the same; only the timings differ
    assert [_without_timings(r) for r in results["videos"]["results"]] == [
        _without_timings(r) for r in results["folders"]["results"]
    ]
    assert [r["method"] for r in results["videos"]["results"]] == ["sad", "hog"]


def _without_timings(result: dict) -> dict:
    return {k: v for k, v in result.items() if k not in ("timing", "dataset")}


def test_evaluate_samples_videos_with_fps(tmp_path):
    route = tmp_path / "route"
    route.mkdir()
    frames = route_frames(40, seed=6)
    write_video(route / "a.avi", frames, fps=20)
    write_video(route / "b.avi", frames, fps=20)
    out = tmp_path / "r.json"
    assert (
        main(
            [
                "evaluate",
                "--data",
                str(route),
                "--reference",
                "a",
                "--query",
                "b",
                "--method",
                "sad",
                "--fps",
                "4",
                "--json",
                str(out),
                "--workers",
                "0",
            ]
        )
        == 0
    )
    result = json.loads(out.read_text())["results"][0]  # one schema: a list of results, one per method
    assert result["num_queries"] == result["num_references"] == 8  # 40 frames at 20 fps, taken at 4 fps
    assert result["recall_at_n"]["1"] == 1.0  # the same frames: each query finds itself
    with sources.using_options(sources.SourceOptions(fps=4)):
        assert [frame_index(p) for p in list_images(route / "a.avi")] == list(range(0, 40, 5))


# ----------------------------------------------------------------------------- bags

BAG_KINDS = ["traverse.bag", "traverse_ros2", "traverse_mcap"]  # ROS 1, ROS 2 sqlite3, ROS 2 mcap


@pytest.fixture(params=BAG_KINDS)
def bag(tmp_path, request):
    frames = route_frames(12, seed=7)
    return camera_bag(tmp_path / request.param, frames, period_ns=100_000_000), frames


def test_bag_raw_and_compressed_images_times_and_positions(bag):
    path, frames = bag
    with pytest.raises(ConfigError, match="2 image topics .*--topic"):
        list_images(path)
    raw = list_images(f"{path}:/camera/image_raw")
    with sources.using_options(sources.SourceOptions(topic="/camera/image/compressed")):
        packed = list_images(path)
    assert len(raw) == len(packed) == 12
    assert raw[3].name == f"frame_000003_{T0_NS + 300_000_000}ns"
    for i in (0, 5, 11, 2):
        assert np.array_equal(load_image_uint8(raw[i]), frames[i])
        assert np.array_equal(load_image_uint8(packed[i]), frames[i])  # PNG: lossless
    records = frame_records(raw)
    assert [r.timestamp for r in records] == pytest.approx([T0_NS / 1e9 + 0.1 * i for i in range(12)])
    assert {r.topic for r in records} == {"/camera/image_raw"}
    # fixes every 50 ms moving 1e-5 degrees north each: frame i (at 100 ms * i) is fix 2i
    lats = [r.position[0] for r in records]
    assert lats == pytest.approx([51.5 + 2e-5 * i for i in range(12)], abs=1e-12)
    assert all(r.position_kind == "degrees" and r.position[1] == pytest.approx(-0.1) for r in records)
    # the compressed images are recorded 1 ns later: interpolated between fixes
    assert frame_records(packed)[4].position[0] == pytest.approx(51.5 + 8e-5 + 1e-5 * 1 / 50e6, abs=1e-12)
    metres = positions_in_metres(records)
    steps = np.diff(np.asarray(metres)[:, 1])
    assert steps == pytest.approx(np.full(11, 2e-5 * np.pi / 180 * 6_371_008.8), rel=1e-6)


def test_bag_sampling_by_window_and_rate(bag):
    path, _ = bag
    with sources.using_options(sources.SourceOptions(topic="camera/image_raw", window=(0.3, 1.0), fps=5)):
        paths = list_images(path)
    assert [frame_index(p) for p in paths] == [3, 5, 7, 9]


def test_positions_from_odometry_interpolated_and_none_outside(tmp_path, caplog):
    store = _store(False)
    Odometry = store.types["nav_msgs/msg/Odometry"]
    msgs = store.types
    pose = lambda x, y: msgs["geometry_msgs/msg/PoseWithCovariance"](  # noqa: E731
        pose=msgs["geometry_msgs/msg/Pose"](
            position=msgs["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
            orientation=msgs["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        ),
        covariance=np.zeros(36),
    )
    twist = msgs["geometry_msgs/msg/TwistWithCovariance"](
        twist=msgs["geometry_msgs/msg/Twist"](
            linear=msgs["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            angular=msgs["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        ),
        covariance=np.zeros(36),
    )
    frames = route_frames(5, seed=8)
    images = [(T0_NS + i * 10**9, image_message(store, False, T0_NS + i * 10**9, f)) for i, f in enumerate(frames)]
    # odometry from 0.5 s to 3.5 s, x = 10 m/s
    from tests.data.source_files import _header

    odometry = [
        (
            T0_NS + k * 500_000_000,
            Odometry(header=_header(store, False, 0), child_frame_id="base", pose=pose(5.0 * k, 1.0), twist=twist),
        )
        for k in range(1, 8)
    ]
    path = write_bag(
        tmp_path / "odo", {"/cam": ("sensor_msgs/msg/Image", images), "/odom": ("nav_msgs/msg/Odometry", odometry)}
    )
    with caplog.at_level("WARNING", logger="fdnet.data.sources"):
        paths = list_images(path)
    assert "2 of 5 frames lie outside the time span of /odom's positions" in caplog.text
    records = frame_records(paths)
    assert [r.position for r in records] == [None, (10.0, 1.0), (20.0, 1.0), (30.0, 1.0), None]
    assert records[1].position_kind == "metres"
    with pytest.raises(DataError, match="2 of 5 frames .*outside the time span of the positions on /odom"):
        source_positions(path)


def test_groundtruth_from_two_bags_and_database_stores_times_and_positions(tmp_path):
    frames = route_frames(10, seed=9)
    first = camera_bag(tmp_path / "first.bag", frames)
    second = camera_bag(tmp_path / "second_ros2", frames[::-1].copy(), start_lat=51.5 + 18e-5, step_deg=-1e-5)
    gt = tmp_path / "gt.csv"
    assert (
        main(
            [
                "groundtruth",
                "--positions",
                str(first),
                str(second),
                "--topic",
                "/camera/image_raw",
                "--tolerance-m",
                "0.5",
                "--out",
                str(gt),
            ]
        )
        == 0
    )
    rows = list(csv.DictReader(gt.open()))
    # the second traverse drives the route backwards: its frame i is the first's frame 9 - i
    assert [(int(r["query_index"]), int(r["reference_indices"])) for r in rows] == [(i, 9 - i) for i in range(10)]
    assert rows[0]["query_name"] == f"frame_000000_{T0_NS}ns"
    db = tmp_path / "map.db"
    assert (
        main(
            [
                "database",
                "build",
                "--images",
                f"{first}:/camera/image_raw",
                "--method",
                "sad",
                "--every",
                "3",
                "--db",
                str(db),
                "--workers",
                "0",
            ]
        )
        == 0
    )
    with sqlite3.connect(db) as conn:
        rows = conn.execute("SELECT name, x, y, metadata FROM places ORDER BY id").fetchall()
    assert [r[0].rsplit("/", 1)[1] for r in rows] == [
        f"frame_{i:06d}_{T0_NS + i * 100_000_000}ns" for i in (0, 3, 6, 9)
    ]
    meta = [json.loads(r[3]) for r in rows]
    assert [m["timestamp"] for m in meta] == pytest.approx([T0_NS / 1e9 + 0.1 * i for i in (0, 3, 6, 9)])
    assert {m["source"] for m in meta} == {str(first.resolve())} and meta[0]["topic"] == "/camera/image_raw"
    assert np.diff([r[2] for r in rows]) == pytest.approx(np.full(3, 6e-5 * np.pi / 180 * 6_371_008.8), rel=1e-6)


def test_loop_closure_over_a_bag_uses_its_times(tmp_path):
    frames = route_frames(8, seed=10)
    store = _store(True)
    # the robot passes the same 8 places twice, one frame a second
    images = [(T0_NS + i * 10**9, image_message(store, True, T0_NS + i * 10**9, frames[i % 8])) for i in range(16)]
    path = write_bag(tmp_path / "loop.bag", {"/cam": ("sensor_msgs/msg/Image", images)})
    events = tmp_path / "events.csv"
    assert (
        main(
            [
                "loop-closure",
                "--images",
                str(path),
                "--method",
                "sad",
                "--exclude-last",
                "4",
                "--accept",
                "raw",
                "--sequence-length",
                "1",
                "--threshold",
                "-0.000001",
                "--out",
                str(events),
                "--workers",
                "0",
                "--no-progress",
            ]
        )
        == 0
    )
    rows = list(csv.DictReader(events.open()))
    assert len(rows) == 8  # sad of identical frames is 0, the highest: each second pass closes the loop
    assert [float(r["timestamp"]) - float(r["match_timestamp"]) for r in rows] == pytest.approx([8.0] * 8)


# ----------------------------------------------------------------------------- bad input


def run_cli(argv, capsys):
    code = main(argv)
    return code, capsys.readouterr().err


def test_a_file_that_is_not_a_video(tmp_path, capsys):
    fake = tmp_path / "notes.mp4"
    fake.write_text("not a video\n")
    code, err = run_cli(
        ["groundtruth", "--aligned", "--reference", str(fake), "--query", str(fake), "--out", str(tmp_path / "gt.csv")],
        capsys,
    )
    assert code == 2
    assert err.startswith("fdnet groundtruth: error: ") and f"{fake}: cannot be opened as a video" in err
    assert err.count("\n") == 1  # FFmpeg's own complaints are kept quiet


def test_a_video_cut_short_stops_at_the_missing_frame(tmp_path, video, capsys):
    path, _ = video
    cut = tmp_path / "cut.avi"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])  # the header still announces 50 frames
    code, err = run_cli(
        [
            "match",
            "--reference",
            str(cut),
            "--query",
            str(cut),
            "--method",
            "sad",
            "--workers",
            "0",
            "--out",
            str(tmp_path / "m.csv"),
        ],
        capsys,
    )
    assert code == 2
    assert re.match(rf"fdnet match: error: {re.escape(str(cut))}: frame [0-9]+ cannot be decoded", err), err


def test_bag_errors_name_the_file_and_topic(tmp_path, capsys):
    store = _store(False)
    frames = route_frames(2, seed=11)
    depth = np.arange(2 * 32 * 48, dtype=np.uint16).reshape(2, 32, 48)
    bag = write_bag(
        tmp_path / "depth",
        {
            "/depth": (
                "sensor_msgs/msg/Image",
                [(T0_NS + i, image_message(store, False, T0_NS + i, d, "16UC1")) for i, d in enumerate(depth)],
            ),
            "/cam": (
                "sensor_msgs/msg/Image",
                [(T0_NS + i, image_message(store, False, T0_NS + i, f)) for i, f in enumerate(frames)],
            ),
        },
    )
    navsat_only = write_bag(tmp_path / "gps.bag", {"/gps/fix": ("sensor_msgs/msg/NavSatFix", [])})
    out = str(tmp_path / "gt.csv")

    def error(images, *extra):
        code, err = run_cli(
            ["groundtruth", "--aligned", "--reference", images, "--query", images, "--out", out, *extra], capsys
        )
        assert code == 2 and err.startswith("fdnet groundtruth: error: "), err
        return err

    err = error(str(bag), "--topic", "/depth")
    assert f"{bag}, topic /depth: image encoding '16UC1' cannot be decoded" in err
    err = error(f"{bag}:/nothing")
    assert f"{bag}: has no topic /nothing; its image topics: /cam, /depth" in err
    err = error(str(bag), "--topic", "/cam", "--position-topic", "/gps")
    assert "no NavSatFix or Odometry topic /gps" in err
    err = error(str(navsat_only))
    assert f"{navsat_only}: has no image topics" in err and "/gps/fix (sensor_msgs/msg/NavSatFix)" in err
    # a ROS 1 bag cut short (its index, at the end, is gone)
    whole = camera_bag(tmp_path / "whole.bag", route_frames(4, seed=12))
    cut = tmp_path / "cut.bag"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    err = error(str(cut))
    assert f"{cut}: cannot read the bag" in err and "truncated" in err
    # a ROS 2 sqlite bag cut short
    whole2 = camera_bag(tmp_path / "whole_ros2", route_frames(4, seed=12))
    db3 = next(whole2.glob("*.db3"))
    db3.write_bytes(db3.read_bytes()[: db3.stat().st_size // 3])
    err = error(str(whole2), "--topic", "/camera/image_raw")
    assert f"{whole2}" in err and "cannot read the bag" in err


def test_bad_sampling_options(tmp_path, video, capsys):
    path, _ = video
    with pytest.raises(ConfigError, match="--fps or --every"):
        sources.SourceOptions(fps=1, every=2).check()
    with pytest.raises(ConfigError, match="END must be after START"):
        sources.SourceOptions(window=(3.0, 1.0)).check()
    with pytest.raises(DataError, match="keeps none of its 50 frames"):
        sources.list_frames(path, sources.SourceOptions(window=(10.0, None)))
    code, err = run_cli(
        [
            "groundtruth",
            "--aligned",
            "--reference",
            str(path),
            "--query",
            str(path),
            "--out",
            str(tmp_path / "gt.csv"),
            "--fps",
            "-1",
        ],
        capsys,
    )
    assert code == 2 and "fdnet groundtruth: error: --fps must be a positive number" in err


def test_match_takes_radius_s_from_video_times_and_radius_m_from_bag_positions(tmp_path, video):
    path, _ = video
    bag = camera_bag(tmp_path / "gps.bag", route_frames(6, seed=13))
    for references, setting in ((str(path), "radius_s=0.2"), (f"{bag}:/camera/image_raw", "radius_m=3")):
        out = tmp_path / "m.csv"
        assert (
            main(
                [
                    "match",
                    "--reference",
                    references,
                    "--query",
                    references,
                    "--method",
                    "sad",
                    "--accept",
                    "margin",
                    "--accept-set",
                    setting,
                    "--out",
                    str(out),
                    "--workers",
                    "0",
                ]
            )
            == 0
        )
        rows = list(csv.DictReader(out.open()))
        assert rows and all(r["acceptance_score"] not in ("", None) for r in rows)


def test_extract_stores_each_frames_source_and_timestamp(tmp_path, video):
    from fdnet.descriptors import create
    from tests.cli.test_extract import _tiny_run

    path, frames = video
    run = _tiny_run(tmp_path / "run")
    out = tmp_path / "v.npz"
    assert (
        main(
            [
                "extract",
                "--checkpoint",
                str(run),
                "--images",
                str(path),
                "--every",
                "4",
                "--out",
                str(out),
                "--fp32",
                "--batch-size",
                "4",
                "--workers",
                "1",
                "--device",
                "cpu",
                "--no-progress",
            ]
        )
        == 0
    )
    kept = list(range(0, 50, 4))
    folder = tmp_path / "frames"
    save_folder(folder, frames[kept])
    d = create("fdnet", checkpoint=run, device="cpu")
    from fdnet.data.images import load_images

    expected = d.describe(load_images(list_images(folder), d.input_size))
    with np.load(out, allow_pickle=False) as z:
        assert list(z["names"]) == [f"frame_{i:06d}_{i * 40}ms" for i in kept]
        assert list(z["sources"]) == [str(path)] * len(kept)
        assert z["timestamps"] == pytest.approx([i / 25 for i in kept])
        np.testing.assert_allclose(z["content"], expected, rtol=1e-5, atol=1e-6)


def test_a_method_learns_from_a_video_given_to_fit(video):
    from fdnet.descriptors.fitting import fit_image_paths

    path, _ = video
    paths, described = fit_image_paths(path, "10:20")
    assert [frame_index(p) for p in paths] == list(range(10, 20))
    assert "10 images" in described
