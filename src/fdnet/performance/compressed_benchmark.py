"""Place queries over maps too large for memory: compressed codes in RAM, float vectors on disk
(:mod:`fdnet.matching.compressed`), 10^5 to 10^7 places, against exhaustive float search.

The map is built streamed to a :class:`~fdnet.matching.compressed.VectorFile` (never all vectors
in memory at once): distractors drawn from a Gaussian with the mean and covariance of real FDNet
vectors (unit length, like the descriptor's), and in the middle of the map the real reference
traverses (Nordland summer, Gardens Point day-left). The queries are the same places seen again
(Nordland winter; Gardens Point day-right and night-right), one at a time, as a robot would.

Per size the row gives: resident memory after the queries (the process's RSS, and its anonymous
part: mapped pages of the vector file are page cache the kernel takes back under pressure), bytes
per place in memory (the codes) and on disk (the vector file), the time to build (write the file,
train, encode), ms per query (median and p99; codes scanned, short list re-ranked from the file),
the same against one matrix-vector product over a slice of the map held in memory, scaled to the
map (the exhaustive search's floor), measured in the same run, and the share of queries whose
decision agrees with exhaustive float search over the whole file: the same best place, and the
same closure decision by the margin rule (best minus second best over the median margin).
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Callable

import numpy as np

from fdnet.decisions.loop_traverse import DEFAULT_SEQUENCE_LENGTH

#: rows drawn, written and searched per chunk while building and while searching exhaustively
CHUNK = 131_072
#: queries searched in one call for the blocked timing: loop closure's block at its default
#: sequence length (:attr:`fdnet.decisions.loop_search.IndexedCandidates.block`)
BLOCK = DEFAULT_SEQUENCE_LENGTH - 1


HEADLINE = (
    "\nCompressed place search: maps of distractors drawn like the real FDNet vectors given, the real "
    "reference traverses in the middle; codes in memory, vectors in a file, short list re-ranked exactly; "
    "queries one at a time against exhaustive float search over the file "
    "(fdnet.performance.compressed_benchmark)"
)


def real_vectors(sources) -> tuple[np.ndarray, np.ndarray, list]:
    """(references, queries, per query the index of its place among the references) from FDNet
    vectors in .npz files (``v``; ``cond``: 0 for the reference traverse, others for the same
    places seen again; ``ids``: the place of each)."""
    from fdnet.errors import DataError

    refs, queries, truth = [], [], []
    offset = 0
    for source in sources:
        try:
            with np.load(source) as data:
                vectors, cond, ids = data["v"].astype(np.float32), data["cond"], data["ids"]
        except (OSError, ValueError, KeyError) as exc:
            raise DataError(f"{source}: not FDNet vectors with v, cond and ids ({exc})") from exc
        ref = cond == 0
        where = {int(i): k for k, i in enumerate(ids[ref])}
        refs.append(vectors[ref])
        for c in sorted(set(cond.tolist()) - {0}):
            queries.append(vectors[cond == c])
            truth += [offset + where.get(int(i), -1) for i in ids[cond == c]]
        offset += int(ref.sum())
    return np.concatenate(refs), np.concatenate(queries), truth


def distractors(sample: np.ndarray, count: int, seed: int):
    """``count`` unit vectors from a Gaussian with ``sample``'s mean and covariance, in chunks."""
    mean = sample.mean(0)
    cov = np.cov(sample, rowvar=False) + 1e-6 * np.eye(sample.shape[1])
    factor = np.linalg.cholesky(cov).astype(np.float32)
    rng = np.random.default_rng(seed)
    for start in range(0, count, CHUNK):
        z = rng.standard_normal((min(CHUNK, count - start), sample.shape[1]), dtype=np.float32)
        v = z @ factor.T + mean
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        yield v


def build_file(path: Path, size: int, refs: np.ndarray, sample: np.ndarray, seed: int = 11) -> int:
    """Write a map of ``size`` places to ``path``: distractors with ``refs`` in the middle; returns
    the first reference's place."""
    from fdnet.matching.compressed import VectorFile

    path.unlink(missing_ok=True)
    at = max(0, (size - len(refs)) // 2)
    with VectorFile(path, refs.shape[1]) as out:
        for chunk in distractors(sample, size - len(refs), seed):
            if len(out) <= at < len(out) + len(chunk):
                cut = at - len(out)
                out.extend(chunk[:cut])
                out.extend(refs)
                chunk = chunk[cut:]
            out.extend(chunk)
        if len(out) <= at:
            out.extend(refs)
        out.sync()
    return at


def exhaustive_top2(path: Path, dim: int, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact best two places and scores of every query over the whole file, streamed in chunks."""
    from fdnet.matching.compressed import VectorFile

    ids = np.full((len(queries), 2), -1, np.int64)
    scores = np.full((len(queries), 2), -np.inf, np.float32)
    with VectorFile(path, dim) as file:
        for start in range(0, len(file), CHUNK):
            block = queries @ file.read(start, start + CHUNK).T  # (Q, rows): each query's row contiguous
            top = np.argpartition(-block, min(1, block.shape[1] - 1), axis=1)[:, :2]  # each query's best two
            cand_ids = np.concatenate([ids, top + start], 1)
            cand = np.concatenate([scores, np.take_along_axis(block, top, 1)], 1)
            order = _best2(cand_ids, cand)
            ids = np.take_along_axis(cand_ids, order, 1)
            scores = np.take_along_axis(cand, order, 1)
    return ids, scores


def _best2(ids: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """Per row, the positions of the two best scores, ties to the lower id."""
    return np.stack([np.lexsort((i, -s))[:2] for i, s in zip(ids, scores)])


def compressed_rows(
    sizes,
    workdir: str | os.PathLike,
    sources,
    describe_ms: float | None = None,
    settings=None,
    log: Callable[[str], None] = lambda line: None,
) -> list[dict]:
    """Measure each map size (see the module docstring) on maps made from the FDNet vectors of
    ``sources`` (.npz files); the vector file of each is deleted after."""
    from fdnet.matching.compressed import CompressedIndex, VectorFile
    from fdnet.performance.timing import process_memory

    refs, queries, truth = real_vectors(sources)
    sample = np.concatenate([refs, queries])
    rows = []
    for size in sizes:
        path = Path(workdir) / f"compressed-map-{size}.f32"
        log(f"  {size:>11,} places: writing the map ...")
        t0 = time.perf_counter()
        at = build_file(path, int(size), refs, sample)
        written = time.perf_counter() - t0
        reference_ids, reference_scores = exhaustive_top2(path, refs.shape[1], queries)
        try:
            with VectorFile(path, refs.shape[1]) as file:
                index = CompressedIndex(refs.shape[1], settings)
                t1 = time.perf_counter()
                index.sync(file)
                encoded = time.perf_counter() - t1
                row = _query_rows(index, file, queries, reference_ids, reference_scores)
                row.update(process_memory())
                row.update(
                    map_size=int(size),
                    build_s=written + encoded,
                    write_s=written,
                    encode_s=encoded,
                    memory_bytes_per_place=index.memory_bytes() / size,
                    disk_bytes_per_place=4 * refs.shape[1],
                    index=index.describe(),
                    gemv_ms=_gemv_ms_scaled(file, size),
                )
                found = np.array(truth) >= 0
                places = at + np.array(truth)
                row["recall_at_1"] = float(np.mean(np.abs(row.pop("ids") - places)[found] <= 2))
                row["exhaustive_recall_at_1"] = float(np.mean(np.abs(reference_ids[:, 0] - places)[found] <= 2))
        finally:
            path.unlink(missing_ok=True)
        if describe_ms is not None:
            row["describe_ms"] = describe_ms
            row["fdnet_frames_per_s"] = 1e3 / (describe_ms + row["query_ms_median"])
        rows.append(row)
        log(_line(row))
    return rows


def _query_rows(index, file, queries, reference_ids, reference_scores) -> dict:
    from fdnet.matching.index import one_faiss_thread

    times, ids, scores = [], [], []
    with one_faiss_thread():  # one query at a time, as a robot: OpenMP's start costs more than it saves
        for q in queries:
            t0 = time.perf_counter()
            i, s = index.search(q[None], 2, file)
            times.append(time.perf_counter() - t0)
            ids.append(i[0])
            scores.append(s[0])
        # as loop closure searches a block of frames described ahead: one call for BLOCK queries
        blocked, blocked_ms = _in_blocks(index, file, queries)
    # the same blocks on all of faiss's threads (each takes some of a block's queries)
    blocked_all, blocked_all_ms = _in_blocks(index, file, queries)
    ids, scores = np.array(ids), np.array(scores)
    same_place = ids[:, 0] == reference_ids[:, 0]
    margin = reference_scores[:, 0] - reference_scores[:, 1]
    threshold = float(np.median(margin))
    closure_ref = margin >= threshold
    closure = (scores[:, 0] - scores[:, 1]) >= threshold
    agree = (closure == closure_ref) & (same_place | ~closure_ref)
    return {
        "queries": len(queries),
        "query_ms_median": 1e3 * float(np.median(times)),
        "query_ms_p99": 1e3 * float(np.percentile(times, 99)),
        "query_ms_in_blocks": blocked_ms,
        "blocks_answer_alike": bool(np.array_equal(np.concatenate(blocked), ids)),
        "query_ms_in_blocks_all_threads": blocked_all_ms,
        "blocks_all_threads_answer_alike": bool(np.array_equal(np.concatenate(blocked_all), ids)),
        "same_place": float(same_place.mean()),
        "decision_agreement": float(agree.mean()),
        "margin_threshold": threshold,
        "ids": ids[:, 0],
    }


def _in_blocks(index, file, queries) -> tuple[list, float]:
    """(each block's place ids, ms a query) of ``queries`` searched :data:`BLOCK` at a call."""
    t0 = time.perf_counter()
    blocked = [index.search(queries[s : s + BLOCK], 2, file)[0] for s in range(0, len(queries), BLOCK)]
    return blocked, 1e3 * (time.perf_counter() - t0) / len(queries)


def _gemv_ms_scaled(file, size: int, rows: int = 100_000) -> float:
    """ms of one matrix-vector product over ``rows`` places held in memory (one thread), scaled to
    ``size`` places: what the exhaustive search costs at the least."""
    from fdnet.performance.timing import gemv_ms

    block = file.read(0, min(rows, size))
    return gemv_ms(block) * size / len(block)


def _line(row: dict) -> str:
    gb = 1 << 30
    fps = "" if "fdnet_frames_per_s" not in row else f", with FDNet {row['fdnet_frames_per_s']:.1f} frames/s"
    return (
        f"  {row['map_size']:>11,} places: RSS {row['VmRSS'] / gb:.2f} GB (anonymous {row['RssAnon'] / gb:.2f}), "
        f"{row['memory_bytes_per_place']:.1f} B/place in memory, {row['disk_bytes_per_place']} on disk, built in "
        f"{row['build_s']:.0f} s; query {row['query_ms_median']:.2f} ms (p99 {row['query_ms_p99']:.2f}) = "
        f"{row['query_ms_median'] / row['gemv_ms']:.4f} x exhaustive GEMV ({row['gemv_ms']:.0f} ms), in blocks of "
        f"{BLOCK} {row['query_ms_in_blocks']:.2f} ms a query (same answers: {row['blocks_answer_alike']}), on all "
        f"threads {row['query_ms_in_blocks_all_threads']:.2f} "
        f"({row['query_ms_in_blocks'] / row['query_ms_in_blocks_all_threads']:.2f}x; "
        f"same answers: {row['blocks_all_threads_answer_alike']}); same place "
        f"{row['same_place']:.3f}, same decision {row['decision_agreement']:.3f}, "
        f"R@1 (+-2 places) {row['recall_at_1']:.3f}, exhaustive {row['exhaustive_recall_at_1']:.3f}{fps}"
    )
