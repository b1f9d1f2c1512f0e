"""Vectors computed elsewhere as a descriptor: ``--method precomputed --vectors FILE [--vectors FILE ...]``.

A descriptor here is anything that maps images to vectors, so vectors another tool computed
(MegaLoc, BoQ, SALAD run in their own projects) serve every command after the descriptor:
acceptance rules, calibration, sequences, loop closure, the place database, the metrics. The
vectors are keyed by image, not computed from pixels: the streaming pipeline hands this
descriptor each batch's image paths (:attr:`keyed_by_image`, :meth:`lookup`).

Files (several merge; one per folder is the common case):

* fdnet's own ``.npz`` from ``fdnet extract``: ``descriptors`` (or FDNet's ``content``), with
  ``names`` and ``sources``: an image is ``SOURCE/NAME``;
* ``.npy`` (N, D) plus a names list: ``--method-set names=FILE``, default the ``.txt`` beside
  it with the same stem, one image name (or path) per line in row order;
* hloc's global-features ``.h5``: ``global_descriptor`` per image name (names relative to the
  image root, as hloc writes them).

``normalise=l2`` (default) makes every vector unit length (rows already unit length are kept
bit for bit); ``normalise=none`` compares them as stored (dot product).

An image is found by its file name and, when the vectors file names one, its folder's name
(``day/0001.png`` is never ``dusk/0001.png``'s vector); where several vectors still fit
(``a/day/0001.png``, ``b/day/0001.png``), by the most trailing folders in common with the image's
path, then by a name whose every folder agrees with the path (``day/0001.png`` before
``x/day/0001.png`` for ``ROOT/day/0001.png``). So relative names (hloc's), moved data and absolute
paths all resolve; an image listed through a symbolic link that matches nothing is looked up
again by its resolved path. Two equally good candidates are an error naming both, never a guess;
so is an image with no vector (naming it and the files searched), and so is one vector asked for
by two different images (a name without folders, ``0001.png``, fits every folder's
``0001.png``: a file of such names is warned about when loaded).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Sequence

import numpy as np

from fdnet.data.arrays import load_npz_member
from fdnet.descriptors.base import Descriptor, check_vectors, row_norms
from fdnet.descriptors.settings import MethodSettings
from fdnet.errors import ConfigError, DataError

logger = logging.getLogger(__name__)

#: what ``normalise`` may be: ``l2`` (unit vectors, cosine similarity) or ``none`` (as stored)
NORMALISE_CHOICES = ("l2", "none")


def _parts(name: str | os.PathLike) -> tuple[str, ...]:
    """A name's path components, without ``.`` (``./a/b.png`` and ``a/b.png`` are one name)."""
    return tuple(p for p in Path(os.fspath(name)).parts if p not in (".", ""))


def _common_tail(a: tuple[str, ...], b: tuple[str, ...]) -> int:
    n = 0
    while n < min(len(a), len(b)) and a[-1 - n] == b[-1 - n]:
        n += 1
    return n


def _read_npz(path: Path, array: str | None) -> tuple[list[str], np.ndarray, dict]:
    try:
        with np.load(path, allow_pickle=False) as data:
            keys = set(data.files)
            chosen = array or next((k for k in ("descriptors", "content") if k in keys), None)
            if chosen is None or chosen not in keys:
                raise DataError(
                    f"{path}: no {array or 'descriptors or content'} array "
                    f"(holds {', '.join(sorted(keys))}); give the array with --method-set array=NAME"
                )
            if "names" not in keys:
                raise DataError(f"{path}: no names array: an image's vector cannot be found without its name")

            def member(key: str, ndim: int | None = None) -> np.ndarray:
                # the header's shape is checked against the member's size and this process's memory
                # before anything is allocated: a few compressed bytes may claim gigabytes
                return load_npz_member(path, key, ndim=ndim, what=f"{key} array")

            vectors = _numbers(path, member(chosen), chosen)
            names = _texts(path, member("names"), "names")
            sources = _texts(path, member("sources"), "sources") if "sources" in keys else None
            recorded = {}
            if "method" in keys:
                recorded["method"] = str(member("method"))
            if "fingerprint" in keys:
                recorded["fingerprint"] = str(member("fingerprint"))
            if "settings" in keys:
                try:
                    recorded["settings"] = json.loads(str(member("settings")))
                except ValueError:
                    pass
            if "sizes" in keys and "mtimes_ns" in keys:  # what each image was when described
                recorded["facts"] = (member("sizes", 1).astype(np.int64), member("mtimes_ns", 1).astype(np.int64))
    except DataError:
        raise
    except (OSError, ValueError, KeyError, EOFError) as exc:
        raise DataError(f"{path}: not a readable .npz of vectors ({' '.join(str(exc).split())})") from exc
    facts = recorded.get("facts")
    if facts is not None and not len(facts[0]) == len(facts[1]) == len(names):
        raise DataError(
            f"{path}: {len(facts[0])} sizes and {len(facts[1])} modification times for {len(names)} "
            "names; the file is damaged"
        )
    if sources is not None:
        if len(sources) != len(names):  # without them the names lose their folders: refused, not guessed
            raise DataError(
                f"{path}: {len(sources)} sources for {len(names)} names; each image's source (its "
                "folder) is needed to find its vector"
            )
        names = [os.path.join(s, n) for s, n in zip(sources, names)]
    return names, vectors, recorded


def _texts(path: Path, array: np.ndarray, what: str) -> list[str]:
    """A 1-D array of text (``str``, or UTF-8 ``bytes`` as some writers store it) as a list."""
    if array.ndim != 1 or array.dtype.kind not in "US":
        raise DataError(
            f"{path}: {what} is an array of {array.dtype} of shape {array.shape}; expected one text " "per image"
        )
    if array.dtype.kind == "S":
        return [bytes(n).decode("utf-8", "surrogateescape") for n in array]
    return [str(n) for n in array]


def _numbers(path: Path, array: np.ndarray, what: str) -> np.ndarray:
    """``array`` as float32, refusing what is not real numbers (complex ones would lose a part)."""
    if array.dtype.kind not in "fiu":
        raise DataError(f"{path}: {what} holds {array.dtype}, not real numbers")
    with np.errstate(over="ignore", invalid="ignore"):  # beyond float32's range: infinity, said below
        return np.asarray(array, dtype=np.float32)


def _read_npy(path: Path, names_file: str | None) -> tuple[list[str], np.ndarray, dict]:
    listing = Path(names_file) if names_file else path.with_suffix(".txt")
    try:
        vectors = _numbers(path, np.load(path, allow_pickle=False), "the array")
    except (OSError, ValueError, EOFError) as exc:
        raise DataError(f"{path}: not a readable .npy array ({' '.join(str(exc).split())})") from exc
    if not listing.is_file():
        raise DataError(
            f"{path}: no names list {listing} (one image name per line, in the rows' order); give "
            "it with --method-set names=FILE"
        )
    try:
        names = [line.strip() for line in listing.read_text(encoding="utf-8").splitlines() if line.strip()]
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{listing}: cannot read the names list ({exc})") from exc
    return names, vectors, {}


def _read_h5(path: Path) -> tuple[list[str], np.ndarray, dict]:
    from fdnet.descriptors.hloc_formats import read_global_attributes, read_global_features

    facts: list[tuple[int, int]] = []
    names, vectors = read_global_features(path, facts=facts)
    recorded = read_global_attributes(path)
    if any(size >= 0 for size, _ in facts):  # what each image was when described (fdnet's own file)
        recorded["facts"] = (np.array([f[0] for f in facts], np.int64), np.array([f[1] for f in facts], np.int64))
    root = recorded.pop("root", None)
    if root:  # fdnet's own file: its names are relative to this folder, so they keep their folders
        names = [os.path.join(root, name) for name in names]
    return names, np.asarray(vectors, dtype=np.float32), recorded


def read_vectors(
    path: str | os.PathLike, names_file: str | None = None, array: str | None = None
) -> tuple[list[str], np.ndarray, dict]:
    """(image names, (N, D) float32 vectors, what the file records about how they were made)
    from one vectors file, by its suffix (``.npz``, ``.npy``, ``.h5``/``.hdf5``)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: {'not a file' if path.exists() else 'vectors file not found'}")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        names, vectors, recorded = _read_npz(path, array)
    elif suffix == ".npy":
        names, vectors, recorded = _read_npy(path, names_file)
    elif suffix in (".h5", ".hdf5"):
        names, vectors, recorded = _read_h5(path)
    else:
        raise DataError(
            f"{path}: not a vectors file fdnet reads (.npz from fdnet extract, .npy with a names list, " "hloc's .h5)"
        )
    if vectors.ndim != 2 or vectors.shape[0] == 0 or vectors.shape[1] == 0:
        raise DataError(f"{path}: vectors of shape {tuple(vectors.shape)}; expected (images, length)")
    if len(names) != len(vectors):
        raise DataError(f"{path}: {len(vectors)} vectors but {len(names)} image names")
    vectors = check_vectors(vectors, path, lambda row: names[row])
    empty = next((i for i, name in enumerate(names) if not _parts(name)), None)
    if empty is not None:
        raise DataError(f"{path}: row {empty} has an empty image name")
    return names, vectors, recorded


def _same_file(a: str, b: str) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.abspath(a) == os.path.abspath(b)


@dataclass(frozen=True)
class PrecomputedSettings(MethodSettings):
    method: ClassVar[str] = "precomputed"
    #: the vectors files (--vectors, repeatable: the files merge): fdnet extract's .npz, .npy
    #: with a names list, hloc's .h5
    vectors: str | tuple[str, ...] | None = None
    #: a .npy's row names: a text file, one image a line
    names: str | None = None
    #: the array of a .npz or .h5 holding the vectors (default: the file's own)
    array: str | None = None
    #: l2 (rows brought to unit length) or none (as stored)
    normalise: str = "l2"
    #: (height, width) pixels are read at where a command needs them (default: the recorded size, else 120x160)
    input_size: tuple[int, int] | str | None = None

    def check(self) -> None:
        vectors = self.vectors
        files = [vectors] if isinstance(vectors, (str, os.PathLike)) else vectors
        if files is not None and (
            not isinstance(files, (list, tuple)) or not all(isinstance(f, (str, os.PathLike)) for f in files)
        ):
            self.refuse("vectors", "must be a file name or a list of them")
        if self.need_path("names") is not None and files is not None and len(files) > 1:
            raise ConfigError("precomputed: names=FILE lists the rows of one .npy; give one --vectors with it")
        self.need_text("array", optional=True)
        if self.normalise not in NORMALISE_CHOICES:
            self.refuse("normalise", f"choose {' or '.join(NORMALISE_CHOICES)}")
        self.need_size("input_size", optional=True)


class PrecomputedDescriptor(Descriptor):
    """Vectors from files, looked up by image (module docstring). Settings: :class:`PrecomputedSettings`."""

    name = "precomputed"
    keyed_by_image = True
    Settings: ClassVar[type] = PrecomputedSettings

    def __init__(self, settings: PrecomputedSettings | None = None, **options):
        conf = self.conf = PrecomputedSettings.build(settings, options)
        vectors, names, array, normalise = conf.vectors, conf.names, conf.array, conf.normalise
        input_size = conf.input_size
        if not vectors:
            raise ConfigError(
                "precomputed: give the vectors with --vectors FILE (repeatable: .npz from fdnet "
                "extract, .npy with a names list, hloc's .h5)"
            )
        files = [vectors] if isinstance(vectors, (str, os.PathLike)) else list(vectors)
        self.files = [str(f) for f in files]
        self.normalise = normalise
        rows: list[np.ndarray] = []
        self._keys: list[tuple[str, ...]] = []
        self._row_files: list[str] = []
        self.recorded: dict = {}
        by_key: dict[tuple[str, ...], str] = {}
        digest = hashlib.sha256()
        sizes: list[np.ndarray] = []
        made_by: list[str | None] = []  # the model each file records, if it does
        mtimes: list[np.ndarray] = []
        for i, file in enumerate(self.files):
            twice = next((f for f in self.files[:i] if _same_file(f, file)), None)
            if twice is not None:
                raise DataError(f"{file}: given twice (as {twice} too); give each vectors file once")
            file_names, file_vectors, recorded = read_vectors(file, names, array)
            facts = recorded.pop("facts", None)
            unknown = np.full(len(file_names), -1, np.int64)
            sizes.append(facts[0] if facts is not None else unknown)
            mtimes.append(facts[1] if facts is not None else unknown)
            if rows and file_vectors.shape[1] != rows[0].shape[1]:
                raise DataError(
                    f"{file}: vectors of length {file_vectors.shape[1]}, but {self.files[0]}'s are "
                    f"{rows[0].shape[1]} long: one descriptor's vectors only"
                )
            if recorded and self.recorded and recorded.get("method") != self.recorded.get("method"):
                raise DataError(
                    f"{file}: vectors of {recorded.get('method')}, but {self.files[0]}'s are of "
                    f"{self.recorded.get('method')}: one descriptor's vectors only"
                )
            made_by.append(recorded.get("fingerprint"))
            if len({f for f in made_by if f is not None}) > 1:
                raise DataError(
                    f"{file}: vectors of another {recorded.get('method')} model than {self.files[0]}'s "
                    "(the files record different models): one model's vectors only"
                )
            self.recorded = self.recorded or recorded
            bare = next((name for name in file_names if len(_parts(name)) == 1), None)
            if bare is not None:
                logger.warning(
                    f"{file}: images named without a folder (e.g. {bare}) are found by their file name "
                    f"alone: this file's {bare} is the vector of any folder's {bare}"
                )
            for name in file_names:
                key = _parts(name)
                if key in by_key:
                    raise DataError(
                        f"{file}: image {name} has a vector already (in {by_key[key]}); give each "
                        "image's vector once"
                    )
                by_key[key] = file
                self._keys.append(key)
                self._row_files.append(file)
            rows.append(file_vectors)
            digest.update(np.ascontiguousarray(file_vectors).tobytes())
            digest.update("\n".join(file_names).encode("utf-8", "surrogateescape"))
        # Pixels are still decoded where a command reads them (the loop-closure gates): at the size
        # the vectors' own method read them, when the file records it.
        from fdnet.data.images import check_image_size

        where = "precomputed: input_size"
        recorded_settings = self.recorded.get("settings")
        if input_size is None and isinstance(recorded_settings, dict) and recorded_settings.get("input_size"):
            input_size, where = recorded_settings["input_size"], f"{self.files[0]}: the recorded input_size"
        self.input_size = check_image_size((120, 160) if input_size is None else input_size, where)
        matrix = np.concatenate(rows)
        if normalise == "l2":
            # Rows already of unit length are kept bit for bit: dividing by a norm of 1 +- 1e-7
            # would change last bits, and the vectors' own method's numbers must come back exactly.
            # (norms in float64: large float32 values would overflow to infinity and give zeros)
            norms = row_norms(matrix)
            off = np.abs(norms - 1.0) > 1e-5
            matrix[off] = (matrix[off] / np.maximum(norms[off, None], 1e-12)).astype(np.float32)
        self.vectors = matrix
        self._by_name: dict[str, list[int]] = defaultdict(list)
        for row, key in enumerate(self._keys):
            self._by_name[key[-1] if key else ""].append(row)
        self.vectors_sha256 = digest.hexdigest()
        if None in made_by:  # a file that does not say which model made it: identified by its vectors
            self.recorded.pop("fingerprint", None)
        #: per row, the size and modification time (ns) of the image file it was computed from; -1: not recorded
        self._sizes, self._mtimes = np.concatenate(sizes), np.concatenate(mtimes)
        self._warned_mtime = False
        #: row -> the (resolved) image it described: one vector is never two images'
        self._served: dict[int, tuple[str, str]] = {}

    @property
    def dim(self) -> int:
        return int(self.vectors.shape[1])

    def settings(self) -> dict:
        return {
            "input_size": list(self.input_size),
            "vectors": self.files,
            "normalise": self.normalise,
            "vectors_sha256": self.vectors_sha256,
            "images": len(self._keys),
            **({"source_method": self.recorded["method"]} if "method" in self.recorded else {}),
            **({"source_fingerprint": self.recorded["fingerprint"]} if "fingerprint" in self.recorded else {}),
        }

    def fingerprint(self) -> str:
        # Files that record the model that made them (fdnet extract's) are that model's vectors,
        # whatever images they hold: a database of them grows with later files of the same model.
        # Others are identified by their vectors' bytes and names (vectors_sha256): hashing the
        # merged matrix again, as the base class would, only costs time on a large map.
        settings = {k: v for k, v in self.settings().items() if k != "vectors"}
        if "source_fingerprint" in settings:
            settings = {k: v for k, v in settings.items() if k not in ("vectors", "vectors_sha256", "images")}
        return hashlib.sha256(f"method={self.name}\n{json.dumps(settings, sort_keys=True)}".encode()).hexdigest()

    def row_of(self, path: str | os.PathLike) -> int:
        """The row holding ``path``'s vector (module docstring: by name, then trailing folders)."""
        listed = os.path.abspath(os.fspath(path))
        key = _parts(listed)
        candidates = self._candidates(key)
        if not candidates and os.path.realpath(listed) != listed:  # through a symbolic link
            key = _parts(os.path.realpath(listed))
            candidates = self._candidates(key)
        if not candidates:
            raise DataError(
                f"{path}: no vector for this image in {', '.join(self.files)} (looked up by its file "
                f"name and folder, {'/'.join(key[-2:]) if key else path!r}); every image a command "
                "reads needs one"
            )
        if len(candidates) == 1:
            return candidates[0]
        # most trailing folders in common; then a name all of whose folders agree (not moved data)
        fits = [
            (_common_tail(key, self._keys[row]), _common_tail(key, self._keys[row]) == len(self._keys[row]))
            for row in candidates
        ]
        best = max(fits)
        chosen = [row for row, fit in zip(candidates, fits) if fit == best]
        if len(chosen) > 1:
            a, b = ("/".join(self._keys[row]) for row in chosen[:2])
            raise DataError(
                f"{path}: two vectors fit this image equally well ({a} and {b}); name the images by "
                "their folders in the vectors files"
            )
        return chosen[0]

    def _candidates(self, key: tuple[str, ...]) -> list[int]:
        # the file name and, where the stored name has one, its folder's name must agree
        return [
            row
            for row in self._by_name.get(key[-1] if key else "", [])
            if _common_tail(key, self._keys[row]) >= min(2, len(self._keys[row]))
        ]

    def lookup(self, paths: Sequence[str | os.PathLike]) -> np.ndarray:
        """(len(paths), dim) float32: each image's vector. DataError when a vector was already
        another image's (two images, one vector: at least one would get a wrong one)."""
        rows = []
        for path in paths:
            row = self.row_of(path)
            image = os.path.realpath(os.fspath(path))
            first = self._served.setdefault(row, (image, os.fspath(path)))
            if first[0] != image:
                raise DataError(
                    f"{path}: its vector would be {'/'.join(self._keys[row])}'s, which {first[1]} "
                    "already took: one vector cannot be two images'; name the images by their folders "
                    "in the vectors files (e.g. extract the folder holding both with --recursive)"
                )
            self._check_same_image(path, row)
            rows.append(row)
        return self.vectors[rows]

    def _check_same_image(self, path, row: int) -> None:
        """The image must be the file the vector was computed from, where the vectors file records
        its size and modification time (``fdnet extract`` does): another route's or condition's
        image of the same name and folder is refused; a file of the same size with another time
        (copied without keeping times) is warned about once."""
        if self._sizes[row] < 0:
            return
        from fdnet.data.identity import image_facts

        facts = image_facts(path)
        if facts is None:
            return  # unreadable: the command's own reading says so
        file = self._file_of(row)
        if facts[1] != self._sizes[row]:
            raise DataError(
                f"{path}: not the image that {file}'s vector for {Path(*self._keys[row])} was computed "
                f"from ({facts[1]} bytes here, {int(self._sizes[row])} then): these vectors are of "
                "other images with the same names (another route or copy); extract them for these"
            )
        if facts[2] != self._mtimes[row] and not self._warned_mtime:
            self._warned_mtime = True
            logger.warning(
                f"{path}: modified at another time than the image that {file}'s vector for "
                f"{Path(*self._keys[row])} was computed from (same size); using the vector"
            )

    def _file_of(self, row: int) -> str:
        return self._row_files[row]

    @contextlib.contextmanager
    def images_of(self, paths: Sequence):
        """Within the block, :meth:`describe` looks up the vectors of ``paths``."""
        self._batch_paths = list(paths)
        try:
            yield self
        finally:
            self._batch_paths = None

    def describe(self, images: np.ndarray) -> np.ndarray:
        names = getattr(self, "_batch_paths", None)
        if names is None or len(names) != len(images):
            raise DataError(
                "precomputed: vectors are looked up by image name, so they describe image files "
                "(or video and bag frames), not pixel arrays; give the images' paths"
            )
        return self.lookup(names)
