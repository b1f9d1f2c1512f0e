"""A batch of places on its way into a place database: checked completely before the
transaction starts (so a refusal changes nothing), then inserted inside the caller's transaction,
duplicates skipped by name."""

from __future__ import annotations

import sqlite3
from typing import Sequence

import numpy as np

from fdnet.descriptors.base import check_vectors
from fdnet.errors import ConfigError
from fdnet.matching.database.storage import canonical_json, check_place_names

#: Stay well under SQLite's limit on bound parameters per statement.
_NAMES_PER_QUERY = 500


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
