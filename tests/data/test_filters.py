"""Frame filters: dark (tunnel) and near-duplicate (stationary) frames, applied to all conditions."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from fdnet.data.dataset import RouteDataset
from fdnet.data.filters import filter_route, near_duplicates
from fdnet.data.groundtruth import GroundTruth
from fdnet.errors import ConfigError, DataError

from conftest import require_shared


def _route(tmp_path, frames: dict[str, list[np.ndarray]]) -> RouteDataset:
    for cond, images in frames.items():
        (tmp_path / cond).mkdir()
        for i, im in enumerate(images):
            Image.fromarray((np.clip(im, 0, 1) * 255).astype(np.uint8)).save(tmp_path / cond / f"{i:03d}.png")
    return RouteDataset.from_folder(tmp_path, list(frames))


def _scene(rng, n):
    """n distinct random grey-ish frames (32x64)."""
    return [np.repeat(rng.random((32, 64, 1)), 3, axis=2) * 0.8 + 0.2 for _ in range(n)]


def test_dark_in_one_condition_drops_the_position_everywhere(tmp_path, rng):
    a, b = _scene(rng, 8), _scene(rng, 8)
    a[2] = np.full((32, 64, 3), 0.02)  # tunnel in condition a only
    b[5] = np.full((32, 64, 3), 0.05)  # tunnel in condition b only
    ds, report = filter_route(_route(tmp_path, {"a": a, "b": b}))
    assert list(report.kept) == [0, 1, 3, 4, 6, 7]
    assert list(report.dark["a"]) == [2] and list(report.dark["b"]) == [5]
    assert list(ds["a"].frame_ids) == list(ds["b"].frame_ids) == [0, 1, 3, 4, 6, 7]
    assert [p.name for p in ds["b"].paths] == ["000.png", "001.png", "003.png", "004.png", "006.png", "007.png"]
    # Frame-aligned ground truth still pairs the same places.
    gt = GroundTruth.from_frames(ds["a"].frame_ids, ds["b"].frame_ids, 0)
    assert all(list(p) == [i] for i, p in enumerate(gt.positives))
    assert report.to_dict()["num_dropped_dark"] == 2


def test_stationary_frames_are_dropped_against_last_kept(tmp_path, rng):
    a, b = _scene(rng, 7), _scene(rng, 7)
    a[3] = a[2] + 0.004  # train stopped in a: 3 and 4 repeat 2
    a[4] = a[2] - 0.004
    ds, report = filter_route(_route(tmp_path, {"a": a, "b": b}), dark_threshold=None)
    assert list(report.kept) == [0, 1, 2, 5, 6]
    assert list(report.duplicate["a"]) == [3, 4] and len(report.duplicate["b"]) == 0
    assert len(ds["b"]) == 5


def test_near_duplicates_compares_with_last_kept_not_previous():
    # A slow creep: each step is small, but after a few steps the view has changed enough.
    steps = np.arange(6, dtype=np.float32)[:, None, None] * 0.006 * np.ones((1, 2, 2), np.float32)
    dup = near_duplicates(steps[None], threshold=0.01)
    assert list(np.flatnonzero(~dup[0])) == [0, 2, 4]


def test_thresholds_off_keep_everything(tmp_path, rng):
    a = _scene(rng, 4)
    a[1] = np.zeros((32, 64, 3))
    a[2] = a[3].copy()
    _, report = filter_route(_route(tmp_path, {"a": a}), dark_threshold=None, duplicate_threshold=None)
    assert len(report.kept) == 4


def test_mostly_dark_traverse_is_refused_not_emptied(tmp_path, rng):
    night = [np.full((32, 64, 3), 0.05) + 0.02 * rng.random((32, 64, 3)) for _ in range(6)]
    with pytest.raises(ConfigError, match="night-time traverse"):
        filter_route(_route(tmp_path, {"day": _scene(rng, 6), "night": night}))


def test_different_frame_counts_are_refused(tmp_path, rng):
    with pytest.raises(DataError, match="same number of frames"):
        filter_route(_route(tmp_path, {"a": _scene(rng, 3), "b": _scene(rng, 4)}))


def test_bad_threshold_is_config_error(tmp_path, rng):
    with pytest.raises(ConfigError):
        filter_route(_route(tmp_path, {"a": _scene(rng, 2)}), dark_threshold=30)


def test_real_nordland_tunnel_and_stationary_frames():
    """Frames 1100-1300 hold a tunnel (1191-1202 in both seasons, plus single dark frames)."""
    root = require_shared("nordland_trimmed")
    ds = RouteDataset.from_folder(root, ["summer", "winter"]).frames(1100, 1300)
    filtered, report = filter_route(ds)
    dropped = set(ds["summer"].frame_ids[report.dropped_dark].tolist())
    assert set(range(1191, 1203)) <= dropped
    assert 12 <= len(report.dark["summer"]) <= 30 and 12 <= len(report.dark["winter"]) <= 30
    assert list(filtered["summer"].frame_ids) == list(filtered["winter"].frame_ids)
    assert not set(filtered["summer"].frame_ids.tolist()) & dropped


def test_one_grey_conversion_and_one_measure_of_brightness_and_change():
    """The training filters and loop closure's gates read the same measures: the BT.601 weights
    are written once (fdnet.data.images), and neither module measures pixels its own way."""
    from pathlib import Path

    src = Path(__file__).resolve().parents[2] / "src" / "fdnet"
    weights = sorted(str(p.relative_to(src)) for p in src.rglob("*.py") if "0.587" in p.read_text())
    assert weights == ["data/images.py"]
    for module in ("data/filters.py", "decisions/loop_gates.py"):
        text = (src / module).read_text()
        assert "grey_levels(" in text and "thumbnail_difference(" in text
        assert ".mean(axis=1)" not in text and "np.abs(" not in text


def test_grey_levels_and_thumbnail_difference():
    from fdnet.data.images import grey_levels, thumbnail_difference, to_grey

    frames = np.zeros((2, 4, 4, 3), np.float32)
    frames[1, :2] = 1.0  # top half white
    grey = to_grey(frames)
    np.testing.assert_allclose(grey_levels(grey), [[0.0, 0.0], [0.5, 0.5]], atol=1e-6)
    assert grey_levels(grey[:0]).shape == (0, 2)
    np.testing.assert_allclose(thumbnail_difference(grey[0], grey[1]), 0.5, atol=1e-6)
    np.testing.assert_allclose(thumbnail_difference(grey[None], grey[None]), [[0.0, 0.0]])
