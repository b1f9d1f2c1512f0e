"""The SQLite place database: round trips, refusals, fingerprints, and what several processes
(and a kill -9) may and may not do to one file."""

import os
import random
import signal
import sqlite3
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

import fdnet
from fdnet.descriptors.base import Descriptor, l2_normalize
from fdnet.errors import ConfigError, DataError
from fdnet.matching.database import PlaceDatabase

SRC = str(Path(fdnet.__file__).resolve().parents[1])


class Projection(Descriptor):
    """A tiny dot-product descriptor whose weights are a numpy array (seed = which weights)."""

    name = "projection"

    def __init__(self, seed: int = 0, dim: int = 8):
        self.input_size = (2, 2)
        self.weights = np.random.default_rng(seed).normal(size=(12, dim)).astype(np.float32)

    @property
    def dim(self) -> int:
        return self.weights.shape[1]

    def describe(self, images):
        return l2_normalize(np.asarray(images, np.float32).reshape(len(images), -1) @ self.weights)


class TorchLinear(Descriptor):
    """The same idea with a torch module, as trained methods hold their weights."""

    name = "torch-linear"

    def __init__(self, seed: int = 0):
        import torch

        torch.manual_seed(seed)
        self.input_size = (2, 2)
        self.layers = [torch.nn.Linear(12, 4)]

    @property
    def dim(self) -> int:
        return 4

    def describe(self, images):
        import torch

        with torch.no_grad():
            x = torch.from_numpy(np.asarray(images, np.float32).reshape(len(images), -1))
            return l2_normalize(self.layers[0](x).numpy())


class NegativeL1(Projection):
    name = "negative-l1"
    dot_product_similarity = False

    def similarity(self, queries, references):
        return -np.abs(np.asarray(queries)[:, None] - np.asarray(references)[None]).sum(-1)


def unit(rng, n, d):
    v = rng.normal(size=(n, d)).astype(np.float32)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_add_query_reopen_round_trip(tmp_path, rng):
    v = unit(rng, 50, 8)
    path = tmp_path / "map.db"
    with PlaceDatabase.create(path, Projection()) as db:
        first = db.add(v[:20], [f"img{i}.png" for i in range(20)], positions=[(i, 0) for i in range(20)])
        db.add(
            v[20:],
            [f"img{i}.png" for i in range(20, 50)],
            positions=[(i, 0) for i in range(20, 50)],
            metadata=[{"frame": i} for i in range(20, 50)],
        )
        best = db.query(v[7], k=3)[0]
        assert (first.added, first.places, first.data_version) == (20, 20, 1)
        assert best[0].index == 7 and best[0].name == "img7.png" and best[0].position == (7.0, 0.0)
        before = [m.index for m in db.query(v[33], k=2)[0]]
    with PlaceDatabase.open(path, descriptor=Projection()) as loaded:
        np.testing.assert_array_equal(loaded.vectors, v)
        assert len(loaded) == 50
        assert [m.index for m in loaded.query(v[33], k=2)[0]] == before
        top = loaded.query(v[33], k=1)[0][0]
        assert top.position == (33.0, 0.0) and top.metadata == {"frame": 33}
        assert loaded.info()["data_version"] == 2


def test_a_full_disk_is_an_output_error_and_adds_nothing(tmp_path, rng):
    """SQLite's SQLITE_FULL (here: the file may not grow past its current pages, which is what a
    full disk looks like to SQLite) is an OutputError with ENOSPC, and the add is all-or-nothing."""
    import errno

    from fdnet.errors import OutputError

    with PlaceDatabase.create(tmp_path / "map.db", Projection()) as db:
        db.add(unit(rng, 5, 8), [f"a{i}" for i in range(5)])
        pages = db._conn.execute("PRAGMA page_count").fetchone()[0]
        db._conn.execute(f"PRAGMA max_page_count = {pages}")
        with pytest.raises(OutputError, match="map.db: adding places: database or disk is full") as full:
            db.add(unit(rng, 2000, 8), [f"b{i}" for i in range(2000)])
        assert full.value.errno == errno.ENOSPC and len(db) == 5


def test_an_open_database_sees_places_another_connection_adds(tmp_path, rng):
    v = unit(rng, 6, 8)
    path = tmp_path / "map.db"
    with PlaceDatabase.create(path, Projection(), places=[(v[:3], ["a", "b", "c"])]) as reader:
        assert reader.query(v[0], k=1)[0][0].name == "a"
        with PlaceDatabase.open(path) as writer:
            writer.add(v[3:], ["d", "e", "f"])
        assert reader.query(v[5], k=1)[0][0].name == "f"
        assert reader.names == ["a", "b", "c", "d", "e", "f"]


def test_a_query_searches_the_first_places_it_is_given(rng):
    v = unit(rng, 10, 8)
    db = PlaceDatabase.for_descriptor(Projection())
    db.add(v, [str(i) for i in range(10)])
    matches = db.query(v[9], k=3, searchable=5)[0]
    assert matches and all(m.index < 5 for m in matches)
    assert db.query(v[9], k=1)[0][0].index == 9 and db.query(v[9], k=1, searchable=0) == [[]]


def test_custom_similarity_database(tmp_path, rng):
    v = rng.normal(size=(20, 8)).astype(np.float32)
    path = tmp_path / "l1.db"
    PlaceDatabase.create(path, NegativeL1(), places=[(v, [str(i) for i in range(20)])]).close()
    with PlaceDatabase.open(path, descriptor=NegativeL1()) as db:
        assert db.query(v[4], k=1)[0][0].index == 4
    with PlaceDatabase.open(path) as db, pytest.raises(ConfigError, match="its own similarity"):
        db.query(v[4], k=1)


def test_errors_are_clear(tmp_path, rng):
    db = PlaceDatabase.for_descriptor(Projection())
    with pytest.raises(ConfigError, match="empty"):
        db.query(unit(rng, 1, 8))
    with pytest.raises(ConfigError, match="8-d"):
        db.add(unit(rng, 2, 3), ["a", "b"])
    db.add(unit(rng, 2, 8), ["a", "b"])
    with pytest.raises(ConfigError, match="top-k"):
        db.query(unit(rng, 1, 8), k=0)
    with pytest.raises(ConfigError, match="searchable"):
        db.query(unit(rng, 1, 8), searchable=-1)
    with pytest.raises(DataError, match="no such place database"):
        PlaceDatabase.open(tmp_path / "missing.db")
    assert not (tmp_path / "missing.db").exists()


def test_fingerprint_follows_the_weights_not_the_object():
    assert Projection(seed=0).fingerprint() == Projection(seed=0).fingerprint()
    assert Projection(seed=0).fingerprint() != Projection(seed=1).fingerprint()
    assert Projection(dim=8).fingerprint() != Projection(dim=9).fingerprint()
    assert TorchLinear(seed=0).fingerprint() == TorchLinear(seed=0).fingerprint()
    assert TorchLinear(seed=0).fingerprint() != TorchLinear(seed=1).fingerprint()
    assert len(Projection().fingerprint()) == 64


def test_descriptor_base_does_not_import_torch():
    code = "import sys, fdnet.descriptors.base; print('torch' in sys.modules)"
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, env={**os.environ, "PYTHONPATH": SRC}
    )
    assert out.stdout.strip() == "False"


def test_vectors_from_another_model_are_refused(tmp_path, rng):
    path = tmp_path / "map.db"
    built, retrained = Projection(seed=0), Projection(seed=1)
    PlaceDatabase.create(path, built, places=[(unit(rng, 3, 8), ["a", "b", "c"])]).close()
    with pytest.raises(ConfigError, match="fingerprint mismatch") as refused:
        PlaceDatabase.open(path, descriptor=retrained)
    assert built.fingerprint()[:12] in str(refused.value) and retrained.fingerprint()[:12] in str(refused.value)
    with PlaceDatabase.open(path) as db:
        with pytest.raises(ConfigError, match=retrained.fingerprint()[:12]):
            db.add(unit(rng, 1, 8), ["d"], fingerprint=retrained.fingerprint())
        assert db.add(unit(rng, 1, 8), ["d"], fingerprint=built.fingerprint()).added == 1
        assert len(db) == 4


def test_non_finite_vectors_are_refused_and_nothing_is_added(tmp_path, rng):
    db = PlaceDatabase.create(tmp_path / "map.db", Projection())
    v = unit(rng, 3, 8)
    v[1, 2] = np.nan
    with pytest.raises(DataError, match="map.db: nothing was added: the vector of frame_1.png holds NaN"):
        db.add(v, ["frame_0.png", "frame_1.png", "frame_2.png"])
    assert len(db) == 0
    with pytest.raises(DataError, match="frame_1.png"):
        PlaceDatabase.create(tmp_path / "new.db", Projection(), places=[(v, ["frame_0.png", "frame_1.png", "x"])])
    assert not (tmp_path / "new.db").exists()


def test_all_zero_vectors_are_refused_and_nothing_is_added(tmp_path, rng):
    db = PlaceDatabase.create(tmp_path / "map.db", Projection())
    v = unit(rng, 3, 8)
    zero = v.copy()
    zero[1] = 0.0
    with pytest.raises(DataError, match="the vector of frame_1.png is all zero"):
        db.add(zero, ["frame_0.png", "frame_1.png", "frame_2.png"])
    assert len(db) == 0


def test_duplicates_are_skipped_and_reported_unless_allowed(tmp_path, rng):
    db = PlaceDatabase.create(tmp_path / "map.db", Projection())
    db.add(unit(rng, 2, 8), ["a", "b"])
    result = db.add(unit(rng, 3, 8), ["b", "c", "c"])
    assert (result.added, result.skipped, result.places) == (1, ["b", "c"], 3)
    again = db.add(unit(rng, 2, 8), ["a", "b"], allow_duplicates=True)
    assert (again.added, again.skipped, again.places) == (2, [], 5)
    assert Counter(db.names) == {"a": 2, "b": 2, "c": 1}


def test_create_refuses_an_existing_file_unless_overwrite(tmp_path, rng):
    path = tmp_path / "map.db"
    PlaceDatabase.create(path, Projection(), places=[(unit(rng, 4, 8), list("abcd"))]).close()
    with pytest.raises(ConfigError, match="already exists.*overwrite"):
        PlaceDatabase.create(path, Projection())
    with PlaceDatabase.create(path, Projection(seed=3), overwrite=True, places=[(unit(rng, 2, 8), ["x", "y"])]) as db:
        assert db.names == ["x", "y"] and db.fingerprint == Projection(seed=3).fingerprint()
    foreign = tmp_path / "other.db"
    with sqlite3.connect(foreign) as conn:
        conn.execute("CREATE TABLE photos (id INTEGER)")
    for overwrite in (False, True):
        with pytest.raises(DataError, match="not an fdnet place database.*photos.*refusing to overwrite"):
            PlaceDatabase.create(foreign, Projection(), overwrite=overwrite)
    noise = tmp_path / "noise.db"
    noise.write_bytes(b"\x00\x01" * 600)
    with pytest.raises(DataError, match="not a SQLite file.*refusing to overwrite"):
        PlaceDatabase.create(noise, Projection(), overwrite=True)
    assert noise.read_bytes() == b"\x00\x01" * 600
    empty = tmp_path / "empty.db"
    empty.touch()  # nothing to lose (e.g. made by mktemp): used as it is
    assert len(PlaceDatabase.create(empty, Projection(), places=[(unit(rng, 1, 8), ["a"])])) == 1


@pytest.mark.parametrize(
    "content, message",
    [
        (b"", "empty file"),
        (bytes(range(256)) * 4, "not a SQLite file"),
        ("sqlite-with-other-tables", "SQLite database but not an fdnet place database.*photos"),
    ],
)
def test_a_file_that_is_not_a_place_database_is_a_clear_error(tmp_path, content, message):
    path = tmp_path / "map.db"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        with sqlite3.connect(path) as conn:
            conn.execute("CREATE TABLE photos (id INTEGER)")
    with pytest.raises(DataError, match=message):
        PlaceDatabase.open(path)


def test_a_folder_is_refused_in_one_line_naming_it(tmp_path):
    (tmp_path / "maps").mkdir()
    with pytest.raises(DataError, match=r"maps: is a folder, not a place database file \(e\.g\. .*map\.db\)$"):
        PlaceDatabase.open(tmp_path / "maps")


# ---------------------------------------------------------------------- several processes
WRITER = r"""
import sys
import numpy as np
from fdnet.matching.database import PlaceDatabase

path, tag, batches, size = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
rng = np.random.default_rng([ord(c) for c in tag])
with PlaceDatabase.open(path) as db:
    print("ready", flush=True)
    sys.stdin.readline()  # all writers start together, so their adds overlap
    batch = 0
    while batches == 0 or batch < batches:
        db.add(rng.normal(size=(size, db.dim)).astype(np.float32), [f"{tag}-{batch}-{i}" for i in range(size)])
        batch += 1
        if batch == 1:
            print("added", flush=True)
"""


def start_writer(path, tag, batches, size):
    proc = subprocess.Popen(
        [sys.executable, "-c", WRITER, str(path), tag, str(batches), str(size)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": SRC},
    )
    assert proc.stdout.readline().strip() == "ready"
    return proc


def batches_of(names):
    """{(writer, batch): places stored} from names written as WRITER-BATCH-I."""
    return Counter(name.rsplit("-", 1)[0] for name in names)


def test_concurrent_writers_lose_nothing_and_readers_never_see_half_an_add(tmp_path):
    path, size, batches = tmp_path / "map.db", 5, 15
    PlaceDatabase.create(path, Projection(dim=16)).close()
    with PlaceDatabase.open(path) as reader:
        for round_ in range(3):
            writers = [start_writer(path, f"r{round_}w{w}", batches, size) for w in range(2)]
            for proc in writers:
                proc.stdin.write("go\n")
                proc.stdin.flush()
            while any(proc.poll() is None for proc in writers):
                assert len(reader) % size == 0
                assert set(batches_of(reader.names).values()) <= {size}
            assert [proc.wait() for proc in writers] == [0, 0]
        counts = batches_of(reader.names)
    assert len(counts) == 3 * 2 * batches and set(counts.values()) == {size}


def test_a_writer_killed_at_any_moment_leaves_whole_batches(tmp_path):
    path, size = tmp_path / "map.db", 7
    PlaceDatabase.create(path, Projection(dim=64)).close()
    moments = random.Random(0)
    previous = 0
    for attempt in range(15):
        proc = start_writer(path, f"k{attempt}", 0, size)
        proc.stdin.write("go\n")
        proc.stdin.flush()
        assert proc.stdout.readline().strip() == "added"  # it is in its loop of adds
        try:
            proc.wait(timeout=moments.uniform(0.0, 0.3))
        except subprocess.TimeoutExpired:
            pass
        proc.send_signal(signal.SIGKILL)
        assert proc.wait() == -signal.SIGKILL
        with sqlite3.connect(path) as conn:
            assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        with PlaceDatabase.open(path) as db:
            names = db.names
        assert len(names) % size == 0 and set(batches_of(names).values()) == {size}
        assert len(names) > previous  # the first add was acknowledged, so it must have survived
        previous = len(names)


def test_database_metadata_is_stored_in_one_transaction_and_survives_reopening(tmp_path, rng):
    path = tmp_path / "map.db"
    with PlaceDatabase.create(path, Projection(), places=[(unit(rng, 3, 8), ["a", "b", "c"])]) as db:
        assert db.get_metadata("calibration") is None  # no metadata table yet: nothing stored
        db.set_metadata("calibration", {"rule": "margin", "threshold": 0.25})
        db.set_metadata("calibration", {"rule": "margin", "threshold": 0.5})  # replaced, not duplicated
    with PlaceDatabase.open(path) as db:
        assert db.get_metadata("calibration") == {"rule": "margin", "threshold": 0.5}
        assert len(db) == 3 and db.info()["places"] == 3
        with pytest.raises(ConfigError, match="cannot be stored as JSON"):
            db.set_metadata("bad", {"threshold": float("inf")})
