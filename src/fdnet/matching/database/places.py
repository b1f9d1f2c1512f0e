"""A batch of places on its way into a place database: checked completely before the
transaction starts (so a refusal changes nothing), then inserted inside the caller's transaction,
duplicates skipped by name."""

from __future__ import annotations

import sqlite3
from typing import Iterator, Sequence

import numpy as np

from fdnet.descriptors.base import check_vectors
from fdnet.errors import ConfigError, DataError
from fdnet.matching.database.storage import canonical_json, check_place_names

#: Stay well under SQLite's limit on bound parameters per statement.
_NAMES_PER_QUERY = 500
#: Rows read from the file per fetch while loading places (bounded memory besides the index).
ROWS_PER_FETCH = 65536


def prepare_batch(
    path: str, dim: int, method: str, vectors, names, positions, metadata, dot_product: bool = True
) -> dict:
    """The batch as rows to insert (names, x, y, metadata JSON, vector blobs), or the
    ConfigError/DataError naming the database ``path`` and what is wrong with it."""
    try:
        v = np.asarray(vectors, dtype=np.float32)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: vectors are not a numeric array ({exc})") from exc
    if v.ndim != 2 or v.shape[1] != dim:
        raise ConfigError(f"{path}: holds {dim}-d vectors ({method}), got shape {v.shape}")
    if names is None or len(names) != len(v):
        raise ConfigError(f"{path}: {len(v)} vectors but {0 if names is None else len(names)} names")
    names = [str(n) for n in names]
    check_place_names(names)
    # NaN, infinite and all-zero vectors: a place that can never be matched
    check_vectors(v, f"{path}: nothing was added", lambda i: names[i], directions=dot_product)
    xs: list[float | None] = [None] * len(v)
    ys: list[float | None] = [None] * len(v)
    if positions is not None:
        if len(positions) != len(v):
            raise ConfigError(f"{path}: {len(v)} vectors but {len(positions)} positions")
        for i, p in enumerate(positions):
            if p is None:
                continue
            try:
                x, y = (float(c) for c in p)
            except (TypeError, ValueError) as exc:
                raise ConfigError(f"{path}: position of {names[i]} must be (x, y), got {p!r}") from exc
            if not (np.isfinite(x) and np.isfinite(y)):
                raise ConfigError(f"{path}: position of {names[i]} is not finite: {p!r}")
            xs[i], ys[i] = x, y
    texts: list[str | None] = [None] * len(v)
    if metadata is not None:
        if len(metadata) != len(v):
            raise ConfigError(f"{path}: {len(v)} vectors but {len(metadata)} metadata entries")
        for i, meta in enumerate(metadata):
            if meta is not None:
                if not isinstance(meta, dict):
                    raise ConfigError(f"{path}: metadata of {names[i]} must be a dict, got " f"{type(meta).__name__}")
                texts[i] = canonical_json(meta, f"{path}: metadata of {names[i]}")
    blobs = [row.tobytes() for row in v.astype("<f4", copy=False)]
    return {"names": names, "x": xs, "y": ys, "metadata": texts, "blobs": blobs}


def insert_rows(conn: sqlite3.Connection, batch: dict, allow_duplicates: bool) -> tuple[int, list[str]]:
    """Insert a prepared batch (inside the caller's transaction): (places added, names skipped)."""
    names = batch["names"]
    keep = list(range(len(names)))
    skipped: list[str] = []
    if not allow_duplicates:
        present = names_present(conn, names)
        keep = []
        for i, name in enumerate(names):
            if name in present:
                skipped.append(name)
            else:
                keep.append(i)
                present.add(name)  # a name twice in one batch is a duplicate too
    conn.executemany(
        "INSERT INTO places (name, x, y, metadata, vector) VALUES (?, ?, ?, ?, ?)",
        [(names[i], batch["x"][i], batch["y"][i], batch["metadata"][i], batch["blobs"][i]) for i in keep],
    )
    return len(keep), skipped


def names_present(conn: sqlite3.Connection, names: Sequence[str]) -> set[str]:
    unique = list(dict.fromkeys(names))
    found: set[str] = set()
    for start in range(0, len(unique), _NAMES_PER_QUERY):
        chunk = unique[start : start + _NAMES_PER_QUERY]
        marks = ", ".join("?" * len(chunk))
        found.update(r[0] for r in conn.execute(f"SELECT DISTINCT name FROM places WHERE name IN ({marks})", chunk))
    return found


def read_vectors(conn: sqlite3.Connection, path: str, dim: int, after_id: int, up_to_id: int) -> Iterator[np.ndarray]:
    """Stored vectors of the places with after_id < id <= up_to_id, in id order, in chunks."""
    rows = conn.execute(
        "SELECT id, name, vector FROM places WHERE id > ? AND id <= ? ORDER BY id", (after_id, up_to_id)
    )
    width = 4 * dim
    while chunk := rows.fetchmany(ROWS_PER_FETCH):
        for row in chunk:
            if not isinstance(row[2], bytes) or len(row[2]) != width:
                raise DataError(
                    f"{path}: place {row[1]!r} (id {row[0]}) has a vector of "
                    f"{len(row[2]) if isinstance(row[2], bytes) else type(row[2]).__name__} bytes, "
                    f"expected {width} ({dim} float32); the file is damaged"
                )
        yield np.frombuffer(b"".join(r[2] for r in chunk), dtype="<f4").reshape(len(chunk), dim).astype(np.float32)


def check_query_settings(path: str, k, searchable) -> None:
    """Refuse a query's top-``k`` or ``searchable`` that is not a whole number (in range)."""
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise ConfigError(f"{path}: top-k must be a whole number of at least 1, got {k!r}")
    if searchable is not None and (
        isinstance(searchable, bool) or not isinstance(searchable, (int, np.integer)) or searchable < 0
    ):
        raise ConfigError(f"{path}: searchable must be a whole number of places, got {searchable!r}")


def query_vectors(path: str, dim: int, method: str, vectors) -> np.ndarray:
    """Query vectors as a (Q, dim) float32 array, or the error naming the database ``path``."""
    q = np.asarray(vectors, dtype=np.float32)
    if q.ndim == 1:
        q = q[None]
    if q.ndim != 2 or q.shape[1] != dim:
        raise ConfigError(f"{path}: holds {dim}-d vectors ({method}), got queries of shape {q.shape}")
    bad = np.flatnonzero(~np.isfinite(q).all(axis=1))
    if len(bad):
        raise DataError(f"{path}: query vector(s) {', '.join(map(str, bad[:5]))} are not finite (NaN or inf)")
    return q


def chunk_parts(path, chunk) -> tuple:
    """(vectors, names, positions, metadata) of a chunk of places given as (vectors, names) or
    (vectors, names, positions, metadata)."""
    if not isinstance(chunk, (tuple, list)) or len(chunk) not in (2, 4):
        raise ConfigError(f"{path}: a batch must be (vectors, names) or (vectors, names, positions, metadata)")
    return (chunk[0], chunk[1], *((chunk[2], chunk[3]) if len(chunk) == 4 else (None, None)))
