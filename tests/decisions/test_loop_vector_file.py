"""Loop closure over a database that keeps its vectors in a file (``compressed_from``): the map reads
them from there (not held in memory), decides as searching every place in memory, and a traverse
killed with kill -9 while storing a frame resumes to the decisions of an uninterrupted run."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np

from fdnet.decisions.loop_closure import LoopClosureDetector
from fdnet.matching.compressed import CompressedIndex
from fdnet.matching.database import PlaceDatabase
from fdnet.matching.database.vector_store import COMPRESSED_FLOOR, vector_file_path
from fdnet.matching.file_rows import FileRows
from fdnet.matching.index import IndexSettings
from fdnet.performance.loop_benchmark import StoredVectors
from tests.decisions.test_loop_compressed import DIM, MAP, ROUTE, SETTINGS, earlier_and_route

SRC = str(Path(__file__).resolve().parents[2] / "src")


def database(path, earlier, index=None):
    db = (
        PlaceDatabase.create(path, StoredVectors(DIM), index=index)
        if path
        else PlaceDatabase.for_descriptor(StoredVectors(DIM))
    )
    db.add(earlier, [f"earlier/{i}" for i in range(MAP)])
    return db


def decisions(detector) -> list[tuple[int, bool]]:
    return [(d.match, d.accepted) for d in detector.decisions]


def test_the_map_reads_its_vectors_from_the_file_and_decides_as_every_place(tmp_path):
    earlier, frames = earlier_and_route()
    with LoopClosureDetector(StoredVectors(DIM), database(None, earlier), search="exact", **SETTINGS) as exact:
        for i, v in enumerate(frames):
            exact.process_vector(v, name=f"traverse/{i}")
    path = tmp_path / "map.db"
    database(path, earlier, IndexSettings(compressed_from=COMPRESSED_FLOOR)).close()
    with LoopClosureDetector(StoredVectors(DIM), path, **SETTINGS) as detector:
        assert isinstance(detector.map.vectors, FileRows)
        for i, v in enumerate(frames):
            detector.process_vector(v, name=f"traverse/{i}")
            assert detector.map.vectors.in_memory == 0  # each frame, once stored, is read from the file
        assert isinstance(detector.candidates.indexed._index, CompressedIndex)
    assert os.path.getsize(vector_file_path(path)) == (MAP + len(frames)) * 4 * DIM
    # on the revisits whose sequence reaches the place seen before: the same place, accepted alike
    want, got = decisions(exact)[ROUTE:], decisions(detector)[ROUTE:]
    found = np.abs(np.array([m for m, _ in want]) - (MAP + np.arange(ROUTE))) <= 1
    assert found.mean() > 0.9
    assert [g for g, f in zip(got, found) if f] == [w for w, f in zip(want, found) if f]


def test_a_detector_that_makes_its_database_keeps_the_vectors_in_a_file_from_compressed_from(tmp_path):
    earlier, frames = earlier_and_route()
    path = tmp_path / "new.db"
    LoopClosureDetector(StoredVectors(DIM), path, compressed_from=COMPRESSED_FLOOR, **SETTINGS).close()
    with PlaceDatabase.open(path) as db:
        assert db.index_settings.compressed_from == COMPRESSED_FLOOR
        db.add(earlier, [f"earlier/{i}" for i in range(MAP)])
    assert vector_file_path(path).exists()
    with LoopClosureDetector(StoredVectors(DIM), path, compressed_from=COMPRESSED_FLOOR, **SETTINGS) as detector:
        for i, v in enumerate(frames[:3]):
            detector.process_vector(v, name=f"traverse/{i}")
        assert isinstance(detector.map.vectors, FileRows) and detector.map.vectors.in_memory == 0


TRAVERSE = r"""
import os, signal, sys
import numpy as np
from fdnet.decisions.loop_closure import LoopClosureDetector
from fdnet.matching import compressed
from fdnet.performance.loop_benchmark import StoredVectors

path, frames_file, kill_at = sys.argv[1], sys.argv[2], int(sys.argv[3])
syncs = [0]
real_sync = compressed.VectorFile.sync

def sync(self):
    # the frame's row is in the vector file, the transaction that counts it not committed yet
    syncs[0] += 1
    if syncs[0] == kill_at:
        os.kill(os.getpid(), signal.SIGKILL)
    real_sync(self)

compressed.VectorFile.sync = sync
frames = np.load(frames_file)
detector = LoopClosureDetector(StoredVectors(frames.shape[1]), path, exclude_last=5, rule="margin",
                               threshold=0.0, sequence_length=5)
with detector:
    for i, v in enumerate(frames):
        detector.process_vector(v, name=f"traverse/{i}")
"""


def test_a_traverse_killed_while_storing_a_frame_resumes_to_the_uninterrupted_decisions(tmp_path):
    earlier, frames = earlier_and_route()
    small = IndexSettings(compressed_from=COMPRESSED_FLOOR)
    whole = tmp_path / "whole.db"
    database(whole, earlier, small).close()
    with LoopClosureDetector(StoredVectors(DIM), whole, **SETTINGS) as uninterrupted:
        for i, v in enumerate(frames):
            uninterrupted.process_vector(v, name=f"traverse/{i}")
    cut = tmp_path / "cut.db"
    database(cut, earlier, small).close()
    np.save(tmp_path / "frames.npy", frames)
    stop = ROUTE + 7  # among the revisits: frame 47 is killed while it is being stored
    proc = subprocess.run(
        [sys.executable, "-c", TRAVERSE, str(cut), str(tmp_path / "frames.npy"), str(stop + 1)],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": SRC},
        timeout=300,
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    row = 4 * DIM
    assert os.path.getsize(vector_file_path(cut)) == (MAP + stop + 1) * row  # the killed frame's row
    with LoopClosureDetector(StoredVectors(DIM), cut, **SETTINGS) as resumed:
        assert resumed.places == MAP + stop  # ... is not a stored place: read-only until the next
        assert os.path.getsize(vector_file_path(cut)) == (MAP + stop + 1) * row  # add, which cuts it off
        resumed.resume(stop)
        for i in range(stop, len(frames)):
            resumed.process_vector(frames[i], name=f"traverse/{i}")
    assert decisions(resumed) == decisions(uninterrupted)
    assert vector_file_path(cut).read_bytes() == vector_file_path(whole).read_bytes()


def test_the_detector_leaves_its_codes_in_the_database_cache_and_the_next_run_loads_them(tmp_path):
    from fdnet.matching.database.codes_cache import codes_cache_path

    earlier, frames = earlier_and_route()
    path = tmp_path / "map.db"
    database(path, earlier, IndexSettings(compressed_from=COMPRESSED_FLOOR)).close()
    runs = []
    for run in range(2):  # the same route twice, each run a new session of the database
        with LoopClosureDetector(StoredVectors(DIM), path, **SETTINGS) as detector:
            for i, v in enumerate(frames):
                detector.process_vector(v, name=f"run{run}/{i}")
            runs.append((detector.candidates.indexed._index, decisions(detector)))
        if run == 0:
            cached = codes_cache_path(path).read_bytes()
    first, second = runs
    assert first[0].trainings == 1 and first[0].trained_on == MAP  # trained on the database's places ...
    assert second[0].trainings == 0 and second[0].trained_on == MAP  # ... and loaded, not trained again
    assert codes_cache_path(path).read_bytes() == cached  # a loaded cache is left as it was
    # the second run's map holds the first run's frames: its first pass finds their places (either pass)
    found, at = np.array([m for m, _ in second[1][5:ROUTE]]), MAP + np.arange(5, ROUTE)
    assert np.mean(np.minimum(np.abs(found - at), np.abs(found - at - ROUTE)) <= 1) > 0.8


def test_a_resume_finds_the_codes_it_started_from_though_another_process_extended_the_cache(tmp_path):
    from fdnet.matching.compressed_file import read_header
    from fdnet.matching.database.codes_cache import codes_cache_path
    from tests.decisions.test_loop_compressed import unit

    earlier, frames = earlier_and_route()
    later = unit(np.random.default_rng(9).standard_normal((1200, DIM)))  # a later session's places
    stop = ROUTE + 7

    def make(path):
        with PlaceDatabase.create(
            path, StoredVectors(DIM), index=IndexSettings(compressed_from=COMPRESSED_FLOOR)
        ) as db:
            db.add(earlier, [f"earlier/{i}" for i in range(MAP)])
            db.build_index()  # codes trained on MAP places, cached
            db.add(later, [f"later/{i}" for i in range(len(later))])  # the cache still holds MAP
        return path

    def run(path, until, resume=0):
        with LoopClosureDetector(StoredVectors(DIM), path, **SETTINGS) as detector:
            if resume:
                detector.resume(resume)
            for i in range(resume, until):
                detector.process_vector(frames[i], name=f"traverse/{i}")
        return detector

    whole = run(make(tmp_path / "whole.db"), len(frames))
    cut = make(tmp_path / "cut.db")
    run(cut, stop)  # killed after frame stop - 1 (its frames are stored)
    with PlaceDatabase.open(cut) as db:  # a query in between extends the cache to every stored place
        db.build_index()
    assert read_header(codes_cache_path(cut))["count"] == MAP + len(later) + stop
    resumed = run(cut, len(frames), resume=stop)
    assert resumed.candidates.indexed._index.trained_on == whole.candidates.indexed._index.trained_on == MAP
    assert decisions(resumed) == decisions(whole)


def test_a_full_disk_while_the_detector_writes_its_codes_loses_no_decision_and_leaves_no_cache(tmp_path, monkeypatch):
    import errno

    from fdnet.matching import compressed_file
    from fdnet.matching.database.codes_cache import codes_cache_path

    earlier, frames = earlier_and_route()
    path = tmp_path / "map.db"
    database(path, earlier, IndexSettings(compressed_from=COMPRESSED_FLOOR)).close()
    real_open = open

    def full_disk_open(file, mode="r", *args, **kwargs):  # the codes file's temporary: no space left
        if "w" in mode and ".fdnet-codes" in str(file):
            raise OSError(errno.ENOSPC, "No space left on device", str(file))
        return real_open(file, mode, *args, **kwargs)

    monkeypatch.setattr(compressed_file, "open", full_disk_open, raising=False)
    with LoopClosureDetector(StoredVectors(DIM), path, **SETTINGS) as full:
        for i, v in enumerate(frames):
            full.process_vector(v, name=f"traverse/{i}")
    assert not codes_cache_path(path).exists() and not list(tmp_path.glob(".map.db.fdnet-codes*"))
    monkeypatch.undo()
    with PlaceDatabase.open(path) as db:  # every frame was stored
        assert len(db) == MAP + len(frames)
    whole = tmp_path / "whole.db"
    database(whole, earlier, IndexSettings(compressed_from=COMPRESSED_FLOOR)).close()
    with LoopClosureDetector(StoredVectors(DIM), whole, **SETTINGS) as spacious:
        for i, v in enumerate(frames):
            spacious.process_vector(v, name=f"traverse/{i}")
    assert decisions(full) == decisions(spacious) and codes_cache_path(whole).exists()
