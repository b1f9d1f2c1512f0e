"""The derived search index of a place database, cached beside its file.

The faiss index is derived data: it is rebuilt from the stored vectors when a database is first
queried and extended when other processes add places, so it can never disagree with the file.
For the approximate kinds (hnsw, ivf, ivfpq), whose building (training) costs, it is also kept in
a cache file beside the database (``map.db.fdnet-index``), used only when it belongs to this
database (same database_id, build settings and fingerprint) and holds exactly its first places,
by content: the cache records a digest of those places' ids, names and stored vectors, so a copy
of the database restored from a backup (same database_id, same ids, other places after it) never
loads an index built from places it does not hold.
"""

from __future__ import annotations

import hashlib
import sqlite3
from pathlib import Path

from fdnet.errors import ConfigError, DataError
from fdnet.matching.database.identity import Identity
from fdnet.matching.database.storage import MEMORY
from fdnet.matching.index import VectorIndex

#: Suffix of the derived index cache beside a database file (approximate kinds only).
INDEX_CACHE_SUFFIX = ".fdnet-index"
#: Index settings that only change how a search runs, not what the built index holds.
_SEARCH_SETTINGS = ("ivf_probe", "hnsw_ef_search", "refine", "compressed_from")


def index_cache_path(database_path: str, identity: Identity) -> Path | None:
    """Where the derived index of an approximate kind (hnsw, ivf, ivfpq) is cached: beside the
    database file, ``map.db.fdnet-index``. None for ``flat`` (rebuilding it is a copy), for
    methods searched with their own similarity and for in-memory databases."""
    if database_path == MEMORY or not identity.dot_product or identity.index_settings.kind == "flat":
        return None
    return Path(f"{database_path}{INDEX_CACHE_SUFFIX}")


class IndexCache:
    """The cache file of one database's index: :meth:`load` it when it is current, :meth:`save`
    it when the index was built here or has grown enough since."""

    def __init__(self, database_path: str, identity: Identity):
        self.path = index_cache_path(database_path, identity)
        self._database_name = Path(database_path).name
        self._identity = identity
        #: places the cache file held when it was loaded or written
        self.places = 0

    def load(self, conn: sqlite3.Connection) -> tuple[VectorIndex | None, int]:
        """The cached index and the last place id it holds, when the cache belongs to this
        database (same database_id, build settings and fingerprint) and holds exactly the places
        with id <= that id; otherwise (None, 0) and the index is rebuilt from the file."""
        cache = self.path
        if cache is None or not cache.is_file():
            return None, 0
        ident = self._identity
        try:
            header = VectorIndex.read_header(cache)
            meta = header.get("metadata", {})
            build = {k: v for k, v in vars(ident.index_settings).items() if k not in _SEARCH_SETTINGS}
            cached = {k: v for k, v in header["settings"].items() if k in build}
            last_id, count = int(meta.get("last_id", -1)), int(header["count"])
            if (
                meta.get("database_id") != ident.database_id
                or cached != build
                or meta.get("fingerprint") != ident.fingerprint
                or header["dim"] != ident.dim
            ):
                return None, 0
            if conn.execute("SELECT count(*) FROM places WHERE id <= ?", (last_id,)).fetchone()[0] != count:
                return None, 0
            if meta.get("content") != places_digest(conn, last_id):
                return None, 0  # same ids and count, other places (a restored backup): not this index
            search = {k: getattr(ident.index_settings, k) for k in _SEARCH_SETTINGS}
            index = VectorIndex.load(cache, search=search)
        except (DataError, ConfigError, ValueError, TypeError, KeyError):
            return None, 0  # a damaged or foreign cache is only a cache: rebuild
        self.places = count
        return index, last_id

    def save(
        self, index: VectorIndex | None, conn: sqlite3.Connection, data_version: int, last_id: int, force: bool = False
    ) -> bool:
        """Write ``index`` (holding the places up to ``last_id``) to the cache file when it was
        built here or grew by 5 % (at least 1000 places) since the cache was read; a cache that
        cannot be written is skipped."""
        cache = self.path
        if cache is None or index is None or len(index) == 0:
            return False
        grown = len(index) - self.places
        if not force and self.places and grown < max(1000, 0.05 * self.places):
            return False
        try:
            conn.execute("BEGIN DEFERRED")
            try:
                content = places_digest(conn, last_id)
            finally:
                conn.execute("COMMIT")
            index.save(
                cache,
                metadata={
                    "database_id": self._identity.database_id,
                    "data_version": data_version,
                    "last_id": last_id,
                    "fingerprint": self._identity.fingerprint,
                    "database": self._database_name,
                    "content": content,
                },
            )
        except (OSError, sqlite3.Error):
            return False
        self.places = len(index)
        return True


def places_digest(conn: sqlite3.Connection, last_id: int) -> str:
    """sha256 over the id, name and stored vector of every place with id <= ``last_id``, in id
    order: what an index built from those places was built from."""
    digest = hashlib.sha256()
    rows = conn.execute("SELECT id, name, vector FROM places WHERE id <= ? ORDER BY id", (last_id,))
    while chunk := rows.fetchmany(4096):
        for place_id, name, vector in chunk:
            name_bytes = str(name).encode("utf-8", "surrogateescape")
            blob = vector if isinstance(vector, bytes) else b""
            digest.update(b"%d:%d:%d:" % (place_id, len(name_bytes), len(blob)))
            digest.update(name_bytes)
            digest.update(blob)
    return digest.hexdigest()
