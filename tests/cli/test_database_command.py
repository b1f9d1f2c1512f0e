"""`fdnet database build|add|query|info` on images and files the tests make."""

import json
import sqlite3

import numpy as np
import pytest

from fdnet.cli import main
from fdnet.descriptors import create
from fdnet.descriptors.classic import RawThumbnail

from conftest import read_csv_rows, write_random_places


def make_route(folder, n=6, seed=0):
    """n distinct random-texture places; the same seed gives the same places."""
    return write_random_places(folder, n, seed)


def info(db, capsys):
    capsys.readouterr()
    assert main(["database", "info", "--db", str(db)]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.fixture
def no_describing(monkeypatch):
    """Make describing an image fail the test: a refusal must come before that work."""

    def describe(self, images):
        raise AssertionError("images were described before the refusal")

    monkeypatch.setattr(RawThumbnail, "describe", describe)


@pytest.fixture
def built(tmp_path):
    db = tmp_path / "map.db"
    assert (
        main(
            [
                "database",
                "build",
                "--images",
                str(make_route(tmp_path / "first", seed=1)),
                "--method",
                "raw",
                "--db",
                str(db),
            ]
        )
        == 0
    )
    return db


def test_build_add_query_info(tmp_path, built, capsys):
    second = make_route(tmp_path / "second", n=4, seed=2)
    assert main(["database", "add", "--db", str(built), "--images", str(second)]) == 0
    out = tmp_path / "q.csv"
    assert (
        main(["database", "query", "--db", str(built), "--images", str(second), "--top-k", "2", "--out", str(out)]) == 0
    )
    rows = read_csv_rows(out)
    assert list(rows[0]) == ["query_index", "query", "rank", "place", "place_index", "score"]
    best = [r for r in rows if r["rank"] == "1"]
    assert [r["place"] == r["query"] == str(second / f"frame_{i:03d}.png") for i, r in enumerate(best)] == [True] * 4
    assert [r["place_index"] for r in best] == ["6", "7", "8", "9"]
    summary = info(built, capsys)
    assert {"places", "method", "dim", "fingerprint", "settings", "schema_version", "data_version", "index"} <= set(
        summary
    )
    assert (summary["places"], summary["method"], summary["dim"], summary["data_version"]) == (10, "raw", 2048, 2)
    assert summary["fingerprint"] == create("raw").fingerprint() and summary["index"]["kind"] == "flat"


def test_re_adding_images_skips_and_reports_them_unless_allowed(tmp_path, built, capsys):
    more = make_route(tmp_path / "more", n=2, seed=3)
    capsys.readouterr()
    assert main(["database", "add", "--db", str(built), "--images", str(tmp_path / "first")]) == 0
    assert "added 0 places (skipped 6 already in the database" in capsys.readouterr().out
    assert main(["database", "add", "--db", str(built), "--images", str(more)]) == 0
    assert "added 2 places, 8 in all" in capsys.readouterr().out
    assert main(["database", "add", "--db", str(built), "--images", str(more)]) == 0
    assert "added 0 places (skipped 2 already" in capsys.readouterr().out
    assert main(["database", "add", "--db", str(built), "--images", str(more), "--allow-duplicates"]) == 0
    assert "added 2 places, 10 in all" in capsys.readouterr().out
    assert info(built, capsys)["places"] == 10


def test_add_refuses_another_models_vectors(tmp_path, built, capsys):
    # Same method and dimension (32x64 and 64x32 thumbnails are both 2048-d), different model.
    assert (
        main(
            [
                "database",
                "add",
                "--db",
                str(built),
                "--images",
                str(make_route(tmp_path / "x", n=2, seed=5)),
                "--method-set",
                "size=64x32",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith(f"fdnet database: error: {built}: descriptor fingerprint mismatch")
    assert create("raw").fingerprint()[:12] in err and create("raw", size="64x32").fingerprint()[:12] in err
    assert info(built, capsys)["places"] == 6


def test_add_refuses_nan_vectors_naming_the_image(tmp_path, built, capsys, monkeypatch):
    def nan_for_the_second(self, images):
        v = np.ones((len(images), self.dim), np.float32) / np.sqrt(self.dim)
        v[1:2] = np.nan
        return v

    monkeypatch.setattr(RawThumbnail, "describe", nan_for_the_second)
    images = make_route(tmp_path / "nan", n=3, seed=6)
    assert main(["database", "add", "--db", str(built), "--images", str(images)]) == 2
    err = capsys.readouterr().err
    assert "frame_001.png holds NaN" in err and "nothing was added" in err
    assert info(built, capsys)["places"] == 6


def test_build_over_an_existing_database_needs_overwrite(tmp_path, built, capsys, monkeypatch):
    with monkeypatch.context() as patch:
        patch.setattr(RawThumbnail, "describe", lambda self, images: pytest.fail("described before refusing"))
        assert (
            main(["database", "build", "--images", str(tmp_path / "first"), "--method", "raw", "--db", str(built)]) == 2
        )
    assert f"fdnet database: error: {built}: already exists; pass --overwrite" in capsys.readouterr().err
    other = make_route(tmp_path / "other", n=3, seed=7)
    assert (
        main(["database", "build", "--images", str(other), "--method", "raw", "--db", str(built), "--overwrite"]) == 0
    )
    assert info(built, capsys)["places"] == 3


@pytest.mark.parametrize(
    "flag, value, message", [("--top-k", "0", "must be at least 1"), ("--exclude-last", "-1", "must be 0 or more")]
)
def test_query_rejects_impossible_counts(tmp_path, built, capsys, flag, value, message):
    with pytest.raises(SystemExit) as stopped:
        main(["database", "query", "--db", str(built), "--images", str(tmp_path / "first"), flag, value])
    assert stopped.value.code == 2
    assert f"argument {flag}: {message}" in capsys.readouterr().err


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda p: p.write_bytes(b""), "an empty file, not an fdnet place database"),
        (
            lambda p: p.write_bytes(np.random.default_rng(0).bytes(3000)),
            "not an fdnet place database (not a SQLite file)",
        ),
        (
            lambda p: sqlite3.connect(p).execute("CREATE TABLE photos (id INTEGER)"),
            "a SQLite database but not an fdnet place database (it has tables: photos)",
        ),
    ],
)
def test_a_file_that_is_not_a_place_database(tmp_path, capsys, make, message):
    path = tmp_path / "thing.db"
    make(path)
    for action in (["info"], ["add", "--images", str(tmp_path)], ["query", "--images", str(tmp_path)]):
        assert main(["database", action[0], "--db", str(path), *action[1:]]) == 2
        assert capsys.readouterr().err == f"fdnet database: error: {path}: {message}\n"


def test_a_folder_is_not_a_place_database(tmp_path, capsys):
    folder = tmp_path / "maps"
    folder.mkdir()
    (folder / "database.json").write_text("{}")  # whatever it holds, a folder is not a database file
    for action in (["info"], ["add", "--images", str(tmp_path)], ["query", "--images", str(tmp_path)]):
        assert main(["database", action[0], "--db", str(folder), *action[1:]]) == 2
        assert capsys.readouterr().err == (
            f"fdnet database: error: {folder}: is a folder, not a place database " f"file (e.g. {folder / 'map.db'})\n"
        )
    with pytest.raises(SystemExit):  # no command converts folders: there is one format, the file
        main(["database", "migrate", "--from", str(folder), "--db", str(tmp_path / "map.db")])
    assert "invalid choice: 'migrate'" in capsys.readouterr().err


def test_unwritable_outputs_fail_before_describing(tmp_path, built, capsys, no_describing):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    assert (
        main(
            [
                "database",
                "build",
                "--images",
                str(tmp_path / "first"),
                "--method",
                "raw",
                "--db",
                str(blocker / "map.db"),
            ]
        )
        == 2
    )
    assert "cannot create the place database folder" in capsys.readouterr().err
    assert (
        main(
            [
                "database",
                "query",
                "--db",
                str(built),
                "--images",
                str(tmp_path / "first"),
                "--out",
                str(blocker / "q.csv"),
            ]
        )
        == 2
    )
    assert "cannot create the query CSV folder" in capsys.readouterr().err


def test_build_with_an_approximate_index_caches_it_and_adds_in_one_transaction(tmp_path, capsys):
    route = make_route(tmp_path / "route", n=60)
    more = make_route(tmp_path / "more", n=8, seed=5)
    db = tmp_path / "map.db"
    assert (
        main(
            [
                "database",
                "build",
                "--images",
                str(route),
                "--method",
                "raw",
                "--db",
                str(db),
                "--index",
                "ivfpq",
                "--index-set",
                "pq_bytes=16",
                "--index-set",
                "refine=8",
                "--batch-size",
                "7",
                "--workers",
                "1",
                "--device",
                "cpu",
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "60 places" in printed and "ivfpq index built" in printed
    cache = tmp_path / "map.db.fdnet-index"
    assert cache.is_file()
    assert info(db, capsys)["index"]["pq_bytes"] == 16
    assert main(["database", "add", "--db", str(db), "--images", str(more), "--batch-size", "3"]) == 0
    assert "added 8 places" in capsys.readouterr().out
    assert info(db, capsys)["data_version"] == 2  # one version step for the whole add
    out = tmp_path / "q.csv"
    assert main(["database", "query", "--db", str(db), "--images", str(more), "--top-k", "1", "--out", str(out)]) == 0
    assert [r["place"].rsplit("/", 1)[-1] for r in read_csv_rows(out)] == [f"frame_{i:03d}.png" for i in range(8)]
    # no spool files are left beside the database
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


def test_a_non_dot_product_method_is_refused_an_approximate_index(tmp_path, capsys, no_describing):
    route = make_route(tmp_path / "route")
    assert (
        main(
            [
                "database",
                "build",
                "--images",
                str(route),
                "--method",
                "sad",
                "--db",
                str(tmp_path / "m.db"),
                "--index",
                "ivf",
            ]
        )
        == 2
    )
    assert "use --index flat" in capsys.readouterr().err


def test_a_file_name_that_is_not_utf8_is_refused_before_any_work(tmp_path, capsys, no_describing):
    import os

    images = make_route(tmp_path / "odd", n=3)
    os.rename(images / "frame_001.png", os.path.join(os.fsencode(images), b"caf\xe9.png"))
    db = tmp_path / "map.db"
    assert main(["database", "build", "--images", str(images), "--method", "raw", "--db", str(db)]) == 2
    err = capsys.readouterr().err
    assert "caf\\xe9.png': the file name is not valid UTF-8" in err and "Traceback" not in err
    assert not db.exists()  # no half-made database left behind


def test_query_quotes_names_a_spreadsheet_would_run_as_formulas(tmp_path, capsys):
    images = make_route(tmp_path / "odd", n=3)
    (images / "frame_000.png").rename(images / "=cmd.png")
    (images / "frame_001.png").rename(images / "@x.png")
    db = tmp_path / "map.db"
    assert main(["database", "build", "--images", str(images), "--method", "raw", "--db", str(db)]) == 0
    out = tmp_path / "q.csv"
    assert main(["database", "query", "--db", str(db), "--images", str(images), "--top-k", "3", "--out", str(out)]) == 0
    rows = read_csv_rows(out)
    # images are named by absolute path, which starts with / (nothing for a spreadsheet to run)
    assert {r["query"] for r in rows} == {str(images / n) for n in ("=cmd.png", "@x.png", "frame_002.png")}
    assert all(not r["place"].startswith(("=", "@", "'")) for r in rows)


def test_add_removes_the_spools_that_killed_writers_left_beside_the_database(tmp_path, built, capsys):
    import sys

    from tests.descriptors.test_pipeline import _spool_writer

    if sys.platform == "win32":
        pytest.skip("spools are swept with flock, which Windows lacks")
    writers = [_spool_writer(built.parent) for _ in range(3)]  # three `database add`s describing at once ...
    for writer, _ in writers:  # ... killed with -9
        writer.kill()
        writer.wait()
    stale = [spool for _, spool in writers]
    assert all(p.exists() for p in stale)
    assert (
        main(
            [
                "database",
                "add",
                "--db",
                str(built),
                "--images",
                str(make_route(tmp_path / "more", n=2, seed=5)),
                "--workers",
                "0",
            ]
        )
        == 0
    )
    assert not any(p.exists() for p in stale)
    assert not list(built.parent.glob(".fdnet-spool.*"))


def test_a_database_on_read_only_storage_is_queried_read_only(tmp_path, capsys, make_read_only):
    import os

    images = make_route(tmp_path / "first", seed=1)
    built = tmp_path / "maps" / "map.db"
    assert main(["database", "build", "--images", str(images), "--method", "raw", "--db", str(built)]) == 0
    make_read_only(built.parent)
    assert not os.access(built.parent, os.W_OK)
    assert info(built, capsys)["places"] == 6
    out_csv = tmp_path / "q.csv"  # the query's CSV goes to a writable folder
    capsys.readouterr()
    assert (
        main(
            [
                "database",
                "query",
                "--db",
                str(built),
                "--images",
                str(images),
                "--top-k",
                "1",
                "--workers",
                "0",
                "--out",
                str(out_csv),
            ]
        )
        == 0
    )
    assert "opened read-only" in capsys.readouterr().err
    assert [r["place_index"] for r in read_csv_rows(out_csv)] == [str(i) for i in range(6)]
    assert (
        main(
            [
                "database",
                "add",
                "--db",
                str(built),
                "--images",
                str(tmp_path / "first"),
                "--allow-duplicates",
                "--workers",
                "0",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "cannot be written (read-only media or mount), so nothing can be added" in err and "Traceback" not in err


def test_a_read_only_database_with_a_log_left_behind_is_read_through_it_or_refused_clearly(tmp_path, make_read_only):
    import shutil

    from fdnet.errors import DataError
    from fdnet.matching.database import PlaceDatabase

    live = tmp_path / "live"
    live.mkdir()
    db = PlaceDatabase.create(live / "map.db", RawThumbnail())
    db._conn.execute("PRAGMA wal_autocheckpoint = 0")  # the adds stay in the log, as when a writer is killed
    db.add(np.ones((2, RawThumbnail().dim), np.float32), ["a", "b"])
    shutil.copytree(live, tmp_path / "with-log")  # the file, its -wal and -shm: what a killed writer leaves
    shutil.copytree(live, tmp_path / "log-without-shm")
    (tmp_path / "log-without-shm" / "map.db-shm").unlink()
    db.close()  # the last connection copies the log into the file
    assert not (live / "map.db-wal").exists() and (tmp_path / "with-log" / "map.db-wal").stat().st_size > 0
    make_read_only(tmp_path)
    for folder in ("live", "with-log"):  # immutable; read through the log and its -shm
        with PlaceDatabase.open(tmp_path / folder / "map.db") as opened:
            assert opened.read_only and len(opened) == 2 and opened.names == ["a", "b"]
    with pytest.raises(DataError, match=r"its write-ahead log .*map.db-wal holds adds not yet copied into the file"):
        PlaceDatabase.open(tmp_path / "log-without-shm" / "map.db")


def test_a_database_whose_folder_is_not_writable_opens_immutable_on_any_machine(tmp_path, built, capsys, monkeypatch):
    """The same path as read-only media, where the test cannot mount: the folder reported
    unwritable (what os.access says there) opens the file immutable, with the note."""
    import fdnet.matching.database as database
    import fdnet.matching.database.storage as storage

    monkeypatch.setattr(storage.os, "access", lambda path, mode: False)
    capsys.readouterr()
    assert main(["database", "info", "--db", str(built)]) == 0
    printed = capsys.readouterr()
    assert "opened read-only" in printed.err and json.loads(printed.out)["places"] == 6
    with database.PlaceDatabase.open(built) as db:
        assert db.read_only and len(db) == 6
        with pytest.raises(storage.DataError, match="readonly"):
            db.add(np.ones((1, db.dim), np.float32), ["new"])


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_query_refuses_a_min_score_that_is_not_finite(tmp_path, built, capsys, value):
    with pytest.raises(SystemExit) as stopped:
        main(["database", "query", "--db", str(built), "--images", str(tmp_path / "first"), f"--min-score={value}"])
    assert stopped.value.code == 2
    assert f"argument --min-score: must be a finite number, got '{value}'" in capsys.readouterr().err


def test_the_empty_file_an_unfinished_build_leaves_says_so_and_is_reused(tmp_path, capsys):
    import contextlib

    db = tmp_path / "map.db"
    with contextlib.closing(sqlite3.connect(db)) as conn:
        conn.execute("CREATE TABLE t (x)")
        conn.execute("DROP TABLE t")  # a real SQLite header, no tables: what a killed first commit leaves
    assert main(["database", "info", "--db", str(db)]) == 2
    assert "not yet an fdnet place database (a `database build` that did not finish" in capsys.readouterr().err
    assert (
        main(
            [
                "database",
                "build",
                "--images",
                str(make_route(tmp_path / "images", n=2)),
                "--method",
                "raw",
                "--db",
                str(db),
            ]
        )
        == 0
    )
    assert info(db, capsys)["places"] == 2


def test_every_listed_image_is_a_place_under_its_own_name_links_too(tmp_path, capsys):
    """a.png, b.png -> a.png, c.png: three places in the folder's order, each under the name it
    was listed by (a link is not replaced by its target, and not merged with it)."""
    folder = write_random_places(tmp_path / "f", 2)
    first, second = sorted(folder.iterdir())
    (folder / "b_link.png").symlink_to(first.name)
    names = sorted(p.name for p in folder.iterdir())
    db = tmp_path / "links.db"
    assert main(["database", "build", "--images", str(folder), "--method", "raw", "--db", str(db)]) == 0
    assert "3 places" in capsys.readouterr().out
    with sqlite3.connect(db) as conn:
        stored = [row[0] for row in conn.execute("SELECT name FROM places ORDER BY id")]
    assert [s.rsplit("/", 1)[1] for s in stored] == names
    assert str(folder / "b_link.png") in stored


def test_torchrun_database_build_writes_the_one_process_database_and_its_index(tmp_path, capsys):
    """`torchrun --nproc-per-node 2 -m fdnet database build`: each process describes half the
    images, rank 0 writes the database (names exactly, vectors within 1e-5 of one process's, the
    same fingerprint) and builds the hnsw index once on all of them; info records world_size 2."""
    from fdnet.matching.database.store import PlaceDatabase
    from tests.descriptors.test_sharding import spools, torchrun

    images = make_route(tmp_path / "route", n=11)
    common = [
        "database",
        "build",
        "--images",
        str(images),
        "--method",
        "raw",
        "--index",
        "hnsw",
        "--batch-size",
        "2",
        "--workers",
        "0",
    ]
    assert main([*common, "--db", str(tmp_path / "one.db")]) == 0
    result = torchrun(*common, "--db", tmp_path / "two.db", tmpdir=tmp_path / "tmp")
    assert result.returncode == 0, result.stderr
    assert result.stdout.count("wrote ") == 1 and "11 places" in result.stdout and "hnsw index built" in result.stdout
    with PlaceDatabase.open(tmp_path / "one.db") as one, PlaceDatabase.open(tmp_path / "two.db") as two:
        assert two.names == one.names and two.fingerprint == one.fingerprint
        np.testing.assert_allclose(two.vectors, one.vectors, rtol=0, atol=1e-5)
        queries = one.vectors[:3]
        assert [[m.name for m in q] for q in two.query(queries, k=2)] == [
            [m.name for m in q] for q in one.query(queries, k=2)
        ]
    assert info(tmp_path / "two.db", capsys)["build"] == {"world_size": 2}
    assert "build" not in info(tmp_path / "one.db", capsys)
    assert (tmp_path / "two.db.fdnet-index").is_file()
    assert not list(tmp_path.glob(".fdnet-spool.*")) and spools(tmp_path / "tmp") == []


def test_torchrun_database_build_with_rank_0_killed_leaves_no_database_and_a_rerun_builds_it(tmp_path):
    """Rank 0 (the writer) killed after its first batch: process 1 stops with one error line, no
    database is written; the killed writer's spool beside it is removed by the next build, which
    writes every place."""
    from fdnet.descriptors.sharding import KILL_VARIABLE
    from fdnet.matching.database.store import PlaceDatabase
    from tests.descriptors.test_sharding import error_lines, torchrun

    images = make_route(tmp_path / "route", n=12)
    db = tmp_path / "maps" / "map.db"
    common = [
        "database",
        "build",
        "--images",
        images,
        "--method",
        "raw",
        "--db",
        db,
        "--batch-size",
        "2",
        "--workers",
        "0",
    ]
    killed = torchrun(*common, tmpdir=tmp_path / "tmp", env={KILL_VARIABLE: "0:1"})
    assert killed.returncode != 0
    errors = error_lines(killed, "database")
    assert len(errors) == 1, killed.stderr
    assert "process 1 of 2 lost contact" in errors[0] or "stopped by SIGTERM" in errors[0]
    left = [p.name for p in db.parent.iterdir()]
    assert len(left) == 1 and left[0].startswith(".fdnet-spool."), left  # no database; the killed writer's spool
    again = torchrun(*common, tmpdir=tmp_path / "tmp")
    assert again.returncode == 0, again.stderr
    assert sorted(p.name for p in db.parent.iterdir()) == ["map.db"]
    with PlaceDatabase.open(db) as database:
        assert len(database) == 12
