"""The SQLite file under a place database: its schema and format constants, connections and
transactions, SQLite's errors as the project's, and the checks made before a file is created or
opened.

Why SQLite: every ``add`` is one transaction (``BEGIN IMMEDIATE``), so concurrent writers queue
behind each other instead of overwriting each other's batch, readers see the database before or
after an add but never half of one, and a process killed at any instant leaves the old or the
new state. The write-ahead log (WAL) lets queries read while a writer writes.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import sqlite3
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from fdnet.data.images import image_name
from fdnet.errors import ConfigError, DataError, output_error

#: ``PRAGMA user_version`` of the files this code writes; a newer file is refused, not guessed at.
SCHEMA_VERSION = 1
#: ``PRAGMA application_id``: tells an fdnet place database from any other SQLite file.
APPLICATION_ID = int.from_bytes(b"fdPD", "big")
#: How long a writer waits for another writer's transaction before giving up. Adds are short
#: (describing images happens before the transaction), so a minute means something is stuck.
BUSY_TIMEOUT_S = 60.0
MEMORY = ":memory:"
SQLITE_MAGIC = b"SQLite format 3\x00"

SCHEMA = """
CREATE TABLE fdnet_database (
    singleton INTEGER PRIMARY KEY CHECK (singleton = 1),
    database_id TEXT NOT NULL,
    method TEXT NOT NULL,
    settings TEXT NOT NULL,
    method_options TEXT NOT NULL,
    dim INTEGER NOT NULL CHECK (dim > 0),
    dot_product INTEGER NOT NULL CHECK (dot_product IN (0, 1)),
    index_settings TEXT NOT NULL,
    fingerprint TEXT NOT NULL,
    data_version INTEGER NOT NULL,
    created TEXT NOT NULL,
    fdnet_version TEXT NOT NULL
);
CREATE TABLE places (
    id INTEGER PRIMARY KEY,
    name TEXT NOT NULL,
    x REAL,
    y REAL,
    metadata TEXT,
    vector BLOB NOT NULL,
    CHECK ((x IS NULL) = (y IS NULL))
);
CREATE INDEX places_by_name ON places (name);
"""
TABLES = ("fdnet_database", "places")


def canonical_json(value, where: str) -> str:
    try:
        return json.dumps(value, sort_keys=True, allow_nan=False, default=_json_default)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: cannot be stored as JSON ({exc})") from exc


def _json_default(value):
    if isinstance(value, (Path, os.PathLike)):
        return str(value)
    if isinstance(value, (np.integer, np.floating, np.bool_)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON")


def check_header(path: Path) -> None:
    if path.is_dir():
        raise DataError(f"{path}: is a folder, not a place database file (e.g. {path / 'map.db'})")
    try:
        with open(path, "rb") as fh:
            head = fh.read(len(SQLITE_MAGIC))
    except FileNotFoundError as exc:
        raise DataError(f"{path}: no such place database (make one with `fdnet database build`)") from exc
    except OSError as exc:
        raise DataError(f"{path}: cannot read the place database ({exc.strerror or exc})") from exc
    if not head:
        raise DataError(f"{path}: an empty file, not an fdnet place database")
    if head != SQLITE_MAGIC:
        raise DataError(f"{path}: not an fdnet place database (not a SQLite file)")


def describe_foreign(conn: sqlite3.Connection) -> str:
    tables = [r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table' ORDER BY name")]
    return f"it has tables: {', '.join(tables)}" if tables else "it has no tables"


def _sqlite_message(exc: sqlite3.Error, path=None) -> str:
    text = str(exc)
    if "locked" in text or "busy" in text:
        return f"another process held the database's write lock for more than {BUSY_TIMEOUT_S:.0f} s ({text})"
    if (
        path is not None
        and path != MEMORY
        and any(words in text for words in ("unable to open", "disk I/O error", "readonly", "disk is full"))
    ):
        why = _storage_problem(path)
        if why:
            return f"{text}: {why}"
    return text


def _storage_problem(path) -> str:
    """Why SQLite cannot open or write ``path``, from what the operating system says about its
    folder (SQLite itself only says "unable to open database file" or "disk I/O error"); "" when
    nothing is found. SQLite's write-ahead log needs to create ``-wal`` and ``-shm`` files beside
    the database, even to read it."""
    folder = Path(path).resolve().parent
    problems = []
    try:
        stats = os.statvfs(folder)
        free = stats.f_bavail * stats.f_frsize
        if stats.f_flag & getattr(os, "ST_RDONLY", 1):
            problems.append(f"its folder {folder} is on a read-only file system")
        elif free < (1 << 20):
            problems.append(f"no space left on the device ({free // 1024} KiB free in {folder})")
    except (OSError, AttributeError):  # no statvfs (Windows)
        pass
    if not problems and not os.access(folder, os.W_OK):
        problems.append(f"this user cannot write in its folder {folder}")
    try:
        import resource

        limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
        if limit != resource.RLIM_INFINITY and limit < (1 << 30):
            problems.append(f"this process may only write files up to {limit} bytes (ulimit -f)")
    except (ImportError, OSError, ValueError):
        pass
    return "; ".join(problems)


def read_only_storage(path: Path) -> bool:
    """True when the database's folder cannot be written (read-only media, a read-only mount or
    share): SQLite's write-ahead log then cannot create its ``-shm`` file to open it as usual."""
    return not os.access(path.resolve().parent, os.W_OK)


@contextlib.contextmanager
def sqlite_errors(path, doing: str) -> Iterator[None]:
    """SQLite's exceptions as the project's errors, naming the file and what was being done: a
    full disk (SQLITE_FULL) is an :class:`~fdnet.errors.OutputError` with ENOSPC, anything else
    a DataError."""
    try:
        yield
    except sqlite3.Error as exc:
        message = f"{path}: {doing}: {_sqlite_message(exc, path)}"
        if getattr(exc, "sqlite_errorcode", None) == sqlite3.SQLITE_FULL:
            raise output_error(message, OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))) from exc
        raise DataError(message) from exc


@contextlib.contextmanager
def transaction(conn: sqlite3.Connection, mode: str) -> Iterator[sqlite3.Connection]:
    """``BEGIN IMMEDIATE`` takes the write lock up front, so two writers queue (busy timeout)
    instead of both reading, then one failing to upgrade its lock; ``BEGIN DEFERRED`` gives a
    reader one consistent snapshot across several SELECTs."""
    conn.execute(f"BEGIN {mode}")
    try:
        yield conn
    except BaseException:
        if conn.in_transaction:
            conn.execute("ROLLBACK")
        raise
    conn.execute("COMMIT")


def connect_database(target: str, uri: bool = False) -> sqlite3.Connection:
    # isolation_level=None: the module must not open transactions behind our back; each add is
    # exactly the BEGIN IMMEDIATE ... COMMIT written below.
    conn = sqlite3.connect(target, timeout=BUSY_TIMEOUT_S, isolation_level=None, uri=uri)
    # FULL, not NORMAL: with WAL, NORMAL may lose the last commits on power loss, and the
    # database promises that an add it has acknowledged is on disk.
    conn.execute("PRAGMA synchronous = FULL")
    return conn


def connect_read_only(path: Path) -> sqlite3.Connection:
    """A database on storage this process cannot write. Without a write-ahead log left beside it
    the file holds every committed add and is opened ``immutable`` (no -shm needed, no locks: on
    read-only storage nobody can change it). A log left there (a writer killed, the medium then
    made read-only) holds commits not yet in the file: they are read through its ``-shm`` file
    (``mode=ro``), and refused with a clear message when that is missing too."""
    uri = path.resolve().as_uri()
    wal = Path(f"{path}-wal")
    if not (wal.exists() and wal.stat().st_size > 0):
        return connect_database(uri + "?immutable=1", uri=True)
    try:
        conn = connect_database(uri + "?mode=ro", uri=True)
        conn.execute("SELECT count(*) FROM sqlite_master").fetchone()
        return conn
    except sqlite3.Error as exc:
        raise DataError(
            f"{path}: its folder cannot be written and its write-ahead log {wal} holds adds not yet "
            f"copied into the file, which SQLite can only read with {path}-shm beside it; copy the "
            "database and its -wal file to a writable folder and open it there"
        ) from exc


def place_name(path: str | os.PathLike) -> str:
    """An image's place name, the one rule for every writer of places (``database build``/``add``,
    ``loop-closure``): :func:`fdnet.data.images.image_name`, the name every output gives it."""
    return image_name(path)


def check_place_names(names: Sequence[str]) -> None:
    """Refuse a place name that is not valid UTF-8 (a file name Python keeps as surrogates):
    SQLite text is UTF-8, so it could not be stored. Callers check before describing images."""
    for name in names:
        try:
            str(name).encode("utf-8")
        except UnicodeEncodeError as exc:
            raise DataError(
                f"{os.fsencode(str(name))!r}: the file name is not valid UTF-8, which a place database "
                "cannot store as a place name; rename the file"
            ) from exc


def is_fdnet_database(conn: sqlite3.Connection) -> bool:
    return conn.execute("PRAGMA application_id").fetchone()[0] == APPLICATION_ID


def holds_a_database(path: str | os.PathLike) -> bool:
    """Whether ``path`` holds a database to open, rather than what a create killed before its
    first commit leaves (an empty file, or a SQLite file without tables), which is reused."""
    path = Path(path)
    if str(path) == MEMORY or not path.is_file() or path.stat().st_size == 0:
        return False
    with open(path, "rb") as fh:
        if fh.read(len(SQLITE_MAGIC)) != SQLITE_MAGIC:
            return True  # not SQLite: opening it says what it is
    conn = connect_database(path.resolve().as_uri() + "?mode=ro", uri=True)
    try:
        with sqlite_errors(path, "checking the existing file"):
            return bool(conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'").fetchall())
    finally:
        conn.close()


def check_can_create(path: str | os.PathLike, overwrite: bool = False) -> None:
    """Refuse, before any image is described, a database path that ``create`` would refuse.

    A file with content is only replaced with ``overwrite``, and only if it is an fdnet place
    database; an empty file, or a SQLite file without tables (what a create killed before its
    first commit leaves), holds nothing to lose and is simply reused.
    """
    path = Path(path)
    if str(path) == MEMORY:
        return
    if path.is_dir():
        raise ConfigError(f"{path}: is a folder; name the database file to write (e.g. {path / 'map.db'})")
    if path.exists():
        if path.stat().st_size == 0:
            return
        with open(path, "rb") as fh:
            if fh.read(len(SQLITE_MAGIC)) != SQLITE_MAGIC:
                raise DataError(
                    f"{path}: exists and is not an fdnet place database (not a SQLite file); "
                    "refusing to overwrite it"
                )
        conn = connect_database(path.resolve().as_uri() + "?mode=rw", uri=True)
        try:
            with sqlite_errors(path, "checking the existing file"):
                tables = conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'").fetchall()
                if tables and not is_fdnet_database(conn):
                    raise DataError(
                        f"{path}: is a SQLite database but not an fdnet place database "
                        f"({describe_foreign(conn)}); refusing to overwrite it"
                    )
        finally:
            conn.close()
        if tables and not overwrite:
            raise ConfigError(f"{path}: already exists; pass --overwrite (overwrite=True) to replace it")
    elif Path(f"{path}-wal").exists():
        # SQLite would replay a stray log into the new file: a corrupt database from the start.
        raise DataError(
            f"{path}-wal: a write-ahead log left without its database; remove it "
            f"(and {path}-shm) before creating {path}"
        )


#: page size of a new database file. A place's row is its vector blob (2 KB at 512 float32) and a
#: few dozen bytes: with SQLite's default 4 KB pages one row fits a page and a half of it is
#: empty (4132 bytes a 512-d place, measured), with 32 KB pages 14 rows fill one (2218 bytes a
#: place), which also made bulk adds and reads by id faster. Ignored for a file that has pages
#: (``build --overwrite`` keeps them).
PAGE_SIZE = 32768


def use_write_ahead_log(conn: sqlite3.Connection, target: str) -> None:
    """Put a new database file in SQLite's write-ahead log (readers beside one writer, and a
    commit survives a crash); refuse a file system that cannot (a network share). A file
    without pages yet first gets :data:`PAGE_SIZE` (it cannot change once in the log)."""
    if target == MEMORY:
        return
    conn.execute(f"PRAGMA page_size = {PAGE_SIZE}")
    mode = conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]
    if str(mode).lower() != "wal":
        raise DataError(
            f"{target}: the file system does not support SQLite's write-ahead log "
            f"(journal mode stays {mode!r}); put the database on a local disk"
        )


def write_schema(conn: sqlite3.Connection, target: str, overwrite: bool, identity: dict) -> None:
    """Inside the caller's write transaction: drop an existing place database's tables when
    ``overwrite`` (anything else in the file is refused), create the tables and write the
    database's one identity row (``identity``: column -> value)."""
    existing = [r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")]
    if existing:
        # Checked again under the write lock: another build may have won the race.
        if not is_fdnet_database(conn):
            raise DataError(
                f"{target}: is a SQLite database but not an fdnet place database "
                f"({describe_foreign(conn)}); refusing to overwrite it"
            )
        if not overwrite:
            raise ConfigError(f"{target}: already exists; pass --overwrite (overwrite=True) to replace it")
        for table in TABLES:
            conn.execute(f"DROP TABLE IF EXISTS {table}")
    for statement in SCHEMA.split(";"):
        if statement.strip():
            conn.execute(statement)
    conn.execute(f"PRAGMA application_id = {APPLICATION_ID}")
    conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
    columns = ", ".join(identity)
    conn.execute(
        f"INSERT INTO fdnet_database (singleton, {columns}) VALUES (1, {', '.join('?' * len(identity))})",
        tuple(identity.values()),
    )


def check_schema(conn: sqlite3.Connection, target: str, read_only: bool) -> None:
    """Refuse a file that is not an fdnet place database this version reads (another SQLite
    database, one a killed build left empty, a newer schema, a damaged one)."""
    if not is_fdnet_database(conn):
        foreign = describe_foreign(conn)
        if foreign == "it has no tables":  # what a create stopped before its first commit leaves
            raise DataError(
                f"{target}: an empty SQLite file, not yet an fdnet place database (a "
                "`database build` that did not finish, e.g. on a full disk or killed, "
                "leaves this); build it again with --db there (the file is reused)"
            )
        raise DataError(f"{target}: a SQLite database but not an fdnet place database ({foreign})")
    schema = conn.execute("PRAGMA user_version").fetchone()[0]
    if schema > SCHEMA_VERSION:
        raise DataError(
            f"{target}: written by a newer fdnet (schema version {schema}; this one "
            f"reads up to {SCHEMA_VERSION}); upgrade fdnet"
        )
    if schema < 1:
        raise DataError(f"{target}: has no fdnet schema version; the file is damaged")
    if not read_only:
        # Persistent once set; this only matters for a file copied from a non-WAL tool.
        conn.execute("PRAGMA journal_mode = WAL")
