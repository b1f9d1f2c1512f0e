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
path. So relative names (hloc's), moved data and absolute paths all resolve. Two equally good
candidates are an error naming both, never a guess; so is an image with no vector (naming it and
the files searched).
"""

from __future__ import annotations

import hashlib
import json
import os
from collections import defaultdict
from pathlib import Path
from typing import Sequence

import numpy as np

from fdnet.descriptors.base import Descriptor, l2_normalize
from fdnet.errors import ConfigError, DataError

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
                raise DataError(f"{path}: no {array or 'descriptors or content'} array (holds {', '.join(sorted(keys))}); "
                                "give the array with --method-set array=NAME")
            if "names" not in keys:
                raise DataError(f"{path}: no names array: an image's vector cannot be found without its name")
            vectors = np.asarray(data[chosen], dtype=np.float32)
            names = [str(n) for n in data["names"]]
            sources = [str(s) for s in data["sources"]] if "sources" in keys else None
            recorded = {}
            if "method" in keys:
                recorded["method"] = str(data["method"])
            if "settings" in keys:
                try:
                    recorded["settings"] = json.loads(str(data["settings"]))
                except ValueError:
                    pass
    except DataError:
        raise
    except (OSError, ValueError, KeyError, EOFError) as exc:
        raise DataError(f"{path}: not a readable .npz of vectors ({' '.join(str(exc).split())})") from None
    if sources is not None and len(sources) == len(names):
        names = [os.path.join(s, n) for s, n in zip(sources, names)]
    return names, vectors, recorded


def _read_npy(path: Path, names_file: str | None) -> tuple[list[str], np.ndarray, dict]:
    listing = Path(names_file) if names_file else path.with_suffix(".txt")
    try:
        vectors = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise DataError(f"{path}: not a readable .npy array ({' '.join(str(exc).split())})") from None
    if not listing.is_file():
        raise DataError(f"{path}: no names list {listing} (one image name per line, in the rows' order); give "
                        "it with --method-set names=FILE")
    try:
        names = [line.strip() for line in listing.read_text(encoding="utf-8").splitlines() if line.strip()]
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{listing}: cannot read the names list ({exc})") from None
    return names, np.asarray(vectors, dtype=np.float32), {}


def _read_h5(path: Path) -> tuple[list[str], np.ndarray, dict]:
    from fdnet.descriptors.hloc_formats import read_global_features

    names, vectors = read_global_features(path)
    return names, np.asarray(vectors, dtype=np.float32), {}


def read_vectors(path: str | os.PathLike, names_file: str | None = None,
                 array: str | None = None) -> tuple[list[str], np.ndarray, dict]:
    """(image names, (N, D) float32 vectors, what the file records about how they were made)
    from one vectors file, by its suffix (``.npz``, ``.npy``, ``.h5``/``.hdf5``)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: vectors file not found")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        names, vectors, recorded = _read_npz(path, array)
    elif suffix == ".npy":
        names, vectors, recorded = _read_npy(path, names_file)
    elif suffix in (".h5", ".hdf5"):
        names, vectors, recorded = _read_h5(path)
    else:
        raise DataError(f"{path}: not a vectors file fdnet reads (.npz from fdnet extract, .npy with a names list, "
                        "hloc's .h5)")
    if vectors.ndim != 2 or vectors.shape[0] == 0 or vectors.shape[1] == 0:
        raise DataError(f"{path}: vectors of shape {tuple(vectors.shape)}; expected (images, length)")
    if len(names) != len(vectors):
        raise DataError(f"{path}: {len(vectors)} vectors but {len(names)} image names")
    if not np.isfinite(vectors).all():
        row = int(np.flatnonzero(~np.isfinite(vectors).all(axis=1))[0])
        raise DataError(f"{path}: the vector of {names[row]} holds NaN or infinity")
    return names, vectors, recorded


class PrecomputedDescriptor(Descriptor):
    """Vectors from files, looked up by image (module docstring)."""

    name = "precomputed"
    keyed_by_image = True

    def __init__(self, vectors: str | os.PathLike | Sequence[str | os.PathLike] | None = None,
                 names: str | None = None, array: str | None = None, normalise: str = "l2",
                 input_size: Sequence[int] | None = None):
        if not vectors:
            raise ConfigError("precomputed: give the vectors with --vectors FILE (repeatable: .npz from fdnet "
                              "extract, .npy with a names list, hloc's .h5)")
        files = [vectors] if isinstance(vectors, (str, os.PathLike)) else list(vectors)
        if names is not None and len(files) > 1:
            raise ConfigError("precomputed: names=FILE lists the rows of one .npy; give one --vectors with it")
        if normalise not in NORMALISE_CHOICES:
            raise ConfigError(f"precomputed: normalise={normalise!r}; choose {' or '.join(NORMALISE_CHOICES)}")
        self.files = [str(f) for f in files]
        self.normalise = normalise
        rows: list[np.ndarray] = []
        self._keys: list[tuple[str, ...]] = []
        self.recorded: dict = {}
        by_key: dict[tuple[str, ...], str] = {}
        digest = hashlib.sha256()
        for file in self.files:
            file_names, file_vectors, recorded = read_vectors(file, names, array)
            if rows and file_vectors.shape[1] != rows[0].shape[1]:
                raise DataError(f"{file}: vectors of length {file_vectors.shape[1]}, but {self.files[0]}'s are "
                                f"{rows[0].shape[1]} long: one descriptor's vectors only")
            if recorded and self.recorded and recorded.get("method") != self.recorded.get("method"):
                raise DataError(f"{file}: vectors of {recorded.get('method')}, but {self.files[0]}'s are of "
                                f"{self.recorded.get('method')}: one descriptor's vectors only")
            self.recorded = self.recorded or recorded
            for name in file_names:
                key = _parts(name)
                if key in by_key:
                    raise DataError(f"{file}: image {name} has a vector already (in {by_key[key]}); give each "
                                    "image's vector once")
                by_key[key] = file
                self._keys.append(key)
            rows.append(file_vectors)
            digest.update(np.ascontiguousarray(file_vectors).tobytes())
            digest.update("\n".join(file_names).encode("utf-8", "surrogateescape"))
        # Pixels are still decoded where a command reads them (the loop-closure gates): at the size
        # the vectors' own method read them, when the file records it.
        from fdnet.data.images import check_image_size

        if input_size is None:
            input_size = self.recorded.get("settings", {}).get("input_size") or (120, 160)
        self.input_size = check_image_size(input_size, "precomputed: input_size")
        matrix = np.concatenate(rows)
        if normalise == "l2":
            # Rows already of unit length are kept bit for bit: dividing by a norm of 1 +- 1e-7
            # would change last bits, and the vectors' own method's numbers must come back exactly.
            off = np.abs(np.linalg.norm(matrix, axis=1) - 1.0) > 1e-5
            matrix[off] = l2_normalize(matrix[off])
        self.vectors = matrix
        self._by_name: dict[str, list[int]] = defaultdict(list)
        for row, key in enumerate(self._keys):
            self._by_name[key[-1] if key else ""].append(row)
        self.vectors_sha256 = digest.hexdigest()

    @property
    def dim(self) -> int:
        return int(self.vectors.shape[1])

    def settings(self) -> dict:
        return {"input_size": list(self.input_size), "vectors": self.files, "normalise": self.normalise,
                "vectors_sha256": self.vectors_sha256, "images": len(self._keys),
                **({"source_method": self.recorded["method"]} if "method" in self.recorded else {})}

    def fingerprint(self, *, with_locations: bool = False) -> str:
        # The vectors' bytes and names (vectors_sha256) say what they are; hashing the merged
        # matrix again, as the base class would, only costs time on a large map.
        settings = {k: v for k, v in self.settings().items() if with_locations or k != "vectors"}
        return hashlib.sha256(f"method={self.name}\n{json.dumps(settings, sort_keys=True)}".encode()).hexdigest()

    def row_of(self, path: str | os.PathLike) -> int:
        """The row holding ``path``'s vector (module docstring: by name, then trailing folders)."""
        key = _parts(os.path.abspath(os.fspath(path)))
        # the file name and, where the stored name has one, its folder's name must agree
        candidates = [row for row in self._by_name.get(key[-1] if key else "", [])
                      if _common_tail(key, self._keys[row]) >= min(2, len(self._keys[row]))]
        if not candidates:
            raise DataError(f"{path}: no vector for this image in {', '.join(self.files)} (looked up by its file "
                            f"name and folder, {'/'.join(key[-2:]) if key else path!r}); every image a command reads needs one")
        if len(candidates) == 1:
            return candidates[0]
        tails = [_common_tail(key, self._keys[row]) for row in candidates]
        best = max(tails)
        chosen = [row for row, tail in zip(candidates, tails) if tail == best]
        if len(chosen) > 1:
            a, b = ("/".join(self._keys[row]) for row in chosen[:2])
            raise DataError(f"{path}: two vectors fit this image equally well ({a} and {b}); name the images by "
                            "their folders in the vectors files")
        return chosen[0]

    def lookup(self, paths: Sequence[str | os.PathLike]) -> np.ndarray:
        """(len(paths), dim) float32: each image's vector."""
        return self.vectors[[self.row_of(p) for p in paths]]

    def describe(self, images: np.ndarray) -> np.ndarray:
        names = getattr(self, "_batch_paths", None)
        if names is None or len(names) != len(images):
            raise DataError("precomputed: vectors are looked up by image name, so they describe image files "
                            "(or video and bag frames), not pixel arrays; give the images' paths")
        return self.lookup(names)
