"""Oxford RobotCar: raw GBRG Bayer images named by timestamp, gps/ins.csv, demosaic + subsampling."""

import numpy as np
import pytest
from PIL import Image

from fdnet.data.formats import detect_format, open_split
from fdnet.data.formats.oxford_robotcar import subsample
from fdnet.data.images import load_image
from fdnet.errors import DataError

INS_HEADER = (
    "timestamp,ins_status,latitude,longitude,altitude,northing,easting,down,utm_zone,"
    "velocity_north,velocity_east,velocity_down,roll,pitch,yaw"
)
T0 = 1418721000000000  # microseconds
RGB = (200, 100, 30)


def gbrg_mosaic(h=6, w=8, rgb=RGB):
    """A raw GBRG frame of a uniform colour: rows G B G B / R G R G."""
    raw = np.zeros((h, w), np.uint8)
    raw[0::2, 0::2] = rgb[1]
    raw[0::2, 1::2] = rgb[2]
    raw[1::2, 0::2] = rgb[0]
    raw[1::2, 1::2] = rgb[1]
    return raw


def make_run(root, name, n=16, hz=16.0, speed=10.0, gps_start=T0, gps_end=None, north0=5735000.0):
    """n images at ``hz`` while driving north at ``speed`` m/s; an INS row every 20 ms."""
    run = root / name
    cam = run / "stereo" / "centre"
    cam.mkdir(parents=True)
    stamps = [T0 + int(i * 1e6 / hz) for i in range(n)]
    for t in stamps:
        Image.fromarray(gbrg_mosaic(), "L").save(cam / f"{t}.png")
    gps_end = gps_end if gps_end is not None else stamps[-1] + 20000
    (run / "gps").mkdir()
    rows = [INS_HEADER]
    for t in range(gps_start, gps_end + 1, 20000):
        north = north0 + speed * (t - T0) / 1e6
        rows.append(f"{t},INS_SOLUTION_GOOD,51.76,-1.26,110.0,{north:.3f},620000.000,-110.0,30U," f"{speed},0,0,0,0,0")
    (run / "gps" / "ins.csv").write_text("\n".join(rows) + "\n")
    return stamps


def test_day_night_pair_demosaiced_and_positioned(tmp_path):
    root = tmp_path / "robotcar"
    make_run(root, "2014-12-16-09-14-09")
    make_run(root, "2014-12-10-18-10-50", north0=5735005.0)  # night run 5 m further north
    assert detect_format(root) == "oxford_robotcar"
    cache = tmp_path / "cache"
    split = open_split(root, split="all", demosaic_cache=str(cache))
    assert (split.reference.name, split.query.name) == ("2014-12-16-09-14-09", "2014-12-10-18-10-50")
    # 16 images at 16 Hz = 1 s; 5 fps keeps the images nearest to 0, 0.2, ... 0.8 s
    assert split.reference.frame_ids.tolist() == [0, 3, 6, 10, 13]
    np.testing.assert_allclose(split.reference.positions[:, 1] - 5735000.0, [0.0, 1.875, 3.75, 6.25, 8.125])
    # demosaiced once into the cache, as RGB of the mosaic's colour
    assert all(p.parent == cache / "2014-12-16-09-14-09" / "stereo_centre" for p in split.reference.paths)
    pixel = load_image(split.query.paths[0])[3, 4] * 255
    np.testing.assert_allclose(pixel, RGB, atol=1)
    # within 30 m everything matches on a 10 m stretch
    assert split.ground_truth.has_match.all()
    # every image (fps=0) is 0.625 m apart; night image 0 is 5 m north = day image 8
    near = open_split(root, split="all", demosaic_cache=str(cache), tolerance_m=0.3, fps=0)
    assert len(near.query) == 16 and near.ground_truth.positives[0].tolist() == [8]
    assert open_split(root, split="all", demosaic_cache=str(cache), tolerance_m=2.0, fps=0).ground_truth.positives[
        0
    ].tolist() == [5, 6, 7, 8, 9, 10, 11]


def test_distance_subsampling(tmp_path):
    stamps = np.arange(10) * 100000
    xy = np.stack([np.zeros(10), np.arange(10) * 0.7], 1)
    assert subsample(stamps, xy, fps=None, spacing_m=2.0).tolist() == [0, 3, 6, 9]


def test_gps_must_cover_the_images(tmp_path):
    root = tmp_path / "robotcar"
    make_run(root, "2014-12-16-09-14-09")
    make_run(root, "2014-12-10-18-10-50", gps_start=T0 + 500000)  # GPS starts half a second late
    with pytest.raises(DataError, match=r"ins.csv: GPS/INS rows cover timestamps .* but 8 of the 16 images"):
        open_split(root, split="all", demosaic_cache=str(tmp_path / "c"))
    ok = open_split(root, split="all", demosaic_cache=str(tmp_path / "c"), drop_uncovered=True, fps=0)
    assert ok.query.frame_ids.tolist() == list(range(8, 16))


def test_missing_gps_and_bad_columns(tmp_path):
    root = tmp_path / "robotcar"
    make_run(root, "2014-12-16-09-14-09")
    make_run(root, "2014-12-10-18-10-50")
    (root / "2014-12-10-18-10-50" / "gps" / "ins.csv").unlink()
    with pytest.raises(DataError, match="2014-12-10-18-10-50: missing gps/ins.csv"):
        open_split(root, split="all")
    (root / "2014-12-10-18-10-50" / "gps" / "gps.csv").write_text("timestamp,latitude,longitude\n1,2,3\n")
    with pytest.raises(DataError, match="gps.csv: missing column\\(s\\) northing, easting"):
        open_split(root, split="all")
