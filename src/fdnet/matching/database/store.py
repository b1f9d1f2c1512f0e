"""A persistent place database for loop closure and relocalisation, in one SQLite file.

Holds one vector per place with its name (image file), optional position and metadata, and
answers "which stored places look like this?" with ranked candidates and scores. The file also
records which descriptor made its vectors (method, settings, the options that rebuild it, and a
fingerprint of its weights), so vectors from another model are refused instead of mixed in.

Why SQLite: every ``add`` is one transaction (``BEGIN IMMEDIATE``), so concurrent writers queue
behind each other instead of overwriting each other's batch, readers see the database before or
after an add but never half of one, and a process killed at any instant leaves the old or the
new state. The write-ahead log (WAL) lets queries read while a writer writes.

The faiss index is derived data: it is rebuilt from the stored vectors when a database is first
queried and extended when other processes add places, so it can never disagree with the file.
See ``docs/database.md`` for the file format and the guarantees.
"""

from __future__ import annotations

import contextlib
import json
import os
import shlex
import sqlite3
import uuid
from dataclasses import dataclass, field, fields
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np

from fdnet.errors import ConfigError, DataError
from fdnet.matching.index import INDEX_KINDS, IndexSettings, VectorIndex, check_settings
from fdnet.matching.similarity import top_k

#: ``PRAGMA user_version`` of the files this code writes; a newer file is refused, not guessed at.
SCHEMA_VERSION = 1
#: ``PRAGMA application_id``: tells an fdnet place database from any other SQLite file.
APPLICATION_ID = int.from_bytes(b"fdPD", "big")
#: How long a writer waits for another writer's transaction before giving up. Adds are short
#: (describing images happens before the transaction), so a minute means something is stuck.
BUSY_TIMEOUT_S = 60.0
MEMORY = ":memory:"
SQLITE_MAGIC = b"SQLite format 3\x00"
OLD_FORMAT_FILES = ("database.json", "vectors.npy")
#: Stay well under SQLite's limit on bound parameters per statement.
_NAMES_PER_QUERY = 500
#: Rows read from the file per fetch while loading places (bounded memory besides the index).
_ROWS_PER_FETCH = 65536
#: Suffix of the derived index cache beside a database file (approximate kinds only).
INDEX_CACHE_SUFFIX = ".fdnet-index"

_SCHEMA = """
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
_TABLES = ("fdnet_database", "places")


@dataclass
class Match:
    #: 0-based position of the place in insertion order (places are never deleted, so stable)
    index: int
    name: str
    score: float
    position: tuple[float, float] | None = None
    metadata: dict | None = None


@dataclass
class AddResult:
    added: int
    #: names not added because the database (or an earlier row of the same batch) had them
    skipped: list[str]
    #: places in the database after this add
    places: int
    data_version: int


def short_fingerprint(fingerprint: str) -> str:
    return fingerprint[:12]


def migrate_command(folder: str | os.PathLike) -> str:
    folder = Path(folder)
    return f"fdnet database migrate --from {shlex.quote(str(folder))} --out {shlex.quote(str(folder) + '.db')}"


def refuse_old_format(path: str | os.PathLike) -> None:
    """A folder holding the old ``database.json`` + ``vectors.npy`` is named with the exact
    command that converts it, instead of a puzzling 'not a database'."""
    path = Path(path)
    if path.is_dir() and any((path / name).exists() for name in OLD_FORMAT_FILES):
        raise ConfigError(f"{path}: a place database in the old folder format (database.json + vectors.npy); "
                          f"convert it once with: {migrate_command(path)}")


def _canonical_json(value, where: str) -> str:
    try:
        return json.dumps(value, sort_keys=True, allow_nan=False, default=_json_default)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: cannot be stored as JSON ({exc})") from None


def _json_default(value):
    if isinstance(value, (Path, os.PathLike)):
        return str(value)
    if isinstance(value, (np.integer, np.floating, np.bool_)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON")


def _check_header(path: Path) -> None:
    if path.is_dir():
        refuse_old_format(path)
        raise DataError(f"{path}: is a folder, not a place database file (e.g. {path / 'map.db'})")
    try:
        with open(path, "rb") as fh:
            head = fh.read(len(SQLITE_MAGIC))
    except FileNotFoundError:
        raise DataError(f"{path}: no such place database (make one with `fdnet database build`)") from None
    except OSError as exc:
        raise DataError(f"{path}: cannot read the place database ({exc.strerror or exc})") from None
    if not head:
        raise DataError(f"{path}: an empty file, not an fdnet place database")
    if head != SQLITE_MAGIC:
        raise DataError(f"{path}: not an fdnet place database (not a SQLite file)")


def _describe_foreign(conn: sqlite3.Connection) -> str:
    tables = [r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table' ORDER BY name")]
    return f"it has tables: {', '.join(tables)}" if tables else "it has no tables"


def _sqlite_message(exc: sqlite3.Error, path=None) -> str:
    text = str(exc)
    if "locked" in text or "busy" in text:
        return f"another process held the database's write lock for more than {BUSY_TIMEOUT_S:.0f} s ({text})"
    if path is not None and path != MEMORY and any(
            words in text for words in ("unable to open", "disk I/O error", "readonly", "disk is full")):
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


def _read_only_storage(path: Path) -> bool:
    """True when the database's folder cannot be written (read-only media, a read-only mount or
    share): SQLite's write-ahead log then cannot create its ``-shm`` file to open it as usual."""
    return not os.access(path.resolve().parent, os.W_OK)


@contextlib.contextmanager
def _sqlite_errors(path, doing: str) -> Iterator[None]:
    """SQLite's exceptions as the project's errors, naming the file and what was being done."""
    try:
        yield
    except sqlite3.Error as exc:
        raise DataError(f"{path}: {doing}: {_sqlite_message(exc, path)}") from None


@contextlib.contextmanager
def _transaction(conn: sqlite3.Connection, mode: str) -> Iterator[sqlite3.Connection]:
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


def _connect(target: str, uri: bool = False) -> sqlite3.Connection:
    # isolation_level=None: the module must not open transactions behind our back; each add is
    # exactly the BEGIN IMMEDIATE ... COMMIT written below.
    conn = sqlite3.connect(target, timeout=BUSY_TIMEOUT_S, isolation_level=None, uri=uri)
    # FULL, not NORMAL: with WAL, NORMAL may lose the last commits on power loss, and the
    # database promises that an add it has acknowledged is on disk.
    conn.execute("PRAGMA synchronous = FULL")
    return conn


def _connect_read_only(path: Path) -> sqlite3.Connection:
    """A database on storage this process cannot write. Without a write-ahead log left beside it
    the file holds every committed add and is opened ``immutable`` (no -shm needed, no locks: on
    read-only storage nobody can change it). A log left there (a writer killed, the medium then
    made read-only) holds commits not yet in the file: they are read through its ``-shm`` file
    (``mode=ro``), and refused with a clear message when that is missing too."""
    uri = path.resolve().as_uri()
    wal = Path(f"{path}-wal")
    if not (wal.exists() and wal.stat().st_size > 0):
        return _connect(uri + "?immutable=1", uri=True)
    try:
        conn = _connect(uri + "?mode=ro", uri=True)
        conn.execute("SELECT count(*) FROM sqlite_master").fetchone()
        return conn
    except sqlite3.Error:
        raise DataError(f"{path}: its folder cannot be written and its write-ahead log {wal} holds adds not yet "
                        f"copied into the file, which SQLite can only read with {path}-shm beside it; copy the "
                        "database and its -wal file to a writable folder and open it there") from None


def check_place_names(names: Sequence[str]) -> None:
    """Refuse a place name that is not valid UTF-8 (a file name Python keeps as surrogates):
    SQLite text is UTF-8, so it could not be stored. Callers check before describing images."""
    for name in names:
        try:
            str(name).encode("utf-8")
        except UnicodeEncodeError:
            raise DataError(f"{os.fsencode(str(name))!r}: the file name is not valid UTF-8, which a place database "
                            "cannot store as a place name; rename the file") from None


def _is_fdnet_database(conn: sqlite3.Connection) -> bool:
    return conn.execute("PRAGMA application_id").fetchone()[0] == APPLICATION_ID


def check_can_create(path: str | os.PathLike, overwrite: bool = False) -> None:
    """Refuse, before any image is described, a database path that ``create`` would refuse.

    A file with content is only replaced with ``overwrite``, and only if it is an fdnet place
    database; an empty file, or a SQLite file without tables (what a create killed before its
    first commit leaves), holds nothing to lose and is simply reused.
    """
    path = Path(path)
    if str(path) == MEMORY:
        return
    refuse_old_format(path)
    if path.is_dir():
        raise ConfigError(f"{path}: is a folder; name the database file to write (e.g. {path / 'map.db'})")
    if path.exists():
        if path.stat().st_size == 0:
            return
        with open(path, "rb") as fh:
            if fh.read(len(SQLITE_MAGIC)) != SQLITE_MAGIC:
                raise DataError(f"{path}: exists and is not an fdnet place database (not a SQLite file); "
                                "refusing to overwrite it")
        conn = _connect(path.resolve().as_uri() + "?mode=rw", uri=True)
        try:
            with _sqlite_errors(path, "checking the existing file"):
                tables = conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'").fetchall()
                if tables and not _is_fdnet_database(conn):
                    raise DataError(f"{path}: is a SQLite database but not an fdnet place database "
                                    f"({_describe_foreign(conn)}); refusing to overwrite it")
        finally:
            conn.close()
        if tables and not overwrite:
            raise ConfigError(f"{path}: already exists; pass --overwrite (overwrite=True) to replace it")
    elif Path(f"{path}-wal").exists():
        # SQLite would replay a stray log into the new file: a corrupt database from the start.
        raise DataError(f"{path}-wal: a write-ahead log left without its database; remove it "
                        f"(and {path}-shm) before creating {path}")


@dataclass(frozen=True)
class _Identity:
    database_id: str
    method: str
    settings: dict
    method_options: dict
    dim: int
    dot_product: bool
    index_settings: IndexSettings
    fingerprint: str
    created: str
    fdnet_version: str


def _index_settings(value, where: str, error: type = DataError) -> IndexSettings:
    if not isinstance(value, dict):
        raise error(f"{where}: must be an object of index settings, got {type(value).__name__}")
    known = {f.name: f.type for f in fields(IndexSettings)}
    unknown = sorted(set(value) - set(known))
    if unknown:
        raise error(f"{where}: unknown index setting(s) {', '.join(unknown)}; known: {', '.join(known)}")
    settings = IndexSettings(**value)
    if not isinstance(settings.kind, str) or settings.kind not in INDEX_KINDS:
        raise error(f"{where}: index kind {settings.kind!r} is not one of {', '.join(INDEX_KINDS)}")
    return check_settings(settings, where, error)


def _read_identity(path, conn: sqlite3.Connection) -> _Identity:
    columns = ("database_id", "method", "settings", "method_options", "dim", "dot_product", "index_settings",
               "fingerprint", "created", "fdnet_version")
    row = conn.execute(f"SELECT {', '.join(columns)} FROM fdnet_database").fetchone()
    if row is None:
        raise DataError(f"{path}: the fdnet_database table is empty; the file is damaged")
    values = dict(zip(columns, row))

    def column(name: str, kind: type):
        value = values[name]
        if not isinstance(value, kind) or isinstance(value, bool):
            raise DataError(f"{path}: column {name} of fdnet_database must be {kind.__name__}, got {value!r}")
        return value

    def json_column(name: str):
        text = column(name, str)
        try:
            value = json.loads(text)
        except json.JSONDecodeError as exc:
            raise DataError(f"{path}: column {name} of fdnet_database is not valid JSON ({exc})") from None
        if not isinstance(value, dict):
            raise DataError(f"{path}: column {name} of fdnet_database must be a JSON object")
        return value

    return _Identity(
        database_id=column("database_id", str), method=column("method", str),
        settings=json_column("settings"), method_options=json_column("method_options"),
        dim=column("dim", int), dot_product=bool(column("dot_product", int)),
        index_settings=_index_settings(json_column("index_settings"), f"{path}: column index_settings"),
        fingerprint=column("fingerprint", str), created=column("created", str),
        fdnet_version=column("fdnet_version", str))


class PlaceDatabase:
    """One place database file (or an in-memory one). Make it with :meth:`create` or
    :meth:`for_descriptor`, open it with :meth:`open`; :meth:`add` and :meth:`query` may be
    called by several processes on the same file at once."""

    def __init__(self, path: str, conn: sqlite3.Connection | None, identity: _Identity,
                 similarity: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None):
        self.path = path
        self._conn = conn
        self._identity = identity
        self.similarity = similarity
        #: opened read-only because its folder cannot be written (see :meth:`open`): queries and
        #: info work, adds are refused
        self.read_only = False
        # What this process has loaded so far; `_refresh` brings it up to the file's state.
        self._loaded_version = -1
        self._last_id = 0
        self._names: list[str] = []
        self._positions: list[tuple[float, float] | None] = []
        self._metadata: list[str | None] = []
        # Vectors kept in this process only for methods searched with their own similarity;
        # a dot-product database keeps them in its index (reading them back on request).
        self._vector_chunks: list[np.ndarray] = []
        # Made on the first read, so a process that only adds never imports faiss.
        self._index: VectorIndex | None = None
        # Places the derived index cache file held when it was loaded or written (see _refresh).
        self._cached_places = 0

    # ------------------------------------------------------------------ identity
    @property
    def dim(self) -> int:
        return self._identity.dim

    @property
    def method(self) -> str:
        return self._identity.method

    @property
    def method_settings(self) -> dict:
        return dict(self._identity.settings)

    @property
    def method_options(self) -> dict:
        return dict(self._identity.method_options)

    @property
    def dot_product(self) -> bool:
        return self._identity.dot_product

    @property
    def index_settings(self) -> IndexSettings:
        return self._identity.index_settings

    @property
    def fingerprint(self) -> str:
        return self._identity.fingerprint

    # ------------------------------------------------------------------ making and opening
    @classmethod
    def for_descriptor(cls, descriptor, index: IndexSettings | None = None, method_options: dict | None = None,
                       path: str | os.PathLike = MEMORY, overwrite: bool = False) -> "PlaceDatabase":
        """An empty database for ``descriptor``'s vectors: in memory by default (a scratch map
        for one process), or the file ``path`` (see :meth:`create`)."""
        return cls.create(path, descriptor, index=index, method_options=method_options, overwrite=overwrite)

    @classmethod
    def create(cls, path: str | os.PathLike, descriptor, *, index: IndexSettings | None = None,
               method_options: dict | None = None, overwrite: bool = False,
               vectors: np.ndarray | None = None, names: Sequence[str] | None = None,
               positions: Sequence[tuple[float, float] | None] | np.ndarray | None = None,
               metadata: Sequence[dict | None] | None = None, allow_duplicates: bool = False,
               batches: Iterable | None = None) -> "PlaceDatabase":
        """Write a new database for ``descriptor``'s vectors, with an optional first batch of
        places, in one transaction: a crash leaves no half-made database behind.

        ``batches`` (instead of ``vectors``/``names``...) gives the first places as an iterable of
        ``(vectors, names)`` or ``(vectors, names, positions, metadata)`` chunks, all stored in
        the same transaction (see :meth:`add_batches`): a map of any size, a chunk in memory at a
        time.

        ``method_options`` rebuild the descriptor later (``fdnet.descriptors.create(method,
        **method_options)``). An existing file is refused unless ``overwrite``; then an existing
        place database is replaced in one transaction, and any other file is still refused.
        """
        target = str(path)
        check_can_create(target, overwrite)
        index = index or IndexSettings()
        index_json = _canonical_json(vars(index), "index settings")
        _index_settings(json.loads(index_json), "index settings", ConfigError)
        settings_json = _canonical_json(descriptor.settings(), f"{descriptor.name} settings")
        options_json = _canonical_json(dict(method_options or {}), "method_options")
        from fdnet import __version__

        identity = _Identity(
            database_id=uuid.uuid4().hex, method=descriptor.name, settings=json.loads(settings_json),
            method_options=json.loads(options_json), dim=int(descriptor.dim),
            dot_product=bool(descriptor.dot_product_similarity), index_settings=index,
            fingerprint=descriptor.fingerprint(),
            created=datetime.now(timezone.utc).isoformat(timespec="seconds"), fdnet_version=__version__)
        similarity = None if identity.dot_product else descriptor.similarity
        db = cls(target, None, identity, similarity)
        # Before the file is touched: a refused first batch must not leave a file behind.
        if batches is not None and vectors is not None:
            raise ConfigError("give the first places as vectors/names or as batches, not both")
        batch = None if vectors is None else db._prepare(vectors, names, positions, metadata, None)
        if target != MEMORY:
            Path(target).parent.mkdir(parents=True, exist_ok=True)
        with _sqlite_errors(target, "creating the place database"):
            conn = db._conn = _connect(target)
        try:
            with _sqlite_errors(target, "creating the place database"):
                if target != MEMORY:
                    mode = conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]
                    if str(mode).lower() != "wal":
                        raise DataError(f"{target}: the file system does not support SQLite's write-ahead log "
                                        f"(journal mode stays {mode!r}); put the database on a local disk")
                with _transaction(conn, "IMMEDIATE"):
                    existing = [r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")]
                    if existing:
                        # Checked again under the write lock: another build may have won the race.
                        if not _is_fdnet_database(conn):
                            raise DataError(f"{target}: is a SQLite database but not an fdnet place database "
                                            f"({_describe_foreign(conn)}); refusing to overwrite it")
                        if not overwrite:
                            raise ConfigError(f"{target}: already exists; pass --overwrite (overwrite=True) "
                                              "to replace it")
                        for table in _TABLES:
                            conn.execute(f"DROP TABLE IF EXISTS {table}")
                    for statement in _SCHEMA.split(";"):
                        if statement.strip():
                            conn.execute(statement)
                    conn.execute(f"PRAGMA application_id = {APPLICATION_ID}")
                    conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
                    conn.execute(
                        "INSERT INTO fdnet_database (singleton, database_id, method, settings, method_options, dim, "
                        "dot_product, index_settings, fingerprint, data_version, created, fdnet_version) "
                        "VALUES (1, ?, ?, ?, ?, ?, ?, ?, ?, 0, ?, ?)",
                        (identity.database_id, identity.method, settings_json, options_json, identity.dim,
                         int(identity.dot_product), index_json, identity.fingerprint, identity.created,
                         identity.fdnet_version))
                    if batch is not None:
                        db._insert(conn, batch, allow_duplicates)
                    elif batches is not None:
                        db._insert_batches(conn, batches, allow_duplicates)
        except BaseException:
            conn.close()
            raise
        return db

    @classmethod
    def open(cls, path: str | os.PathLike, descriptor=None) -> "PlaceDatabase":
        """Open an existing database. With ``descriptor``, refuse it unless its fingerprint is the
        database's (same method, settings and weights), and use its similarity for methods whose
        comparison is not a dot product."""
        path = Path(path)
        refuse_old_format(path)
        _check_header(path)
        target = str(path)
        read_only = _read_only_storage(path)
        with _sqlite_errors(target, "opening the place database"):
            # mode=rw: a path that vanished since the check must not become a new empty file.
            conn = _connect_read_only(path) if read_only else _connect(path.resolve().as_uri() + "?mode=rw", uri=True)
        try:
            with _sqlite_errors(target, "reading the place database"):
                if not _is_fdnet_database(conn):
                    foreign = _describe_foreign(conn)
                    if foreign == "it has no tables":  # what a create stopped before its first commit leaves
                        raise DataError(f"{target}: an empty SQLite file, not yet an fdnet place database (a "
                                        "`database build` that did not finish, e.g. on a full disk or killed, "
                                        "leaves this); build it again with --out there (the file is reused)")
                    raise DataError(f"{target}: a SQLite database but not an fdnet place database ({foreign})")
                schema = conn.execute("PRAGMA user_version").fetchone()[0]
                if schema > SCHEMA_VERSION:
                    raise DataError(f"{target}: written by a newer fdnet (schema version {schema}; this one "
                                    f"reads up to {SCHEMA_VERSION}); upgrade fdnet")
                if schema < 1:
                    raise DataError(f"{target}: has no fdnet schema version; the file is damaged")
                if not read_only:
                    # Persistent once set; this only matters for a file copied from a non-WAL tool.
                    conn.execute("PRAGMA journal_mode = WAL")
                identity = _read_identity(target, conn)
            similarity = None
            if descriptor is not None:
                _check_descriptor(target, identity, descriptor)
                similarity = None if identity.dot_product else descriptor.similarity
        except BaseException:
            conn.close()
            raise
        db = cls(target, conn, identity, similarity)
        db.read_only = read_only
        return db

    def check_descriptor(self, descriptor) -> None:
        """Refuse ``descriptor`` unless it is the model whose vectors the database holds."""
        _check_descriptor(self.path, self._identity, descriptor)

    def close(self) -> None:
        self._conn.close()

    def __enter__(self) -> "PlaceDatabase":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ adding
    def __len__(self) -> int:
        """Places in the database now (including other processes' committed adds)."""
        with _sqlite_errors(self.path, "counting places"):
            return int(self._conn.execute("SELECT count(*) FROM places").fetchone()[0])

    def existing_names(self, names: Sequence[str]) -> set[str]:
        """Which of ``names`` the database already holds (to skip describing them again)."""
        with _sqlite_errors(self.path, "looking up place names"):
            return _names_present(self._conn, [str(n) for n in names])

    def add(self, vectors: np.ndarray, names: Sequence[str],
            positions: Sequence[tuple[float, float] | None] | np.ndarray | None = None, *,
            metadata: Sequence[dict | None] | None = None, fingerprint: str | Sequence[str] | None = None,
            allow_duplicates: bool = False) -> AddResult:
        """Store a batch of places in one transaction: all of it is added or none.

        ``fingerprint`` is that of the descriptor that made ``vectors``; a different one is
        refused (another model's vectors are not comparable). Names already in the database are
        skipped and reported in the result unless ``allow_duplicates``. Non-finite vectors are
        refused (a NaN would be stored and never found).
        """
        batch = self._prepare(vectors, names, positions, metadata, fingerprint)
        if not batch["names"]:
            with _sqlite_errors(self.path, "reading the data version"):
                version = self._conn.execute("SELECT data_version FROM fdnet_database").fetchone()[0]
            return AddResult(0, [], len(self), int(version))
        with _sqlite_errors(self.path, "adding places"):
            with _transaction(self._conn, "IMMEDIATE") as conn:
                self._check_same_database(conn)
                return self._insert(conn, batch, allow_duplicates)

    def add_batches(self, batches: Iterable, *, fingerprint: str | Sequence[str] | None = None,
                    allow_duplicates: bool = False) -> AddResult:
        """Store many chunks of places in ONE transaction: all of them are added or none (an
        ``add`` of a million images, a chunk in memory at a time). Each chunk is
        ``(vectors, names)`` or ``(vectors, names, positions, metadata)``, checked as :meth:`add`
        checks a batch; a refused chunk rolls back the chunks before it. The data version goes up
        once. Chunks should be ready data (e.g. read back from a spool file): the write lock is
        held while they are consumed, so describing images inside the iterable would make other
        writers wait.
        """
        if fingerprint is not None:
            _check_fingerprint(self.path, self._identity, fingerprint, None)
        with _sqlite_errors(self.path, "adding places"):
            with _transaction(self._conn, "IMMEDIATE") as conn:
                self._check_same_database(conn)
                return self._insert_batches(conn, batches, allow_duplicates)

    def _insert_batches(self, conn: sqlite3.Connection, batches: Iterable, allow_duplicates: bool) -> AddResult:
        added, skipped = 0, []
        for chunk in batches:
            if not isinstance(chunk, (tuple, list)) or len(chunk) not in (2, 4):
                raise ConfigError(f"{self.path}: a batch must be (vectors, names) or (vectors, names, positions, "
                                  "metadata)")
            vectors, names = chunk[0], chunk[1]
            positions, metadata = (chunk[2], chunk[3]) if len(chunk) == 4 else (None, None)
            prepared = self._prepare(vectors, names, positions, metadata, None)
            if prepared["names"]:
                kept, refused = self._insert_rows(conn, prepared, allow_duplicates)
                added += kept
                skipped.extend(refused)
        if added:
            conn.execute("UPDATE fdnet_database SET data_version = data_version + 1")
        version = conn.execute("SELECT data_version FROM fdnet_database").fetchone()[0]
        total = conn.execute("SELECT count(*) FROM places").fetchone()[0]
        return AddResult(added, skipped, int(total), int(version))

    def _prepare(self, vectors, names, positions, metadata, fingerprint) -> dict:
        """Check a batch completely before the transaction starts, so a refusal changes nothing."""
        if fingerprint is not None:
            _check_fingerprint(self.path, self._identity, fingerprint, None)
        try:
            v = np.asarray(vectors, dtype=np.float32)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{self.path}: vectors are not a numeric array ({exc})") from None
        if v.ndim != 2 or v.shape[1] != self.dim:
            raise ConfigError(f"{self.path}: holds {self.dim}-d vectors ({self.method}), got shape {v.shape}")
        if names is None or len(names) != len(v):
            raise ConfigError(f"{self.path}: {len(v)} vectors but {0 if names is None else len(names)} names")
        names = [str(n) for n in names]
        check_place_names(names)
        bad = np.flatnonzero(~np.isfinite(v).all(axis=1))
        if len(bad):
            listed = ", ".join(names[i] for i in bad[:5]) + (f" and {len(bad) - 5} more" if len(bad) > 5 else "")
            raise DataError(f"{self.path}: refusing {len(bad)} non-finite vector(s) (NaN or inf) for {listed}; "
                            "nothing was added (a NaN place can never be matched)")
        xs: list[float | None] = [None] * len(v)
        ys: list[float | None] = [None] * len(v)
        if positions is not None:
            if len(positions) != len(v):
                raise ConfigError(f"{self.path}: {len(v)} vectors but {len(positions)} positions")
            for i, p in enumerate(positions):
                if p is None:
                    continue
                try:
                    x, y = (float(c) for c in p)
                except (TypeError, ValueError):
                    raise ConfigError(f"{self.path}: position of {names[i]} must be (x, y), got {p!r}") from None
                if not (np.isfinite(x) and np.isfinite(y)):
                    raise ConfigError(f"{self.path}: position of {names[i]} is not finite: {p!r}")
                xs[i], ys[i] = x, y
        texts: list[str | None] = [None] * len(v)
        if metadata is not None:
            if len(metadata) != len(v):
                raise ConfigError(f"{self.path}: {len(v)} vectors but {len(metadata)} metadata entries")
            for i, meta in enumerate(metadata):
                if meta is not None:
                    if not isinstance(meta, dict):
                        raise ConfigError(f"{self.path}: metadata of {names[i]} must be a dict, got "
                                          f"{type(meta).__name__}")
                    texts[i] = _canonical_json(meta, f"{self.path}: metadata of {names[i]}")
        blobs = [row.tobytes() for row in v.astype("<f4", copy=False)]
        return {"names": names, "x": xs, "y": ys, "metadata": texts, "blobs": blobs}

    def _check_same_database(self, conn: sqlite3.Connection) -> None:
        row = conn.execute("SELECT database_id FROM fdnet_database").fetchone()
        if row is None or row[0] != self._identity.database_id:
            raise DataError(f"{self.path}: was rebuilt (build --overwrite) by another process while open here; "
                            "open it again")

    def _insert(self, conn: sqlite3.Connection, batch: dict, allow_duplicates: bool) -> AddResult:
        added, skipped = self._insert_rows(conn, batch, allow_duplicates)
        if added:
            conn.execute("UPDATE fdnet_database SET data_version = data_version + 1")
        version = conn.execute("SELECT data_version FROM fdnet_database").fetchone()[0]
        total = conn.execute("SELECT count(*) FROM places").fetchone()[0]
        return AddResult(added, skipped, int(total), int(version))

    def _insert_rows(self, conn: sqlite3.Connection, batch: dict, allow_duplicates: bool) -> tuple[int, list[str]]:
        """Insert a prepared batch (inside the caller's transaction): (places added, names skipped)."""
        names = batch["names"]
        keep = list(range(len(names)))
        skipped: list[str] = []
        if not allow_duplicates:
            present = _names_present(conn, names)
            keep = []
            for i, name in enumerate(names):
                if name in present:
                    skipped.append(name)
                else:
                    keep.append(i)
                    present.add(name)  # a name twice in one batch is a duplicate too
        conn.executemany("INSERT INTO places (name, x, y, metadata, vector) VALUES (?, ?, ?, ?, ?)",
                         [(names[i], batch["x"][i], batch["y"][i], batch["metadata"][i], batch["blobs"][i])
                          for i in keep])
        return len(keep), skipped

    # ------------------------------------------------------------------ reading
    @property
    def index_cache_path(self) -> Path | None:
        """Where the derived index of an approximate kind (hnsw, ivf, ivfpq) is cached: beside
        the database file, ``map.db.fdnet-index``. None for ``flat`` (rebuilding it is a copy)
        and in-memory databases."""
        if self.path == MEMORY or not self.dot_product or self.index_settings.kind == "flat":
            return None
        return Path(f"{self.path}{INDEX_CACHE_SUFFIX}")

    def _load_cached_index(self, conn: sqlite3.Connection) -> tuple[VectorIndex | None, int]:
        """The cached index and the last place id it holds, when the cache belongs to this
        database (same database_id, build settings and fingerprint) and holds exactly the places
        with id <= that id; otherwise (None, 0) and the index is rebuilt from the file."""
        cache = self.index_cache_path
        if cache is None or not cache.is_file():
            return None, 0
        try:
            header = VectorIndex.read_header(cache)
            meta = header.get("metadata", {})
            build = {k: v for k, v in vars(self.index_settings).items() if k not in ("ivf_probe", "hnsw_ef_search",
                                                                                     "refine")}
            cached = {k: v for k, v in header["settings"].items() if k in build}
            last_id, count = int(meta.get("last_id", -1)), int(header["count"])
            if (meta.get("database_id") != self._identity.database_id or cached != build
                    or meta.get("fingerprint") != self.fingerprint or header["dim"] != self.dim):
                return None, 0
            if conn.execute("SELECT count(*) FROM places WHERE id <= ?", (last_id,)).fetchone()[0] != count:
                return None, 0
            search = {k: getattr(self.index_settings, k) for k in ("ivf_probe", "hnsw_ef_search", "refine")}
            index = VectorIndex.load(cache, search=search)
        except (DataError, ConfigError, ValueError, TypeError, KeyError):
            return None, 0  # a damaged or foreign cache is only a cache: rebuild
        self._cached_places = count
        return index, last_id

    def _save_index_cache(self, force: bool = False) -> bool:
        """Write the index to its cache file when it was built here or grew by 5 % (at least
        1000 places) since the cache was read; a cache that cannot be written is skipped."""
        cache = self.index_cache_path
        if cache is None or self._index is None or len(self._index) == 0:
            return False
        grown = len(self._index) - self._cached_places
        if not force and self._cached_places and grown < max(1000, 0.05 * self._cached_places):
            return False
        try:
            self._index.save(cache, metadata={"database_id": self._identity.database_id,
                                              "data_version": self._loaded_version, "last_id": self._last_id,
                                              "fingerprint": self.fingerprint, "database": Path(self.path).name})
        except OSError:
            return False
        self._cached_places = len(self._index)
        return True

    def build_index(self) -> VectorIndex | None:
        """Load every place and build (train) the search index now rather than at the first query,
        and for hnsw/ivf/ivfpq write its cache beside the file (``index_cache_path``) so later
        processes load it instead of building it again. Returns the index (None for methods
        searched exhaustively with their own similarity)."""
        self._refresh()
        if self._index is not None:
            self._index.build()
            self._save_index_cache()
        return self._index

    def _refresh(self) -> None:
        """Load the places committed since the last call, from one consistent snapshot, a
        bounded number of rows at a time. Vectors of a dot-product database go into its index
        (loaded from the cache file when it is current, then extended by the newer places)."""
        built_here = False
        with _sqlite_errors(self.path, "reading places"):
            with _transaction(self._conn, "DEFERRED") as conn:
                self._check_same_database(conn)
                version = conn.execute("SELECT data_version FROM fdnet_database").fetchone()[0]
                if version == self._loaded_version:
                    return
                vectors_after = self._last_id
                if self.dot_product and self._index is None:
                    self._index, cached_last = self._load_cached_index(conn)
                    vectors_after = max(vectors_after, cached_last)
                    if self._index is None:
                        self._index = VectorIndex(self.dim, self.index_settings)
                        built_here = True
                rows = conn.execute("SELECT id, name, x, y, metadata FROM places WHERE id > ? ORDER BY id",
                                    (self._last_id,))
                last = self._last_id
                while chunk := rows.fetchmany(_ROWS_PER_FETCH):
                    self._names.extend(r[1] for r in chunk)
                    self._positions.extend(None if r[2] is None else (float(r[2]), float(r[3])) for r in chunk)
                    self._metadata.extend(r[4] for r in chunk)
                    last = chunk[-1][0]
                for vectors in self._read_vectors(conn, vectors_after, last):
                    if self.dot_product:
                        self._index.add(vectors)
                    else:
                        self._vector_chunks.append(vectors)
                self._last_id = last
                self._loaded_version = version
        if built_here and self._index is not None and self._index.trainable and len(self._index) >= 10_000:
            # an approximate index worth caching: train it once, here, and keep it
            self._index.build()
            self._save_index_cache(force=True)

    def _read_vectors(self, conn: sqlite3.Connection, after_id: int, up_to_id: int) -> Iterator[np.ndarray]:
        """Stored vectors of the places with after_id < id <= up_to_id, in id order, in chunks."""
        rows = conn.execute("SELECT id, name, vector FROM places WHERE id > ? AND id <= ? ORDER BY id",
                            (after_id, up_to_id))
        width = 4 * self.dim
        while chunk := rows.fetchmany(_ROWS_PER_FETCH):
            for row in chunk:
                if not isinstance(row[2], bytes) or len(row[2]) != width:
                    raise DataError(f"{self.path}: place {row[1]!r} (id {row[0]}) has a vector of "
                                    f"{len(row[2]) if isinstance(row[2], bytes) else type(row[2]).__name__} bytes, "
                                    f"expected {width} ({self.dim} float32); the file is damaged")
            yield np.frombuffer(b"".join(r[2] for r in chunk), dtype="<f4").reshape(len(chunk), self.dim).astype(
                np.float32)

    @property
    def names(self) -> list[str]:
        self._refresh()
        return list(self._names)

    @property
    def positions(self) -> list[tuple[float, float] | None]:
        self._refresh()
        return list(self._positions)

    @property
    def metadata(self) -> list[dict | None]:
        """Every place's metadata (e.g. a loop-closure frame's timestamp), in insertion order."""
        self._refresh()
        return [None if text is None else json.loads(text) for text in self._metadata]

    @property
    def vectors(self) -> np.ndarray:
        """Every stored vector, in insertion order (read from the file for dot-product databases,
        whose vectors otherwise live only in the index)."""
        self._refresh()
        if self.dot_product:
            with _sqlite_errors(self.path, "reading vectors"):
                with _transaction(self._conn, "DEFERRED") as conn:
                    chunks = list(self._read_vectors(conn, 0, self._last_id))
            return np.concatenate(chunks) if chunks else np.zeros((0, self.dim), dtype=np.float32)
        if not self._vector_chunks:
            return np.zeros((0, self.dim), dtype=np.float32)
        if len(self._vector_chunks) > 1:
            self._vector_chunks = [np.concatenate(self._vector_chunks)]
        return self._vector_chunks[0]

    def query(self, vectors: np.ndarray, k: int = 5, exclude_last: int = 0) -> list[list[Match]]:
        """Top-``k`` stored places per query vector, best first.

        ``exclude_last`` ignores the most recently added places: for loop closure a robot's
        previous few frames always look alike and must not count as revisits. Places other
        processes added since the last call are included.
        """
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
            raise ConfigError(f"{self.path}: top-k must be a whole number of at least 1, got {k!r}")
        if isinstance(exclude_last, bool) or not isinstance(exclude_last, (int, np.integer)) or exclude_last < 0:
            raise ConfigError(f"{self.path}: exclude-last must be a whole number of at least 0, got {exclude_last!r}")
        self._refresh()
        count = len(self._names)
        if count == 0:
            raise ConfigError(f"{self.path}: the place database is empty: add places before querying")
        q = np.asarray(vectors, dtype=np.float32)
        if q.ndim == 1:
            q = q[None]
        if q.ndim != 2 or q.shape[1] != self.dim:
            raise ConfigError(f"{self.path}: holds {self.dim}-d vectors ({self.method}), "
                              f"got queries of shape {q.shape}")
        bad = np.flatnonzero(~np.isfinite(q).all(axis=1))
        if len(bad):
            raise DataError(f"{self.path}: query vector(s) {', '.join(map(str, bad[:5]))} are not finite (NaN or inf)")
        searchable = count - int(exclude_last)
        if searchable <= 0:
            return [[] for _ in range(len(q))]
        want = min(int(k), searchable)
        if self._index is not None:
            # Ask for extra candidates, then drop the excluded (most recent) ones.
            idx, scores = self._index.search(q, min(count, want + int(exclude_last)))
        else:
            if self.similarity is None:
                raise ConfigError(f"{self.path}: method {self.method!r} compares vectors with its own similarity; "
                                  "open the database with its descriptor: PlaceDatabase.open(path, descriptor)")
            idx, scores = top_k(q, self.vectors[:searchable], want, similarity=self.similarity)
        out = []
        for row_i, row_s in zip(idx, scores):
            keep = [(int(i), float(s)) for i, s in zip(row_i, row_s) if 0 <= i < searchable][:want]
            out.append([Match(i, self._names[i], s, self._positions[i],
                              None if self._metadata[i] is None else json.loads(self._metadata[i]))
                        for i, s in keep])
        return out

    # ------------------------------------------------------------------ database metadata
    def set_metadata(self, key: str, value: dict) -> None:
        """Store ``value`` (a JSON object, e.g. a calibration) under ``key`` in the database's own
        metadata, in one transaction (readers see the old or the new value). The table is created
        on first use, so files written before it existed stay readable by every version."""
        text = _canonical_json(value, f"{self.path}: metadata {key!r}")
        with _sqlite_errors(self.path, f"storing metadata {key!r}"):
            with _transaction(self._conn, "IMMEDIATE") as conn:
                self._check_same_database(conn)
                conn.execute("CREATE TABLE IF NOT EXISTS fdnet_metadata (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
                conn.execute("INSERT OR REPLACE INTO fdnet_metadata (key, value) VALUES (?, ?)", (key, text))

    def get_metadata(self, key: str) -> dict | None:
        """The value stored under ``key`` by :meth:`set_metadata`, or None."""
        with _sqlite_errors(self.path, f"reading metadata {key!r}"):
            exists = self._conn.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'fdnet_metadata'"
                                        ).fetchone()
            row = self._conn.execute("SELECT value FROM fdnet_metadata WHERE key = ?", (key,)).fetchone() \
                if exists else None
        if row is None:
            return None
        try:
            return json.loads(row[0])
        except json.JSONDecodeError as exc:
            raise DataError(f"{self.path}: metadata {key!r} is not valid JSON ({exc})") from None

    def info(self) -> dict:
        """What ``fdnet database info`` prints: identity, size and versions, without loading vectors."""
        with _sqlite_errors(self.path, "reading the database summary"):
            with _transaction(self._conn, "DEFERRED") as conn:
                version = conn.execute("SELECT data_version FROM fdnet_database").fetchone()[0]
                places = conn.execute("SELECT count(*) FROM places").fetchone()[0]
                schema = conn.execute("PRAGMA user_version").fetchone()[0]
                journal = conn.execute("PRAGMA journal_mode").fetchone()[0]
        ident = self._identity
        return {
            "path": self.path, "places": int(places), "method": ident.method, "dim": ident.dim,
            "dot_product": ident.dot_product, "fingerprint": ident.fingerprint, "settings": ident.settings,
            "method_options": ident.method_options, "index": vars(ident.index_settings),
            "schema_version": int(schema), "data_version": int(version), "journal_mode": journal,
            "created": ident.created, "fdnet_version": ident.fdnet_version,
        }


def _names_present(conn: sqlite3.Connection, names: Sequence[str]) -> set[str]:
    unique = list(dict.fromkeys(names))
    found: set[str] = set()
    for start in range(0, len(unique), _NAMES_PER_QUERY):
        chunk = unique[start:start + _NAMES_PER_QUERY]
        marks = ", ".join("?" * len(chunk))
        found.update(r[0] for r in conn.execute(f"SELECT DISTINCT name FROM places WHERE name IN ({marks})", chunk))
    return found


def _check_descriptor(path, identity: _Identity, descriptor) -> None:
    _check_fingerprint(path, identity, descriptor.fingerprints(), descriptor.name)


def _check_fingerprint(path, identity: _Identity, fingerprint: str | Sequence[str], method: str | None) -> None:
    """Refuse vectors of another model. ``fingerprint`` may list several spellings of the same
    model's fingerprint (``Descriptor.fingerprints()``: databases built before the weights'
    locations were left out of it hold the older one)."""
    accepted = (fingerprint,) if isinstance(fingerprint, str) else tuple(fingerprint)
    fingerprint = accepted[0]
    if identity.fingerprint not in accepted:
        made_by = f"the {method!r} descriptor given has" if method else "these vectors come from"
        raise ConfigError(
            f"{path}: descriptor fingerprint mismatch: the database holds {identity.method!r} vectors with "
            f"fingerprint {short_fingerprint(identity.fingerprint)}, {made_by} {short_fingerprint(fingerprint)}; "
            "a different model (weights or settings changed since the database was built). Describe with "
            "the database's model, or build a new database (--overwrite)")


# ---------------------------------------------------------------------- the old folder format
@dataclass
class MigrationReport:
    places: int
    #: names whose vectors were NaN/inf in the old database (it stored them; they could never match)
    dropped_non_finite: list[str] = field(default_factory=list)
    #: names that occur more than once (kept: the old database held them)
    duplicate_names: int = 0


def _old_field(meta: dict, key: str, kinds, json_path: Path, what: str, required: bool = True, default=None):
    if key not in meta:
        if required:
            raise DataError(f"{json_path}: field {key!r} is missing (expected {what})")
        return default
    value = meta[key]
    if isinstance(value, bool) and bool not in (kinds if isinstance(kinds, tuple) else (kinds,)):
        raise DataError(f"{json_path}: field {key!r} must be {what}, got {value!r}")
    if not isinstance(value, kinds):
        raise DataError(f"{json_path}: field {key!r} must be {what}, got {type(value).__name__} {value!r:.60}")
    return value


def read_old_format(folder: str | os.PathLike) -> tuple[dict, np.ndarray]:
    """Validate and read an old ``database.json`` + ``vectors.npy`` folder.

    Every field is checked (the old loader accepted exactly these, with the same defaults), and
    the ``.npy`` header is checked against the JSON before any data is read, so a header claiming
    a huge shape is refused instead of allocated.
    """
    folder = Path(folder)
    json_path, npy_path = folder / "database.json", folder / "vectors.npy"
    if not folder.is_dir():
        raise DataError(f"{folder}: not a folder (the old format is a folder with database.json and vectors.npy)")
    try:
        meta = json.loads(json_path.read_text())
    except FileNotFoundError:
        raise DataError(f"{json_path}: not found; is {folder} an old-format place database?") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataError(f"{json_path}: not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise DataError(f"{json_path}: must hold a JSON object, got {type(meta).__name__}")
    version = _old_field(meta, "format_version", int, json_path, "the integer 1", required=False, default=1)
    if version != 1:
        raise DataError(f"{json_path}: field 'format_version' is {version}; only version 1 can be migrated")
    dim = _old_field(meta, "dim", int, json_path, "a positive integer")
    if dim < 1:
        raise DataError(f"{json_path}: field 'dim' must be a positive integer, got {dim}")
    method = _old_field(meta, "method", str, json_path, "a method name")
    settings = _old_field(meta, "method_settings", dict, json_path, "an object", required=False, default={})
    options = _old_field(meta, "method_options", dict, json_path, "an object", required=False, default={})
    dot_product = _old_field(meta, "dot_product", bool, json_path, "true or false")
    index = _index_settings(_old_field(meta, "index", dict, json_path, "an object", required=False, default={}),
                            f"{json_path}: field 'index'")
    names = _old_field(meta, "names", list, json_path, "a list of image names")
    for i, name in enumerate(names):
        if not isinstance(name, str):
            raise DataError(f"{json_path}: field 'names' entry {i} must be a string, got {name!r:.60}")
    positions = _old_field(meta, "positions", list, json_path, "a list of [x, y] or null", required=False,
                           default=[])
    if positions and len(positions) != len(names):
        raise DataError(f"{json_path}: field 'positions' has {len(positions)} entries but 'names' has {len(names)}")
    for i, p in enumerate(positions):
        ok = p is None or (isinstance(p, list) and len(p) == 2
                           and all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in p))
        if not ok:
            raise DataError(f"{json_path}: field 'positions' entry {i} must be [x, y] or null, got {p!r:.60}")
    vectors = _read_checked_npy(npy_path, (len(names), dim))
    return ({"dim": dim, "method": method, "method_settings": settings, "method_options": options,
             "dot_product": dot_product, "index": index, "names": names,
             "positions": [None if p is None else (float(p[0]), float(p[1])) for p in positions] or None},
            vectors)


def _read_checked_npy(npy_path: Path, shape: tuple[int, int]) -> np.ndarray:
    from numpy.lib import format as npy_format

    try:
        with open(npy_path, "rb") as fh:
            try:
                major, minor = npy_format.read_magic(fh)
                if (major, minor) == (1, 0):
                    header_shape, fortran, dtype = npy_format.read_array_header_1_0(fh)
                elif (major, minor) == (2, 0):
                    header_shape, fortran, dtype = npy_format.read_array_header_2_0(fh)
                else:
                    raise DataError(f"{npy_path}: .npy format version {major}.{minor} is not supported (1.0 or 2.0)")
            except ValueError as exc:
                raise DataError(f"{npy_path}: not a valid .npy file ({exc})") from None
            if tuple(header_shape) != shape:
                raise DataError(f"{npy_path}: holds an array of shape {tuple(header_shape)} but database.json "
                                f"describes {shape[0]} places of dimension {shape[1]}")
            if dtype.kind != "f" or dtype.itemsize not in (4, 8):
                raise DataError(f"{npy_path}: holds {dtype} values, expected float32 vectors")
            expected = int(np.prod(shape)) * dtype.itemsize
            available = os.fstat(fh.fileno()).st_size - fh.tell()
            if available != expected:
                raise DataError(f"{npy_path}: has {available} bytes of data, its header promises {expected}; "
                                "the file is truncated or damaged")
            data = np.fromfile(fh, dtype=dtype, count=int(np.prod(shape)))
    except FileNotFoundError:
        raise DataError(f"{npy_path}: not found; an old-format database needs vectors.npy") from None
    except OSError as exc:
        raise DataError(f"{npy_path}: cannot read ({exc.strerror or exc})") from None
    return data.reshape(shape, order="F" if fortran else "C").astype(np.float32)


def migrate_old_format(folder: str | os.PathLike, out: str | os.PathLike, overwrite: bool = False,
                       create_descriptor: Callable | None = None) -> MigrationReport:
    """Convert an old-format folder into a database file ``out``.

    The descriptor is rebuilt from the folder's ``method_options`` to compute the fingerprint; it
    must have the recorded dimension, similarity and settings, otherwise the vectors were made
    by a different model than the one the options now build, and the migration is refused.
    """
    folder = Path(folder)
    json_path = folder / "database.json"
    check_can_create(out, overwrite)
    meta, vectors = read_old_format(folder)
    if create_descriptor is None:
        from fdnet.descriptors import create as create_descriptor
    from fdnet.errors import FdnetError

    try:
        descriptor = create_descriptor(meta["method"], **meta["method_options"])
    except FdnetError as exc:
        raise ConfigError(f"{json_path}: cannot rebuild the {meta['method']!r} descriptor from its method_options "
                          f"to fingerprint it ({exc}); fix method_options in database.json") from None
    if int(descriptor.dim) != meta["dim"] or bool(descriptor.dot_product_similarity) != meta["dot_product"]:
        raise DataError(f"{json_path}: records {meta['dim']}-d vectors (dot_product={meta['dot_product']}) but the "
                        f"descriptor rebuilt from method_options makes {descriptor.dim}-d vectors "
                        f"(dot_product={descriptor.dot_product_similarity})")
    rebuilt = json.loads(_canonical_json(descriptor.settings(), "settings"))
    recorded = json.loads(_canonical_json(meta["method_settings"], "method_settings"))
    if recorded and recorded != rebuilt:
        raise DataError(f"{json_path}: method_settings {recorded} differ from the settings of the descriptor rebuilt "
                        f"from method_options {rebuilt}; the vectors were made by another model")
    names = meta["names"]
    finite = np.isfinite(vectors).all(axis=1)
    keep = np.flatnonzero(finite)
    positions = meta["positions"]
    PlaceDatabase.create(
        out, descriptor, index=meta["index"], method_options=meta["method_options"], overwrite=overwrite,
        vectors=vectors[keep], names=[names[i] for i in keep],
        positions=None if positions is None else [positions[i] for i in keep],
        allow_duplicates=True).close()
    return MigrationReport(places=len(keep), dropped_non_finite=[names[i] for i in np.flatnonzero(~finite)],
                           duplicate_names=len(names) - len(set(names)))
