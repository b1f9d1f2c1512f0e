"""The old folder format of a place database (``database.json`` + ``vectors.npy``): every field
read and checked, and converted once into a database file (``fdnet database migrate``)."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from fdnet.config import load_json_text
from fdnet.errors import ConfigError, DataError
from fdnet.matching.database.identity import _index_settings
from fdnet.matching.database.storage import _canonical_json, check_can_create
from fdnet.matching.database.store import PlaceDatabase


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
        meta = load_json_text(json_path.read_text(), str(json_path), DataError)
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
        places=[(vectors[keep], [names[i] for i in keep],
                 None if positions is None else [positions[i] for i in keep], None)],
        allow_duplicates=True).close()
    return MigrationReport(places=len(keep), dropped_non_finite=[names[i] for i in np.flatnonzero(~finite)],
                           duplicate_names=len(names) - len(set(names)))
