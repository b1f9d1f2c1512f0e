"""Oxford RobotCar (Maddern, Pascoe, Linegar, Newman, "1 Year, 1000km: The Oxford RobotCar Dataset",
IJRR 2017; SDK https://github.com/ori-mrg/robotcar-dataset-sdk).

The downloads, extracted into one folder as the SDK recommends, give one folder per traversal::

    robotcar/2014-12-16-09-14-09/stereo/centre/<unix time, microseconds>.png   raw Bayer images
    robotcar/2014-12-16-09-14-09/gps/ins.csv    timestamp,ins_status,latitude,longitude,altitude,
                                                northing,easting,down,utm_zone,velocity_*,roll,pitch,yaw
    robotcar/2014-12-16-09-14-09/gps/gps.csv    timestamp,...,northing,easting,... (used when ins.csv is absent)

Processing, following the SDK: stereo images are raw Bayer mosaics with the GBRG pattern
(``python/image.py``: ``BAYER_STEREO = 'gbrg'``, mono cameras ``rggb``), demosaiced here with OpenCV
and cached as RGB PNGs (``demosaic_cache``; default ``$FDNET_CACHE/robotcar`` or
``~/.cache/fdnet/robotcar``), only for the frames a split uses. Each image's UTM position is the
INS/GPS track (northing, easting columns) linearly interpolated at the image timestamp; images
outside the track's time span are an error (``drop_uncovered=true`` drops them instead). Images
are not undistorted (the paper does not say it did).

Protocol (Qin et al. 5.2.1, Table 1): 2014-12-16-09-14-09 (day, reference) against
2014-12-10-18-10-50 (night, query), images taken at 5 frames per second (``fps``; ``fps=0`` keeps all; or every
``spacing_m`` metres travelled), tolerance 30 m, 1758 training and 754 test images. The paper
says the route is "approximately three kilometers" but not which part: ``train`` = the first
1758 subsampled frames of each traversal and ``test`` the next 754; use ``--split START:END``
for another stretch.
"""

from __future__ import annotations

import csv
import os
import re
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fdnet.data.dataset import RouteDataset, Traverse
from fdnet.data.formats._common import DatasetFormat, describe, fixed, pick_conditions, resolve_split
from fdnet.data.groundtruth import GroundTruth
from fdnet.data.images import list_images
from fdnet.data.split import EvaluationSplit
from fdnet.errors import ConfigError, DataError
from fdnet.io import atomic_write_bytes

RUN_NAME = re.compile(r"^\d{4}-\d{2}-\d{2}-\d{2}-\d{2}-\d{2}$")
DAY, NIGHT = "2014-12-16-09-14-09", "2014-12-10-18-10-50"
TRAIN_FRAMES, TEST_FRAMES = 1758, 754


@dataclass
class OxfordOptions:
    tolerance_m: float = 30.0
    fps: float = 5.0  # images per second to keep; 0 keeps every image
    spacing_m: float | None = None  # or: keep one image every spacing_m metres (overrides fps)
    camera: str = "stereo/centre"
    bayer_pattern: str = "gbrg"  # SDK: stereo gbrg, mono rggb
    gps_file: str | None = None  # relative to the traversal folder; default gps/ins.csv, else gps/gps.csv
    demosaic_cache: str | None = None
    drop_uncovered: bool = False


def run_folders(root: Path, camera: str) -> list[str]:
    if not root.is_dir():
        return []
    return sorted(p.name for p in root.iterdir() if p.is_dir() and RUN_NAME.match(p.name) and (p / camera).is_dir())


def bayer_code(pattern: str) -> int:
    """OpenCV conversion code for a Bayer pattern named by its top-left 2x2 block (e.g. GBRG).

    OpenCV >= 4.5.3 has codes spelled that way; older ones name patterns by the second row's
    2nd/3rd pixels, so GBRG was ``COLOR_BayerGR2BGR`` there (checked in the tests on a mosaic of
    known colours).
    """
    import cv2

    pattern = pattern.upper()
    legacy = {"GBRG": "GR", "RGGB": "BG", "BGGR": "RG", "GRBG": "GB"}
    if pattern not in legacy:
        raise ConfigError(f"bayer_pattern {pattern!r}: expected one of {', '.join(legacy)}")
    code = getattr(cv2, f"COLOR_Bayer{pattern}2BGR", None)
    return code if code is not None else getattr(cv2, f"COLOR_Bayer{legacy[pattern]}2BGR")


def demosaic(raw_path: Path, out_path: Path, pattern: str) -> None:
    import cv2

    raw = cv2.imread(str(raw_path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise DataError(f"{raw_path}: cannot read image")
    if raw.ndim != 2:
        raise DataError(f"{raw_path}: expected a single-channel raw Bayer image, got shape {raw.shape}")
    bgr = cv2.cvtColor(raw, bayer_code(pattern))
    ok, encoded = cv2.imencode(".png", bgr)
    if not ok:  # pragma: no cover - OpenCV always encodes PNG
        raise DataError(f"{raw_path}: could not encode the demosaiced image")
    atomic_write_bytes(out_path, encoded.tobytes())


def read_track(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps (N,) int64 microseconds, easting/northing (N, 2) metres) sorted by time."""
    try:
        with open(path, newline="") as f:
            reader = csv.reader(f)
            header = [h.strip().lower() for h in next(reader, [])]
            rows = list(enumerate(reader, start=2))
    except FileNotFoundError as exc:
        raise DataError(f"{path}: GPS/INS file not found") from exc
    missing = [c for c in ("timestamp", "northing", "easting") if c not in header]
    if missing:
        raise DataError(f"{path}: missing column(s) {', '.join(missing)}; found: {', '.join(header) or 'none'}")
    it, inn, ie = header.index("timestamp"), header.index("northing"), header.index("easting")
    stamps, xy = [], []
    for line_no, row in rows:
        if not row:
            continue
        try:
            stamps.append(int(row[it]))
            xy.append((float(row[ie]), float(row[inn])))
        except (ValueError, IndexError) as exc:
            raise DataError(
                f"{path}, line {line_no}: expected numeric timestamp, northing, easting; " f"got {','.join(row)!r}"
            ) from exc
    if not stamps:
        raise DataError(f"{path}: no GPS/INS rows")
    stamps_arr, xy_arr = np.asarray(stamps, dtype=np.int64), np.asarray(xy, dtype=np.float64)
    order = np.argsort(stamps_arr, kind="stable")
    return stamps_arr[order], xy_arr[order]


def subsample(stamps: np.ndarray, xy: np.ndarray, fps: float | None, spacing_m: float | None) -> np.ndarray:
    """Indices of the images kept: by distance, the next image at least ``spacing_m`` metres
    along the track after the last kept one; by rate, the image nearest each 1/fps tick."""
    if spacing_m is not None:
        if spacing_m <= 0:
            raise ConfigError(f"spacing_m must be > 0, got {spacing_m}")
        step = np.r_[0.0, np.linalg.norm(np.diff(xy, axis=0), axis=1)]
        travelled = np.cumsum(step)
        keep, last = [0], travelled[0]
        for i in range(1, len(travelled)):
            if travelled[i] - last >= spacing_m:
                keep.append(i)
                last = travelled[i]
        return np.asarray(keep, dtype=np.int64)
    if fps is None or fps == 0:
        return np.arange(len(stamps))
    if fps < 0:
        raise ConfigError(f"fps must be >= 0 (0 keeps every image), got {fps}")
    # The image nearest to each tick of a 1/fps clock: a 16 Hz camera at 5 fps then keeps 5
    # images a second on average (a greedy "at least 1/fps apart" rule would keep only 4).
    if len(stamps) == 1:
        return np.zeros(1, dtype=np.int64)
    ticks = np.arange(stamps[0], stamps[-1] + 1, 1e6 / fps)
    right = np.clip(np.searchsorted(stamps, ticks), 1, len(stamps) - 1)
    left = right - 1
    nearest = np.where(np.abs(stamps[left] - ticks) <= np.abs(stamps[right] - ticks), left, right)
    return np.unique(nearest).astype(np.int64)


class OxfordRobotCarFormat(DatasetFormat):
    name = "oxford_robotcar"
    summary = "Oxford RobotCar: raw Bayer stereo/centre images + gps/ins.csv, demosaiced and subsampled"
    Options = OxfordOptions
    splits = {
        "train": f"subsampled frames 0:{TRAIN_FRAMES}",
        "test": f"subsampled frames {TRAIN_FRAMES}:{TRAIN_FRAMES + TEST_FRAMES}",
    }
    split_rules = {"train": fixed(0, TRAIN_FRAMES), "test": fixed(TRAIN_FRAMES, TRAIN_FRAMES + TEST_FRAMES)}
    default_eval_split = "test"
    default_train_split = "train"

    def detect(self, root: Path) -> bool:
        return len(run_folders(root, "stereo/centre")) >= 1

    def cache_dir(self, options: OxfordOptions) -> Path:
        if options.demosaic_cache:
            return Path(options.demosaic_cache)
        base = os.environ.get("FDNET_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "fdnet")
        return Path(base) / "robotcar"

    def read_run(self, root: Path, name: str, options: OxfordOptions) -> Traverse:
        """All images of one traversal with timestamps and interpolated positions, subsampled;
        paths still point at the raw Bayer files."""
        run = root / name
        image_dir = run / options.camera
        if not image_dir.is_dir():
            raise DataError(
                f"{image_dir}: folder not found; traversals here: "
                f"{', '.join(run_folders(root, options.camera)) or 'none'}"
            )
        # Digit-only names are microsecond timestamps: their natural order is time order.
        raw = [
            p for p in list_images(image_dir) if p.suffix.lower() == ".png" and p.stem.isascii() and p.stem.isdigit()
        ]
        if not raw:
            raise DataError(f"{image_dir}: no <timestamp>.png images")
        stamps = np.array([int(p.stem) for p in raw], dtype=np.int64)
        if options.gps_file:
            track_path = run / options.gps_file
        else:
            track_path = next((run / f for f in ("gps/ins.csv", "gps/gps.csv") if (run / f).is_file()), None)
            if track_path is None:
                raise DataError(
                    f"{run}: missing gps/ins.csv (and gps/gps.csv); download the traversal's GPS "
                    f"archive into the same folder"
                )
        track_t, track_xy = read_track(track_path)
        outside = (stamps < track_t[0]) | (stamps > track_t[-1])
        if outside.any():
            if not options.drop_uncovered:
                raise DataError(
                    f"{track_path}: GPS/INS rows cover timestamps {track_t[0]}..{track_t[-1]} but "
                    f"{int(outside.sum())} of the {len(stamps)} images in {image_dir} lie outside "
                    f"(e.g. {raw[int(np.flatnonzero(outside)[0])].name}); the GPS file is partial or of "
                    f"another traversal (drop_uncovered=true skips those images)"
                )
            keep = np.flatnonzero(~outside)
            if len(keep) == 0:
                raise DataError(f"{track_path}: covers none of the images in {image_dir}")
            raw, stamps = [raw[i] for i in keep], stamps[keep]
            frame_ids = keep
        else:
            frame_ids = np.arange(len(raw))
        xy = np.stack([np.interp(stamps, track_t, track_xy[:, 0]), np.interp(stamps, track_t, track_xy[:, 1])], 1)
        kept = subsample(stamps, xy, options.fps, options.spacing_m)
        return Traverse(
            name,
            [raw[i] for i in kept],
            frame_ids=np.asarray(frame_ids)[kept],
            positions=xy[kept],
            timestamps=stamps[kept],
        )

    def demosaiced(self, traverse: Traverse, options: OxfordOptions) -> Traverse:
        """The same frames with paths to cached RGB versions (made once, atomically)."""
        folder = self.cache_dir(options) / traverse.name / options.camera.replace("/", "_")
        targets = [folder / p.name for p in traverse.paths]
        todo = [(src, dst) for src, dst in zip(traverse.paths, targets) if not dst.is_file()]
        if todo:
            with ThreadPoolExecutor(max_workers=2) as pool:  # OpenCV releases the GIL
                list(pool.map(lambda pair: demosaic(pair[0], pair[1], options.bayer_pattern), todo))
        return Traverse(
            traverse.name,
            targets,
            frame_ids=traverse.frame_ids,
            positions=traverse.positions,
            timestamps=traverse.timestamps,
        )

    def _pair(self, root: Path, reference, query, options) -> tuple[str, str]:
        runs = run_folders(root, options.camera)
        if reference and query:
            return reference, query
        if {DAY, NIGHT} <= set(runs):
            return reference or DAY, query or NIGHT
        if len(runs) == 2:
            return reference or runs[0], query or runs[1]
        raise ConfigError(
            f"{root}: traversals {', '.join(runs) or 'none'}; name the pair with " f"--reference and --query"
        )

    def evaluation_split(self, root, reference, query, split, options: OxfordOptions) -> EvaluationSplit:
        reference, query = self._pair(root, reference, query, options)
        ref_full, qry_full = self.read_run(root, reference, options), self.read_run(root, query, options)
        start, end = resolve_split(split, self.split_rules, min(len(ref_full), len(qry_full)), str(root))
        ref = self.demosaiced(ref_full.frames(start, end), options)
        qry = self.demosaiced(qry_full.frames(start, end), options)
        gt = GroundTruth.from_positions(qry.positions, ref.positions, options.tolerance_m)
        return EvaluationSplit(ref, qry, gt, describe(root, qry, ref, gt, f"split {split or 'all'}"))

    def training_dataset(self, root, split, conditions, options) -> RouteDataset:
        runs = pick_conditions(run_folders(root, options.camera), conditions, root)
        traverses = [self.read_run(root, r, options) for r in runs]
        start, end = resolve_split(split, self.split_rules, min(len(t) for t in traverses), str(root))
        return RouteDataset(root, {t.name: self.demosaiced(t.frames(start, end), options) for t in traverses})


FORMAT = OxfordRobotCarFormat()
