"""Which model made a place database's vectors: the identity row stored in the file (method,
settings, the options that rebuild the descriptor, dimension, similarity, index settings and the
descriptor's fingerprint), read back with every column checked, and the refusal of vectors from
another model."""

from __future__ import annotations

import json
import sqlite3
from dataclasses import dataclass, fields

from fdnet.errors import ConfigError, DataError
from fdnet.matching.index import INDEX_KINDS, IndexSettings, check_settings


def short_fingerprint(fingerprint: str) -> str:
    return fingerprint[:12]


@dataclass(frozen=True)
class Identity:
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


def read_index_settings(value, where: str, error: type = DataError) -> IndexSettings:
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


def read_identity(path, conn: sqlite3.Connection) -> Identity:
    columns = (
        "database_id",
        "method",
        "settings",
        "method_options",
        "dim",
        "dot_product",
        "index_settings",
        "fingerprint",
        "created",
        "fdnet_version",
    )
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
            raise DataError(f"{path}: column {name} of fdnet_database is not valid JSON ({exc})") from exc
        if not isinstance(value, dict):
            raise DataError(f"{path}: column {name} of fdnet_database must be a JSON object")
        return value

    return Identity(
        database_id=column("database_id", str),
        method=column("method", str),
        settings=json_column("settings"),
        method_options=json_column("method_options"),
        dim=column("dim", int),
        dot_product=bool(column("dot_product", int)),
        index_settings=read_index_settings(json_column("index_settings"), f"{path}: column index_settings"),
        fingerprint=column("fingerprint", str),
        created=column("created", str),
        fdnet_version=column("fdnet_version", str),
    )


def check_descriptor(path, identity: Identity, descriptor) -> None:
    check_fingerprint(path, identity, descriptor.fingerprint(), descriptor.name)


def check_fingerprint(path, identity: Identity, fingerprint: str, method: str | None) -> None:
    """Refuse vectors of another model (``Descriptor.fingerprint()``)."""
    if identity.fingerprint != fingerprint:
        made_by = f"the {method!r} descriptor given has" if method else "these vectors come from"
        raise ConfigError(
            f"{path}: descriptor fingerprint mismatch: the database holds {identity.method!r} vectors with "
            f"fingerprint {short_fingerprint(identity.fingerprint)}, {made_by} {short_fingerprint(fingerprint)}; "
            "a different model (weights or settings changed since the database was built). Describe with "
            "the database's model, or build a new database (--overwrite)"
            + (
                "; a precomputed database grows only with vectors files that record the model that made them "
                "(fdnet extract's do), others are identified by their vectors alone"
                if identity.method == "precomputed"
                else ""
            )
        )
