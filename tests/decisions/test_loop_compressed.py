"""Loop closure over compressed codes (``compressed_from``): the same decisions as searching every
place, and a resumed traverse replays them."""

from __future__ import annotations

import numpy as np
import pytest

from fdnet.decisions.loop_closure import LoopClosureDetector
from fdnet.decisions.loop_search import COMPRESSED_FROM
from fdnet.errors import ConfigError
from fdnet.matching.compressed import CompressedIndex
from fdnet.matching.database import PlaceDatabase
from fdnet.performance.loop_benchmark import StoredVectors

DIM, MAP, ROUTE = 32, 5000, 40
SETTINGS = {"exclude_last": 5, "rule": "margin", "threshold": 0.0, "sequence_length": 5}


def unit(v: np.ndarray) -> np.ndarray:
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def earlier_and_route():
    rng = np.random.default_rng(3)
    earlier = unit(rng.standard_normal((MAP, DIM)))
    route = unit(rng.standard_normal((ROUTE, DIM)))
    frames = np.concatenate(
        [unit(route + 0.1 * rng.standard_normal(route.shape)), unit(route + 0.1 * rng.standard_normal(route.shape))]
    )
    return earlier, frames


def decide(db, frames, **settings):
    detector = LoopClosureDetector(StoredVectors(DIM), db, **SETTINGS, **settings)
    with detector:
        for i, v in enumerate(frames):
            detector.process_vector(v, name=f"traverse/{i}")
    return detector


def test_compressed_search_decides_as_every_place():
    earlier, frames = earlier_and_route()
    decided = {}
    for search, extra in (("exact", {}), ("compressed", {"search": "index", "compressed_from": 4096})):
        db = PlaceDatabase.for_descriptor(StoredVectors(DIM))
        db.add(earlier, [f"earlier/{i}" for i in range(MAP)])
        detector = decide(db, frames, **({"search": "exact"} | extra))
        decided[search] = [(d.match, d.accepted) for d in detector.decisions]
        if search == "compressed":
            assert isinstance(detector.candidates.indexed._index, CompressedIndex)
    # on the revisits whose sequence reaches the place seen before (the first pass's best places,
    # and the sequences still made of first-pass frames, are noise): the same place, accepted alike
    exact, compressed = decided["exact"][ROUTE:], decided["compressed"][ROUTE:]
    found = np.abs(np.array([m for m, _ in exact]) - (MAP + np.arange(ROUTE))) <= 1
    assert found.mean() > 0.9
    assert [c for c, f in zip(compressed, found) if f] == [e for e, f in zip(exact, found) if f]


def test_a_resumed_traverse_over_compressed_codes_replays_the_same_decisions(tmp_path):
    earlier, frames = earlier_and_route()
    whole_db = tmp_path / "whole.db"
    with PlaceDatabase.create(whole_db, StoredVectors(DIM)) as db:
        db.add(earlier, [f"earlier/{i}" for i in range(MAP)])
    settings = {"search": "index", "compressed_from": 4096}
    whole = decide(whole_db, frames, **settings)
    cut_db = tmp_path / "cut.db"
    with PlaceDatabase.create(cut_db, StoredVectors(DIM)) as db:
        db.add(earlier, [f"earlier/{i}" for i in range(MAP)])
    decide(cut_db, frames[: ROUTE + 7], **settings)  # a run stopped among the revisits
    resumed = LoopClosureDetector(StoredVectors(DIM), cut_db, **SETTINGS, **settings)
    with resumed:
        resumed.resume(ROUTE + 7)
        for i in range(ROUTE + 7, len(frames)):
            resumed.process_vector(frames[i], name=f"traverse/{i}")
    assert [(d.match, d.accepted) for d in resumed.decisions] == [(d.match, d.accepted) for d in whole.decisions]


def test_compressed_from_is_checked():
    with pytest.raises(ConfigError, match="compressed-from must be a whole number"):
        LoopClosureDetector(StoredVectors(DIM), None, compressed_from=-1, **SETTINGS)


def test_the_map_sample_depends_on_the_map_size_alone_and_is_read_again_after_a_sixteenth():
    from fdnet.decisions.loop_search import IndexedCandidates, sample_count

    assert [sample_count(n) for n in (0, 31, 1000, 1023, 1024, 1087, 1088)] == [0, 31, 992, 992, 1024, 1024, 1088]
    vectors = unit(np.random.default_rng(5).standard_normal((1200, DIM)))

    class Counted(np.ndarray):
        reads = 0

        def __getitem__(self, key):
            if isinstance(key, np.ndarray):
                Counted.reads += 1
            return np.asarray(self).__getitem__(key)

    search = IndexedCandidates(DIM, 5)
    for count, reads in ((1000, 1), (1023, 1), (1024, 2), (1087, 2), (1000, 3)):  # (1000 again: a resumed run)
        ids, rows = search.map_sample(vectors[:count].view(Counted))
        assert Counted.reads == reads
        np.testing.assert_array_equal(ids, np.linspace(0, sample_count(count) - 1, len(ids)).astype(np.int64))
        np.testing.assert_array_equal(rows, vectors[ids])
    informative = np.ones(1000, bool)
    v = vectors[0]
    one_segment = np.zeros(1, np.int64)  # every place in one segment: no levels
    pick = np.linspace(0, len(rows) - 1, 512).astype(np.int64)  # the median's 512 of the sample
    assert search.scale(v, vectors[:1000], informative, one_segment)[1] == pytest.approx(
        float(np.median(rows[pick] @ v))
    )
    informative[ids[::2]] = False  # a gate's uninformative places: the median of the sample's others
    others = rows[1::2]
    pick = np.linspace(0, len(others) - 1, 496).astype(np.int64)
    assert search.scale(v, vectors[:1000], informative, one_segment)[1] == pytest.approx(
        float(np.median(others[pick] @ v))
    )
    informative[ids] = False
    assert search.scale(v, vectors[:1000], informative, one_segment)[1] == 0.0  # no informative place in the sample


@pytest.mark.parametrize("all_threads_from", [COMPRESSED_FROM, 0])
def test_frames_described_ahead_are_searched_in_one_call_and_decide_the_same(monkeypatch, all_threads_from):
    import faiss

    import fdnet.decisions.loop_search as loop_search

    # 0: every block of frames is searched on all of faiss's threads (the default from 2 x 10^6 places)
    monkeypatch.setattr(loop_search, "BLOCK_ON_ALL_THREADS_FROM", all_threads_from)
    earlier, frames = earlier_and_route()
    calls, threads = [], []
    real = CompressedIndex.search

    def counted(self, q, *a, **k):
        calls.append(len(q))
        threads.append(faiss.omp_get_max_threads())
        return real(self, q, *a, **k)

    monkeypatch.setattr(CompressedIndex, "search", counted)
    decided = {}
    for batch in (None, 16, 7):  # one frame at a time (a robot), or batches described ahead (the command)
        calls.clear()
        db = PlaceDatabase.for_descriptor(StoredVectors(DIM))
        db.add(earlier, [f"earlier/{i}" for i in range(MAP)])
        with LoopClosureDetector(StoredVectors(DIM), db, **SETTINGS, search="index", compressed_from=4096) as detector:
            for i, v in enumerate(frames):
                if batch:
                    detector.look_ahead(frames[i + 1 : (i // batch + 1) * batch])
                # the second pass is a new recording: a block starts again there
                detector.process_vector(v, name=f"traverse/{i}", new_segment=i == ROUTE)
        decided[batch] = [(d.match, d.accepted, d.score) for d in detector.decisions]
        searched = list(calls)
        assert sum(searched) == len(frames)  # every frame's neighbours were found once
        if batch is None:
            assert set(searched) == {1}
        else:  # blocks of L - 1 = 4 frames, fewer where a batch or the first pass ends
            assert max(searched) == 4 and len(searched) < len(frames) / 2
        # one frame on one thread; a block on all of them where the map is large enough
        expected = [1 if n == 1 or all_threads_from else faiss.omp_get_max_threads() for n in searched]
        assert threads == expected
        threads.clear()
    assert decided[16] == decided[None] and decided[7] == decided[None]


def test_look_ahead_refuses_vectors_of_another_length():
    from fdnet.errors import DataError

    with LoopClosureDetector(StoredVectors(DIM), None, **SETTINGS) as detector:
        detector.look_ahead([])  # nothing ahead: fine
        with pytest.raises(
            DataError, match=rf"look_ahead: expected \(frames, {DIM}\) vectors .* shape \(2, {DIM + 1}\)"
        ):
            detector.look_ahead(np.zeros((2, DIM + 1)))
