"""fdnet.tasks.database: build, add, query and info as library calls (no CLI)."""

import csv
import io
import logging

import numpy as np
import pytest

from fdnet.descriptors.pipeline import PipelineSettings
from fdnet.errors import ConfigError
from fdnet.matching.database import PlaceDatabase
from fdnet.tasks.database import (
    AddRequest,
    BuildRequest,
    QueryRequest,
    add_to_database,
    build_database,
    database_info,
    query_database,
)

from conftest import write_random_places

QUIET = PipelineSettings(progress=False)


def make_route(folder, n=5, seed=0):
    """n distinct random-texture places; the same seed gives the same places."""
    return write_random_places(folder, n, seed)


def rows(text):
    return list(csv.DictReader(io.StringIO(text)))


def test_build_add_query_and_info_through_the_library(tmp_path):
    first, second = make_route(tmp_path / "first", seed=1), make_route(tmp_path / "second", n=3, seed=2)
    db = tmp_path / "map.db"
    built = build_database(BuildRequest(first, db, "raw", method_options={"size": [16, 32]}, pipeline=QUIET))
    assert (built.places, built.method, built.dim, built.index_seconds) == (5, "raw", 16 * 32 * 1, None)
    assert built.lines()[0].startswith(f"wrote {db}: 5 places, raw (512-d), fingerprint ")
    with PlaceDatabase.open(db) as opened:
        assert opened.method_options == {"size": [16, 32]}  # recorded, so add/query rebuild it

    added = add_to_database(AddRequest(db, second, pipeline=QUIET))
    assert (added.added, added.skipped, added.places) == (3, 0, 8)
    again = add_to_database(AddRequest(db, first, pipeline=QUIET))
    assert (again.added, again.skipped, again.places) == (0, 5, 8)
    assert "skipped 5 already in the database" in again.lines()[0]

    out = tmp_path / "q.csv"
    result = query_database(QueryRequest(db, second, top_k=2, out=out, pipeline=QUIET))
    assert out.read_bytes() == result.csv_text.encode() and (result.queries, result.places) == (3, 8)
    assert result.lines() == [f"wrote {out}: 3 queries against 8 places"]
    table = rows(result.csv_text)
    assert list(table[0]) == ["query_index", "query", "rank", "place", "place_index", "score"] and len(table) == 6
    best = [r for r in table if r["rank"] == "1"]
    assert [r["place"] for r in best] == [r["query"] for r in best]  # one name per image
    assert [r["place_index"] for r in best] == ["5", "6", "7"]
    # the same answers as arrays, for a program (no CSV to parse)
    assert result.indices.shape == (3, 2) and result.indices[:, 0].tolist() == [5, 6, 7]
    assert result.scores.dtype == np.float32 and (result.scores[:, 0] >= result.scores[:, 1]).all()
    assert [result.place_names[i] for i in result.indices[:, 0]] == [r["place"] for r in best]
    assert result.query_names == [r["query"] for r in best] and result.acceptance_scores is None

    # the last 3 places (the second route) excluded: the best answers come from the first route
    result = query_database(QueryRequest(db, second, top_k=1, exclude_last=3, pipeline=QUIET))
    assert all(int(r["place_index"]) < 5 for r in rows(result.csv_text)) and result.lines() == []

    info = database_info(db)
    assert (info["places"], info["method"], info["dim"]) == (8, "raw", 512)


def test_an_approximate_index_for_a_method_without_dot_product_is_refused_before_any_file(tmp_path):
    db = tmp_path / "map.db"
    with pytest.raises(ConfigError, match="use --index flat"):
        build_database(BuildRequest(make_route(tmp_path / "route"), db, "sad", index="hnsw", pipeline=QUIET))
    assert not db.exists()


def test_an_acceptance_rule_adds_its_score_column(tmp_path):
    from fdnet.decisions.acceptance import parse_acceptance

    route = make_route(tmp_path / "route", seed=3)
    db = tmp_path / "map.db"
    build_database(BuildRequest(route, db, "raw", pipeline=QUIET))
    messages = []
    scored = query_database(
        QueryRequest(db, route, top_k=1, accept=parse_acceptance("raw", []), pipeline=QUIET), log=messages.append
    )
    table = rows(scored.csv_text)
    assert list(table[0]) == ["query_index", "query", "rank", "place", "place_index", "score", "acceptance_score"]
    # raw: the acceptance score is the best match's similarity
    assert [float(r["acceptance_score"]) for r in table] == pytest.approx([float(r["score"]) for r in table])
    assert scored.acceptance_scores == pytest.approx(scored.scores[:, 0]) and scored.accepted is None
    assert messages == []  # no stored calibration to announce, none used


def test_messages_go_to_the_module_logger_by_default(tmp_path, caplog, monkeypatch):
    from fdnet.matching.database import store

    db = tmp_path / "map.db"
    build_database(BuildRequest(make_route(tmp_path / "route"), db, "raw", pipeline=QUIET))
    monkeypatch.setattr(store, "read_only_storage", lambda path: True)
    with caplog.at_level(logging.INFO, logger="fdnet"):
        database_info(db)
    assert any("is in a folder that cannot be written" in r.getMessage() for r in caplog.records)
