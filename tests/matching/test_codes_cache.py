"""A large place database's compressed codes cached beside it (``map.db.fdnet-codes``): loaded by
later processes instead of trained again, extended after adds, never trusted when it does not
match (another database, fewer or other rows, a damaged file); and the vector file read without
a write lock (opened read-only at the committed count)."""

from __future__ import annotations

import logging
import os
import signal
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fdnet.matching import compressed
from fdnet.matching.database import PlaceDatabase
from fdnet.matching.database import store as store_module
from fdnet.matching.database.codes_cache import codes_cache_path
from fdnet.matching.database.vector_store import COMPRESSED_FLOOR
from fdnet.matching.index import IndexSettings
from fdnet.performance.loop_benchmark import StoredVectors

SRC = str(Path(__file__).resolve().parents[2] / "src")
DIM, BATCH = 32, 1000
SMALL = IndexSettings(compressed_from=COMPRESSED_FLOOR)


def batch(b: int, n: int = BATCH) -> tuple[np.ndarray, list[str]]:
    v = np.random.default_rng(b).standard_normal((n, DIM))
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32), [f"b{b}/{i}" for i in range(n)]


@pytest.fixture
def trainings(monkeypatch) -> list[int]:
    """How many times any compressed index trained its codes (counted, not timed)."""
    count = [0]
    real = compressed.CompressedIndex._train

    def train(self, vectors, n):
        count[0] += 1
        real(self, vectors, n)

    monkeypatch.setattr(compressed.CompressedIndex, "_train", train)
    return count


def make(path, batches: int = 5) -> np.ndarray:
    with PlaceDatabase.create(path, StoredVectors(DIM), index=SMALL) as db:
        for b in range(batches):
            db.add(*batch(b))
    return np.concatenate([batch(b)[0] for b in range(batches)])


def best(db, stored: np.ndarray, targets) -> list[int]:
    queries = stored[targets] + 0.02 * np.random.default_rng(9).standard_normal((len(targets), DIM))
    return [m[0].index for m in db.query(queries.astype(np.float32), k=1)]


TARGETS = [0, 17, 2500, 4999]


def test_a_second_open_loads_the_codes_instead_of_training_them(tmp_path, trainings):
    path = tmp_path / "map.db"
    stored = make(path)
    with PlaceDatabase.open(path) as db:
        assert best(db, stored, TARGETS) == TARGETS
    assert trainings[0] == 1 and codes_cache_path(path).is_file()
    with PlaceDatabase.open(path) as db:
        assert best(db, stored, TARGETS) == TARGETS
        assert db.build_index().describe()["count"] == 5 * BATCH
    assert trainings[0] == 1  # loaded, not trained


def test_after_an_add_the_cached_codes_are_extended_not_used_as_they_are(tmp_path, trainings):
    path = tmp_path / "map.db"
    stored = make(path)
    with PlaceDatabase.open(path) as db:
        db.build_index()
    written = codes_cache_path(path).stat().st_mtime_ns
    with PlaceDatabase.open(path) as db:
        db.add(*batch(5, 1500))
    stored = np.concatenate([stored, batch(5, 1500)[0]])
    with PlaceDatabase.open(path) as db:
        assert best(db, stored, [*TARGETS, 5000, 6499]) == [*TARGETS, 5000, 6499]  # the new places are found
        assert db.build_index().describe()["count"] == 6500
    assert trainings[0] == 1  # the cache's 5000 codes plus 1500 encoded (below the growth that retrains)
    assert codes_cache_path(path).stat().st_mtime_ns != written  # grown by >= 1000: written again
    with PlaceDatabase.open(path) as db:
        assert db.build_index().describe()["count"] == 6500
    assert trainings[0] == 1


@pytest.mark.parametrize("damage", ["truncated", "flipped", "empty", "foreign"])
def test_a_damaged_or_foreign_cache_is_rebuilt_not_trusted(tmp_path, trainings, caplog, damage):
    path = tmp_path / "map.db"
    stored = make(path)
    with PlaceDatabase.open(path) as db:
        db.build_index()
    cache = codes_cache_path(path)
    data = cache.read_bytes()
    if damage == "truncated":
        cache.write_bytes(data[: len(data) // 2])
    elif damage == "flipped":  # one byte of the codes: the checksum catches it before faiss reads it
        cache.write_bytes(data[:1000] + bytes([data[1000] ^ 0xFF]) + data[1001:])
    elif damage == "empty":
        cache.write_bytes(b"")
    else:  # another database's cache (same rows, another database_id)
        other = tmp_path / "other.db"
        make(other)
        with PlaceDatabase.open(other) as db:
            db.build_index()
        cache.write_bytes(codes_cache_path(other).read_bytes())
    trainings[0] = 0
    with caplog.at_level(logging.INFO, logger="fdnet.matching.database.codes_cache"):
        with PlaceDatabase.open(path) as db:
            assert best(db, stored, TARGETS) == TARGETS
    assert trainings[0] == 1  # built again
    if damage != "foreign":
        assert any(r.levelno == logging.WARNING and str(cache) in r.getMessage() for r in caplog.records)
    trainings[0] = 0
    with PlaceDatabase.open(path) as db:  # and the cache written again is good
        assert best(db, stored, TARGETS) == TARGETS
    assert trainings[0] == 0


def test_a_cache_of_other_rows_is_not_used(tmp_path, trainings):
    """Same database, same count, other vectors in the file (e.g. a backup restored): the rows'
    digest differs, so the codes are built again."""
    path = tmp_path / "map.db"
    stored = make(path)
    with PlaceDatabase.open(path) as db:
        db.build_index()
    vectors = path.with_name("map.db.vectors")
    data = bytearray(vectors.read_bytes())
    data[-4 * DIM :] = np.ones(DIM, np.float32).tobytes()  # the last place's row, changed
    vectors.write_bytes(bytes(data))
    trainings[0] = 0
    with PlaceDatabase.open(path) as db:
        assert best(db, stored, TARGETS[:3]) == TARGETS[:3]
    assert trainings[0] == 1


def test_a_reader_needs_no_write_lock(tmp_path):
    path = tmp_path / "map.db"
    stored = make(path)
    with PlaceDatabase.open(path) as db:
        db.build_index()
    with sqlite3.connect(path, timeout=0.1) as writer:  # another process in the middle of an add
        writer.execute("BEGIN IMMEDIATE")
        with PlaceDatabase.open(path) as db:
            assert best(db, stored, TARGETS) == TARGETS
        writer.execute("ROLLBACK")


def test_a_read_only_database_above_the_size_searches_its_vector_file(tmp_path, monkeypatch, trainings):
    path = tmp_path / "map.db"
    stored = make(path)
    with PlaceDatabase.open(path) as db:
        db.build_index()
    size = path.with_name("map.db.vectors").stat().st_size
    monkeypatch.setattr(store_module, "read_only_storage", lambda p: True)
    trainings[0] = 0
    with PlaceDatabase.open(path) as db:
        assert db.read_only
        assert best(db, stored, TARGETS) == TARGETS
        assert db.build_index().describe()["vector_file"].endswith("map.db.vectors")
    assert trainings[0] == 0  # the cache, read
    assert path.with_name("map.db.vectors").stat().st_size == size


KILLED_SAVE = r"""
import os, signal, sys
import numpy as np
from fdnet.matching.database import PlaceDatabase

def replace(src, dst):  # the new cache is written and fsynced, not renamed yet: die here
    os.kill(os.getpid(), signal.SIGKILL)

os.replace = replace  # the atomic write's rename (fdnet.io.atomic_path)
with PlaceDatabase.open(sys.argv[1]) as db:
    db.build_index()
"""


def test_a_writer_killed_while_saving_the_cache_leaves_the_old_one(tmp_path, trainings):
    path = tmp_path / "map.db"
    stored = make(path)
    with PlaceDatabase.open(path) as db:
        db.build_index()
    old = codes_cache_path(path).read_bytes()
    with PlaceDatabase.open(path) as db:
        db.add(*batch(5, 1500))  # grown enough that the next process writes the cache again
    proc = subprocess.run(
        [sys.executable, "-c", KILLED_SAVE, str(path)],
        capture_output=True,
        env={**os.environ, "PYTHONPATH": SRC},
        timeout=300,
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert codes_cache_path(path).read_bytes() == old  # the old cache, whole
    (left,) = tmp_path.glob(".map.db.fdnet-codes.*.tmp")  # and the killed writer's file
    os.utime(left, (1, 1))  # long abandoned
    trainings[0] = 0
    stored = np.concatenate([stored, batch(5, 1500)[0]])
    with PlaceDatabase.open(path) as db:
        assert best(db, stored, [*TARGETS, 6499]) == [*TARGETS, 6499]
        assert db.build_index().describe()["count"] == 6500
    assert trainings[0] == 0  # the old cache loaded and extended
    assert not left.exists()  # removed when the cache was written again
    assert codes_cache_path(path).read_bytes() != old
