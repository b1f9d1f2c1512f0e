"""Indexed search at scale: every index kind against exact search, saved and
reloaded without pickle, and the place database's derived index cache and chunked adds."""

from __future__ import annotations

import numpy as np
import pytest

from fdnet.descriptors.base import Descriptor, l2_normalize
from fdnet.errors import ConfigError, DataError
from fdnet.matching.database import PlaceDatabase
from fdnet.matching.index import (
    INDEX_KINDS,
    IndexSettings,
    VectorIndex,
    ivf_lists_for,
    parse_index_settings,
)
from fdnet.matching.similarity import top_k


def unit(rng, n, d):
    v = rng.normal(size=(n, d)).astype(np.float32)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def revisits(rng, refs, n, noise=0.5):
    """Queries near stored vectors: a stored vector plus noise of norm ``noise``."""
    source = rng.choice(len(refs), n, replace=False)
    q = refs[source] + noise / np.sqrt(refs.shape[1]) * rng.normal(size=(n, refs.shape[1])).astype(np.float32)
    return source, l2_normalize(q)


@pytest.mark.parametrize("kind", INDEX_KINDS)
def test_every_kind_finds_revisited_places_and_survives_save_and_load(tmp_path, rng, kind):
    refs = unit(rng, 20000, 32)
    index = VectorIndex(32, IndexSettings(kind=kind, hnsw_neighbors=16, pq_bytes=8, refine=4 if kind == "ivfpq" else 0))
    for start in range(0, len(refs), 5000):
        index.add(refs[start : start + 5000])
    index.build()
    source, queries = revisits(rng, refs, 200)
    exact = top_k(queries, refs, 1)[0][:, 0]
    idx, scores = index.search(queries, 5)
    assert idx.shape == (200, 5) and (scores[:, :-1] >= scores[:, 1:] - 1e-6).all()
    assert (idx[:, 0] == exact).mean() >= 0.95
    assert index.memory_bytes() > 0 and len(index) == 20000
    path = tmp_path / f"{kind}.index"
    index.save(path, metadata={"note": "test"})
    header = VectorIndex.read_header(path)
    assert header["kind"] == kind and header["count"] == 20000 and header["metadata"] == {"note": "test"}
    loaded = VectorIndex.load(path)
    assert loaded.settings == index.settings
    np.testing.assert_array_equal(loaded.search(queries, 5)[0], idx)
    if kind != "ivfpq":
        np.testing.assert_array_equal(loaded.reconstruct_all()[:10], refs[:10])


def test_search_settings_can_change_on_a_saved_index_build_settings_cannot(tmp_path, rng):
    index = VectorIndex(16, IndexSettings(kind="ivf", ivf_lists=20))
    index.add(unit(rng, 2000, 16))
    index.save(tmp_path / "i")
    loaded = VectorIndex.load(tmp_path / "i", search={"ivf_probe": 20})
    assert loaded.settings.ivf_probe == 20 and loaded.describe()["ivf_lists"] == 20
    with pytest.raises(ConfigError, match="fixed when the index is built"):
        VectorIndex.load(tmp_path / "i", search={"ivf_lists": 5})


def test_damaged_or_foreign_index_files_are_data_errors(tmp_path, rng):
    (tmp_path / "pickle").write_bytes(b"\x80\x04K\x01.")
    with pytest.raises(DataError, match="not an fdnet index file"):
        VectorIndex.load(tmp_path / "pickle")
    with pytest.raises(DataError, match="not found"):
        VectorIndex.load(tmp_path / "missing")
    index = VectorIndex(8)
    index.add(unit(rng, 10, 8))
    index.save(tmp_path / "ok")
    data = (tmp_path / "ok").read_bytes()
    (tmp_path / "cut").write_bytes(data[:-40])
    with pytest.raises(DataError, match="cannot be read"):
        VectorIndex.load(tmp_path / "cut")


def test_index_settings_from_flags():
    s = parse_index_settings("ivfpq", ["pq_bytes=16", "refine=8"])
    assert (s.kind, s.pq_bytes, s.refine) == ("ivfpq", 16, 8)
    for bad in (["pq_bytes"], ["lists=4"], ["ivf_probe=many"], ["ivf_probe=-1"]):
        with pytest.raises(ConfigError, match="--index-set"):
            parse_index_settings("ivf", bad)
    with pytest.raises(ConfigError, match="must divide"):
        VectorIndex(30, IndexSettings(kind="ivfpq", pq_bytes=4))
    assert ivf_lists_for(3000, IndexSettings()) == 76  # the old rule for small maps
    assert ivf_lists_for(1_000_000, IndexSettings()) == 1000  # sqrt(N) for large ones


class Unit(Descriptor):
    name = "unit"

    def __init__(self):
        self.input_size = (1, 1)

    @property
    def dim(self) -> int:
        return 16

    def describe(self, images):  # pragma: no cover - vectors are given directly
        raise NotImplementedError


def test_database_takes_chunks_in_one_transaction(tmp_path, rng):
    d = Unit()
    db = PlaceDatabase.create(tmp_path / "map.db", d, method_options={})
    v = unit(rng, 30, 16)
    names = [f"p{i}" for i in range(30)]
    result = db.add_batches([(v[:10], names[:10]), (v[10:20], names[10:20])], fingerprint=d.fingerprint())
    assert (result.added, result.places, result.data_version) == (20, 20, 1)
    bad = v[20:].copy()
    bad[5, 0] = np.nan
    with pytest.raises(DataError, match="the vector of p25 holds NaN"):
        db.add_batches([(v[20:25], names[20:25]), (bad, names[20:])])
    assert len(db) == 20  # the good first chunk was rolled back too
    again = db.add_batches([(v[:5], names[:5]), (v[20:], names[20:])])
    assert again.added == 10 and again.skipped == names[:5] and again.data_version == 2
    np.testing.assert_array_equal(db.vectors, np.concatenate([v[:20], v[20:]]))
    db.close()


def test_database_index_cache_is_derived_current_and_reused(tmp_path, rng):
    d = Unit()
    v = unit(rng, 12000, 16)
    names = [f"p{i}" for i in range(len(v))]
    path = tmp_path / "map.db"
    db = PlaceDatabase.create(
        path,
        d,
        method_options={},
        index=IndexSettings(kind="ivf", ivf_probe=8),
        places=[(v[:6000], names[:6000]), (v[6000:], names[6000:])],
    )
    assert db.build_index() is not None
    cache = db.index_cache_path
    assert cache.is_file() and VectorIndex.read_header(cache)["metadata"]["last_id"] == 12000
    queries = v[:50]
    first = db.query(queries, k=3)
    db.close()
    # a new process (here: a new handle) loads the cache; its answers are the same
    with PlaceDatabase.open(path) as again:
        assert [[m.index for m in row] for row in again.query(queries, k=3)] == [
            [m.index for m in row] for row in first
        ]
        assert again._index_cache.places == 12000
        # places added later are added to the loaded index, never missing from answers
        more = unit(rng, 5, 16)
        again.add(more, [f"new{i}" for i in range(5)])
        hits = again.query(more, k=1)
        assert [row[0].name for row in hits] == [f"new{i}" for i in range(5)]
    # a cache from another database is ignored, not trusted
    other = PlaceDatabase.create(
        tmp_path / "other.db", d, method_options={}, index=IndexSettings(kind="ivf"), places=[(v[:100], names[:100])]
    )
    cache.replace(other.index_cache_path)
    assert other.query(v[:3], k=1)[0][0].index == 0 and other._index_cache.places == 0
    other.close()
    # flat databases have no cache: rebuilding is a copy
    with PlaceDatabase.create(tmp_path / "flat.db", d, method_options={}, places=[(v[:10], names[:10])]) as flat:
        assert flat.index_cache_path is None


def test_a_restored_backup_never_loads_the_index_cache_of_places_it_does_not_hold(tmp_path, rng):
    """A copy restored from a backup shares the database's id, its place ids and (after other
    adds) its count: the cache is identified by the places' content, so it is rebuilt."""
    import shutil

    d = Unit()
    v = unit(rng, 80, 16)
    path = tmp_path / "map.db"
    with PlaceDatabase.create(
        path,
        d,
        method_options={},
        index=IndexSettings(kind="hnsw", hnsw_neighbors=8),
        places=[(v[:60], [f"p{i}" for i in range(60)])],
    ):
        pass
    shutil.copyfile(path, tmp_path / "backup.db")
    with PlaceDatabase.open(path) as db:
        db.add(v[60:70], [f"a{i}" for i in range(10)])
        db.build_index()
        assert VectorIndex.read_header(db.index_cache_path)["metadata"]["last_id"] == 70
    shutil.copyfile(tmp_path / "backup.db", path)
    for extra in ("-wal", "-shm"):
        (tmp_path / f"map.db{extra}").unlink(missing_ok=True)
    with PlaceDatabase.open(path) as db:
        db.add(v[70:80], [f"b{i}" for i in range(10)])
        hits = db.query(v[70:80], k=1)
    assert [row[0].name for row in hits] == [f"b{i}" for i in range(10)]
    assert all(abs(row[0].score - 1.0) < 1e-5 for row in hits)
