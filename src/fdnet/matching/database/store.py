"""The place database itself: :class:`PlaceDatabase` makes, opens, adds to and queries one file
(or an in-memory database), and :class:`Match`/:class:`AddResult` are what it answers."""

from __future__ import annotations

import json
import os
import sqlite3
import uuid
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from fdnet.errors import ConfigError, DataError
from fdnet.matching.database.identity import (
    Identity,
    check_descriptor,
    check_fingerprint,
    read_identity,
    read_index_settings,
)
from fdnet.matching.database.index_cache import IndexCache
from fdnet.matching.database.places import (
    ROWS_PER_FETCH,
    check_query_settings,
    chunk_parts,
    insert_rows,
    names_present,
    prepare_batch,
    query_vectors,
    read_vectors,
)
from fdnet.matching.database.storage import (
    MEMORY,
    canonical_json,
    check_can_create,
    check_header,
    check_schema,
    connect_database,
    connect_read_only,
    read_only_storage,
    sqlite_errors,
    transaction,
    use_write_ahead_log,
    write_schema,
)
from fdnet.matching.database.vector_store import CompressedPlaces, VectorStore
from fdnet.matching.file_rows import FileRows
from fdnet.matching.index import IndexSettings, VectorIndex
from fdnet.matching.place_map import GrowingArray, PlaceMap


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


class PlaceDatabase:
    """One place database file (or an in-memory one). Make it with :meth:`create` or
    :meth:`for_descriptor`, open it with :meth:`open`; :meth:`add` and :meth:`query` may be
    called by several processes on the same file at once."""

    def __init__(
        self,
        path: str,
        conn: sqlite3.Connection | None,
        identity: Identity,
        similarity: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    ):
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
        # The places loaded: their vectors are kept in this process only for methods searched
        # with their own similarity; a dot-product database keeps them in the map's index, made
        # on the first read so that a process that only adds never imports faiss (and reads
        # them back from the file on request).
        self._map = PlaceMap(None if identity.dot_product else identity.dim)
        # The derived index's cache file beside the database (see _refresh).
        self._index_cache = IndexCache(path, identity)
        # From a size, the vectors' file beside the database (vector_store)
        self._vector_store = VectorStore(
            path,
            identity.dim,
            identity.database_id,
            identity.index_settings.compressed_from if identity.dot_product and path != MEMORY else None,
        )

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
    def for_descriptor(
        cls,
        descriptor,
        index: IndexSettings | None = None,
        method_options: dict | None = None,
        path: str | os.PathLike = MEMORY,
        overwrite: bool = False,
    ) -> "PlaceDatabase":
        """An empty database for ``descriptor``'s vectors: in memory by default (a scratch map
        for one process), or the file ``path`` (see :meth:`create`)."""
        return cls.create(path, descriptor, index=index, method_options=method_options, overwrite=overwrite)

    @classmethod
    def create(
        cls,
        path: str | os.PathLike,
        descriptor,
        *,
        index: IndexSettings | None = None,
        method_options: dict | None = None,
        overwrite: bool = False,
        places: Iterable | None = None,
        allow_duplicates: bool = False,
    ) -> "PlaceDatabase":
        """Write a new database for ``descriptor``'s vectors, with optional first places, in one
        transaction: a crash leaves no half-made database behind.

        ``places`` gives the first places as an iterable of ``(vectors, names)`` or ``(vectors,
        names, positions, metadata)`` chunks, all stored in the same transaction (see
        :meth:`add_batches`): a list of chunks is checked whole before the file is touched (a
        refused chunk leaves no file); a generator, a map of any size a chunk in memory at a time.

        ``method_options`` rebuild the descriptor later (``fdnet.descriptors.create(method,
        **method_options)``). An existing file is refused unless ``overwrite``; then an existing
        place database is replaced in one transaction, and any other file is still refused.
        """
        target = str(path)
        check_can_create(target, overwrite)
        index = index or IndexSettings()
        index_json = canonical_json(vars(index), "index settings")
        read_index_settings(json.loads(index_json), "index settings", ConfigError)
        settings_json = canonical_json(descriptor.settings(), f"{descriptor.name} settings")
        options_json = canonical_json(dict(method_options or {}), "method_options")
        from fdnet.version import __version__

        identity = Identity(
            database_id=uuid.uuid4().hex,
            method=descriptor.name,
            settings=json.loads(settings_json),
            method_options=json.loads(options_json),
            dim=int(descriptor.dim),
            dot_product=bool(descriptor.dot_product_similarity),
            index_settings=index,
            fingerprint=descriptor.fingerprint(),
            created=datetime.now(timezone.utc).isoformat(timespec="seconds"),
            fdnet_version=__version__,
        )
        similarity = None if identity.dot_product else descriptor.similarity
        db = cls(target, None, identity, similarity)
        # Before the file is touched: refused places given whole must not leave a file behind.
        prepared = (
            [db._prepare(*chunk_parts(db.path, chunk), None) for chunk in places]
            if isinstance(places, (list, tuple))
            else None
        )
        if target != MEMORY:
            Path(target).parent.mkdir(parents=True, exist_ok=True)
        with sqlite_errors(target, "creating the place database"):
            conn = db._conn = connect_database(target)
        try:
            with sqlite_errors(target, "creating the place database"):
                use_write_ahead_log(conn, target)
                with transaction(conn, "IMMEDIATE"):
                    write_schema(
                        conn,
                        target,
                        overwrite,
                        {
                            "database_id": identity.database_id,
                            "method": identity.method,
                            "settings": settings_json,
                            "method_options": options_json,
                            "dim": identity.dim,
                            "dot_product": int(identity.dot_product),
                            "index_settings": index_json,
                            "fingerprint": identity.fingerprint,
                            "data_version": 0,
                            "created": identity.created,
                            "fdnet_version": identity.fdnet_version,
                        },
                    )
                    if prepared is not None:
                        for batch in prepared:
                            db._insert(conn, batch, allow_duplicates)
                    elif places is not None:
                        db._insert_batches(conn, places, allow_duplicates)
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
        check_header(path)
        target = str(path)
        read_only = read_only_storage(path)
        with sqlite_errors(target, "opening the place database"):
            # mode=rw: a path that vanished since the check must not become a new empty file.
            conn = (
                connect_read_only(path)
                if read_only
                else connect_database(path.resolve().as_uri() + "?mode=rw", uri=True)
            )
        try:
            with sqlite_errors(target, "reading the place database"):
                check_schema(conn, target, read_only)
                identity = read_identity(target, conn)
            similarity = None
            if descriptor is not None:
                check_descriptor(target, identity, descriptor)
                similarity = None if identity.dot_product else descriptor.similarity
        except BaseException:
            conn.close()
            raise
        db = cls(target, conn, identity, similarity)
        db.read_only = read_only
        return db

    def check_descriptor(self, descriptor) -> None:
        """Refuse ``descriptor`` unless it is the model whose vectors the database holds."""
        check_descriptor(self.path, self._identity, descriptor)

    def close(self) -> None:
        self._vector_store.close()
        self._conn.close()

    def __enter__(self) -> "PlaceDatabase":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ adding
    def __len__(self) -> int:
        """Places in the database now (including other processes' committed adds)."""
        with sqlite_errors(self.path, "counting places"):
            return int(self._conn.execute("SELECT count(*) FROM places").fetchone()[0])

    def existing_names(self, names: Sequence[str]) -> set[str]:
        """Which of ``names`` the database already holds (to skip describing them again)."""
        with sqlite_errors(self.path, "looking up place names"):
            return names_present(self._conn, [str(n) for n in names])

    def add(
        self,
        vectors: np.ndarray,
        names: Sequence[str],
        positions: Sequence[tuple[float, float] | None] | np.ndarray | None = None,
        *,
        metadata: Sequence[dict | None] | None = None,
        fingerprint: str | None = None,
        allow_duplicates: bool = False,
    ) -> AddResult:
        """Store a batch of places in one transaction: all of it is added or none (:meth:`add_batches`
        of one chunk).

        ``fingerprint`` is that of the descriptor that made ``vectors``; a different one is
        refused (another model's vectors are not comparable). Names already in the database are
        skipped and reported in the result unless ``allow_duplicates``. Non-finite vectors are
        refused (a NaN would be stored and never found).
        """
        return self.add_batches(
            [(vectors, names, positions, metadata)], fingerprint=fingerprint, allow_duplicates=allow_duplicates
        )

    def add_batches(
        self, batches: Iterable, *, fingerprint: str | None = None, allow_duplicates: bool = False
    ) -> AddResult:
        """Store many chunks of places in ONE transaction: all of them are added or none (an
        ``add`` of a million images, a chunk in memory at a time). Each chunk is
        ``(vectors, names)`` or ``(vectors, names, positions, metadata)``, checked as :meth:`add`
        checks a batch; a refused chunk rolls back the chunks before it. The data version goes up
        once. Chunks should be ready data (e.g. read back from a spool file): the write lock is
        held while they are consumed, so describing images inside the iterable would make other
        writers wait.
        """
        if fingerprint is not None:
            check_fingerprint(self.path, self._identity, fingerprint, None)
        with sqlite_errors(self.path, "adding places"):
            with transaction(self._conn, "IMMEDIATE") as conn:
                self._check_same_database(conn)
                return self._insert_batches(conn, batches, allow_duplicates)

    def _insert_batches(self, conn: sqlite3.Connection, batches: Iterable, allow_duplicates: bool) -> AddResult:
        added, skipped = 0, []
        for chunk in batches:
            prepared = self._prepare(*chunk_parts(self.path, chunk), None)
            if prepared["names"]:
                kept, refused = self._insert_rows(conn, prepared, allow_duplicates)
                added += kept
                skipped.extend(refused)
        return self._finish_insert(conn, added, skipped)

    def _prepare(self, vectors, names, positions, metadata, fingerprint) -> dict:
        """Check a batch completely before the transaction starts, so a refusal changes nothing."""
        if fingerprint is not None:
            check_fingerprint(self.path, self._identity, fingerprint, None)
        return prepare_batch(self.path, self.dim, self.method, vectors, names, positions, metadata, self.dot_product)

    def _check_same_database(self, conn: sqlite3.Connection) -> None:
        row = conn.execute("SELECT database_id FROM fdnet_database").fetchone()
        if row is None or row[0] != self._identity.database_id:
            raise DataError(
                f"{self.path}: was rebuilt (build --overwrite) by another process while open here; " "open it again"
            )

    def _insert(self, conn: sqlite3.Connection, batch: dict, allow_duplicates: bool) -> AddResult:
        added, skipped = self._insert_rows(conn, batch, allow_duplicates)
        return self._finish_insert(conn, added, skipped)

    def _finish_insert(self, conn: sqlite3.Connection, added: int, skipped: list[str]) -> AddResult:
        """Inside the add's transaction: bump the data version and, from the size on, append the
        new places' vectors to the vector file and record its row count (vector_store)."""
        if added:
            conn.execute("UPDATE fdnet_database SET data_version = data_version + 1")
        version = conn.execute("SELECT data_version FROM fdnet_database").fetchone()[0]
        total = conn.execute("SELECT count(*) FROM places").fetchone()[0]
        if added and self._vector_store.wanted(total):
            self._vector_store.store(conn)
        return AddResult(added, skipped, int(total), int(version))

    def _insert_rows(self, conn: sqlite3.Connection, batch: dict, allow_duplicates: bool) -> tuple[int, list[str]]:
        return insert_rows(conn, batch, allow_duplicates)

    # ------------------------------------------------------------------ reading
    @property
    def index_cache_path(self) -> Path | None:
        """Where the derived index of an approximate kind (hnsw, ivf, ivfpq) is cached: beside
        the database file, ``map.db.fdnet-index``. None for ``flat`` (rebuilding it is a copy)
        and in-memory databases."""
        return self._index_cache.path

    def _save_index_cache(self, force: bool = False) -> bool:
        return self._index_cache.save(self._map.index, self._conn, self._loaded_version, self._last_id, force)

    def build_index(self) -> VectorIndex | CompressedPlaces | None:
        """Load every place and build (train) the search index now rather than at the first query,
        and for hnsw/ivf/ivfpq write its cache beside the file (``index_cache_path``) so later
        processes load it instead of building it again. Returns the index (None for methods
        searched exhaustively with their own similarity). Above ``compressed_from`` places the
        compressed codes are built (or loaded) and cached beside the file (``map.db.fdnet-codes``)."""
        self._refresh()
        if self._map.index is not None:
            self._map.index.build()
            if not isinstance(self._map.index, CompressedPlaces):
                self._save_index_cache()
        return self._map.index

    def _refresh(self) -> None:
        """Load the places committed since the last call, from one consistent snapshot, a
        bounded number of rows at a time. Vectors of a dot-product database go into its index
        (loaded from the cache file when it is current, then extended by the newer places), or
        from ``compressed_from`` places stay in its vector file (vector_store)."""
        built_here = in_file = False
        with sqlite_errors(self.path, "reading places"):
            with transaction(self._conn, "DEFERRED") as conn:
                self._check_same_database(conn)
                version = conn.execute("SELECT data_version FROM fdnet_database").fetchone()[0]
                if version == self._loaded_version:
                    return
                rows = conn.execute(
                    "SELECT id, name, x, y, metadata FROM places WHERE id > ? ORDER BY id", (self._last_id,)
                )
                last = self._last_id
                while chunk := rows.fetchmany(ROWS_PER_FETCH):
                    self._map.extend(
                        [r[1] for r in chunk],
                        [None if r[2] is None else (r[2], r[3]) for r in chunk],
                        [r[4] for r in chunk],
                    )
                    last = chunk[-1][0]
                in_file = isinstance(self._map.index, CompressedPlaces)
                in_file = in_file or self._vector_store.usable(conn, len(self._map), self.read_only)
                if in_file and not isinstance(self._map.index, CompressedPlaces):
                    self._map.index = CompressedPlaces(self._vector_store)  # the vectors in memory are dropped
                elif not in_file:
                    built_here = self._load_vectors(conn, last)
                self._last_id = last
                self._loaded_version = version
        index = self._map.index
        if in_file:
            with sqlite_errors(self.path, "reading the vector file"):
                self._vector_store.cover(self._conn, len(self._map), self.read_only)
            index.places = len(self._map)
        elif built_here and index is not None and index.trainable and len(index) >= 10_000:
            # an approximate index worth caching: train it once, here, and keep it
            index.build()
            self._save_index_cache(force=True)

    def _load_vectors(self, conn: sqlite3.Connection, last: int) -> bool:
        """Add the vectors of the places after those loaded so far, up to id ``last``, to the map
        (its index for a dot-product database, from the cache file when it is current); whether
        the index was made here (not loaded from the cache)."""
        built_here = False
        vectors_after = self._last_id
        if self.dot_product and self._map.index is None:
            self._map.index, cached_last = self._index_cache.load(conn)
            vectors_after = max(vectors_after, cached_last)
            if self._map.index is None:
                self._map.index = VectorIndex(self.dim, self.index_settings)
                built_here = True
        for vectors in read_vectors(conn, self.path, self.dim, vectors_after, last):
            if self.dot_product:
                self._map.index.add(vectors)
            else:
                self._map.vectors.extend(vectors)
        return built_here

    @property
    def names(self) -> list[str]:
        self._refresh()
        return list(self._map.names)

    @property
    def positions(self) -> list[tuple[float, float] | None]:
        self._refresh()
        return list(self._map.positions)

    @property
    def metadata(self) -> list[dict | None]:
        """Every place's metadata (e.g. a loop-closure frame's timestamp), in insertion order."""
        self._refresh()
        return self._map.all_metadata()

    @property
    def vectors(self) -> np.ndarray:
        """Every stored vector, in insertion order (read from the file for dot-product databases,
        whose vectors otherwise live only in the index)."""
        self._refresh()
        if self.dot_product:
            with sqlite_errors(self.path, "reading vectors"):
                with transaction(self._conn, "DEFERRED") as conn:
                    chunks = list(read_vectors(conn, self.path, self.dim, 0, self._last_id))
            return np.concatenate(chunks) if chunks else np.zeros((0, self.dim), dtype=np.float32)
        return self._map.vectors.view()

    def place_map(self, vectors: bool = True) -> PlaceMap:
        """Every place (up to the file's state) as a :class:`~fdnet.matching.place_map.PlaceMap` of its
        own, with the vectors when asked: the loop-closure detector appends its frames to it. The
        places loaded here are handed over, not copied, and forgotten here (a later read loads them
        again), so a map of 10^7 places is held once, not twice."""
        self._refresh()
        loaded, in_file = self._map, vectors and isinstance(self._map.index, CompressedPlaces)
        out = PlaceMap(self.dim if vectors and not in_file else None)
        out.names, out.positions, out.metadata_text = loaded.names, loaded.positions, loaded.metadata_text
        if out.vectors is not None:
            out.vectors = loaded.vectors if not self.dot_product else GrowingArray(self.dim, self.vectors)
        elif in_file:  # read from the vector file as they are needed
            out.vectors = self._vector_store.rows(len(out))
        self._map, self._last_id, self._loaded_version = PlaceMap(None if self.dot_product else self.dim), 0, -1
        return out

    def stored_vectors(self, count: int) -> FileRows | None:
        """The first ``count`` places' vectors as rows of the vector file, when the database keeps
        its vectors there (above ``compressed_from`` places) and the file, as this process last
        opened or wrote it, holds them; else None."""
        file = self._vector_store.file()
        return None if file is None or len(file) < count else self._vector_store.rows(count)

    def codes_cache(self):
        """(codes cache, vector file) when its vectors are in a file (for the loop detector's codes); else None."""
        return None if (file := self._vector_store.file()) is None else (self._vector_store.codes, file)

    def query(self, vectors: np.ndarray, k: int = 5, searchable: int | None = None) -> list[list[Match]]:
        """Top-``k`` stored places per query vector, best first, among the first ``searchable``
        places (None: every place; a robot's own last frames are left out by the caller, e.g.
        ``fdnet database query --exclude-last``). Places other processes added since the last
        call are included."""
        check_query_settings(self.path, k, searchable)
        self._refresh()
        if len(self._map) == 0:
            raise ConfigError(f"{self.path}: the place database is empty: add places before querying")
        q = query_vectors(self.path, self.dim, self.method, vectors)
        if self._map.index is None and self.similarity is None:
            raise ConfigError(
                f"{self.path}: method {self.method!r} compares vectors with its own similarity; "
                "open the database with its descriptor: PlaceDatabase.open(path, descriptor)"
            )
        idx, scores = self._map.search(q, int(k), searchable, similarity=self.similarity)
        return [
            [
                Match(int(i), self._map.names[i], float(s), self._map.positions[i], self._map.metadata(i))
                for i, s in zip(row_i, row_s)
                if i >= 0
            ]
            for row_i, row_s in zip(idx, scores)
        ]

    # ------------------------------------------------------------------ database metadata
    def set_metadata(self, key: str, value: dict) -> None:
        """Store ``value`` (a JSON object, e.g. a calibration) under ``key`` in the database's own
        metadata, in one transaction (readers see the old or the new value). The table is created
        on first use, so a database that never stored metadata holds only its schema's tables."""
        text = canonical_json(value, f"{self.path}: metadata {key!r}")
        with sqlite_errors(self.path, f"storing metadata {key!r}"):
            with transaction(self._conn, "IMMEDIATE") as conn:
                self._check_same_database(conn)
                conn.execute("CREATE TABLE IF NOT EXISTS fdnet_metadata (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
                conn.execute("INSERT OR REPLACE INTO fdnet_metadata (key, value) VALUES (?, ?)", (key, text))

    def get_metadata(self, key: str) -> dict | None:
        """The value stored under ``key`` by :meth:`set_metadata`, or None."""
        with sqlite_errors(self.path, f"reading metadata {key!r}"):
            exists = self._conn.execute(
                "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'fdnet_metadata'"
            ).fetchone()
            row = (
                self._conn.execute("SELECT value FROM fdnet_metadata WHERE key = ?", (key,)).fetchone()
                if exists
                else None
            )
        if row is None:
            return None
        try:
            return json.loads(row[0])
        except json.JSONDecodeError as exc:
            raise DataError(f"{self.path}: metadata {key!r} is not valid JSON ({exc})") from exc

    def info(self) -> dict:
        """What ``fdnet database info`` prints: identity, size and versions, without loading vectors."""
        with sqlite_errors(self.path, "reading the database summary"):
            with transaction(self._conn, "DEFERRED") as conn:
                version = conn.execute("SELECT data_version FROM fdnet_database").fetchone()[0]
                places = conn.execute("SELECT count(*) FROM places").fetchone()[0]
                schema = conn.execute("PRAGMA user_version").fetchone()[0]
                journal = conn.execute("PRAGMA journal_mode").fetchone()[0]
        ident = self._identity
        return {
            "path": self.path,
            "places": int(places),
            "method": ident.method,
            "dim": ident.dim,
            "dot_product": ident.dot_product,
            "fingerprint": ident.fingerprint,
            "settings": ident.settings,
            "method_options": ident.method_options,
            "index": vars(ident.index_settings),
            "schema_version": int(schema),
            "data_version": int(version),
            "journal_mode": journal,
            "created": ident.created,
            "fdnet_version": ident.fdnet_version,
        }
