"""``fdnet benchmark --parts loop``: the loop-closure detector's cost per frame on maps of 10^4 to
10^6 places, exhaustive search against the index (:mod:`fdnet.decisions.loop_search`).

The map is an earlier session's places (random unit vectors, as the scale benchmark's); the
traverse is a route of ``route`` new places driven twice (the second pass is the first plus
noise), decided frame by frame with the command's defaults (margin, sequences of 10, the gates)
after the map's places. Each map size reports milliseconds per frame of the decision alone (no
describing; the database commits 100 frames at a time so SQLite's fsync is not what is timed),
the reference of one (places x dim) matrix-vector product measured in the same run, how often
the index's decision names the same place as the exhaustive one on the revisits, and Recall@1
of each there. With an
FDNet checkpoint (the ``fdnet`` part measured its ``cpu``-preset descriptor through the public
API in the same run) it also gives frames/s of the whole loop: 1000 / (describe ms + decide ms).
Nothing is asserted by tests: the report holds figures measured side by side.
"""

from __future__ import annotations

import math
import time
from typing import Callable

import numpy as np

from fdnet.descriptors.base import Descriptor
from fdnet.performance.timing import gemv_ms

DEFAULT_SIZES = (10_000, 100_000, 1_000_000)


class StoredVectors(Descriptor):
    """Vectors computed elsewhere (here: made up), compared by dot product: what the detector
    needs of a descriptor when it is fed vectors, never images."""

    name = "stored-vectors"

    def __init__(self, dim: int):
        self._dim = int(dim)
        self.input_size = (1, 1)

    @property
    def dim(self) -> int:
        return self._dim

    def describe(self, images: np.ndarray) -> np.ndarray:
        raise NotImplementedError("stored vectors describe no images")

    def settings(self) -> dict:
        return {"dim": self._dim}


def loop_rows(
    sizes,
    dim: int = 512,
    route: int = 300,
    noise: float = 0.5,
    describe_ms: float | None = None,
    log: Callable[[str], None] = lambda line: None,
) -> list[dict]:
    """Measure the detector on each map size (see the module docstring); one row per size."""
    from fdnet.decisions.loop_closure import LoopClosureDetector
    from fdnet.matching.database import PlaceDatabase
    from fdnet.performance.timing import random_map, revisit_queries

    places = random_map(route, dim, seed=7)
    first = revisit_queries(places, route, noise, seed=8)
    second = revisit_queries(places, route, noise, seed=9)
    # revisit_queries picks places in a random order: put both passes back in route order
    order = np.argsort(np.random.default_rng(8).choice(route, size=route, replace=False))
    first = first[order]
    order = np.argsort(np.random.default_rng(9).choice(route, size=route, replace=False))
    second = second[order]
    frames = np.concatenate([first, second])
    descriptor = StoredVectors(dim)
    rows = []
    for size in sizes:
        earlier = random_map(int(size), dim, seed=11)
        log(f"  {size:>9,} places: building the map ...")
        decided = {}
        for search in ("exact", "index"):
            db = PlaceDatabase.for_descriptor(descriptor)
            for start in range(0, len(earlier), 100_000):
                chunk = earlier[start : start + 100_000]
                db.add(chunk, [f"earlier/{start + i}" for i in range(len(chunk))])
            detector = LoopClosureDetector(
                descriptor,
                db,
                exclude_last=5,
                rule="margin",
                threshold=0.0,
                sequence_length=10,
                commit_every=100,
                search=search,
            )
            times = []
            with detector:
                for i, vector in enumerate(frames):
                    t0 = time.perf_counter()
                    detector.process_vector(vector, name=f"traverse/{i}")
                    times.append(time.perf_counter() - t0)
                decided[search] = [d.match for d in detector.decisions]
            db.close()
            revisits = np.arange(route, 2 * route)
            truth = size + revisits - route
            matches = np.array(decided[search])[revisits]
            decided[search + "_ms"] = 1e3 * float(np.median(times[route:]))
            decided[search + "_recall"] = float(np.mean(np.abs(matches - truth) <= 1))
        gemv = gemv_ms(earlier)
        # on the revisits, where a decision can be right (the first pass's best places are noise)
        agree = float(np.mean(np.array(decided["exact"])[route:] == np.array(decided["index"])[route:]))
        row = {
            "map_size": int(size),
            "dim": dim,
            "frames": len(frames),
            "exact_ms": decided["exact_ms"],
            "index_ms": decided["index_ms"],
            "gemv_ms": gemv,
            "agreement": agree,
            "exact_recall_at_1": decided["exact_recall"],
            "index_recall_at_1": decided["index_recall"],
        }
        if describe_ms is not None:
            row["describe_ms"] = describe_ms
            row["fdnet_frames_per_s_exact"] = 1e3 / (describe_ms + row["exact_ms"])
            row["fdnet_frames_per_s_index"] = 1e3 / (describe_ms + row["index_ms"])
        rows.append(row)
        with_fdnet = (
            ""
            if describe_ms is None
            else (
                f" | with FDNet ({describe_ms:.1f} ms/frame): {row['fdnet_frames_per_s_exact']:.1f} -> "
                f"{row['fdnet_frames_per_s_index']:.1f} frames/s"
            )
        )
        log(
            f"  {size:>9,} places: exact {row['exact_ms']:7.2f} ms/frame ({row['exact_ms'] / gemv:5.1f} x one "
            f"{gemv:.2f} ms GEMV), index {row['index_ms']:6.2f} ms/frame, same place on the revisits {agree:.3f}, "
            f"R@1 (+-1 place) exact {row['exact_recall_at_1']:.3f} index {row['index_recall_at_1']:.3f}{with_fdnet}"
        )
        del earlier
    return rows


def per_frame_rows(
    run_dir, images_folder, frames: int = 120, repeats: int = 3, log: Callable[[str], None] = lambda line: None
) -> dict:
    """A robot's path against the command's: the same frames through ``fdnet loop-closure``'s
    :func:`~fdnet.decisions.loop_traverse.run_traverse` (frames described ``batch_size`` at a
    time, decoded by worker processes) and through :meth:`LoopClosureDetector.process` one frame
    at a time (as a robot node calls it), with FDNet from ``run_dir`` and the command's defaults
    (margin, sequences of 10, the gates). The two are alternated ``repeats`` times and each
    reports its best run (the least disturbed by other work on the machine); the per-frame path
    also reports its latency per frame (median and 99th percentile over all its runs)."""
    import tempfile
    from pathlib import Path

    from fdnet.data.images import list_images
    from fdnet.decisions.loop_closure import LoopClosureDetector
    from fdnet.decisions.loop_settings import LoopClosureSettings, TraverseSettings
    from fdnet.decisions.loop_traverse import run_traverse
    from fdnet.descriptors import create

    paths = list_images(images_folder)[:frames]
    descriptor = create("fdnet", checkpoint=str(run_dir))
    batched, single, latency = [], [], []
    with tempfile.TemporaryDirectory(prefix="fdnet-loop-") as scratch:
        folder = Path(scratch) / "frames"
        folder.mkdir()
        for path in paths:  # exactly these frames for both paths
            (folder / Path(path).name).symlink_to(Path(path).resolve())
        for _ in range(repeats):
            settings = TraverseSettings(
                Path(scratch) / "events.csv", LoopClosureSettings(rule="margin", threshold=math.inf, sequence_length=10)
            )
            report = run_traverse(folder, descriptor, None, settings)
            batched.append(report.frames_per_second)
            detector = LoopClosureDetector(descriptor, None, rule="margin", threshold=math.inf, sequence_length=10)
            with detector:
                t0 = time.perf_counter()
                for path in sorted(folder.iterdir()):
                    t1 = time.perf_counter()
                    detector.process(path)
                    latency.append(time.perf_counter() - t1)
                single.append(len(paths) / (time.perf_counter() - t0))
    row = {
        "frames": len(paths),
        "command_frames_per_s": max(batched),
        "process_frames_per_s": max(single),
        "process_latency_ms_median": 1e3 * float(np.median(latency)),
        "process_latency_ms_p99": 1e3 * float(np.percentile(latency, 99)),
        "command_runs": batched,
        "process_runs": single,
    }
    row["ratio"] = row["process_frames_per_s"] / row["command_frames_per_s"]
    log(
        f"  {len(paths)} frames, FDNet {descriptor.input_size[0]}x{descriptor.input_size[1]}: fdnet loop-closure "
        f"{row['command_frames_per_s']:.1f} frames/s (batched); LoopClosureDetector.process one frame at a time "
        f"{row['process_frames_per_s']:.1f} frames/s = {row['ratio']:.2f} x the command, latency per frame median "
        f"{row['process_latency_ms_median']:.1f} ms, p99 {row['process_latency_ms_p99']:.1f} ms (best of {repeats} "
        "alternated runs each)"
    )
    return row
