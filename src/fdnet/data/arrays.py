"""Reading ``.npy`` arrays a user hands fdnet (similarity matrices, ground-truth arrays) without
trusting their headers.

``np.load`` allocates the whole array the header describes before it reads a byte of data, so a
damaged or forged header claiming shape (10**6, 10**6) asks for 3.6 TiB. Here the header is read
first (``numpy.lib.format.read_magic`` and ``read_array_header_1_0/2_0``) and the array is loaded
only when the data it claims is actually in the file and fits in memory; otherwise the error
names the file and the shape it claims. Object arrays are never unpickled by this module.
"""

from __future__ import annotations

import math
import os
import zipfile
from pathlib import Path
from typing import BinaryIO

import numpy as np

from fdnet.errors import DataError

NPY_MAGIC = b"\x93NUMPY"


def physical_memory_bytes() -> int | None:
    """The memory this process may use: this machine's RAM, or less where a limit on the process's
    address space or data (``ulimit -v``/``-d``) says so; None where the OS says nothing (then
    only the file-size check applies)."""
    try:
        found = int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        found = None
    try:
        import resource

        for limit in (resource.RLIMIT_AS, resource.RLIMIT_DATA):
            soft = resource.getrlimit(limit)[0]
            if soft != resource.RLIM_INFINITY and soft > 0:
                found = soft if found is None else min(found, soft)
    except (ImportError, AttributeError, ValueError, OSError):
        pass
    return found


def format_bytes(count: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if count < 1024 or unit == "PiB":
            return f"{count:.0f} {unit}" if unit == "B" else f"{count:.1f} {unit}"
        count /= 1024
    return f"{count:.1f} PiB"  # pragma: no cover - the loop always returns


def read_npy_header(handle: BinaryIO, where: str) -> tuple[tuple[int, ...], bool, np.dtype]:
    """(shape, fortran_order, dtype) from the header at ``handle``'s position; leaves ``handle``
    at the first data byte. A file that is not ``.npy`` is a DataError naming ``where``."""
    fmt = np.lib.format
    try:
        version = fmt.read_magic(handle)
        if version == (1, 0):
            return fmt.read_array_header_1_0(handle)
        if version == (2, 0):
            return fmt.read_array_header_2_0(handle)
        # Version 3.0 (utf-8 field names) has no public reader; numpy's own is used if present.
        read_any = getattr(fmt, "_read_array_header", None)
        if read_any is None:
            raise ValueError(f".npy format version {version[0]}.{version[1]} is not supported")
        return read_any(handle, version)
    except (ValueError, EOFError) as exc:
        raise DataError(f"{where}: not a readable .npy file ({exc})") from exc


def check_npy_claim(
    shape: tuple[int, ...],
    dtype: np.dtype,
    where: str,
    data_bytes: int,
    max_bytes: int | None,
    ndim: int | None = None,
    what: str = "array",
) -> None:
    """Refuse a header whose array is not in the file or would not fit in ``max_bytes``."""
    if ndim is not None and len(shape) != ndim:
        raise DataError(f"{where}: expected a {ndim}-D {what}, but its header says shape {shape}")
    count = math.prod(int(n) for n in shape)
    # An object array is a pickle: at least one byte per element, whatever the pointer size.
    claimed = count * (1 if dtype.hasobject else dtype.itemsize)
    described = f"shape {shape} {dtype}"
    if claimed > data_bytes:
        raise DataError(
            f"{where}: header claims {described} ({format_bytes(count * dtype.itemsize)}) but the file holds "
            f"only {format_bytes(data_bytes)} of data; the file is truncated or its header is damaged"
        )
    in_memory = count * dtype.itemsize
    if max_bytes is not None and in_memory > max_bytes:
        raise DataError(
            f"{where}: {described} needs {format_bytes(in_memory)} of memory, more than the "
            f"{format_bytes(max_bytes)} allowed"
        )


def _default_limit(max_bytes: int | None | str) -> int | None:
    return physical_memory_bytes() if max_bytes == "memory" else max_bytes


def load_npy(
    path: str | os.PathLike, *, max_bytes: int | None | str = "memory", ndim: int | None = None, what: str = "array"
) -> np.ndarray:
    """A plain (non-object) array from a ``.npy`` file, its header checked before any allocation.

    ``max_bytes``: the most memory the array may take (default ``"memory"``: this machine's RAM;
    None: no limit beyond the file-size check). ``ndim``: the number of dimensions required.
    Errors (DataError) name the file: missing, not ``.npy`` (an ``.npz`` archive is named as one),
    a header claiming more data than the file holds or more memory than allowed, object dtype.
    """
    path = Path(path)
    where = str(path)
    try:
        handle = open(path, "rb")
    except FileNotFoundError as exc:
        raise DataError(f"{path}: {what} file not found") from exc
    except IsADirectoryError as exc:
        raise DataError(f"{path}: is a folder; expected a .npy file") from exc
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    with handle:
        start = handle.read(len(NPY_MAGIC))
        if start[:2] == b"PK":
            raise DataError(f"{path}: is an .npz archive; expected one .npy array")
        if start != NPY_MAGIC:
            raise DataError(f"{path}: not a .npy file (no NumPy header); save the {what} with numpy.save")
        handle.seek(0)
        shape, _, dtype = read_npy_header(handle, where)
        if dtype.hasobject:
            raise DataError(
                f"{path}: holds Python objects (dtype object), which are never unpickled; "
                f"save a plain numeric array"
            )
        data_bytes = os.fstat(handle.fileno()).st_size - handle.tell()
        check_npy_claim(shape, dtype, where, data_bytes, _default_limit(max_bytes), ndim, what)
        handle.seek(0)
        try:
            return np.load(handle, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise DataError(f"{path}: not a readable .npy file ({exc.__class__.__name__}: {exc})") from exc


def load_npz_member(
    path: str | os.PathLike,
    key: str,
    *,
    max_bytes: int | None | str = "memory",
    ndim: int | None = None,
    what: str = "array",
) -> np.ndarray:
    """Array ``key`` of an ``.npz`` archive, its header checked against the member's size first."""
    path = Path(path)
    where = f"{path} (array {key!r})"
    try:
        archive = zipfile.ZipFile(path)
    except FileNotFoundError as exc:
        raise DataError(f"{path}: {what} file not found") from exc
    except (zipfile.BadZipFile, OSError) as exc:
        raise DataError(f"{path}: not a readable .npz archive ({exc})") from exc
    with archive:
        names = [n[:-4] for n in archive.namelist() if n.endswith(".npy")]
        if key not in names:
            raise DataError(f"{path}: has no array {key!r} (arrays: {', '.join(names) or 'none'})")
        info = archive.getinfo(f"{key}.npy")
        try:
            with archive.open(info) as member:
                shape, _, dtype = read_npy_header(member, where)
                if dtype.hasobject:
                    raise DataError(
                        f"{where}: holds Python objects (dtype object), which are never "
                        f"unpickled; save a plain numeric array"
                    )
                check_npy_claim(
                    shape, dtype, where, info.file_size - member.tell(), _default_limit(max_bytes), ndim, what
                )
            with archive.open(info) as member:
                return np.lib.format.read_array(member, allow_pickle=False)
        except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
            raise DataError(f"{where}: not a readable array ({exc.__class__.__name__}: {exc})") from exc
