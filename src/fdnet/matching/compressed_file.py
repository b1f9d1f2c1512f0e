"""A :class:`~fdnet.matching.compressed.CompressedIndex`'s codes in one file, so a process loads
them instead of training and encoding the map again.

Layout: the 8 bytes ``FDNETCQ1``; the payload: the OPQ rotation (faiss's serialisation of a
vector transform, empty without one) then the faiss index (the fast-scan codes re-ranked by the
8-bit ones, ``faiss.write_index``), streamed to the file without a copy in memory; a JSON
trailer (the caller's header: settings, place count, identity; plus the payload's length and
CRC-32); the trailer's length (8 bytes, little-endian) and ``FDNETCQE``. A file is written to a
temporary name beside it, fsynced and renamed over the old one, so a kill leaves the old file or
none. Reading checks the whole payload's CRC before faiss parses it: a damaged file is a
:class:`~fdnet.errors.DataError`, never garbage handed to faiss.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from pathlib import Path

import numpy as np

from fdnet.errors import DataError
from fdnet.io import atomic_path

MAGIC = b"FDNETCQ1"
END = b"FDNETCQE"
_TAIL = struct.Struct("<Q8s")
#: the largest trailer accepted (a JSON header of a few hundred bytes)
_MAX_TRAILER = 1 << 20
_CHUNK = 1 << 24


def write_codes(path: str | os.PathLike, header: dict, rotation, index) -> None:
    """Write ``rotation`` (a faiss vector transform or None) and ``index`` (a faiss index) with
    ``header`` (JSON-serialisable) to ``path``, atomically (see the module docstring)."""
    import faiss

    path = Path(path)
    rotation_bytes = b""
    if rotation is not None:
        writer = faiss.VectorIOWriter()
        faiss.write_VectorTransform(rotation, writer)
        rotation_bytes = faiss.vector_to_array(writer.data).tobytes()
    with atomic_path(path) as temporary, open(temporary, "wb") as out:
        out.write(MAGIC)
        written = [0, 0]  # bytes, CRC-32

        def put(data: bytes) -> int:
            out.write(data)
            written[0] += len(data)
            written[1] = zlib.crc32(data, written[1])
            return len(data)

        put(rotation_bytes)
        callback = faiss.PyCallbackIOWriter(put)
        faiss.write_index(index, callback)
        del callback  # flushes what it buffered
        trailer = json.dumps(
            {**header, "rotation_bytes": len(rotation_bytes), "payload_bytes": written[0], "crc32": written[1]}
        ).encode()
        out.write(trailer)
        out.write(_TAIL.pack(len(trailer), END))


def read_header(path: str | os.PathLike) -> dict:
    """The trailer of the codes file ``path`` (cheap: the payload is not read)."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            if size < len(MAGIC) + _TAIL.size or f.read(len(MAGIC)) != MAGIC:
                raise DataError(f"{path}: not a compressed codes file (or cut short)")
            f.seek(size - _TAIL.size)
            length, end = _TAIL.unpack(f.read(_TAIL.size))
            if end != END or length > min(_MAX_TRAILER, size - len(MAGIC) - _TAIL.size):
                raise DataError(f"{path}: the compressed codes file is cut short or damaged")
            f.seek(size - _TAIL.size - length)
            header = json.loads(f.read(length))
    except OSError as exc:
        raise DataError(f"{path}: cannot read the compressed codes ({exc.strerror or exc})") from exc
    except (ValueError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: the compressed codes file's header is damaged ({exc})") from exc
    payload = header.get("payload_bytes") if isinstance(header, dict) else None
    if not isinstance(payload, int) or len(MAGIC) + payload + length + _TAIL.size != size:
        raise DataError(f"{path}: the compressed codes file is cut short or damaged")
    return header


def read_codes(path: str | os.PathLike, header: dict) -> tuple:
    """(rotation or None, faiss index) from the codes file ``path`` whose trailer is ``header``
    (:func:`read_header`), after checking the payload's CRC-32."""
    import faiss

    path = Path(path)
    payload, rotation_bytes = int(header["payload_bytes"]), int(header["rotation_bytes"])
    try:
        with open(path, "rb") as f:
            f.seek(len(MAGIC))
            crc, left = 0, payload
            while left:
                chunk = f.read(min(_CHUNK, left))
                if not chunk:
                    break
                crc, left = zlib.crc32(chunk, crc), left - len(chunk)
            if left or crc != header["crc32"]:
                raise DataError(f"{path}: the compressed codes file is damaged (checksum)")
            f.seek(len(MAGIC))
            rotation = None
            if rotation_bytes:
                reader = faiss.VectorIOReader()
                faiss.copy_array_to_vector(np.frombuffer(f.read(rotation_bytes), np.uint8), reader.data)
                rotation = faiss.read_VectorTransform(reader)
            callback = faiss.PyCallbackIOReader(f.read)
            index = faiss.read_index(callback)
            del callback
    except OSError as exc:
        raise DataError(f"{path}: cannot read the compressed codes ({exc.strerror or exc})") from exc
    except RuntimeError as exc:  # faiss refused what it read
        raise DataError(f"{path}: the compressed codes file is damaged ({exc})") from exc
    return rotation, index
