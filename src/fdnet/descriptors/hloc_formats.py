"""hloc's file formats (cvg/Hierarchical-Localization): global features and retrieval pairs.

**Global features** (``hloc/extract_features.py``, read by ``hloc/pairs_from_retrieval.py``):
an HDF5 file with one group per image, named by the image's path relative to hloc's
``image_dir`` (``db/0001.jpg`` is the group ``0001.jpg`` inside the group ``db``, as h5py's
``create_group`` makes it), holding the dataset ``global_descriptor`` of shape (D,). hloc's
``extract_features.main`` stores float32 arrays as float16 unless ``as_half=False`` (the
function's default is ``as_half=True``, its command line's is float32); its retrieval reads them
back with ``.float()``. fdnet writes float32 (no rounding of the vectors) and reads any float
type as float32. hloc also stores ``image_size`` beside each descriptor; nothing in hloc's
retrieval reads it, and fdnet does not write it. fdnet's files are written with HDF5's 1.8 file
format (``libver=("v108", "v108")``): every HDF5 since 1.8 reads them, hloc's
``libver="latest"`` readers included; the root carries the attributes ``method`` and
``settings`` (JSON) when fdnet extracted the vectors (hloc ignores attributes of the root).

**Pairs** (``hloc/pairs_from_retrieval.py`` writes them, ``hloc/utils/parsers.py``'s
``parse_retrieval`` reads them): a text file, one ``query_name reference_name`` per line, the
two names separated by one space, lines joined by ``\\n`` with no newline after the last one.
hloc's parser skips empty lines, splits every other line on whitespace and needs exactly two
names; it knows no comments (``#`` is part of a name). So an image name holding whitespace
cannot be written at all: it is refused with the name.

Files are written crash-safely: into a hidden ``.NAME.parts.*`` folder beside the target, then
renamed over it (a crash or an error leaves the target as it was; the folder a ``kill -9`` left
is removed by the next writer of that target, as for ``fdnet extract``'s ``.npz``).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from fdnet.errors import DataError, NotAvailableError, OutputError, output_error

logger = logging.getLogger(__name__)

#: the dataset of each image group that holds its global descriptor (hloc's key)
GLOBAL_KEY = "global_descriptor"
#: the suffixes of hloc's HDF5 files
H5_SUFFIXES = (".h5", ".hdf5")
#: HDF5 file format bounds of the files fdnet writes: readable by every HDF5 since 1.8
LIBVER = ("v108", "v108")


def require_h5py():
    """The h5py module, or NotAvailableError saying how to install it (the ``hloc`` extra)."""
    try:
        import h5py
    except ImportError as exc:
        raise NotAvailableError("hloc's .h5 files need the optional extra: pip install 'fdnet[hloc]' (h5py)") from exc
    return h5py


def _locking(h5py, value):
    """``locking=`` for h5py.File where this h5py and HDF5 support it (HDF5 >= 1.12.1)."""
    return {"locking": value} if h5py.version.hdf5_version_tuple >= (1, 12, 1) else {}


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


# ---------------------------------------------------------------------------------------- names
def _utf8(name: str, where) -> str:
    """``name`` when it is valid UTF-8 (what HDF5 and the pairs file store), else DataError."""
    try:
        name.encode("utf-8")
    except UnicodeEncodeError as exc:
        raise DataError(f"{where}: image name {ascii(name)} is not valid UTF-8; rename the file") from exc
    return name


def check_image_name(name, where) -> str:
    """``name`` as hloc's HDF5 files hold it (a relative path with ``/``), or DataError naming
    ``where`` (the file) and the image: empty, absolute, with an empty, ``.`` or ``..`` part, or
    not UTF-8."""
    name = os.fspath(name)
    if not isinstance(name, str):
        raise DataError(f"{where}: image name {name!r} is not text")
    if not name:
        raise DataError(f"{where}: an empty image name")
    if name.startswith("/"):
        raise DataError(f"{where}: image name {name!r} is absolute; hloc names images relative to its image_dir")
    if any(part in ("", ".", "..") for part in name.split("/")) or "\0" in name:
        raise DataError(
            f"{where}: image name {name!r} has an empty, '.' or '..' part; hloc names images by their "
            "plain relative path"
        )
    return _utf8(name, where)


def check_pair_name(name, where) -> str:
    """``name`` as hloc's pairs file can hold it: non-empty UTF-8 text without whitespace (hloc
    splits each line on whitespace), or DataError naming ``where`` and the image."""
    name = os.fspath(name)
    if not isinstance(name, str) or not name:
        raise DataError(f"{where}: an empty image name")
    if any(c.isspace() for c in name):
        raise DataError(
            f"{where}: image name {name!r} holds whitespace, which hloc's pairs file cannot hold "
            "(it splits each line on whitespace); rename the image"
        )
    return _utf8(name, where)


def image_root(inputs: Sequence[str | os.PathLike]) -> Path:
    """The folder hloc's ``image_dir`` must be for images listed from ``inputs`` (folders of
    images, videos, ROS bags, ``BAG:TOPIC``): a folder itself, a video's or bag's parent folder
    (its frames are ``SOURCE/FRAME``), and for several inputs the deepest folder holding them all
    (absolute, not resolved: symbolic links keep their names, as everywhere in fdnet)."""
    from fdnet.data.sources import is_source, split_topic

    roots = []
    for given in inputs:
        if is_source(given):
            source, _ = split_topic(given)
            roots.append(os.path.dirname(os.path.abspath(source)))
        else:
            roots.append(os.path.abspath(os.fspath(given)))
    try:
        return Path(os.path.commonpath(roots))
    except ValueError as exc:  # Windows: different drives
        raise DataError(
            f"{', '.join(map(str, inputs))}: no folder holds them all, so no image_dir can name " "their images"
        ) from exc


def relative_names(paths: Sequence[str | os.PathLike], root: str | os.PathLike) -> list[str]:
    """Each image's path relative to ``root`` with ``/`` (hloc's image names): ``root`` from
    :func:`image_root`. Paths are made absolute as listed, not resolved."""
    root = os.path.abspath(os.fspath(root))
    names = []
    for path in paths:
        relative = os.path.relpath(os.path.abspath(os.fspath(path)), root)
        if relative == ".." or relative.startswith(".." + os.sep):
            raise DataError(f"{path}: not below {root}, the folder its name would be relative to")
        names.append(Path(relative).as_posix())
    return names


# ------------------------------------------------------------------------------ global features
class GlobalFeaturesWriter:
    """hloc's global-features HDF5 written image by image, and atomically.

    ``write(names, rows)`` adds a batch (names relative to the image root, rows (n, D)); the
    groups go straight into an HDF5 file in a hidden ``.NAME.parts.*`` folder beside ``path``, so
    memory holds one batch whatever the number of images. :meth:`close` renames the file over
    ``path`` (synced first); :meth:`discard`, or leaving the ``with`` block by an exception,
    removes it and leaves ``path`` as it was. A ``with`` block left normally closes. ``attrs``
    become attributes of the root (strings or numbers)."""

    def __init__(self, path: str | os.PathLike, key: str = GLOBAL_KEY, attrs: dict | None = None):
        import tempfile

        from fdnet.descriptors.pipeline import lock_folder, remove_stale_parts
        from fdnet.io import ensure_writable

        h5py = self._h5py = require_h5py()
        self.path = Path(path)
        self.key = key
        self.count = 0
        self.dim: int | None = None
        self._file = None
        self._lock = None
        self._closed = False
        ensure_writable(self.path, what="global-features file")
        self._folder = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.parts.", dir=self.path.parent))
        try:
            self._lock = lock_folder(self._folder)
            remove_stale_parts(self.path)
            self._tmp = self._folder / self.path.name
            self._file = h5py.File(self._create(h5py))
            for name, value in (attrs or {}).items():
                self._file.attrs[name] = value
            self._lcpl = h5py.h5p.create(h5py.h5p.LINK_CREATE)
            self._lcpl.set_create_intermediate_group(True)
            self._lcpl.set_char_encoding(h5py.h5t.CSET_UTF8)
            self._key = key.encode("utf-8")
            self._type = h5py.h5t.py_create(np.dtype("<f4"))
        except (OSError, RuntimeError) as exc:
            self.discard()
            raise self._write_error(exc) from exc
        except BaseException:
            self.discard()
            raise

    def _create(self, h5py):
        """The temporary file's HDF5 id: the 1.8 format (:data:`LIBVER`); no lock (the file sits in
        this process's locked folder: HDF5's own lock would add nothing but failures on file
        systems without locks); and no data sieve buffer, so a full disk fails the write that
        meets it: with the buffer, HDF5 met it later, flushing inside an object's close, where
        h5py can only print the error, and closing the file then crashed the process."""
        fapl = h5py.h5p.create(h5py.h5p.FILE_ACCESS)
        fapl.set_libver_bounds(h5py.h5f.LIBVER_V18, h5py.h5f.LIBVER_V18)
        fapl.set_sieve_buf_size(0)
        if _locking(h5py, False):
            fapl.set_file_locking(False, True)
        return h5py.h5f.create(os.fsencode(self._tmp), h5py.h5f.ACC_TRUNC, fapl=fapl)

    def _write_error(self, exc: BaseException) -> OutputError:
        """One line for a failed write: HDF5 reports a full disk as an OSError or, from a flush
        while closing, a RuntimeError whose text holds the errno."""
        import errno as errnos
        import re

        code = getattr(exc, "errno", None)
        if code is None:
            found = re.search(r"errno = (\d+)", str(exc))
            code = int(found.group(1)) if found else None
        reason = (
            "no space left on the device" if code == errnos.ENOSPC else os.strerror(code) if code else _one_line(exc)
        )
        return output_error(
            f"{self.path}: cannot write it ({reason}); nothing was written there", OSError(code, reason)
        )

    def write(self, names: Sequence[str], rows, facts: Sequence | None = None) -> None:
        """Add one group per name holding its row as ``global_descriptor`` (float32 (D,)); with
        ``facts`` (per name: (size, modification time in ns) of the image's file, or None), the
        dataset's attributes ``size`` and ``mtime_ns`` record them (hloc ignores them)."""
        h5py = self._h5py
        if self._closed or self._file is None:
            raise ValueError(f"{self.path}: the writer is closed")
        rows = np.ascontiguousarray(rows, dtype=np.float32)
        names = list(names)
        if rows.ndim != 2 or len(rows) != len(names):
            raise ValueError(f"{len(names)} names for rows of shape {rows.shape}; expected ({len(names)}, D)")
        if self.dim is None:
            self.dim = int(rows.shape[1])
            self._space = h5py.h5s.create_simple((self.dim,))
        elif rows.shape[1] != self.dim:
            raise ValueError(f"rows of length {rows.shape[1]} after rows of length {self.dim}")
        fid = self._file.id
        try:
            for i, (name, row) in enumerate(zip(names, rows)):
                name = check_image_name(name, self.path)
                group = self._group(fid, name)
                if group.links.exists(self._key):
                    if h5py.h5o.get_info(group, self._key).type == h5py.h5o.TYPE_DATASET:
                        raise DataError(f"{self.path}: image {name!r} given twice")
                    raise DataError(
                        f"{self.path}: image {name!r} clashes with an image in its folder "
                        f"{name}/{self.key}: rename one"
                    )
                dataset = h5py.h5d.create(group, self._key, self._type, self._space)
                dataset.write(h5py.h5s.ALL, h5py.h5s.ALL, row)
                fact = facts[i] if facts is not None else None
                if fact is not None:
                    for attribute, value in zip((b"size", b"mtime_ns"), fact):
                        handle = h5py.h5a.create(
                            dataset, attribute, h5py.h5t.STD_I64LE, h5py.h5s.create(h5py.h5s.SCALAR)
                        )
                        handle.write(np.array(value, dtype="<i8"))
                self.count += 1
        except (OSError, RuntimeError) as exc:  # RuntimeError: HDF5's flushes (a full disk)
            raise self._write_error(exc) from exc

    def _group(self, fid, name: str):
        h5py = self._h5py
        encoded = name.encode("utf-8")
        try:
            return h5py.h5g.create(fid, encoded, lcpl=self._lcpl)
        except ValueError:  # the name exists: a folder of an image written before ("a" after "a/b.jpg")
            pass
        try:
            return h5py.h5g.open(fid, encoded)
        except (KeyError, ValueError, TypeError) as exc:
            raise DataError(
                f"{self.path}: image {name!r} clashes with another image's name (one of its folders is "
                f"a {self.key} dataset)"
            ) from exc

    def close(self) -> None:
        """Finish the file and rename it over the target (synced); a second call does nothing."""
        from fdnet.io import fsync_directory, fsync_file, output_mode

        if self._closed:
            return
        try:
            self._file.close()
            os.chmod(self._tmp, output_mode(self.path))
            fsync_file(self._tmp)
            os.replace(self._tmp, self.path)
            fsync_directory(self.path.parent)
        except (OSError, RuntimeError) as exc:  # RuntimeError: HDF5's flush while closing (a full disk)
            raise self._write_error(exc) from exc
        finally:
            self.discard()
        logger.debug("wrote %s: %d images", self.path, self.count)

    def discard(self) -> None:
        """Drop the temporary file and folder (the target is untouched)."""
        import shutil

        self._closed = True
        if self._file is not None:
            try:
                self._file.close()
            except Exception:  # noqa: BLE001 - already failing; the folder goes anyway
                pass
            self._file = None
        shutil.rmtree(self._folder, ignore_errors=True)
        if self._lock is not None:
            os.close(self._lock)
            self._lock = None

    def __enter__(self) -> "GlobalFeaturesWriter":
        return self

    def __exit__(self, exc_type, *rest) -> None:
        if exc_type is not None:
            self.discard()
        else:
            self.close()


def write_global_features(
    path: str | os.PathLike, names: list[str], vectors: np.ndarray, key: str = GLOBAL_KEY
) -> None:
    """hloc's global-features file: a group per image name holding ``key`` (float32 (D,)),
    written atomically (:class:`GlobalFeaturesWriter`)."""
    vectors = np.asarray(vectors)
    if vectors.ndim != 2 or len(vectors) != len(names):
        raise ValueError(f"{len(names)} names for vectors of shape {vectors.shape}; expected ({len(names)}, D)")
    with GlobalFeaturesWriter(path, key=key) as writer:
        writer.write(names, vectors)


def _open_error(path: Path, exc: BaseException) -> DataError:
    text = _one_line(exc)
    if "signature not found" in text:
        return DataError(f"{path}: not an HDF5 file")
    if "truncated" in text:
        return DataError(f"{path}: a truncated HDF5 file (shorter than its header says: an interrupted write or copy)")
    return DataError(f"{path}: cannot read it as HDF5 ({text})")


def read_global_features(
    path: str | os.PathLike, key: str = GLOBAL_KEY, facts: list | None = None
) -> tuple[list[str], np.ndarray]:
    """Every image of hloc's global-features file and its vector: (names, (N, D) float32).

    An image is a group holding a ``key`` dataset; its name is the group's path without the
    leading ``/`` (``db/0001.jpg``). The order is h5py's visit order: depth first, the members
    of each group in increasing byte order of their names (HDF5's name index): ``B.jpg``,
    ``a/b.jpg``, ``a.jpg``, ``db/10.jpg``, ``db/2.jpg``; not the order they were written in
    (hloc itself treats the names as a set). ``facts``, a list, receives per image the (size,
    modification time in ns) fdnet's writer recorded, (-1, -1) where none. DataError, naming the
    file, for a missing file, one that is not HDF5 or is truncated, one without any ``key``
    dataset, a vector that is not 1-D numbers, and vectors of different lengths."""
    h5py = require_h5py()
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: {'not a file' if path.exists() else 'no such file'}")
    try:
        handle = h5py.File(path, "r", **_locking(h5py, "best-effort"))
    except (OSError, ValueError) as exc:
        raise _open_error(path, exc) from exc
    try:
        with handle:
            return _read_vectors(h5py, handle, path, key, facts)
    except DataError:
        raise
    except (OSError, KeyError, ValueError, RuntimeError, TypeError) as exc:
        raise DataError(f"{path}: cannot read it as hloc's global features ({_one_line(exc)})") from exc


def read_global_attributes(path: str | os.PathLike) -> dict:
    """What a global-features file fdnet wrote records about how its vectors were made: the root's
    ``method`` and the model's ``fingerprint`` (text), ``settings`` (a dict, from JSON) and
    ``root`` (the absolute folder its image names are relative to); {} for hloc's own files.
    Attributes of another kind are left out, never guessed at."""
    import json

    h5py = require_h5py()
    path = Path(path)
    try:
        with h5py.File(path, "r", **_locking(h5py, "best-effort")) as handle:
            attrs = {
                name: handle.attrs[name]
                for name in ("method", "fingerprint", "settings", "root")
                if name in handle.attrs
            }
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise _open_error(path, exc) from exc
    recorded = {}
    for name, value in attrs.items():
        if isinstance(value, bytes):
            value = value.decode("utf-8", "replace")
        if isinstance(value, str):
            recorded[name] = value
    if "settings" in recorded:
        try:
            recorded["settings"] = json.loads(recorded["settings"])
        except ValueError:
            del recorded["settings"]
        else:
            if not isinstance(recorded["settings"], dict):
                del recorded["settings"]
    return recorded


def _read_vectors(h5py, handle, path: Path, key: str, facts: list | None = None) -> tuple[list[str], np.ndarray]:
    found: list[str] = []
    members: set[str] = set()  # a few member names, to say what the file holds instead
    suffix = "/" + key

    def visit(name: str):
        if name.endswith(suffix):
            found.append(name)
        elif len(members) < 6:
            members.add(name.rpartition("/")[2])

    # names only: opening every object in Python (visititems) is several times slower
    getattr(handle, "visit_links", handle.visit)(visit)
    if not found:
        held = ", ".join(sorted(members)[:5]) + (", ..." if len(members) > 5 else "") if members else "nothing"
        raise DataError(
            f"{path}: no image group holds a {key!r} dataset, so these are not hloc's global features "
            f"(the file holds {held})"
        )
    fid = handle.id
    vectors = None
    names = []
    first = None
    for link in found:
        encoded = link.encode("utf-8")
        _refuse_links_out(h5py, fid, link, path)
        try:
            dataset = h5py.h5d.open(fid, encoded)
        except KeyError:
            if h5py.h5o.get_info(fid, encoded).type == h5py.h5o.TYPE_GROUP:
                continue  # a folder that happens to have the key's name ("x/global_descriptor/y.jpg")
            raise
        name = link[: -len(suffix)]
        _refuse_storage_elsewhere(h5py, fid, dataset, path, name)
        shape = tuple(dataset.shape)
        kind = dataset.dtype.kind
        if kind not in "fiu":
            raise DataError(f"{path}: image {name!r}: {key} holds {dataset.dtype}, not numbers")
        if len(shape) == 2 and shape[0] == 1:
            shape = shape[1:]
        if len(shape) != 1:
            raise DataError(f"{path}: image {name!r}: {key} of shape {tuple(dataset.shape)}; expected one vector (D,)")
        _check_claim(dataset, (len(found), shape[0]), path, name)
        if vectors is None:
            vectors, first = np.empty((len(found), shape[0]), dtype=np.float32), name
        elif shape[0] != vectors.shape[1]:
            raise DataError(
                f"{path}: vectors of different lengths: {vectors.shape[1]} for {first!r}, {shape[0]} for " f"{name!r}"
            )
        dataset.read(h5py.h5s.ALL, h5py.h5s.ALL, vectors[len(names)].reshape(dataset.shape))
        names.append(name)
        if facts is not None:
            facts.append(_image_facts(h5py, dataset))
    if not names:
        raise DataError(f"{path}: no image group holds a {key!r} dataset, so these are not hloc's global features")
    return names, vectors[: len(names)]


def _image_facts(h5py, dataset) -> tuple[int, int]:
    """(size, modification time in ns) that fdnet's writer recorded for an image; -1 where not."""
    values = []
    for attribute in (b"size", b"mtime_ns"):
        if not h5py.h5a.exists(dataset, attribute):
            return -1, -1
        handle = h5py.h5a.open(dataset, attribute)
        if handle.shape != () or handle.dtype.kind not in "iu":
            return -1, -1
        value = np.zeros((), dtype="<i8")
        handle.read(value)
        values.append(int(value))
    return values[0], values[1]


def _refuse_links_out(h5py, fid, link: str, path: Path) -> None:
    """A vectors file reads nothing but itself: an external link on the way to a dataset (to
    another HDF5 file, anywhere on the disk) is refused."""
    parts = link.split("/")
    for depth in range(1, len(parts) + 1):
        step = "/".join(parts[:depth]).encode("utf-8")
        if fid.links.get_info(step).type == h5py.h5l.TYPE_EXTERNAL:
            raise DataError(
                f"{path}: {step.decode('utf-8', 'replace')!r} is an external link to another file; a "
                "vectors file that reads other files is refused"
            )


def _refuse_storage_elsewhere(h5py, fid, dataset, path: Path, name: str) -> None:
    """Refused: a dataset whose bytes live in other files (HDF5 external storage, e.g. pointing at
    /etc/passwd; a virtual dataset mapping other files) or in another file reached by any link."""
    plist = dataset.get_create_plist()
    if plist.get_external_count() > 0:
        raise DataError(
            f"{path}: image {name!r}: its vector is stored in an external file "
            f"({plist.get_external(0)[0].decode('utf-8', 'replace')}); a vectors file that reads other "
            "files is refused"
        )
    if plist.get_layout() == h5py.h5d.VIRTUAL:
        raise DataError(
            f"{path}: image {name!r}: its vector is a virtual dataset (mapped from other files); a "
            "vectors file that reads other files is refused"
        )
    if h5py.h5f.get_name(dataset) != h5py.h5f.get_name(fid):
        raise DataError(
            f"{path}: image {name!r}: its vector lives in another file "
            f"({h5py.h5f.get_name(dataset).decode('utf-8', 'replace')}); refused"
        )


def _check_claim(dataset, shape: tuple[int, int], path: Path, name: str) -> None:
    """Before anything is allocated: a dataset must hold data (a few bytes can declare
    300 million floats never written), and the vectors must fit in this process's memory."""
    from fdnet.data.arrays import format_bytes, physical_memory_bytes

    if dataset.shape and int(np.prod(dataset.shape)) > 0 and dataset.get_storage_size() == 0:
        raise DataError(
            f"{path}: image {name!r}: declares a vector of shape {tuple(dataset.shape)} but holds no "
            "data (never written); refused"
        )
    needed = int(shape[0]) * int(shape[1]) * 4
    allowed = physical_memory_bytes()
    if allowed is not None and needed > allowed:
        raise DataError(
            f"{path}: {shape[0]} vectors of length {shape[1]} need {format_bytes(needed)} of memory, "
            f"more than the {format_bytes(allowed)} this process may use"
        )


# ------------------------------------------------------------------------------------- pairs
def write_pairs(path: str | os.PathLike, pairs: Iterable[tuple[str, str]]) -> None:
    """hloc's pairs file: ``query reference`` per line, one space between, ``\\n`` between lines
    and none after the last (as ``pairs_from_retrieval`` writes it), written atomically while
    ``pairs`` streams in. A name holding whitespace is refused (DataError naming it) and nothing
    is written."""
    from fdnet.io import atomic_path

    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8", newline="\n") as handle:
        write_pairs_to(handle, pairs, path)


def write_pairs_to(handle, pairs: Iterable[tuple[str, str]], where) -> int:
    """:func:`write_pairs`' lines into an open text ``handle`` (UTF-8, ``newline="\\n"``), for a
    caller that renames several files into place together; DataError naming ``where`` for a name
    holding whitespace. Returns the number of pairs."""
    count = 0
    for pair in pairs:
        query, reference = pair
        line = f"{check_pair_name(query, where)} {check_pair_name(reference, where)}"
        handle.write(line if count == 0 else "\n" + line)
        count += 1
    return count


def read_pairs(path: str | os.PathLike) -> list[tuple[str, str]]:
    """The (query, reference) pairs of hloc's pairs file, in file order, read as hloc's
    ``parse_retrieval`` reads them: empty lines skipped, every other line split on whitespace
    into exactly two names (no comments: ``#`` is part of a name). DataError naming the file and
    line for a line that is not two names (hloc would stop there too)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: {'not a file' if path.exists() else 'no such file'}")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise DataError(f"{path}: not UTF-8 text ({_one_line(exc)}); not a pairs file") from exc
    except OSError as exc:
        raise DataError(f"{path}: cannot read it ({exc.strerror or _one_line(exc)})") from exc
    pairs = []
    # read_text's universal newlines, as hloc's open(path, "r"): \r\n and \r end lines too
    for number, line in enumerate(text.rstrip("\n").split("\n"), start=1):
        if not line:
            continue
        parts = line.split()
        if len(parts) != 2:
            shown = line if len(line) <= 80 else line[:77] + "..."
            raise DataError(
                f"{path}, line {number}: {shown!r} is not two image names (query reference) separated by " "a space"
            )
        pairs.append((parts[0], parts[1]))
    return pairs
