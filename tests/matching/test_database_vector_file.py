"""A place database from ``compressed_from`` places: vectors in ``map.db.vectors`` (not in memory),
queries through compressed codes with an exact re-rank, and an add killed with kill -9 leaves the
previous state (the file is cut back to the committed row count)."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fdnet.matching.compressed import VectorFile
from fdnet.matching.database import PlaceDatabase
from fdnet.matching.database.vector_store import COMPRESSED_FLOOR, CompressedPlaces, vector_file_path
from fdnet.matching.file_rows import FileRows
from fdnet.matching.index import IndexSettings
from fdnet.performance.loop_benchmark import StoredVectors

SRC = str(Path(__file__).resolve().parents[2] / "src")
DIM, BATCH, BATCHES = 32, 1000, 6
SMALL = IndexSettings(compressed_from=COMPRESSED_FLOOR)


def unit(v: np.ndarray) -> np.ndarray:
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def batch(b: int) -> tuple[np.ndarray, list[str]]:
    """The b-th batch of places, the same in every process."""
    return unit(np.random.default_rng(b).standard_normal((BATCH, DIM))), [f"b{b}/{i}" for i in range(BATCH)]


def file_rows(path) -> int:
    return os.path.getsize(vector_file_path(path)) // (4 * DIM)


def test_above_the_size_the_vectors_are_in_the_file_and_queries_find_the_exact_best(tmp_path):
    path = tmp_path / "map.db"
    exact = PlaceDatabase.for_descriptor(StoredVectors(DIM))  # in memory: the exact search of today
    with PlaceDatabase.create(path, StoredVectors(DIM), index=SMALL) as db:
        for b in range(BATCHES):
            vectors, names = batch(b)
            db.add(vectors, names)
            exact.add(vectors, names)
            assert vector_file_path(path).exists() == ((b + 1) * BATCH >= COMPRESSED_FLOOR)
    assert file_rows(path) == BATCH * BATCHES
    with sqlite3.connect(path) as conn:
        assert conn.execute("SELECT rows FROM fdnet_vector_file").fetchone()[0] == BATCH * BATCHES
    rng = np.random.default_rng(7)
    targets = rng.choice(BATCH * BATCHES, 40, replace=False)
    stored = exact.vectors
    queries = unit(stored[targets] + 0.05 * rng.standard_normal((40, DIM)))
    with PlaceDatabase.open(path) as db:
        found = db.query(queries, k=3)
        want = exact.query(queries, k=3)
        assert [m[0].index for m in found] == [m[0].index for m in want] == list(targets)
        # exact scores on top of the codes
        assert np.allclose([m[0].score for m in found], [m[0].score for m in want], atol=1e-5)
        # excluding the last places still holds
        last = db.query(queries[:5], k=2, searchable=BATCH * BATCHES - 100)
        assert all(m.index < BATCH * BATCHES - 100 for row in last for m in row)
        assert isinstance(db.build_index(), CompressedPlaces)
        # no float vector in memory: the map reads them from the file
        rows = db.place_map().vectors
        assert isinstance(rows, FileRows) and rows.in_memory == 0
        assert np.array_equal(rows[[3, 4100, 17]], stored[[3, 4100, 17]])
        assert np.array_equal(rows[10:20], stored[10:20])


def test_below_the_size_nothing_changes(tmp_path):
    path = tmp_path / "map.db"
    with PlaceDatabase.create(path, StoredVectors(DIM)) as db:  # default size: 2,000,000 places
        for b in range(BATCHES):
            db.add(*batch(b))
        assert not isinstance(db.place_map().vectors, FileRows)
        assert not vector_file_path(path).exists()
        with sqlite3.connect(path) as conn:
            tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        assert "fdnet_vector_file" not in tables


# ---------------------------------------------------------------------- killed adds
WRITER = r"""
import os, signal, sys
import numpy as np
from fdnet.matching import compressed
from fdnet.matching.database import PlaceDatabase
from fdnet.matching.index import IndexSettings
from fdnet.performance.loop_benchmark import StoredVectors

path, kill_at, dim, size, batches = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
syncs = [0]
real_sync = compressed.VectorFile.sync

def sync(self):
    # the rows are written, their count not committed yet: the worst moment to die
    syncs[0] += 1
    if syncs[0] == kill_at:
        os.kill(os.getpid(), signal.SIGKILL)
    real_sync(self)

compressed.VectorFile.sync = sync
if not os.path.exists(path):
    PlaceDatabase.create(path, StoredVectors(dim), index=IndexSettings(compressed_from=4096)).close()
with PlaceDatabase.open(path) as db:
    for b in range(batches):
        names = [f"b{b}/{i}" for i in range(size)]
        if db.existing_names(names[:1]):
            continue  # stored by an earlier run
        v = np.random.default_rng(b).standard_normal((size, dim))
        db.add((v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32), names)
        print("added", b, flush=True)
"""


def write(path, kill_at: int = 0) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", WRITER, str(path), str(kill_at), str(DIM), str(BATCH), str(BATCHES)],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": SRC},
        timeout=300,
    )


def test_an_add_killed_after_writing_its_vectors_leaves_the_previous_state_and_a_re_add_ends_equal(tmp_path):
    whole = tmp_path / "whole.db"
    assert write(whole).returncode == 0
    cut = tmp_path / "cut.db"
    # the 5th batch reaches the size (5000 places); the 6th add is killed after its rows were
    # written to the vector file, before the transaction that counts them committed
    killed = write(cut, kill_at=2)
    assert killed.returncode == -signal.SIGKILL
    assert killed.stdout.split("\n")[-2] == "added 4"
    assert file_rows(cut) == 6 * BATCH  # the killed add's rows are in the file...
    with sqlite3.connect(cut) as conn:
        assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        assert conn.execute("SELECT rows FROM fdnet_vector_file").fetchone()[0] == 5 * BATCH
    with PlaceDatabase.open(cut) as db:  # ...but not in the database: a reader reads the committed rows
        assert len(db.names) == 5 * BATCH
        assert db.query(batch(0)[0][:2], k=1)[0][0].index == 0
        assert file_rows(cut) == 6 * BATCH  # opened read-only: nothing cut, no write lock taken
    resumed = write(cut)  # the next add cuts the killed add's rows off, then appends the same ones
    assert resumed.returncode == 0 and resumed.stdout.split() == ["added", "5"]
    assert vector_file_path(cut).read_bytes() == vector_file_path(whole).read_bytes()
    with PlaceDatabase.open(cut) as a, PlaceDatabase.open(whole) as b:
        assert a.names == b.names and np.array_equal(a.vectors, b.vectors)
        queries = batch(3)[0][:10]
        assert [m[0].index for m in a.query(queries)] == [m[0].index for m in b.query(queries)]


@pytest.mark.parametrize("kill_at", [1])
def test_the_add_that_reaches_the_size_killed_leaves_no_vector_file_rows(tmp_path, kill_at):
    """The first add above the size copies every stored place into the file; killed before its
    commit, the database is below the size again and the next add copies them anew."""
    path = tmp_path / "map.db"
    killed = write(path, kill_at=kill_at)
    assert killed.returncode == -signal.SIGKILL
    assert file_rows(path) == 5 * BATCH
    with PlaceDatabase.open(path) as db:
        assert len(db) == 4 * BATCH
    assert write(path).returncode == 0
    with PlaceDatabase.open(path) as db:
        assert np.array_equal(VectorFile(vector_file_path(path), DIM, BATCHES * BATCH).read(0, len(db)), db.vectors)


def test_a_new_database_file_packs_512_float_places_into_large_pages(tmp_path):
    # SQLite's default 4 KB pages hold one 2 KB vector row each and leave half of every page empty
    from fdnet.matching.database.storage import PAGE_SIZE

    path = tmp_path / "map.db"
    db = PlaceDatabase.for_descriptor(StoredVectors(512), path=str(path))
    vectors = unit(np.random.default_rng(0).standard_normal((3000, 512)))
    db.add(vectors, [f"frames/{i:07d}.png" for i in range(len(vectors))])
    db.close()
    conn = sqlite3.connect(path)
    try:
        page_size, pages = (
            conn.execute("PRAGMA page_size").fetchone()[0],
            conn.execute("PRAGMA page_count").fetchone()[0],
        )
    finally:
        conn.close()
    assert page_size == PAGE_SIZE == 32768
    assert page_size * pages / len(vectors) < 2400  # a 2048-byte vector, its name and the row's overhead
    with PlaceDatabase.open(str(path)) as again:
        assert np.array_equal(again.vectors, vectors)
