"""``fdnet benchmark --parts loop``: the loop-closure detector's cost per frame on maps of 10^4 to
10^7 places, exhaustive search against the index (:mod:`fdnet.decisions.loop_search`).

The map is an earlier session's places (random unit vectors, as the scale benchmark's); the
traverse is a route of ``route`` new places driven twice (the second pass is the first plus
noise), decided frame by frame with the command's defaults (margin, sequences of 10, the gates)
after the map's places. Each map size reports milliseconds per frame of the decision alone (no
describing; the database commits 100 frames at a time so SQLite's fsync is not what is timed),
the reference of one (places x dim) matrix-vector product measured in the same run, how often
the index's decision names the same place as the exhaustive one on the revisits, and Recall@1
of each there. With an
FDNet checkpoint (the ``fdnet`` part measured its ``cpu``-preset descriptor through the public
API in the same run) it also gives frames/s of the whole loop: 1000 / (describe ms + decide ms),
with the descriptor's time one image a call for the paths fed one frame at a time (a robot
node's) and in the command's batches for the batched path (:class:`DescribeMs`).
A map above :data:`IN_MEMORY_UP_TO` places is never held in memory: a process of its own (the
earlier session's) makes and stores it in the file database a chunk at a time, so the memory
measured is the detector's over a database written before; only the compressed path can decide
on it (the exhaustive
search would need the whole map in memory), and its agreement is the batched path's with one
frame at a time; its GEMV reference is one chunk's, scaled to the map.
Nothing is asserted by tests: the report holds figures measured side by side.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, NamedTuple

import numpy as np

from fdnet.decisions.loop_search import IVF_FROM
from fdnet.decisions.loop_traverse import DEFAULT_SEQUENCE_LENGTH
from fdnet.descriptors.base import Descriptor
from fdnet.errors import DataError
from fdnet.matching.database.storage import MEMORY
from fdnet.performance.timing import gemv_ms, process_memory, release_free_heap

DEFAULT_SIZES = (10_000, 100_000, 1_000_000)
#: above this many places the map is not held in memory (4 GB of 512 floats at 2 x 10^6): it is
#: streamed into a file database chunk by chunk, and only the compressed path is measured
IN_MEMORY_UP_TO = 2_000_000
#: what a streamed map measures: both compressed paths (agreement: of the batched with one at a time)
STREAMED_SEARCHES = ("compressed", "compressed_batched")
#: places made and stored at a time
CHUNK = 100_000
#: disk bytes a stored place takes beyond its vector's twice: the database row's name and overhead
#: (2212 bytes a 512-float place at 10^7 in 32 KB pages: 164), the codes cache beside it (168 at
#: the default codes) and the write-ahead log of an add, with room to spare
DISK_BYTES_OVER_VECTOR = 600
#: frames described ahead per batch on the compressed path's batched variant (the command's
#: default ``--batch-size``)
AHEAD = 64


class DescribeMs(NamedTuple):
    """A descriptor's ms/image given one image a call (what a robot node's ``process`` pays) and
    given the command's batches (``fdnet loop-closure`` describes ``--batch-size`` frames a call)."""

    one: float
    batch: float

    @classmethod
    def of(cls, value) -> "DescribeMs | None":
        """``value`` as a pair (a single number: the same both ways; None stays None)."""
        if value is None or isinstance(value, cls):
            return value
        return cls(float(value), float(value))


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
    describe_ms: DescribeMs | float | None = None,
    log: Callable[[str], None] = lambda line: None,
    workdir: str | None = None,
    describe_bf16_ms: DescribeMs | float | None = None,
) -> list[dict]:
    """Measure the detector on each map size (see the module docstring); one row per size.
    ``workdir``: where the compressed path's database and vector file are written (None: that
    path is not measured, nor any map above :data:`IN_MEMORY_UP_TO`). ``describe_ms``: the
    descriptor's fp32 time (a :class:`DescribeMs`, or one number for both ways);
    ``describe_bf16_ms``: its time with bf16 autocast (where the CPU runs bf16 natively;
    ``--method-set fdnet:bf16=true``), for a second frames/s figure."""
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
    rows = []
    for size in sizes:
        size = int(size)
        streamed = size > IN_MEMORY_UP_TO
        if streamed and workdir is None:
            log(f"  {size:>9,} places: skipped (a map this large is only streamed to a file database)")
            continue
        if streamed:
            _check_room(workdir, size, dim)
        log(f"  {size:>9,} places: building the map ...")
        row = _size_row(MapSource(size, dim, streamed), frames, route, workdir)
        _frames_per_s(row, row["searches"], describe_ms, describe_bf16_ms)
        rows.append(row)
        log(_line(row))
    return rows


def _check_room(workdir: str, size: int, dim: int) -> None:
    """Refuse a streamed map the folder has no room for, before writing any of it: the database
    keeps each vector twice (its row, 32 KB pages: :data:`DISK_BYTES_OVER_VECTOR` over the float
    bytes, and the vector file)."""
    import shutil

    needed = size * (2 * 4 * dim + DISK_BYTES_OVER_VECTOR)
    free = shutil.disk_usage(workdir).free
    if free < needed:
        raise DataError(
            f"{workdir}: a streamed map of {size:,} places needs about {needed / 1e9:.0f} GB of disk there "
            f"(its database and vector file), {free / 1e9:.0f} GB are free; give a smaller --loop-map-size "
            "or free space"
        )


@dataclass
class MapSource:
    """The earlier session's map: ``size`` random unit vectors, held in memory, or
    ``streamed``: made chunk by chunk as they are stored, never all at once (the same vectors)."""

    size: int
    dim: int
    streamed: bool = False
    seed: int = 11

    def array(self, size: int | None = None) -> np.ndarray:
        """The map's first ``size`` places (None: all) in memory."""
        from fdnet.performance.timing import random_map

        return random_map(self.size if size is None else size, self.dim, seed=self.seed, chunk=CHUNK)

    def chunks(self, array: np.ndarray | None = None):
        """The map :data:`CHUNK` places at a time: sliced from ``array`` when it is held, else made."""
        from fdnet.performance.timing import random_map_chunks

        if array is not None:
            return (array[s : s + CHUNK] for s in range(0, len(array), CHUNK))
        return random_map_chunks(self.size, self.dim, seed=self.seed, chunk=CHUNK)


def _size_row(source: MapSource, frames: np.ndarray, route: int, workdir) -> dict:
    """One map size's row: every search the size allows, decided over the same frames."""
    earlier = None if source.streamed else source.array()
    if source.streamed:
        searches = STREAMED_SEARCHES
        # one GEMV over the first chunk, scaled to the map: the map is never in memory at once
        gemv = gemv_ms(source.array(CHUNK)) * source.size / CHUNK
    else:
        searches = ("exact", "index")
        if workdir is not None and source.size >= IVF_FROM:
            searches += ("compressed", "compressed_batched")
        gemv = gemv_ms(earlier)
    row = {"map_size": source.size, "dim": source.dim, "frames": len(frames), "gemv_ms": gemv}
    row["searches"] = list(searches)
    row["streamed"] = source.streamed
    decided = {}
    revisits = np.arange(route, 2 * route)
    truth = source.size + revisits - route
    for search in searches:
        times, decided[search], memory = _decide_route(source, earlier, frames, search, workdir)
        if source.streamed and "RssAnon" in memory:  # (a held map's would count the map itself)
            row[f"{search}_rss_bytes"], row[f"{search}_rss_anon_bytes"] = memory["VmRSS"], memory["RssAnon"]
        matches = np.array(decided[search])[revisits]
        row[f"{search}_ms"] = 1e3 * float(np.median(times[route:]))
        row[f"{search}_mean_ms"] = 1e3 * float(np.mean(times[route:]))
        row[f"{search}_p99_ms"] = 1e3 * float(np.percentile(times[route:], 99))
        row[f"{search}_recall_at_1"] = float(np.mean(np.abs(matches - truth) <= 1))
    # on the revisits, where a decision can be right (the first pass's best places are noise)
    reference = "exact" if "exact" in decided else "compressed"
    for search in searches:
        if search != reference:
            same = np.array(decided[reference])[route:] == np.array(decided[search])[route:]
            row["agreement" if search == "index" else f"{search}_agreement"] = float(np.mean(same))
    row["agreement_reference"] = reference
    return row


def _frames_per_s(row: dict, searches, describe_ms, describe_bf16_ms) -> None:
    """frames/s of the whole loop with the descriptor's time: 1000 / (describe ms + decide ms),
    describing one image a call where frames are decided one at a time and in the command's
    batches where they are searched in blocks."""
    for key, describe in (("describe_ms", describe_ms), ("describe_bf16_ms", describe_bf16_ms)):
        describe = DescribeMs.of(describe)
        if describe is None:
            continue
        row[key] = describe.one
        row[key.replace("_ms", "_batch_ms")] = describe.batch
        label = "fdnet_frames_per_s" if key == "describe_ms" else "fdnet_bf16_frames_per_s"
        for search in searches:
            # (from the mean where frames are searched in blocks: a block's first frame pays for all)
            batched = search == "compressed_batched"
            ms = row[f"{search}_mean_ms" if batched else f"{search}_ms"]
            row[f"{label}_{search}"] = 1e3 / ((describe.batch if batched else describe.one) + ms)
            if search in ("exact", "index"):
                # the command below the compressed path: frames described in batches, decided one by one
                row[f"{label}_{search}_command"] = 1e3 / (describe.batch + ms)


def _decide_route(source: MapSource, earlier, frames: np.ndarray, search: str, workdir) -> tuple[list, list, dict]:
    """(seconds per frame, matched place per frame, the process's memory after the last frame:
    :func:`~fdnet.performance.timing.process_memory`) of a detector deciding ``frames`` after the
    map (``earlier``, or made by ``source`` chunk by chunk): ``exact`` / ``index`` in memory;
    ``compressed`` through a database in a file of ``workdir`` that keeps its vectors in a
    vector file, searched through compressed codes (the codes' training and first encoding
    happen on the first frame, which is not timed)."""
    import tempfile

    from fdnet.matching.database import PlaceDatabase
    from fdnet.matching.index import IndexSettings

    descriptor = StoredVectors(source.dim)
    with tempfile.TemporaryDirectory(prefix="fdnet-loop-map-", dir=workdir) as scratch:
        compressed = search.startswith("compressed")
        if source.streamed:  # the earlier session's process wrote it; this one only opens it
            _store_in_a_process_of_its_own(source, f"{scratch}/map.db")
            db = PlaceDatabase.open(f"{scratch}/map.db", descriptor)
        else:
            db = PlaceDatabase.for_descriptor(
                descriptor,
                index=IndexSettings(compressed_from=IVF_FROM) if compressed else None,
                path=f"{scratch}/map.db" if compressed else MEMORY,
            )
        try:
            if not source.streamed:
                _store(db, source.chunks(earlier))
            release_free_heap()  # the detector's memory, not what earlier parts freed
            ahead = AHEAD if search == "compressed_batched" else 0
            return _decide_on(descriptor, db, frames, search, compressed, ahead)
        finally:
            db.close()  # (before its folder goes: a failed run leaves no open file behind)


def _store(db, chunks) -> None:
    start = 0
    for chunk in chunks:
        db.add(chunk, [f"earlier/{start + i}" for i in range(len(chunk))])
        start += len(chunk)


def _store_map(source: MapSource, path: str) -> None:
    """The earlier session: ``source``'s map stored in a new file database at ``path``."""
    from fdnet.matching.database import PlaceDatabase
    from fdnet.matching.index import IndexSettings

    index = IndexSettings(compressed_from=IVF_FROM)
    with PlaceDatabase.for_descriptor(StoredVectors(source.dim), index=index, path=path) as db:
        _store(db, source.chunks())


def _store_in_a_process_of_its_own(source: MapSource, path: str) -> None:
    """:func:`_store_map` in a new process, so the memory measured after is what a robot's node
    holds over a database written before (10^7 places: the build's heap is not the detector's)."""
    import multiprocessing

    process = multiprocessing.get_context("spawn").Process(target=_store_map, args=(source, path))
    process.start()
    try:
        process.join()
    finally:
        if process.is_alive():  # the benchmark was stopped (Ctrl-C, SIGTERM): the build stops with it
            process.terminate()
            process.join()
    if process.exitcode != 0:
        raise DataError(f"{path}: storing the benchmark's map failed (its process exited with {process.exitcode})")


def _decide_on(descriptor, db, frames: np.ndarray, search: str, compressed: bool, ahead: int):
    """:func:`_decide_route`'s work and result on the database ``db`` (the map already stored); ``ahead``:
    frames come in batches of this many, each frame told the rest of its batch
    (:meth:`LoopClosureDetector.look_ahead`, as ``fdnet loop-closure`` does), or 0: one at a time."""
    from fdnet.decisions.loop_closure import LoopClosureDetector

    detector = LoopClosureDetector(
        descriptor,
        db,
        exclude_last=5,
        rule="margin",
        threshold=0.0,
        sequence_length=DEFAULT_SEQUENCE_LENGTH,
        commit_every=100,
        search="index" if compressed else search,
        compressed_from=IVF_FROM if compressed else None,
    )
    times = []
    with detector:
        for i, vector in enumerate(frames):
            t0 = time.perf_counter()
            if ahead:
                detector.look_ahead(frames[i + 1 : (i // ahead + 1) * ahead])
            detector.process_vector(vector, name=f"traverse/{i}")
            times.append(time.perf_counter() - t0)
        memory = process_memory()
    return times, [d.match for d in detector.decisions], memory


def _line(row: dict) -> str:
    searches, gemv = row["searches"], row["gemv_ms"]
    parts = []
    if "exact" in searches:
        parts.append(
            f"  {row['map_size']:>9,} places: exact {row['exact_ms']:7.2f} ms/frame ({row['exact_ms'] / gemv:5.1f} x "
            f"one {gemv:.2f} ms GEMV)"
        )
        parts.append(
            f"index {row['index_ms']:6.2f} ms/frame (p99 {row['index_p99_ms']:.2f}), same place on the revisits "
            f"{row['agreement']:.3f}"
        )
    else:
        memory = ""
        if all(f"{search}_rss_bytes" in row for search in searches):
            rss = max(row[f"{search}_rss_bytes"] for search in searches) / 2**30
            anon = max(row[f"{search}_rss_anon_bytes"] for search in searches) / 2**30
            memory = f"; RSS {rss:.2f} GB, anonymous {anon:.2f}"
        parts.append(
            f"  {row['map_size']:>9,} places (streamed to the file database; one GEMV over the map {gemv:.0f} ms, "
            f"scaled from its first chunk; no exhaustive search: the map is never in memory{memory})"
        )
    if "compressed" in searches:
        same = "" if row["agreement_reference"] != "exact" else f", same place {row['compressed_agreement']:.3f}"
        parts.append(
            f"compressed {row['compressed_ms']:6.2f} ms/frame (p99 {row['compressed_p99_ms']:.2f}){same}; in batches "
            f"of {AHEAD} described ahead: mean {row['compressed_batched_mean_ms']:.2f} ms/frame against "
            f"{row['compressed_mean_ms']:.2f} one at a time (p99 {row['compressed_batched_p99_ms']:.2f}), same place "
            f"{row['compressed_batched_agreement']:.3f}"
            + ("" if row["agreement_reference"] == "exact" else " as one at a time")
        )
    recall = " ".join(f"{search} {row[f'{search}_recall_at_1']:.3f}" for search in searches)
    parts.append(f"R@1 (+-1 place) {recall}")
    line = ", ".join(parts)
    for key, label, name in (
        ("describe_ms", "fdnet_frames_per_s", " | with FDNet fp32"),
        ("describe_bf16_ms", "fdnet_bf16_frames_per_s", "; bf16"),
    ):
        if key in row:
            fps = " -> ".join(
                f"{row[f'{label}_{search}']:.1f}"
                + (f" ({row[f'{label}_{search}_command']:.1f})" if f"{label}_{search}_command" in row else "")
                for search in searches
            )
            line += (
                f"{name} ({row[key]:.1f} ms an image one a call, {row[key.replace('_ms', '_batch_ms')]:.1f} in "
                f"batches): {fps} frames/s"
            )
    if "describe_ms" in row and "index" in searches:
        line += " (in brackets: described in the command's batches)"
    return line


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
    batched, single, latency, threads = [], [], [], {}
    with tempfile.TemporaryDirectory(prefix="fdnet-loop-") as scratch:
        folder = Path(scratch) / "frames"
        folder.mkdir()
        for path in paths:  # exactly these frames for both paths
            (folder / Path(path).name).symlink_to(Path(path).resolve())
        for _ in range(repeats):
            settings = TraverseSettings(
                Path(scratch) / "events.csv",
                LoopClosureSettings(rule="margin", threshold=math.inf, sequence_length=DEFAULT_SEQUENCE_LENGTH),
            )
            report = run_traverse(folder, descriptor, None, settings)
            batched.append(report.frames_per_second)
            detector = LoopClosureDetector(
                descriptor, None, rule="margin", threshold=math.inf, sequence_length=DEFAULT_SEQUENCE_LENGTH
            )
            with detector:
                t0 = time.perf_counter()
                for path in sorted(folder.iterdir()):
                    t1 = time.perf_counter()
                    detector.process(path)
                    latency.append(time.perf_counter() - t1)
                single.append(len(paths) / (time.perf_counter() - t0))
                for count, frames_on in detector.frame_threads.used.items():
                    threads[count] = threads.get(count, 0) + frames_on
    row = {
        "frames": len(paths),
        "command_frames_per_s": max(batched),
        "process_frames_per_s": max(single),
        "process_latency_ms_median": 1e3 * float(np.median(latency)),
        "process_latency_ms_p99": 1e3 * float(np.percentile(latency, 99)),
        "command_runs": batched,
        "process_runs": single,
        "process_frames_per_thread_count": threads,
    }
    row["ratio"] = row["process_frames_per_s"] / row["command_frames_per_s"]
    log(
        f"  {len(paths)} frames, FDNet {descriptor.input_size[0]}x{descriptor.input_size[1]}: fdnet loop-closure "
        f"{row['command_frames_per_s']:.1f} frames/s (batched); LoopClosureDetector.process one frame at a time "
        f"{row['process_frames_per_s']:.1f} frames/s = {row['ratio']:.2f} x the command, latency per frame median "
        f"{row['process_latency_ms_median']:.1f} ms, p99 {row['process_latency_ms_p99']:.1f} ms (best of {repeats} "
        "alternated runs each); frames described on 1 / more torch threads: "
        + " / ".join(str(threads.get(count, 0)) for count in sorted(set(threads) | {1}))
    )
    return row
