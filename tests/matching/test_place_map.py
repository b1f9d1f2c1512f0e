"""The one in-memory map of places (fdnet.matching.place_map), and the one sequence scorer: each
defined once and used by the place database, the loop-closure detector and matching."""

import ast
import json
from pathlib import Path

import numpy as np
import pytest

from fdnet.errors import ConfigError
from fdnet.matching.place_map import CategoryColumn, GrowingArray, OptionalFloats, PlaceMap, StringColumn

SRC = Path(__file__).resolve().parents[2] / "src" / "fdnet"


def test_a_map_grows_truncates_and_reads_loop_columns():
    m = PlaceMap(3)
    m.extend(
        ["a", "b"],
        [(0, 1), None],
        [json.dumps({"timestamp": 1.5, "session": "s1"}), None],
        np.eye(3, dtype=np.float32)[:2],
    )
    assert len(m) == 2 and "a" in m and "c" not in m
    assert m.loop_column("timestamp") == [1.5, None] and m.loop_column("session") == ["s1", None]
    m.append(np.ones(3, np.float32), "c", (2.0, 3.0), {"uninformative": True, "segment_start": True, "still": True})
    assert "c" in m and m.metadata(2)["uninformative"] is True
    assert m.loop_column("informative").view().tolist() == [True, True, False]
    assert m.loop_column("still").view().tolist() == [False, False, True]
    assert m.loop_column("segment_start").view().tolist() == [False, False, True]
    np.testing.assert_array_equal(m.vectors.view()[2], np.ones(3))
    m.truncate(1)
    assert m.names == ["a"] and "b" not in m and len(m.vectors) == 1
    assert m.loop_column("timestamp") == [1.5] and len(m.loop_column("informative")) == 1
    assert m.positions == [(0.0, 1.0)]


def test_growing_array_keeps_rows_across_growth():
    g = GrowingArray(2)
    rows = np.arange(5000, dtype=np.float32).reshape(2500, 2)
    for row in rows[:1500]:
        g.append(row)
    g.extend(rows[1500:])
    np.testing.assert_array_equal(g.view(), rows)


def test_a_string_column_holds_any_name_or_none_and_reads_like_a_list():
    odd = "frames/\udcff\udcfe caf\u00e9 \U0001f600.png"  # undecodable bytes as os.fsdecode gives them
    values = ["a.png", None, "", odd, "b" * 3000]
    column = StringColumn(values)
    assert len(column) == 5 and column == values and list(column) == values
    assert column[3] == odd and column[-1] == "b" * 3000 and column[1] is None and column[2] == ""
    assert column[1:4] == values[1:4] and column[::-2] == values[::-2]
    with pytest.raises(IndexError):
        column[5]
    column.extend(f"n{i}" for i in range(2000))  # past the first capacity
    copy = StringColumn()
    copy.extend(column)  # one column into another copies its buffers
    assert copy == column and copy[2004] == "n1999"
    copy.append(None)
    del copy[3:]
    assert copy == values[:3] and column[3] == odd
    copy.append("again")
    assert copy == [*values[:3], "again"]
    with pytest.raises(TypeError):
        del copy[1]
    # membership through the sorted hashes, then through the strings added since, then after a cut
    assert column.contains(odd) and column.contains("n0") and not column.contains("n2000")
    assert not column.contains("b" * 2999) and not column.contains("None")
    column.extend(["n2000", odd + "x"])
    assert column.contains("n2000") and column.contains(odd + "x")
    column.truncate(4)
    assert column.contains(odd) and not column.contains("n0") and not column.contains("n2000")
    column.UNSORTED = 3  # past it the index is sorted again with the new strings
    column.extend([f"m{i}" for i in range(10)])
    assert all(column.contains(f"m{i}") for i in range(10)) and not column.contains("m10")


def test_the_database_hands_its_map_over_and_reads_it_again_when_asked(tmp_path):
    from fdnet.decisions.loop_closure import LoopClosureDetector
    from fdnet.descriptors.classic import RawThumbnail
    from fdnet.matching.database import PlaceDatabase

    d = RawThumbnail()
    rng = np.random.default_rng(0)
    v = rng.standard_normal((4, d.dim)).astype(np.float32)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    names = [f"p{i}" for i in range(4)]
    with PlaceDatabase.create(tmp_path / "map.db", d) as db:
        db.add(v, names, metadata=[{"timestamp": float(i)} for i in range(4)])
        handed = db.place_map()
        assert handed.names == names and len(db._map) == 0  # held once: the database let it go
        np.testing.assert_array_equal(handed.vectors.view(), v)
        handed.append(v[0], "extra", None, None)
        assert len(db) == 4 and db.names == names  # the handed map is the caller's; the file's is read again
        assert [m[0].name for m in db.query(v[[2]], k=1)] == ["p2"]
        with LoopClosureDetector(d, db, rule="margin", threshold=2.0) as detector:
            assert isinstance(detector.map, PlaceMap) and detector.map.names == names
            np.testing.assert_array_equal(detector.map.vectors.view(), v)
            assert detector._times == [0.0, 1.0, 2.0, 3.0]
            np.testing.assert_array_equal(detector._times.array(3), [0.0, 1.0, 2.0])


def test_a_string_column_keeps_no_offsets_until_a_byte_and_widens_them_past_four_gigabytes():
    column = StringColumn([None, "", None])
    assert column._ends is None and column == [None, "", None] and column[1] == ""
    other = StringColumn(["ab", None])
    column.extend(other)  # a column with offsets into one without
    assert column._ends.view().dtype == np.uint32 and column == [None, "", None, "ab", None]
    empty = StringColumn([None])
    other.extend(empty)  # and one without into one with
    assert other == ["ab", None, None] and other.contains("ab") and not other.contains("")
    column.NARROW_UP_TO = 5  # (4 GB in production: the test's buffer passes 5 bytes)
    column.extend(["cdef", "g"])
    assert column._ends.view().dtype == np.int64
    assert column == [None, "", None, "ab", None, "cdef", "g"] and column.contains("cdef")
    column.truncate(4)
    assert column == [None, "", None, "ab"] and not column.contains("cdef")


def test_a_string_column_finds_strings_whose_hashes_collide(monkeypatch):
    import fdnet.matching.place_map as place_map

    monkeypatch.setattr(place_map, "_hash32", lambda value: 7)  # every string one hash
    column = StringColumn(["a", None, "b"])
    assert column.contains("a") and column.contains("b") and not column.contains("c")
    column.extend(["c"])  # after the index was sorted
    assert column.contains("c") and not column.contains("d")


def test_a_category_column_codes_repeated_strings():
    column = CategoryColumn(["s1", None, "s1", "s2"])
    assert column == ["s1", None, "s1", "s2"] and column[-1] == "s2" and column[1:3] == [None, "s1"]
    assert column._codes.view().dtype == np.int32 and column._values == ["s1", "s2"]
    del column[2:]
    column.append("s3")
    assert list(column) == ["s1", None, "s3"] and len(column) == 3
    with pytest.raises(IndexError):
        column[3]


def test_a_map_for_loop_closure_only_keeps_its_loop_columns_not_the_metadata_text():
    m = PlaceMap(None)
    m.extend(["a", "b"], [None, None], [json.dumps({"timestamp": 1.0, "session": "s"}), None])
    m.keep_loop_columns_only()
    assert m.metadata(0) is None and m.metadata_text._ends is None and len(m.metadata_text) == 2
    m.append(None, "c", None, {"timestamp": 3.0, "still": True, "session": "s"})
    assert m.loop_column("timestamp") == [1.0, None, 3.0] and m.loop_column("session") == ["s", None, "s"]
    assert m.loop_column("still").view().tolist() == [False, False, True] and m.metadata(2) is None
    m.truncate(1)
    assert len(m.metadata_text) == 1 and m.loop_column("session") == ["s"]


def test_optional_floats_hold_nothing_until_a_value_and_read_like_a_list():
    times = OptionalFloats()
    times.extend([None] * 5)
    assert times._values is None and times == [None] * 5 and not times.all_present()
    assert np.isnan(times.array()).all() and times.array().shape == (5,)
    times.append(2.5)
    assert times[5] == 2.5 and times[-1] == 2.5 and times[0] is None and times[4:] == [None, 2.5]
    times.truncate(0)
    times.extend([1, 2.0])
    assert times == [1.0, 2.0] and times.all_present() and times.array().dtype == np.float64
    positions = OptionalFloats(2, [None, (1, 2), np.array([3.0, 4.0, 9.0])])
    assert positions == [None, (1.0, 2.0), (3.0, 4.0)] and positions.array().shape == (3, 2)
    del positions[1:]
    assert positions == [None] and not positions.all_present()
    del positions[0:]
    positions.append((5, 6))
    assert positions.all_present() and positions.array().tolist() == [[5.0, 6.0]]
    with pytest.raises(IndexError):
        positions[1]
    with pytest.raises(TypeError):
        del positions[0:1]
    with pytest.raises(ConfigError, match=r"a position needs 2 values \(x, y\), got \(5.0,\)"):
        positions.append((5.0,))
    assert OptionalFloats(None, [1.0, 2.0, 3.0])[::-1] == [3.0, 2.0, 1.0]
    assert OptionalFloats(None, [1.0, None, 3.0])[::2] == [1.0, 3.0]


def _definitions(name: str) -> list[str]:
    found = []
    for path in SRC.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.ClassDef)) and node.name == name:
                found.append(str(path.relative_to(SRC)))
    return found


@pytest.mark.parametrize(
    "name, module",
    [
        ("PlaceMap", "matching/place_map.py"),
        ("GrowingArray", "matching/place_map.py"),
        ("online_sequence_scores", "matching/sequence.py"),
        ("sequence_similarity", "matching/sequence.py"),
    ],
)
def test_one_map_and_one_sequence_scorer(name, module):
    assert _definitions(name) == [module]


def test_every_sequence_score_goes_through_the_one_scorer():
    """The matrix version, the exhaustive loop search and the indexed one call
    online_sequence_scores; nothing else sums a sequence (no second loop over velocities)."""
    callers = sorted(
        str(p.relative_to(SRC))
        for p in SRC.rglob("*.py")
        if "online_sequence_scores(" in p.read_text() and p.name != "sequence.py"
    )
    assert callers == ["decisions/loop_candidates.py", "decisions/loop_search.py"]
    # the mean along a sequence's line (the sum over its frames divided by the frames counted)
    means = sorted(str(p.relative_to(SRC)) for p in SRC.rglob("*.py") if "total / np.maximum(" in p.read_text())
    assert means == ["matching/sequence.py"]


def _unit_rows(count: int, dim: int, seed: int) -> np.ndarray:
    rows = np.random.default_rng(seed).normal(size=(count, dim)).astype(np.float32)
    return rows / np.linalg.norm(rows, axis=1, keepdims=True)


def test_the_one_batch_search_ranks_exhaustively_by_sequences_and_through_an_index():
    from fdnet.matching import VectorIndex, sequence_similarity, similarity_matrix, top_k_of_matrix
    from fdnet.matching.index import IndexSettings
    from fdnet.matching.place_map import PlaceMap

    refs, queries = _unit_rows(40, 8, 0), _unit_rows(12, 8, 1)
    names = [f"r{i}" for i in range(40)]
    exact = PlaceMap.of_vectors(names, refs)
    idx, scores = exact.search(queries, 5)
    want_idx, want_scores = top_k_of_matrix(queries @ refs.T, 5)
    np.testing.assert_array_equal(idx, want_idx)
    np.testing.assert_allclose(scores, want_scores, atol=1e-6)
    # sequences: the same numbers as the full sequence-similarity matrix
    idx, scores = exact.search(queries, 3, sequence_length=4)
    want_idx, want_scores = top_k_of_matrix(sequence_similarity(similarity_matrix(queries, refs), 4), 3)
    np.testing.assert_array_equal(idx, want_idx)
    np.testing.assert_allclose(scores, want_scores, atol=1e-6)
    # through an index: the same ranking; the last places left out when fewer are searchable
    index = VectorIndex(8, IndexSettings(kind="flat"))
    index.add(refs)
    indexed = PlaceMap.of_vectors(names, index=index)
    np.testing.assert_array_equal(indexed.search(queries, 5)[0], exact.search(queries, 5)[0])
    got, _ = indexed.search(queries, 5, searchable=30)
    np.testing.assert_array_equal(got, exact.search(queries, 5, searchable=30)[0])
    assert (got < 30).all()
    # nothing searchable: an empty row per query; more asked than there are places: all of them
    assert exact.search(queries, 5, searchable=0)[0].shape == (12, 0)
    assert exact.search(queries, 100)[0].shape == (12, 40)
    with pytest.raises(ConfigError, match="sequence similarity needs every place"):
        indexed.search(queries, 3, sequence_length=4)


def test_match_and_the_database_query_are_one_search(tmp_path):
    """``fdnet match``'s ranking and a place database's query are the same call on a map, so the
    same vectors give the same places and scores."""
    from fdnet.matching import PlaceDatabase
    from fdnet.matching.place_map import PlaceMap

    class Vectors:
        name, dim, dot_product_similarity, similarity_ceiling = "vectors", 8, True, 1.0
        similarity = None

        def fingerprint(self):
            return "vectors-8"

        def settings(self):
            return {}

    refs, queries = _unit_rows(30, 8, 2), _unit_rows(6, 8, 3)
    names = [f"r{i}" for i in range(30)]
    ranked = PlaceMap.of_vectors(names, refs).search(queries, 4)
    with PlaceDatabase.create(tmp_path / "map.db", Vectors()) as db:
        db.add(refs, names)
        answers = db.query(queries, k=4)
    np.testing.assert_array_equal([[m.index for m in row] for row in answers], ranked[0])
    np.testing.assert_allclose([[m.score for m in row] for row in answers], ranked[1], atol=1e-6)


def test_a_name_is_looked_up_in_the_hashes_own_dtype(monkeypatch):
    # a Python int against the uint32 hashes made numpy convert every hash on each lookup: 10 ms
    # a frame at 10^7 places, twice a frame in the loop detector
    column = StringColumn([f"place/{i}" for i in range(1000)])
    assert column.contains("place/5")  # the index is built
    seen = []
    real = np.searchsorted

    def spy(array, value, *args, **kwargs):
        seen.append((np.asarray(array).dtype, np.asarray(value).dtype))
        return real(array, value, *args, **kwargs)

    monkeypatch.setattr(np, "searchsorted", spy)
    assert column.contains("place/999") and not column.contains("place/1000")
    assert seen and all(array == value for array, value in seen), seen
