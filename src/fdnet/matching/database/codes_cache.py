"""A large place database's compressed codes, cached beside its file (``map.db.fdnet-codes``).

Above ``compressed_from`` places a database searches through a
:class:`~fdnet.matching.compressed.CompressedIndex` over its vector file
(:mod:`~fdnet.matching.database.vector_store`). Training and encoding it costs about a minute at
10^6 places and a quarter of an hour at 10^7, so the process that builds it writes it here
(:mod:`fdnet.matching.compressed_file`: a temporary file, fsynced, renamed over the old one: a
kill leaves the old cache or none), and later processes load it. The cache is derived data and
is never trusted: it is used only when it was written for this database (its ``database_id``),
covers at most the rows the database has committed to its vector file, and those rows are the
ones it was built from (a digest of :data:`SAMPLED_ROWS` rows spread over them, read from the
file: a database restored from a backup or built again over the file does not match). The rows
committed after it are then encoded and added to the loaded codes, not trained again (unless the
index's own rule, growth since its training, says so). A cache that does not match is ignored,
a damaged one logged; either way the codes are built again and the cache rewritten.
"""

from __future__ import annotations

import hashlib
import logging
import time
from pathlib import Path

import numpy as np

from fdnet.errors import ConfigError, DataError

logger = logging.getLogger(__name__)

#: suffix of the codes cache beside a database file
CODES_CACHE_SUFFIX = ".fdnet-codes"
#: rows of the vector file whose contents the cache's key includes
SAMPLED_ROWS = 64
#: a temporary cache file untouched this long (seconds) was left by a killed writer
STALE_SECONDS = 3600


def codes_cache_path(database_path: str | Path) -> Path:
    return Path(f"{database_path}{CODES_CACHE_SUFFIX}")


def rows_digest(file, count: int) -> str:
    """sha256 over :data:`SAMPLED_ROWS` rows spread evenly over the first ``count`` of ``file``
    (a :class:`~fdnet.matching.compressed.VectorFile`), the last one included, and their ids."""
    ids = np.unique(np.linspace(0, count - 1, min(count, SAMPLED_ROWS)).astype(np.int64))
    digest = hashlib.sha256(b"%d:" % count)
    digest.update(ids.tobytes())
    digest.update(np.ascontiguousarray(file.rows(ids)).tobytes())
    return digest.hexdigest()


class CodesCache:
    """The codes cache of one database (see the module docstring)."""

    def __init__(self, database_path: str | Path, database_id: str):
        self.path = codes_cache_path(database_path)
        self._database_id = database_id
        #: places the cache held when it was loaded or last written here
        self.places = 0

    def load(self, file, places: int, settings=None):
        """The cached :class:`~fdnet.matching.compressed.CompressedIndex` of this database's first
        ``places`` rows of ``file``, when it belongs to this database and was built from its rows
        (else None). A cache that covers more rows but was trained on at most ``places`` is cut
        to ``places`` (the codes of the others go): its codes for those places are the ones a
        cache built on them alone would hold (a resumed loop closure finds the codes it started
        from, though another process extended the cache since)."""
        from fdnet.matching.compressed import CompressedIndex
        from fdnet.matching.compressed_file import read_header

        if file is None or not self.path.is_file():
            return None
        try:
            header = read_header(self.path)
            meta, count = header.get("metadata", {}), int(header["count"])
            if (
                meta.get("database_id") != self._database_id
                or not 0 < count <= len(file)
                or not 0 < int(header["trained_on"]) <= int(places)
                or meta.get("rows") != rows_digest(file, count)
            ):
                logger.info("%s: the cached compressed codes are not this database's; building them again", self.path)
                return None
            index = CompressedIndex.load(self.path, settings, header)
        except (DataError, ConfigError, ValueError, TypeError, KeyError, AttributeError) as exc:
            logger.warning("%s: cannot use the cached compressed codes (%s); building them again", self.path, exc)
            return None
        logger.info("%s: loaded the compressed codes of %d places", self.path, min(count, int(places)))
        self.places = count  # (what the file holds: a cut copy is not written back unless it grows past it)
        index.truncate(int(places))
        return index

    def save(self, index, file, force: bool = False) -> bool:
        """Write ``index`` (its places: the first rows of ``file``) when ``force`` (it was trained
        here) or it grew by 5 % (at least 1000 places) since the cache was read or written; a
        cache that cannot be written (a read-only folder, a full disk) is skipped."""
        grown = len(index) - self.places
        if len(index) == 0 or grown <= 0 or (not force and self.places and grown < max(1000, 0.05 * self.places)):
            return False
        self._remove_stale()
        try:
            index.save(self.path, {"database_id": self._database_id, "rows": rows_digest(file, len(index))})
        except (OSError, DataError) as exc:
            logger.info("%s: cannot write the compressed codes cache (%s)", self.path, exc)
            return False
        self.places = len(index)
        return True

    def _remove_stale(self) -> None:
        """Delete temporary cache files a killed writer left (a writer at work touches its own
        every few seconds; one untouched for :data:`STALE_SECONDS` is abandoned)."""
        for temporary in self.path.parent.glob(f".{self.path.name}.*.tmp"):
            try:
                if time.time() - temporary.stat().st_mtime > STALE_SECONDS:
                    temporary.unlink()
                    logger.info("%s: removed a cache file a killed writer left", temporary)
            except OSError:
                pass
