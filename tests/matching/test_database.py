import numpy as np
import pytest

from fdnet.errors import ConfigError, DataError
from fdnet.matching.database import PlaceDatabase


def unit(rng, n, d):
    v = rng.normal(size=(n, d)).astype(np.float32)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_add_query_save_load_round_trip(tmp_path, rng):
    v = unit(rng, 50, 12)
    db = PlaceDatabase(dim=12, method="test")
    db.add(v[:20], [f"img{i}.png" for i in range(20)], positions=[(i, 0) for i in range(20)])
    db.add(v[20:], [f"img{i}.png" for i in range(20, 50)], positions=[(i, 0) for i in range(20, 50)])
    best = db.query(v[7], k=3)[0]
    assert best[0].index == 7 and best[0].name == "img7.png" and best[0].position == (7.0, 0.0)
    db.save(tmp_path / "db")
    loaded = PlaceDatabase.load(tmp_path / "db")
    np.testing.assert_array_equal(loaded.vectors, db.vectors)
    assert [m.index for m in loaded.query(v[33], k=2)[0]] == [m.index for m in db.query(v[33], k=2)[0]]
    assert loaded.query(v[33], k=1)[0][0].position == (33.0, 0.0)


def test_exclude_last_skips_recent_places(rng):
    v = unit(rng, 10, 4)
    db = PlaceDatabase(dim=4, method="test")
    db.add(v, [str(i) for i in range(10)])
    matches = db.query(v[9], k=3, exclude_last=5)[0]
    assert matches and all(m.index < 5 for m in matches)


def test_custom_similarity_database(rng):
    def neg_l1(a, b):
        return -np.abs(a[:, None] - b[None]).sum(-1)

    v = rng.normal(size=(20, 5)).astype(np.float32)
    db = PlaceDatabase(dim=5, method="sad", dot_product=False, similarity=neg_l1)
    db.add(v, [str(i) for i in range(20)])
    assert db.query(v[4], k=1)[0][0].index == 4


def test_errors_are_clear(tmp_path, rng):
    db = PlaceDatabase(dim=4, method="test")
    with pytest.raises(ConfigError, match="empty"):
        db.query(unit(rng, 1, 4))
    with pytest.raises(ConfigError, match="4-d"):
        db.add(unit(rng, 2, 3), ["a", "b"])
    with pytest.raises(DataError, match="database.json"):
        PlaceDatabase.load(tmp_path / "missing")
