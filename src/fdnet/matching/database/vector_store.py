"""A large place database's vectors in a file beside it, searched through compressed codes.

Below ``compressed_from`` places (an :class:`~fdnet.matching.index.IndexSettings` field, never
below :data:`COMPRESSED_FLOOR`) a dot-product database keeps its vectors in memory, in its
search index. From there on (a database in a file):

* every add also appends the new places' vectors to ``map.db.vectors``
  (:class:`~fdnet.matching.compressed.VectorFile`: float32 rows in place order, no header),
  made durable (fsync) and counted in the table ``fdnet_vector_file`` in the **same SQLite
  transaction** as the places. A writer killed before its commit leaves the file longer than
  the committed count; the next add opens the file under the write lock with that count, which
  cuts the extra rows off, so the file is the old state again. A process that only reads opens
  it read-only at the committed count (no write lock, nothing cut; a database opened read-only
  too). The add that
  first reaches the size copies the places stored before it (their SQLite blobs, which stay the
  database's own copy: export, the index cache's digest and ``vectors`` read them);
* queries go through :class:`CompressedPlaces`: a
  :class:`~fdnet.matching.compressed.CompressedIndex` (codes in memory) re-ranking its short
  list exactly with rows read from the file. The codes are derived from committed rows only:
  built (trained, then the file encoded in chunks) by the first process that queries, cached
  beside the database (:mod:`~fdnet.matching.database.codes_cache`, ``map.db.fdnet-codes``),
  loaded by later processes and extended with the rows committed since;
* the loop-closure detector's map reads its vectors from the file
  (:class:`~fdnet.matching.file_rows.FileRows`).
"""

from __future__ import annotations

import logging
import sqlite3
from pathlib import Path

import numpy as np

from fdnet.errors import DataError
from fdnet.matching.database.codes_cache import CodesCache
from fdnet.matching.database.places import read_vectors
from fdnet.matching.file_rows import FileRows

logger = logging.getLogger(__name__)

#: suffix of the vector file beside a database file (``map.db.vectors``)
VECTOR_FILE_SUFFIX = ".vectors"
#: no database keeps its vectors in a file below this many places: the compressed codes'
#: codebooks need places to be trained on (as the loop-closure detector's compressed search)
COMPRESSED_FLOOR = 4096

_TABLE = """
CREATE TABLE IF NOT EXISTS fdnet_vector_file (
    singleton INTEGER PRIMARY KEY CHECK (singleton = 1),
    database_id TEXT NOT NULL,
    rows INTEGER NOT NULL,
    last_id INTEGER NOT NULL
)"""


def vector_file_path(database_path: str | Path) -> Path:
    return Path(f"{database_path}{VECTOR_FILE_SUFFIX}")


def committed_rows(conn: sqlite3.Connection, database_id: str) -> tuple[int, int]:
    """(rows, id of the last place among them) the database committed to its vector file; (0,
    0) before its first add above the size (or for a database built again over the file)."""
    exists = conn.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'fdnet_vector_file'").fetchone()
    row = conn.execute("SELECT database_id, rows, last_id FROM fdnet_vector_file").fetchone() if exists else None
    if row is None or row[0] != database_id:
        return 0, 0
    return int(row[1]), int(row[2])


class VectorStore:
    """One database's vector file (see the module docstring): whether the database uses it, and
    the file opened at the committed row count."""

    def __init__(self, database_path: str, dim: int, database_id: str, threshold: int | None):
        #: None: this database never keeps its vectors in a file (in memory, not dot product)
        self.threshold = None if threshold is None else max(int(threshold), COMPRESSED_FLOOR)
        self.path = vector_file_path(database_path)
        self._database_path = str(database_path)
        self.dim = int(dim)
        self._database_id = database_id
        self._file = None
        #: the compressed codes' cache beside the database
        self.codes = CodesCache(database_path, database_id)

    def wanted(self, places: int) -> bool:
        return self.threshold is not None and places >= self.threshold

    def usable(self, conn: sqlite3.Connection, places: int, read_only: bool) -> bool:
        """Whether a database of ``places`` places searches through the file: from the size on,
        and for a read-only one only when its file holds them (a database that reached the size
        before its vectors were kept in files has none until its next add)."""
        return self.wanted(places) and (not read_only or committed_rows(conn, self._database_id)[0] >= places)

    def file(self):
        """The vector file as last opened (it holds at least the places this process loaded)."""
        return self._file

    def rows(self, count: int) -> FileRows:
        """The first ``count`` places' vectors, read from the file."""
        return FileRows(self.file, count, self.dim)

    def store(self, conn: sqlite3.Connection) -> int:
        """Inside the caller's write transaction (it holds the lock): open the file at the
        committed count (cutting off what a killed add left), append the vectors of the places
        stored since (read from their blobs), fsync, and record the new count; the rows now in
        the file."""
        from fdnet.matching.compressed import VectorFile

        rows, last_id = committed_rows(conn, self._database_id)
        if self._file is None or len(self._file) != rows or self._file.read_only:
            self.close()
            self._file = VectorFile(self.path, self.dim, rows)
        newest = conn.execute("SELECT max(id) FROM places").fetchone()[0] or 0
        added = 0
        for vectors in read_vectors(conn, self._database_path, self.dim, last_id, newest):
            self._file.extend(vectors)
            added += len(vectors)
        last_id = max(last_id, newest)
        if added:
            self._file.sync()  # durable before the count that promises the rows is committed
            conn.execute(_TABLE)
            conn.execute(
                "INSERT OR REPLACE INTO fdnet_vector_file (singleton, database_id, rows, last_id) VALUES (1, ?, ?, ?)",
                (self._database_id, rows + added, last_id),
            )
            if rows == 0:
                logger.info("%s: the vectors of %d places are now kept here", self.path, added)
        return len(self._file)

    def cover(self, conn: sqlite3.Connection, places: int, read_only: bool = False) -> None:
        """Make the opened file hold at least the first ``places`` committed places: opened again
        read-only at the committed count after other processes' adds (no lock held past the
        count's read), or, when the file lacks committed places (``read_only`` False only), their
        vectors copied to it under the write lock."""
        from fdnet.matching.compressed import VectorFile
        from fdnet.matching.database.storage import transaction

        if self._file is not None and len(self._file) >= places:
            return
        with transaction(conn, "DEFERRED"):
            rows = committed_rows(conn, self._database_id)[0]
        if rows >= places or read_only:
            self.close()
            self._file = VectorFile(self.path, self.dim, rows, read_only=True)
            if rows < places:
                raise DataError(f"{self.path}: holds {rows} committed vectors, the database {places} places")
            return
        with transaction(conn, "IMMEDIATE"):
            self.store(conn)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


class CompressedPlaces:
    """A database's search index above the size (see the module docstring): the interface of
    :class:`~fdnet.matching.index.VectorIndex` that :class:`~fdnet.matching.place_map.PlaceMap`
    and the database use (``len``, ``search``, ``build``), over the first :attr:`places` rows
    of the store's file."""

    trainable = False  # not the flat/IVF index cache: its codes have their own (codes_cache)

    def __init__(self, store: VectorStore):
        self._store = store
        self._index = None  # loaded from the cache or made at the first build or query
        #: places of the map (rows of the file) the index covers
        self.places = 0

    def __len__(self) -> int:
        return self.places

    def build(self):
        """The codes of the first :attr:`places` rows, loaded from the cache when it matches,
        extended by the rows committed since (or trained here), and the cache written again when
        they were trained here or have grown enough."""
        from fdnet.matching.compressed import CompressedIndex

        file, codes = self._store.file(), self._store.codes
        if self._index is None:
            self._index = codes.load(file, self.places) or CompressedIndex(self._store.dim)
        trainings = self._index.trainings
        self._index.sync(self._store.rows(self.places))
        if file is not None:
            codes.save(self._index, file, force=self._index.trainings != trainings)
        return self._index

    def search(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        index = self.build()
        return index.search(queries, int(k), self._store.rows(self.places))

    def describe(self) -> dict:
        from fdnet.matching.compressed import CompressedIndex

        index = self._index or CompressedIndex(self._store.dim)
        return {**index.describe(), "vector_file": str(self._store.path), "codes_cache": str(self._store.codes.path)}
